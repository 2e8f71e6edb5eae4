"""The guided upsampling's working-resolution fit as it was before it moved into the core.

Whole-array numpy + OpenCV, as ``m360.upsample.guided_upsample`` computed it: the oracle of
``tests/test_guided_fit.py`` and the baseline of ``benches/bench_upsample.py``.
"""

from __future__ import annotations

import cv2
import numpy as np


def _wrap_columns(image: np.ndarray, pad: int) -> np.ndarray:
    """``image`` with ``pad`` columns of the other side appended at each side (longitude wrap)."""
    return np.concatenate([image[:, -pad:], image, image[:, :pad]], axis=1)


def _box(image: np.ndarray, radius: int, dtype: type) -> np.ndarray:
    """Mean over (2r+1)² windows, wrapping in longitude, reflecting at the pole rows."""
    size = 2 * radius + 1
    padded = _wrap_columns(image, radius)
    out = cv2.boxFilter(padded, -1, (size, size), borderType=cv2.BORDER_REFLECT)
    return np.ascontiguousarray(out[:, radius:-radius], dtype=dtype)


def _edge_weight(
    disparity: np.ndarray, valid: np.ndarray, low: float, high: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the edge weight, and the 3 × 3 minimum and maximum (0 near invalid)."""
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


def oracle_planes(
    disp: np.ndarray,
    grey_small: np.ndarray,
    radius: int,
    eps: float,
    edge_low: float,
    edge_high: float,
    dtype: type = np.float32,
) -> np.ndarray:
    """The planes (p0, m, e, a, b, lo, hi) as the former whole-array fit computed them.

    ``dtype=np.float32`` is that code exactly; ``np.float64`` runs its box filters and fit in
    double precision (the edge weight stays float32, as the core computes it).
    """
    h, w = disp.shape
    p = np.asarray(disp, np.float32)
    valid = np.isfinite(p)
    p0 = np.where(valid, p, np.float32(0))
    m = valid.astype(np.float32)
    grey = grey_small.astype(np.float32) / 255
    p0d, md, greyd = (x.astype(dtype) for x in (p0, m, grey))
    mg = md * greyd
    sums = _box(np.dstack([md, mg, p0d, mg * p0d, mg * greyd]), radius, dtype)
    n = sums[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_i, mean_p, mean_ip, mean_ii = (sums[..., k] / n for k in range(1, 5))
        a = (mean_ip - mean_i * mean_p) / (np.maximum(mean_ii - mean_i * mean_i, 0) + eps)
        b = mean_p - a * mean_i
    fitted = n > 0
    coefficients = _box(
        np.dstack([fitted.astype(dtype), np.where(fitted, a, 0), np.where(fitted, b, 0)]),
        radius,
        dtype,
    )
    count = coefficients[..., 0]
    planes = np.empty((h, w, 7), np.float32)
    planes[..., 0], planes[..., 1] = p0, m
    with np.errstate(invalid="ignore", divide="ignore"):
        for k in (1, 2):  # the window means of a and b: the fast guided filter's coefficients
            planes[..., 2 + k] = np.where(count > 0, coefficients[..., k] / count, 0)
    planes[..., 2], planes[..., 5], planes[..., 6] = _edge_weight(p, valid, edge_low, edge_high)
    return planes


def old_guided_upsample(
    disparity: np.ndarray,
    guide: np.ndarray,
    *,
    method: str = "guided",
    radius: int = 1,
    eps: float = 1e-4,
    edge_low: float = 0.05,
    edge_high: float = 0.15,
) -> np.ndarray:
    """``m360.upsample.guided_upsample`` before the fit moved into the core (uint8 guides)."""
    from m360 import _core

    h, w = disparity.shape
    height, width = guide.shape[:2]
    if method == "bilinear":
        p = np.asarray(disparity, np.float32)
        valid = np.isfinite(p)
        planes = np.dstack([np.where(valid, p, np.float32(0)), valid.astype(np.float32)])
        return _core.upsample_planes(np.ascontiguousarray(planes, np.float32), (height, width))
    grey_full = np.ascontiguousarray(cv2.cvtColor(guide, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
    grey = cv2.resize(grey_full, (w, h), interpolation=cv2.INTER_AREA)
    planes = oracle_planes(disparity, grey, radius, eps, edge_low, edge_high)
    return _core.upsample_planes(planes, (height, width), grey_full)
