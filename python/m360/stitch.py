"""The stitching core: per-tangent perspective disparity in, one ERP spherical disparity out."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._validate import as_array, check_shape
from .errors import InputError
from .geometry import Layout, check_tiles, plan_for

__all__ = ["ALIGN_MODES", "BLEND_MODES", "StitchResult", "stitch"]

#: Alignment modes implemented in this version.
ALIGN_MODES = ("none",)
#: Blend modes implemented in this version.
BLEND_MODES = ("mean", "nn")
_PLANNED_ALIGN = ("multiscale",)
_PLANNED_BLEND = ("poisson", "frustum", "radial")


@dataclass
class StitchResult:
    """Everything :func:`stitch` knows about one stitch.

    Attributes
    ----------
    disparity : (H, W) float32
        Spherical disparity (1/distance up to the tangents' common scale and shift); NaN where
        no tangent has a valid estimate.
    confidence : (H, W) float32
        Overlap disagreement: the standard deviation of the (aligned) tangents' values at each
        pixel, 0 where one tangent sees it, NaN where none does. Lower means more consistent.
    coverage : (H, W) uint8
        Number of tangents whose image contains each pixel.
    grids : list
        Alignment grids per level (empty with ``align="none"``).
    report : dict
        Solver reports per stage (empty with ``align="none"`` and the simple blends).
    timings : dict
        Seconds per stage: ``convert``, ``align``, ``blend``.
    """

    disparity: np.ndarray
    confidence: np.ndarray
    coverage: np.ndarray
    grids: list[Any] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


def stitch(
    tangent_disparity: np.ndarray,
    layout: Layout,
    align: str = "multiscale",
    blend: str = "poisson",
    *,
    mask: np.ndarray | None = None,
    return_details: bool = False,
) -> np.ndarray | StitchResult:
    """Stitch per-tangent perspective disparity into one ERP spherical disparity map.

    Each tangent value is first converted from perspective disparity (1/z, what a monocular
    network predicts up to scale and shift) to spherical disparity (1/distance) with its own
    pixel's ray length, then mapped to the ERP grid (bilinear at the exact projected position)
    and blended.

    Parameters
    ----------
    tangent_disparity : (N, h, w) float32
        One perspective disparity map per camera of ``layout``; NaN marks pixels without an
        estimate. float64 is converted.
    layout : Layout
        The layout the tangents were made with.
    align : str
        ``"none"``: values pass through unchanged (no standardisation). ``"multiscale"`` (the
        default of the method) comes with the alignment module; until then it raises InputError.
    blend : str
        ``"mean"``: average of every tangent that sees the pixel. ``"nn"``: the tangent whose
        un-padded face contains the pixel (falling back to the next nearest face where that one
        has no valid value). ``"poisson"`` and the weighted blends come with the blending module.
    mask : (N, h, w) bool, optional
        False marks pixels with no estimate (sky, tripod). They never contribute, not even
        through a bilinear neighbour.
    return_details : bool
        Return a :class:`StitchResult` instead of the disparity array.

    Returns
    -------
    (H, W) float32 spherical disparity, NaN where no tangent has a valid value; or a
    StitchResult.
    """
    t0 = time.perf_counter()
    tiles = check_tiles(tangent_disparity, layout, "tangent_disparity")
    align = _mode(align, "align", ALIGN_MODES, _PLANNED_ALIGN)
    blend = _mode(blend, "blend", BLEND_MODES, _PLANNED_BLEND)
    valid = None if mask is None else _check_mask(mask, layout)
    if not isinstance(return_details, bool):
        raise InputError(f"return_details must be True or False, got {return_details!r}")

    plan = plan_for(layout)
    spherical = plan.spherical_disparity(tiles, valid)
    t1 = time.perf_counter()
    t2 = t1  # alignment: "none" passes the values through
    disparity, spread = plan.blend(spherical, blend)
    t3 = time.perf_counter()
    if not return_details:
        return disparity
    return StitchResult(
        disparity=disparity,
        confidence=spread,
        coverage=plan.coverage(),
        timings={"convert": t1 - t0, "align": t2 - t1, "blend": t3 - t2},
    )


def _mode(value: object, name: str, available: tuple[str, ...], planned: tuple[str, ...]) -> str:
    if isinstance(value, str) and value in available:
        return value
    options = ", ".join(repr(v) for v in available)
    if isinstance(value, str) and value in planned:
        raise InputError(f"{name}={value!r} is not available in this version yet; use {options}")
    raise InputError(f"{name}={value!r} is not supported; choose one of {options}")


def _check_mask(mask: np.ndarray, layout: Layout) -> np.ndarray:
    array = as_array(mask, "mask")
    h, w = layout.tangent_shape
    check_shape(array, "mask", ("N", "h", "w"), N=len(layout), h=h, w=w)
    if array.dtype != np.bool_:
        raise InputError(
            f"mask must be a bool array (False = no estimate), got dtype {array.dtype}"
        )
    return np.ascontiguousarray(array)
