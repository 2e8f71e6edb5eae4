"""Tiny ONNX graphs with and without input normalisation (test_first_contact, test_models_check).

Each graph is a preprocessing chain (or none) then "output = channel c": its output is exactly
the value the network core receives for that channel.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnx_graphs as g
from m360 import models
from onnx import TensorProto, helper, numpy_helper

MEAN = np.array(models.IMAGENET_MEAN)
STD = np.array(models.IMAGENET_STD)

#: One preprocessing step: ("Transpose", perm), ("Cast",), ("Resize",), ("Shape",) (a Shape
#: node also reading the current tensor) or (op, constant, where) with op Sub/Div/Mul/Add and
#: where "init" (an initializer, constant on the right), "node" (a Constant node, on the
#: right), "left" (initializer on the left), "unsqueeze" / "reshape" (a (3,) constant made
#: (1, 3, 1, 1) by an Unsqueeze / Reshape node).
Step = tuple[Any, ...]


def chain_then_channel(
    path: Path, c: int, steps: Sequence[Step], input_shape: Sequence[int | str] = (1, 3, 8, 8)
) -> Path:
    """``steps`` applied to the input, then output = channel ``c`` (axis 1) of the result."""
    nodes, inits = [], []
    current = "x"
    for i, step in enumerate(steps):
        out = f"t{i}"
        op = step[0]
        if op == "Transpose":
            nodes.append(helper.make_node("Transpose", [current], [out], perm=list(step[1])))
        elif op == "Cast":
            nodes.append(helper.make_node("Cast", [current], [out], to=TensorProto.FLOAT))
        elif op == "Shape":  # a side reader of the size only; the chain goes on from current
            nodes.append(helper.make_node("Shape", [current], [f"shape{i}"]))
            continue
        elif op == "Resize":
            inits.append(numpy_helper.from_array(np.ones(4, np.float32), f"s{i}"))
            nodes.append(helper.make_node("Resize", [current, "", f"s{i}"], [out], mode="linear"))
        else:
            value, where = np.asarray(step[1], dtype=np.float32), step[2]
            const = f"k{i}"
            if where == "node":
                tensor = numpy_helper.from_array(value, f"{const}_value")
                nodes.append(helper.make_node("Constant", [], [const], value=tensor))
            elif where == "unsqueeze":  # a (3,) Constant node unsqueezed to (1, 3, 1, 1)
                tensor = numpy_helper.from_array(value.reshape(3), f"{const}_value")
                nodes.append(helper.make_node("Constant", [], [f"{const}_3"], value=tensor))
                inits.append(numpy_helper.from_array(np.array([0, 2, 3], np.int64), f"{const}_ax"))
                nodes.append(helper.make_node("Unsqueeze", [f"{const}_3", f"{const}_ax"], [const]))
            elif where == "reshape":  # a (3,) initializer reshaped to (1, 3, 1, 1)
                inits.append(numpy_helper.from_array(value.reshape(3), f"{const}_3"))
                shape = np.array([1, 3, 1, 1], np.int64)
                inits.append(numpy_helper.from_array(shape, f"{const}_shape"))
                nodes.append(helper.make_node("Reshape", [f"{const}_3", f"{const}_shape"], [const]))
            else:
                inits.append(numpy_helper.from_array(value, const))
            operands = [const, current] if where == "left" else [current, const]
            nodes.append(helper.make_node(op, operands, [out]))
        current = out
    inits.append(numpy_helper.from_array(np.array(c, dtype=np.int64), "idx"))
    nodes.append(helper.make_node("Gather", [current, "idx"], ["y"], axis=1))
    nhwc = input_shape[-1] == 3 and input_shape[1] != 3
    hw = list(input_shape[1:3]) if nhwc else list(input_shape[2:4])
    graph = helper.make_graph(
        nodes,
        "chain_then_channel",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [input_shape[0], *hw])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", g.OPSET)])
    model.ir_version = g.IR_VERSION
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def per_channel(values: Sequence[float] | np.ndarray, rank: int = 4, axis: int = 1) -> np.ndarray:
    shape = [1] * rank
    shape[axis] = 3
    return np.asarray(values, dtype=np.float32).reshape(shape)


NCHW = (1, 3, 8, 8)
NHWC = (1, 8, 8, 3)
TO_NCHW = ("Transpose", (0, 3, 1, 2))

#: name → (steps, input shape, who normalises, input range the graph expects)
VARIANTS: dict[str, tuple[list[Step], tuple[int, ...], str, float]] = {
    "none": ([], NCHW, "m360", 1.0),
    "sub_div": (
        [("Sub", per_channel(MEAN), "init"), ("Div", per_channel(STD), "init")],
        NCHW,
        "graph",
        1.0,
    ),
    "mul_add_constant_left": (
        [("Mul", per_channel(1 / STD), "left"), ("Add", per_channel(-MEAN / STD), "left")],
        NCHW,
        "graph",
        1.0,
    ),
    "div_then_sub": (
        [("Div", per_channel(STD), "init"), ("Sub", per_channel(MEAN / STD), "init")],
        NCHW,
        "graph",
        1.0,
    ),
    "constant_nodes_after_cast_and_resize": (
        [
            ("Cast",),
            ("Resize",),
            ("Sub", per_channel(MEAN), "node"),
            ("Div", per_channel(STD), "node"),
        ],
        NCHW,
        "graph",
        1.0,
    ),
    # NHWC input, transposed, constants in 0-255 units: the graph wants RGB in [0, 255].
    "nhwc_255_after_transpose": (
        [
            TO_NCHW,
            ("Sub", per_channel(255 * MEAN), "init"),
            ("Div", per_channel(255 * STD), "init"),
        ],
        NHWC,
        "graph",
        255.0,
    ),
    # The constants on the NHWC input itself (channels last), before the transpose.
    "nhwc_normalised_then_transposed": (
        [
            ("Sub", per_channel(MEAN, axis=3), "init"),
            ("Mul", per_channel(1 / STD, axis=3), "init"),
            TO_NCHW,
        ],
        NHWC,
        "graph",
        1.0,
    ),
    # As torch exports mean[None, :, None, None]; the input's size also read by a Shape node.
    "unsqueezed_and_reshaped_constants_with_a_shape_reader": (
        [
            ("Shape",),
            ("Sub", MEAN, "unsqueeze"),
            ("Div", STD, "reshape"),
        ],
        NCHW,
        "graph",
        1.0,
    ),
    # x/255 first, then the [0, 1] constants: also wants [0, 255].
    "scale_255_then_sub_div": (
        [
            ("Mul", np.float32(1 / 255), "init"),
            ("Sub", per_channel(MEAN), "init"),
            ("Div", per_channel(STD), "init"),
        ],
        NCHW,
        "graph",
        255.0,
    ),
}
