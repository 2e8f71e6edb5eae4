"""What an estimator outputs, and its conversion to the perspective disparity m360 stitches.

An estimator declares one ``output_kind`` (docs/architecture.md, estimators):

- ``"affine_disparity"``: perspective disparity 1/z up to an unknown scale and shift (MiDaS, DPT,
  Depth Anything relative models: the paper's assumption); passed through;
- ``"metric_depth"``: z-depth in metres (a metric model); perspective disparity = 1/z;
- ``"distance"``: radial distance |P| in metres; perspective disparity = |q| / distance with the
  pixel ray ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` (docs/conventions.md).
"""

from __future__ import annotations

import functools
from typing import Any, Literal

import numpy as np

from .._validate import as_array
from ..errors import InputError
from ..geometry.layout import Layout, plan_for

__all__ = [
    "OUTPUT_KINDS",
    "OutputKind",
    "check_output_kind",
    "ray_norms",
    "to_perspective_disparity",
]

#: What an estimator may declare it outputs.
OutputKind = Literal["affine_disparity", "metric_depth", "distance"]
OUTPUT_KINDS: tuple[str, ...] = ("affine_disparity", "metric_depth", "distance")


def check_output_kind(kind: Any, name: str = "output_kind") -> OutputKind:
    """``kind`` if it is one of :data:`OUTPUT_KINDS`, else :class:`m360.InputError`.

    Parameters
    ----------
    kind : object
        The declared kind.
    name : str
        How the message names it.

    Returns
    -------
    str
        ``kind``.
    """
    if not isinstance(kind, str) or kind not in OUTPUT_KINDS:
        options = ", ".join(repr(k) for k in OUTPUT_KINDS)
        raise InputError(f"{name}={kind!r} is not supported; choose one of {options}")
    return kind  # type: ignore[return-value]


@functools.lru_cache(maxsize=8)
def _ray_norms_cached(layout: Layout) -> np.ndarray:
    norms = np.array(plan_for(layout).ray_lengths())
    norms.flags.writeable = False
    return norms


def ray_norms(layout: Layout) -> np.ndarray:
    """|q| of every tangent pixel: (N, h, w), read-only, ≥ 1 (computed by the core).

    ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` for the pixel centre (x = column, y = row) of each
    camera (docs/conventions.md); perspective disparity 1/z equals ``|q| / distance``.

    Parameters
    ----------
    layout : Layout
        The tangent layout.

    Returns
    -------
    numpy.ndarray
        (N, h, w) ray lengths.
    """
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    return _ray_norms_cached(layout)


def to_perspective_disparity(values: np.ndarray, kind: str, layout: Layout) -> np.ndarray:
    """Convert an estimator's output of the declared ``kind`` to perspective disparity.

    Parameters
    ----------
    values : (N, h, w) float array
        One map per camera of ``layout``; NaN = no estimate.
    kind : str
        ``"affine_disparity"`` (returned as float32 unchanged), ``"metric_depth"`` (z-depth:
        1/z) or ``"distance"`` (radial: |q| / distance).
    layout : Layout

    Returns
    -------
    (N, h, w) float32 perspective disparity; NaN where the input is NaN, and for depths where
    the value is not > 0.
    """
    check_output_kind(kind)
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    array = as_array(values, "estimator output")
    h, w = layout.tangent_shape
    if array.shape != (len(layout), h, w):
        raise InputError(
            f"estimator output has shape {array.shape}, expected {(len(layout), h, w)} (N, h, w)"
        )
    if kind == "affine_disparity":
        with np.errstate(over="ignore"):  # beyond float32: inf, which stitch() refuses
            return np.ascontiguousarray(array, dtype=np.float32)
    depth = array.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        numerator = 1.0 if kind == "metric_depth" else ray_norms(layout)
        out = np.where(depth > 0, numerator / depth, np.nan).astype(np.float32)
    # A depth so small that its disparity overflows float32 is no estimate either.
    out[np.isinf(out)] = np.nan
    return out
