"""Tiny ONNX graphs built with onnx.helper, for tests and benchmarks (no downloaded weights)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
IR_VERSION = 8

Dim = int | str


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def affine_of_mean(
    path: Path,
    a: float = 1.0,
    b: float = 0.0,
    *,
    input_shape: Sequence[Dim] = ("B", 3, "H", "W"),
    output_4d: bool = False,
) -> Path:
    """output = a · mean over RGB of the (normalised) input + b: shape (B, H, W) or (B, 1, H, W).

    With ``input_shape`` (B, H, W, 3) the input is NHWC and the mean is over the last axis.
    """
    nhwc = input_shape[-1] == 3 and input_shape[1] != 3
    axis = 3 if nhwc else 1
    out_dims: list[Dim] = (
        [input_shape[0], input_shape[1], input_shape[2]]
        if nhwc
        else [input_shape[0], input_shape[2], input_shape[3]]
    )
    nodes = [
        helper.make_node("ReduceMean", ["x"], ["m"], axes=[axis], keepdims=1),
        helper.make_node("Mul", ["m", "a"], ["am"]),
        helper.make_node("Add", ["am", "b"], ["y4"]),
    ]
    if output_4d and not nhwc:
        nodes.append(helper.make_node("Identity", ["y4"], ["y"]))
        out_shape: list[Dim] = [out_dims[0], 1, out_dims[1], out_dims[2]]
    else:
        nodes.append(helper.make_node("Squeeze", ["y4", "axes"], ["y"]))
        out_shape = out_dims
    inits = [
        numpy_helper.from_array(np.array(a, dtype=np.float32), "a"),
        numpy_helper.from_array(np.array(b, dtype=np.float32), "b"),
        numpy_helper.from_array(np.array([axis], dtype=np.int64), "axes"),
    ]
    graph = helper.make_graph(
        nodes,
        "affine_of_mean",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, out_shape)],
        initializer=inits,
    )
    return _save(graph, path)


def channel(path: Path, c: int, *, input_shape: Sequence[Dim] = (1, 3, "H", "W")) -> Path:
    """output = input channel ``c`` (NCHW): shape (B, H, W)."""
    graph = helper.make_graph(
        [helper.make_node("Gather", ["x", "idx"], ["y"], axis=1)],
        "channel",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(input_shape))],
        [
            helper.make_tensor_value_info(
                "y", TensorProto.FLOAT, [input_shape[0], input_shape[2], input_shape[3]]
            )
        ],
        initializer=[numpy_helper.from_array(np.array(c, dtype=np.int64), "idx")],
    )
    return _save(graph, path)


def row_box(path: Path, radius: int) -> Path:
    """output = channel 0 averaged over 2·radius + 1 columns, zero beyond the image's left and
    right borders (a convolution without circular padding): (1, 3, H, W) -> (1, H, W)."""
    return _row_mean(path, "row_box", 2 * radius + 1, "W", pads=[0, radius, 0, radius])


def column_stride(path: Path, stride: int) -> Path:
    """output = channel 0 averaged over each run of ``stride`` columns (no padding, the last
    W mod stride columns dropped): (1, 3, H, W) -> (1, H, W // stride)."""
    return _row_mean(path, "column_stride", stride, "Wo", strides=[1, stride])


def _row_mean(path: Path, name: str, k: int, out_width: str, **conv: list[int]) -> Path:
    """Channel 0 averaged over k columns by a (1, k) convolution with the attributes ``conv``,
    squeezed to (1, H, out_width)."""
    weight = np.zeros((1, 3, 1, k), np.float32)
    weight[0, 0] = 1.0 / k
    graph = helper.make_graph(
        [
            helper.make_node("Conv", ["x", "w"], ["c"], **conv),
            helper.make_node("Squeeze", ["c", "axis"], ["y"]),
        ],
        name,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, "H", out_width])],
        initializer=[
            numpy_helper.from_array(weight, "w"),
            numpy_helper.from_array(np.array([1], dtype=np.int64), "axis"),
        ],
    )
    return _save(graph, path)


def identity(path: Path, shape: Sequence[Dim]) -> Path:
    """output = input, any shape (for wrong-rank / wrong-output tests)."""
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "identity",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, list(shape))],
    )
    return _save(graph, path)


