"""Upsampling an ERP disparity map from a working resolution to the photo's, along its edges.

:func:`guided_upsample` is a fast guided filter (He & Sun, "Fast Guided Filter", 2015): the
local linear model ``disparity ≈ a · grey + b`` of the guided filter is fitted at the working
resolution, against the photo's grey image shrunk to that size, and its coefficients are
interpolated to the full resolution and applied to the full-resolution grey image. A depth
edge that is also an edge in the photo is thus placed where the photo puts it, not smeared over
the width of a working-resolution pixel as bilinear interpolation does.

Where the disparity is smooth, the photo's texture would only leak into it (a textured wall
would get a textured depth), so the guided model is used only where the working-resolution
disparity jumps (relative range over a 3 × 3 window above ``edge_low``, fully above
``edge_high``); elsewhere, and within a pixel of an invalid one, the result is plain bilinear
interpolation. Everything is NaN-aware (invalid pixels weigh nothing and stay invalid) and
wraps at longitude ±180° (column 0 neighbours column W − 1), following docs/conventions.md.

The model is fitted on whole working-resolution arrays with OpenCV (box filters, min/max
filters); the full-resolution pass is one parallel sweep in the core
(``_core.upsample_planes``, separable, reading the guided model only near depth jumps; faster
than OpenCV warps plus numpy expressions, with exact positions: benches/bench_bigpano.py), which
allocates nothing beyond the output.
"""

from __future__ import annotations

import cv2
import numpy as np

from . import _core
from ._validate import as_array
from .errors import InputError

__all__ = ["UPSAMPLE_METHODS", "guided_upsample"]

#: Methods of :func:`guided_upsample`: ``"guided"`` (edge-aware, the default) and
#: ``"bilinear"`` (plain NaN-aware bilinear, wrapping at the seam).
UPSAMPLE_METHODS = ("guided", "bilinear")


def _wrap_columns(image: np.ndarray, pad: int) -> np.ndarray:
    """``image`` with ``pad`` columns of the other side appended at each side (longitude wrap)."""
    return np.concatenate([image[:, -pad:], image, image[:, :pad]], axis=1)


def _box(image: np.ndarray, radius: int) -> np.ndarray:
    """Mean over (2r+1)² windows, wrapping in longitude, reflecting at the pole rows.

    ``image`` is (h, w) or (h, w, C): each channel is filtered alone.
    """
    size = 2 * radius + 1
    padded = _wrap_columns(image, radius)
    out = cv2.boxFilter(padded, -1, (size, size), borderType=cv2.BORDER_REFLECT)
    return np.ascontiguousarray(out[:, radius:-radius], dtype=np.float32)


