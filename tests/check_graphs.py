"""Tiny ONNX graphs for ``m360 models check`` and the model options: size rules, output shapes,
outputs made from the probe scene's true depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnx_graphs as g
from m360.estimators import _probe
from onnx import TensorProto, helper, numpy_helper


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", g.OPSET)])
    model.ir_version = g.IR_VERSION
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def unet(path: Path, levels: int = 5) -> Path:
    """A U-Net-like graph that runs only at multiples of 2**levels.

    The grey level goes down ``levels`` stride-2 convolutions and back up by x2 resizes, each
    added to the skip connection of its level: at a size that is not a multiple of 2**levels a
    stride-2 convolution rounds up, the x2 resize does not match the skip, and the Add fails
    (what FastDepth and PyDNet do).
    """
    box = np.full((1, 1, 3, 3), 1 / 9, np.float32)
    inits = [
        numpy_helper.from_array(box, "box"),
        numpy_helper.from_array(np.array([1, 1, 2, 2], np.float32), "x2"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
    ]
    nodes = [helper.make_node("ReduceMean", ["x"], ["f0"], axes=[1], keepdims=1)]
    for k in range(1, levels + 1):
        nodes.append(
            helper.make_node(
                "Conv", [f"f{k - 1}", "box"], [f"f{k}"], strides=[2, 2], pads=[1, 1, 1, 1]
            )
        )
    up = f"f{levels}"
    for k in range(levels - 1, -1, -1):
        nodes.append(helper.make_node("Resize", [up, "", "x2"], [f"r{k}"], mode="nearest"))
        nodes.append(helper.make_node("Add", [f"r{k}", f"f{k}"], [f"u{k}"]))
        up = f"u{k}"
    nodes.append(helper.make_node("Squeeze", [up, "axis1"], ["y"]))
    graph = helper.make_graph(
        nodes,
        "unet",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, "H", "W"])],
        initializer=inits,
    )
    return _save(graph, path)


def half_resolution(path: Path) -> Path:
    """output = mean RGB + 1, bilinearly halved: (1, H/2, W/2) for any size."""
    inits = [
        numpy_helper.from_array(np.array([1, 1, 0.5, 0.5], np.float32), "half"),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
    ]
    nodes = [
        helper.make_node("ReduceMean", ["x"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Add", ["m", "one"], ["m1"]),
        helper.make_node("Resize", ["m1", "", "half"], ["h"], mode="linear"),
        helper.make_node("Squeeze", ["h", "axis1"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "half",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, "H2", "W2"])],
        initializer=inits,
    )
    return _save(graph, path)


def only_at(path: Path, h: int, w: int) -> Path:
    """A dynamic-size graph that reshapes its input to (1, 3, h, w): it runs at no other size."""
    inits = [
        numpy_helper.from_array(np.array([1, 3, h, w], np.int64), "shape"),
        numpy_helper.from_array(np.array([1], np.int64), "axis1"),
    ]
    nodes = [
        helper.make_node("Reshape", ["x", "shape"], ["r"]),
        helper.make_node("ReduceMean", ["r"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Squeeze", ["m", "axis1"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "only_at",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, h, w])],
        initializer=inits,
    )
    return _save(graph, path)


ORACLE_SIZE = (64, 80)


def oracle(path: Path, transform: str) -> Path:
    """A fixed 64x80 graph whose output is ``transform`` of the first probe view's true depth.

    It ignores its image (0 x its mean is added so that the input is used): what a perfect
    network outputs on that view, and close to it on the others (they overlap).
    """
    z = _probe.depth_at(_probe.views((240, 280))[0][1], ORACLE_SIZE).astype(np.float64)
    value = {
        "depth": z,
        "disparity": 1 / z,
        "negative_depth": z - 20.0,  # negative, growing with depth (PyDNet-like)
        "negative_disparity": -1 / z,  # negative, growing with depth too
        "scaled_depth": 40.0 * z + 100.0,  # grows with depth, far from metres
        "flat": np.full_like(z, 2.0),
    }[transform].astype(np.float32)
    return g.constant_output(path, value, "oracle")