def conv_net(
    path: Path,
    *,
    size: int | None = 256,
    width: int = 32,
    layers: int = 6,
    batch: Dim = "B",
    seed: int = 0,
) -> Path:
    """A random-weight CNN shaped like a small depth network: stride-2 encoder, upsampling decoder.

    ``layers`` 3x3 conv + ReLU blocks at 1/2 resolution with ``width`` channels between a stride-2
    stem and a 1x1 head, then a bilinear x2 resize: output (B, H, W). The cost grows with
    width² x layers; benches/bench_estimate.py sizes it to take about as long per 256² tile as
    MiDaS v2.1 small. ``size=None`` gives a dynamic spatial size.
    """
    rng = np.random.default_rng(seed)
    h: Dim = size if size is not None else "H"
    w: Dim = size if size is not None else "W"
    nodes = []
    inits = []

    def conv(name: str, cin: int, cout: int, k: int, stride: int, src: str) -> str:
        weight = rng.standard_normal((cout, cin, k, k)).astype(np.float32)
        weight *= np.float32(np.sqrt(2.0 / (cin * k * k)))
        inits.append(numpy_helper.from_array(weight, f"{name}_w"))
        inits.append(numpy_helper.from_array(np.zeros(cout, np.float32), f"{name}_b"))
        nodes.append(
            helper.make_node(
                "Conv",
                [src, f"{name}_w", f"{name}_b"],
                [f"{name}_c"],
                kernel_shape=[k, k],
                strides=[stride, stride],
                pads=[k // 2] * 4,
            )
        )
        nodes.append(helper.make_node("Relu", [f"{name}_c"], [f"{name}_r"]))
        return f"{name}_r"

    x = conv("stem", 3, width, 3, 2, "x")
    for i in range(layers):
        x = conv(f"l{i}", width, width, 3, 1, x)
    head = rng.standard_normal((1, width, 1, 1)).astype(np.float32) / np.float32(width)
    inits.append(numpy_helper.from_array(head, "head_w"))
    nodes.append(helper.make_node("Conv", [x, "head_w"], ["head"], kernel_shape=[1, 1]))
    inits.append(numpy_helper.from_array(np.array([1, 1, 2, 2], dtype=np.float32), "scales"))
    nodes.append(helper.make_node("Resize", ["head", "", "scales"], ["up"], mode="linear"))
    inits.append(numpy_helper.from_array(np.array([1], dtype=np.int64), "sq_axes"))
    nodes.append(helper.make_node("Squeeze", ["up", "sq_axes"], ["y"]))
    graph = helper.make_graph(
        nodes,
        "conv_net",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [batch, 3, h, w])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [batch, h, w])],
        initializer=inits,
    )
    return _save(graph, path)


def erp_oracle(path: Path, transform: str, size: tuple[int, int] = (32, 64)) -> Path:
    """A fixed-size panoramic graph: ``transform`` of the probe corridor's true ERP distance.

    Input (1, 3, h, w), output (1, h, w) at ``size``; the image is ignored (0 x its mean is added
    so that the input is used): what a perfect panoramic network outputs on the corridor.
    ``transform``: ``distance``, ``disparity`` (1/distance), ``scaled_distance`` (40 d + 100,
    an affine depth) or ``scaled_disparity`` (3/d + 0.5, an affine disparity).
    """
    from m360.estimators import _probe

    d = _probe.erp_views(size)[0][1].astype(np.float64)
    value = {
        "distance": d,
        "disparity": 1 / d,
        "scaled_distance": 40.0 * d + 100.0,
        "scaled_disparity": 3.0 / d + 0.5,
    }[transform].astype(np.float32)
    return constant_output(path, value, "erp_oracle")


def constant_output(path: Path, value: np.ndarray, name: str) -> Path:
    """A fixed-size graph, input (1, 3, h, w), output (1, h, w) = ``value`` (float32 (h, w)).

    The image is ignored (0 x its mean is added so that the input is used): a perfect network's
    output on the scene ``value`` was computed from.
    """
    size = list(value.shape)
    inits = [
        numpy_helper.from_array(value[None], "value"),
        numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
    ]
    nodes = [
        helper.make_node("ReduceMean", ["x"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["m0"]),
        helper.make_node("Add", ["value", "m0"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        name,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, *size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, *size])],
        initializer=inits,
    )
    return _save(graph, path)


def saturating(path: Path, size: int = 32) -> Path:
    """A fixed-size network that saturates above 1: output = min(channel 0, 1) + a fixed ramp.

    Fed RGB in [0, 1] its output follows the photo; fed raw 0-255 values every lit pixel reads
    1, and every tile gets the ramp (its bias), the same map.
    """
    ramp = np.linspace(1.0, 2.0, size * size, dtype=np.float32).reshape(1, size, size)
    graph = helper.make_graph(
        [
            helper.make_node("Gather", ["x", "idx"], ["c"], axis=1),
            helper.make_node("Min", ["c", "one"], ["clipped"]),
            helper.make_node("Add", ["clipped", "ramp"], ["y"]),
        ],
        "saturating",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, size, size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, size, size])],
        initializer=[
            numpy_helper.from_array(np.array(0, dtype=np.int64), "idx"),
            numpy_helper.from_array(np.array(1.0, dtype=np.float32), "one"),
            numpy_helper.from_array(ramp, "ramp"),
        ],
    )
    return _save(graph, path)