def _grey_u8(rgb: np.ndarray) -> np.ndarray:
    """Grey levels 0-255 (uint8, C-contiguous) of an RGB uint8 or float [0, 1] image."""
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.asarray(rgb, np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def _edge_weight(
    disparity: np.ndarray, valid: np.ndarray, low: float, high: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the edge weight, and the 3 × 3 minimum and maximum (0 near invalid).

    The weight is 0 where the disparity is smooth, 1 across a jump (relative range in 3 × 3),
    and 0 within a pixel of an invalid one.
    """
    kernel = np.ones((3, 3), np.uint8)
    big = np.float32(np.finfo(np.float32).max)
    hi = cv2.dilate(_wrap_columns(np.where(valid, disparity, -big), 1), kernel)[:, 1:-1]
    lo = cv2.erode(_wrap_columns(np.where(valid, disparity, big), 1), kernel)[:, 1:-1]
    all_valid = cv2.erode(_wrap_columns(valid.astype(np.uint8), 1), kernel)[:, 1:-1] > 0
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        jump = (hi - lo) / np.maximum(np.abs(hi), np.abs(lo))
        weight = np.clip((jump - low) / (high - low), 0.0, 1.0)
    edge = np.where(all_valid & np.isfinite(weight), weight, 0.0).astype(np.float32)
    return (
        edge,
        np.where(all_valid, lo, 0).astype(np.float32),
        np.where(all_valid, hi, 0).astype(np.float32),
    )


def guided_upsample(
    disparity: np.ndarray,
    guide: np.ndarray,
    *,
    method: str = "guided",
    radius: int = 1,
    eps: float = 1e-4,
    edge_low: float = 0.05,
    edge_high: float = 0.15,
) -> np.ndarray:
    """Upsample an ERP disparity map (h, w) to the size of the ERP photo ``guide`` (H, W, 3).

    Parameters
    ----------
    disparity : (h, w) float array, w == 2h
        The map at the working resolution; NaN = invalid.
    guide : (H, W, 3) uint8 or float RGB, W == 2H, H >= h
        The full-resolution photo.
    method : {"guided", "bilinear"}
        ``"guided"``: the fast guided filter near disparity jumps, bilinear elsewhere (see the
        module documentation); ``"bilinear"``: plain bilinear interpolation.
    radius : int
        Window radius of the guided filter, in working-resolution pixels (>= 1).
    eps : float
        Regularisation of the guided filter (> 0), in squared grey levels of [0, 1]: larger
        follows the photo's weaker edges less.
    edge_low, edge_high : float
        Relative disparity jumps (range / largest value in a 3 × 3 window) at which the guided
        model starts to be used and at which it is used alone (0 <= low < high).

    Returns
    -------
    (H, W) float32
        NaN where the working-resolution map has no valid pixel within interpolation reach.
    """
    disp = as_array(disparity, "disparity")
    img = as_array(guide, "guide")
    if disp.ndim != 2 or disp.shape[1] != 2 * disp.shape[0] or disp.shape[0] < 2:
        raise InputError(f"disparity must be an ERP map (h, 2h), got shape {disp.shape}")
    if disp.dtype.kind != "f":
        raise InputError(f"disparity must be a float array, got dtype {disp.dtype}")
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[1] != 2 * img.shape[0]:
        raise InputError(f"guide must be an ERP RGB photo (H, 2H, 3), got shape {img.shape}")
    if img.shape[0] < disp.shape[0]:
        raise InputError(
            f"guide ({img.shape[0]}x{img.shape[1]}) is smaller than the disparity "
            f"({disp.shape[0]}x{disp.shape[1]}): nothing to upsample"
        )
    if method not in UPSAMPLE_METHODS:
        raise InputError(f"upsample method {method!r} is not one of {UPSAMPLE_METHODS}")
    if not (isinstance(radius, int) and radius >= 1):
        raise InputError(f"radius must be an integer >= 1, got {radius!r}")
    if not (np.isfinite(eps) and eps > 0):
        raise InputError(f"eps must be a positive number, got {eps!r}")
    if not (0 <= edge_low < edge_high):
        raise InputError(f"need 0 <= edge_low < edge_high, got {edge_low!r}, {edge_high!r}")

    h, w = disp.shape
    height, width = img.shape[:2]
    p = np.asarray(disp, np.float32)
    valid = np.isfinite(p)
    p0 = np.where(valid, p, np.float32(0))
    m = valid.astype(np.float32)
    if method == "bilinear":
        planes = np.dstack([p0, m])
        return _core.upsample_planes(np.ascontiguousarray(planes, np.float32), (height, width))
    grey_full = _grey_u8(img)
    grey = cv2.resize(grey_full, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    # The five window sums of the fit in one multi-channel box filter.
    mg = m * grey
    sums = _box(np.dstack([m, mg, p0, mg * p0, mg * grey]), radius)
    n = sums[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_i, mean_p, mean_ip, mean_ii = (sums[..., k] / n for k in range(1, 5))
        a = (mean_ip - mean_i * mean_p) / (np.maximum(mean_ii - mean_i * mean_i, 0) + eps)
        b = mean_p - a * mean_i
    fitted = n > 0
    coefficients = _box(np.dstack([fitted, np.where(fitted, a, 0), np.where(fitted, b, 0)]), radius)
    count = coefficients[..., 0]
    planes = np.empty((h, w, 7), np.float32)
    planes[..., 0], planes[..., 1] = p0, m
    with np.errstate(invalid="ignore", divide="ignore"):
        for k in (1, 2):  # the window means of a and b: the fast guided filter's coefficients
            planes[..., 2 + k] = np.where(count > 0, coefficients[..., k] / count, 0)
    planes[..., 2], planes[..., 5], planes[..., 6] = _edge_weight(p, valid, edge_low, edge_high)
    # The full-resolution pass (one parallel sweep in the core): bilinear p0/m moved towards
    # clamp(a·I + b, lo, hi) by the edge weight; never beyond the values around the pixel.
    return _core.upsample_planes(planes, (height, width), grey_full)
