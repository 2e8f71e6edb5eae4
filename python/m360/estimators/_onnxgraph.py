"""Read the start of an ONNX graph without the ``onnx`` package (not a run-time dependency).

Only what m360 asks of a model file is decoded: the graph's image input, its nodes (op type,
inputs, outputs, attributes on demand) and small constant tensors. The protobuf wire format is
walked over a memoryview, so the multi-hundred-megabyte weights are skipped, never copied.

:func:`input_affine` follows the image input through the first operations of the graph and
returns the per-channel affine map ``x * scale + offset`` they apply, if any: that is how m360
finds whether a model normalises its input itself (``onnx_file.input_normalization`` decides
what the map means).
"""

from __future__ import annotations

import mmap
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..errors import ModelError

# Field numbers of onnx.proto3 (ModelProto, GraphProto, NodeProto, AttributeProto, TensorProto).
_MODEL_GRAPH = 7
_GRAPH_NODE, _GRAPH_INITIALIZER, _GRAPH_INPUT = 1, 5, 11
_NODE_INPUT, _NODE_OUTPUT, _NODE_OP_TYPE, _NODE_ATTRIBUTE = 1, 2, 4, 5
_ATTR_NAME, _ATTR_F, _ATTR_T, _ATTR_FLOATS, _ATTR_INTS = 1, 2, 5, 7, 8
_TENSOR_DIMS, _TENSOR_TYPE, _TENSOR_FLOATS, _TENSOR_NAME, _TENSOR_RAW = 1, 2, 4, 8, 9
_TENSOR_INT64S, _TENSOR_DOUBLES, _TENSOR_LOCATION = 7, 10, 14
# TensorProto.DataType values m360 reads constants of.
_DTYPES = {1: np.float32, 10: np.float16, 11: np.float64, 6: np.int32, 7: np.int64, 2: np.uint8}
#: Constants bigger than this are not normalisation constants: not decoded.
_MAX_CONSTANT = 64
#: Operations that pass the image on unchanged in value (per channel) before the normalisation.
_PASS_THROUGH = {"Cast", "Identity", "Resize", "Upsample", "Transpose"}
_AFFINE = {"Sub", "Div", "Mul", "Add"}
#: How many operations after the input are looked at.
_MAX_STEPS = 8


class _Truncated(Exception):
    pass


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf) or shift > 63:
            raise _Truncated
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7


def _fields(buf: memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """(field number, wire type, value): ints for varint/fixed, a memoryview for bytes."""
    pos, end = 0, len(buf)
    while pos < end:
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
            yield number, wire, value
        elif wire == 2:
            size, pos = _varint(buf, pos)
            if pos + size > end:
                raise _Truncated
            yield number, wire, buf[pos : pos + size]
            pos += size
        elif wire == 5:
            if pos + 4 > end:
                raise _Truncated
            yield number, wire, int.from_bytes(buf[pos : pos + 4], "little")
            pos += 4
        elif wire == 1:
            if pos + 8 > end:
                raise _Truncated
            yield number, wire, int.from_bytes(buf[pos : pos + 8], "little")
            pos += 8
        else:  # groups (3, 4) are not used by onnx.proto; anything else is not protobuf
            raise _Truncated


def _text(value: int | memoryview) -> str:
    if not isinstance(value, memoryview):
        raise _Truncated
    return bytes(value).decode("utf-8", "replace")


def _ints(wire: int, value: int | memoryview) -> list[int]:
    """A repeated int64 field: one varint, or a packed run of them."""
    if isinstance(value, int):
        return [value - (1 << 64) if value >= 1 << 63 else value]
    out, pos = [], 0
    while pos < len(value):
        v, pos = _varint(value, pos)
        out.append(v - (1 << 64) if v >= 1 << 63 else v)
    return out


def _floats(wire: int, value: int | memoryview) -> list[float]:
    if isinstance(value, int):
        return [struct.unpack("<f", value.to_bytes(4, "little"))[0]]
    if len(value) % 4:
        raise _Truncated
    return list(np.frombuffer(value, dtype="<f4").astype(float))


@dataclass
class Node:
    """One graph node; ``attributes`` is the undecoded list of AttributeProto messages."""

    op_type: str
    inputs: list[str]
    outputs: list[str]
    attributes: list[memoryview] = field(default_factory=list)

    def attribute(self, name: str) -> dict[int, list[tuple[int, int | memoryview]]] | None:
        """The fields of attribute ``name``, or None if the node has no such attribute."""
        for raw in self.attributes:
            fields: dict[int, list[tuple[int, int | memoryview]]] = {}
            for number, wire, value in _fields(raw):
                fields.setdefault(number, []).append((wire, value))
            if _ATTR_NAME in fields and _text(fields[_ATTR_NAME][0][1]) == name:
                return fields
        return None


@dataclass
class Graph:
    """The parts of an ONNX graph m360 reads."""

    input_name: str
    input_shape: list[int | str]
    nodes: list[Node]
    initializers: dict[str, memoryview]

    def consumers(self, name: str) -> list[Node]:
        """Nodes that take tensor ``name`` as an input."""
        return [n for n in self.nodes if name in n.inputs]

    def constant(self, name: str, depth: int = 0) -> np.ndarray | None:
        """The value of a small constant tensor, else None.

        An initializer, a Constant node, or one of them reshaped or cast (Unsqueeze, Reshape,
        Squeeze, Cast, Identity): exporters often write ``mean[None, :, None, None]`` that way.
        """
        if name in self.initializers:
            return _tensor(self.initializers[name])
        producer = next((n for n in self.nodes if name in n.outputs), None)
        if producer is None or depth > 4:
            return None
        if producer.op_type == "Constant":
            return _constant_node(producer)
        if producer.op_type in _FOLDABLE and producer.inputs:
            value = self.constant(producer.inputs[0], depth + 1)
            if value is None:
                return None
            return _fold(self, producer, value, depth)
        return None


_FOLDABLE = {"Unsqueeze", "Reshape", "Squeeze", "Cast", "Identity"}


def _constant_node(node: Node) -> np.ndarray | None:
    fields = node.attribute("value")
    if fields and _ATTR_T in fields:
        t = fields[_ATTR_T][0][1]
        return _tensor(t) if isinstance(t, memoryview) else None
    fields = node.attribute("value_float") or node.attribute("value_floats")
    if fields and _ATTR_F in fields:
        return np.array(_floats(*fields[_ATTR_F][0]), dtype=np.float64)
    if fields and _ATTR_FLOATS in fields:
        values = [v for wire, raw in fields[_ATTR_FLOATS] for v in _floats(wire, raw)]
        return np.array(values, dtype=np.float64)
    return None


def _fold(graph: Graph, node: Node, value: np.ndarray, depth: int) -> np.ndarray | None:
    """``node`` applied to a constant ``value`` (shape changes only), or None."""
    if node.op_type in ("Cast", "Identity"):
        return value
    if node.op_type == "Reshape":
        shape = graph.constant(node.inputs[1], depth + 1) if len(node.inputs) > 1 else None
        if shape is None:
            return None
        dims = [int(d) for d in shape.reshape(-1)]
        dims = [value.shape[i] if d == 0 and i < value.ndim else d for i, d in enumerate(dims)]
        return value.reshape(dims)  # ValueError if impossible: the caller says "unreadable"
    # Unsqueeze / Squeeze: axes as an attribute (opset < 13) or a second input.
    fields = node.attribute("axes")
    if fields:
        axes = [v for w, raw in fields.get(_ATTR_INTS, []) for v in _ints(w, raw)]
    elif len(node.inputs) > 1 and node.inputs[1]:
        given = graph.constant(node.inputs[1], depth + 1)
        if given is None:
            return None
        axes = [int(a) for a in given.reshape(-1)]
    elif node.op_type == "Squeeze":
        return value.reshape([d for d in value.shape if d != 1])
    else:
        return None
    if node.op_type == "Squeeze":
        return np.squeeze(value, axis=tuple(axes))
    rank = value.ndim + len(axes)
    out = value
    for axis in sorted(a % rank for a in axes):
        out = np.expand_dims(out, axis)
    return out


def _tensor(raw: memoryview) -> np.ndarray | None:
    dims: list[int] = []
    dtype = 0
    data: memoryview | None = None
    floats: list[float] = []
    ints: list[int] = []
    for number, wire, value in _fields(raw):
        if number == _TENSOR_DIMS:
            dims += _ints(wire, value)
        elif number == _TENSOR_TYPE and isinstance(value, int):
            dtype = value
        elif number == _TENSOR_RAW and isinstance(value, memoryview):
            data = value
        elif number == _TENSOR_FLOATS:
            floats += _floats(wire, value)
        elif number == _TENSOR_DOUBLES:
            floats += (
                [struct.unpack("<d", value.to_bytes(8, "little"))[0]]
                if isinstance(value, int)
                else list(np.frombuffer(value, dtype="<f8"))
                if len(value) % 8 == 0
                else []
            )
        elif number == _TENSOR_INT64S:
            ints += _ints(wire, value)
        elif number == _TENSOR_LOCATION and value == 1:
            return None  # external data: not in this file
    count = int(np.prod(dims)) if dims else 1
    if dtype not in _DTYPES or count > _MAX_CONSTANT or any(d < 0 for d in dims):
        return None
    if data is not None:
        np_type = np.dtype(_DTYPES[dtype]).newbyteorder("<")
        if len(data) != count * np_type.itemsize:
            return None
        array = np.frombuffer(data, dtype=np_type).astype(np.float64)
    else:
        values = floats or [float(v) for v in ints]
        if len(values) != count:
            return None
        array = np.array(values, dtype=np.float64)
    return array.reshape(dims)


def _value_info(raw: memoryview) -> tuple[str, list[int | str]]:
    name, shape = "", []
    for number, _, value in _fields(raw):
        if number == 1:
            name = _text(value)
        elif number == 2 and isinstance(value, memoryview):  # TypeProto
            for n2, _, v2 in _fields(value):
                if n2 == 1 and isinstance(v2, memoryview):  # tensor_type
                    for n3, _, v3 in _fields(v2):
                        if n3 == 2 and isinstance(v3, memoryview):  # shape
                            shape = [_dim(d) for n4, _, d in _fields(v3) if n4 == 1]
    return name, shape


def _dim(raw: int | memoryview) -> int | str:
    if not isinstance(raw, memoryview):
        return "?"
    for number, _, value in _fields(raw):
        if number == 1 and isinstance(value, int):
            return value
        if number == 2:
            return _text(value)
    return "?"


def parse(data: bytes | memoryview) -> Graph:
    """Read the graph of an ONNX model held in ``data`` (ModelError if it is not one)."""
    buf = memoryview(data)
    try:
        graphs = [v for n, w, v in _fields(buf) if n == _MODEL_GRAPH and w == 2]
        if not graphs or not isinstance(graphs[0], memoryview):
            raise _Truncated
        nodes: list[Node] = []
        initializers: dict[str, memoryview] = {}
        inputs: list[tuple[str, list[int | str]]] = []
        for number, wire, value in _fields(graphs[0]):
            if wire != 2 or not isinstance(value, memoryview):
                continue
            if number == _GRAPH_NODE:
                node = Node("", [], [])
                for n2, _, v2 in _fields(value):
                    if n2 == _NODE_INPUT:
                        node.inputs.append(_text(v2))
                    elif n2 == _NODE_OUTPUT:
                        node.outputs.append(_text(v2))
                    elif n2 == _NODE_OP_TYPE:
                        node.op_type = _text(v2)
                    elif n2 == _NODE_ATTRIBUTE and isinstance(v2, memoryview):
                        node.attributes.append(v2)
                nodes.append(node)
            elif number == _GRAPH_INITIALIZER:
                for n2, _, v2 in _fields(value):
                    if n2 == _TENSOR_NAME:
                        initializers[_text(v2)] = value
                        break
            elif number == _GRAPH_INPUT:
                inputs.append(_value_info(value))
    except (_Truncated, ValueError, OverflowError):  # never more than "unreadable"
        raise ModelError("it is not a readable ONNX protobuf (truncated or corrupt)") from None
    # Before IR version 4 initializers were listed among the inputs too.
    images = [i for i in inputs if i[0] not in initializers]
    if not images:
        raise ModelError("its graph has no input")
    return Graph(images[0][0], images[0][1], nodes, initializers)


@dataclass(frozen=True)
class InputAffine:
    """The per-channel map ``x * scale + offset`` the graph's first operations apply.

    ``ops`` lists the operations followed from the input, pass-through ones included.
    """

    scale: tuple[float, float, float]
    offset: tuple[float, float, float]
    ops: tuple[str, ...]


def _per_channel(value: np.ndarray, rank: int, axis: int) -> np.ndarray | None:
    """The 3 per-channel values of a constant broadcast against a rank-``rank`` tensor whose
    channels are on ``axis``; None if it does not vary along the channels only.
    """
    if value.size == 1:
        return np.full(3, float(value.reshape(-1)[0]))
    if value.ndim > rank or value.size != 3:
        return None
    # Broadcasting aligns the constant's dims to the tensor's last ones.
    where = [rank - value.ndim + i for i, d in enumerate(value.shape) if d == 3]
    if where != [axis]:
        return None
    return value.reshape(3).astype(np.float64)


def input_affine(graph: Graph) -> InputAffine | None:
    """Follow the image input through its first operations; the affine map they apply, if any.

    Pass-through operations (Transpose, Cast, Resize, Identity) are followed; then every
    Sub/Div by a constant (the input on the left) and Mul/Add with a constant (either side),
    per channel or scalar, is composed, in any order, until the first other operation.
    """
    shape = graph.input_shape
    rank = len(shape) if shape else 4
    axis = 3 if len(shape) == 4 and shape[3] == 3 and shape[1] != 3 else 1
    scale, offset = np.ones(3), np.zeros(3)
    ops: list[str] = []
    affine = False
    current = graph.input_name
    for _ in range(_MAX_STEPS):
        # Shape/Size read only the size (dynamic exports do): they do not use the values.
        users = [n for n in graph.consumers(current) if n.op_type not in ("Shape", "Size")]
        if len(users) != 1:  # used twice: not a plain preprocessing chain
            break
        node = users[0]
        if node.op_type in _PASS_THROUGH and node.inputs[:1] == [current] and node.outputs:
            if node.op_type == "Transpose":
                fields = node.attribute("perm")
                perm = (
                    [v for w, raw in fields.get(_ATTR_INTS, []) for v in _ints(w, raw)]
                    if fields
                    else list(range(rank))[::-1]
                )
                if sorted(perm) != list(range(rank)):
                    break
                axis = perm.index(axis)
            ops.append(node.op_type)
            current = node.outputs[0]
            continue
        if node.op_type not in _AFFINE or len(node.inputs) != 2 or not node.outputs:
            break
        left = node.inputs[0] == current
        if not left and node.op_type in ("Sub", "Div"):  # c - x, c / x: not a normalisation
            break
        constant = graph.constant(node.inputs[1] if left else node.inputs[0])
        per = None if constant is None else _per_channel(constant, rank, axis)
        if per is None or not np.all(np.isfinite(per)):
            break
        if node.op_type == "Sub":
            offset = offset - per
        elif node.op_type == "Add":
            offset = offset + per
        elif node.op_type == "Mul":
            scale, offset = scale * per, offset * per
        else:
            if np.any(per == 0):
                break
            scale, offset = scale / per, offset / per
        ops.append(node.op_type)
        affine = True
        current = node.outputs[0]
    if not affine:
        return None
    return InputAffine(
        tuple(float(v) for v in scale),  # type: ignore[arg-type]
        tuple(float(v) for v in offset),  # type: ignore[arg-type]
        tuple(ops),
    )


@dataclass(frozen=True)
class Summary:
    """What :func:`inspect_file` found: the image input and the affine map applied to it."""

    input_name: str
    input_shape: tuple[int | str, ...]
    affine: InputAffine | None


def inspect(data: bytes | memoryview) -> Summary:
    """:func:`parse` then :func:`input_affine`, as plain values (no views into ``data``)."""
    graph = parse(data)
    try:
        return Summary(graph.input_name, tuple(graph.input_shape), input_affine(graph))
    except (_Truncated, ValueError, OverflowError):
        raise ModelError("it is not a readable ONNX protobuf (truncated or corrupt)") from None


def inspect_file(path: str | os.PathLike[str]) -> Summary:
    """:func:`inspect` of a file, memory-mapped: the weights are skipped, never read."""
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise ModelError("it is empty")
            mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as exc:
        raise ModelError(f"cannot read {os.fspath(path)!r}: {exc}") from exc
    try:
        return inspect(memoryview(mapped))
    finally:
        try:
            mapped.close()
        except BufferError:  # a view is still referenced (a traceback): the GC unmaps it
            pass
