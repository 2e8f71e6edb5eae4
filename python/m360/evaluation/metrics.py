"""The paper's depth metrics on ERP maps (docs/method.md, evaluation).

The prediction is a disparity known up to scale and shift: fit both by least squares against the
ground-truth disparity 1/depth over the valid pixels, convert the fitted disparity to depth, then
compute AbsRel, MAE, RMSE, RMSE-log (base 10, as the paper), δ<1.25, δ<1.25², δ<1.25³.
Optionally exclude a cap around each pole and weight pixels by solid angle (cos latitude).
:func:`edge_band` selects the pixels near true depth edges, to measure detail there
(``depth_metrics(..., valid=edge_band(depth))``).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from m360._validate import as_array, integer, number, one_of, real_array
from m360.errors import InputError

if TYPE_CHECKING:
    from m360.geometry.layout import Layout

__all__ = ["depth_metrics", "edge_band", "fit_scale_shift", "format_metrics", "seam_score"]

WEIGHTINGS = ("uniform", "solid_angle")
DISPARITY_FLOOR = 1e-3
"""Fitted disparities are clamped below at ``DISPARITY_FLOOR x min(GT disparity over valid)``."""


def fit_scale_shift(
    pred_disparity: np.ndarray,
    gt_disparity: np.ndarray,
    weights: np.ndarray | None = None,
) -> tuple[float, float]:
    """Weighted least-squares scale and shift mapping a prediction onto ground truth.

    Minimises ``Σ w (s·pred + o - gt)²`` with float64 accumulation (centred normal equations).

    Parameters
    ----------
    pred_disparity, gt_disparity : np.ndarray
        Arrays of one shape, finite (mask invalid pixels out before calling).
    weights : np.ndarray, optional
        Same shape, finite and ≥ 0 with a positive sum; 1 everywhere when omitted.

    Returns
    -------
    scale, shift : float
        The minimiser. When the prediction is constant over the positive-weight pixels the
        problem is degenerate; the minimum-norm solution ``scale = 0``, ``shift = weighted mean of
        gt`` is returned.
    """
    p = real_array(pred_disparity, "pred_disparity")
    g = real_array(gt_disparity, "gt_disparity")
    if p.shape != g.shape:
        raise InputError(
            f"pred_disparity and gt_disparity must have the same shape, got {p.shape} and {g.shape}"
        )
    if p.size == 0:
        raise InputError("cannot fit scale and shift on empty arrays: expected at least 1 value")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(g))):
        raise InputError("pred_disparity and gt_disparity must be finite: mask invalid pixels out")
    if weights is None:
        w = np.ones_like(p)
    else:
        w = real_array(weights, "weights")
        if w.shape != p.shape:
            raise InputError(f"weights must have shape {p.shape}, got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise InputError("weights must be finite and >= 0")
    # Solve in units of each array's largest magnitude, so no sum overflows near float64's range.
    p_unit, g_unit, w_unit = (_unit(a) for a in (p, g, w))
    p, g, w = p / p_unit, g / g_unit, w / w_unit
    wsum = w.sum()
    if not wsum > 0:
        raise InputError("weights must have a positive sum, got 0")
    p_mean = (w * p).sum() / wsum
    g_mean = (w * g).sum() / wsum
    dp = p - p_mean
    var = (w * dp * dp).sum()
    if var <= 0 or var <= 1e-300 * wsum:
        return 0.0, float(g_mean * g_unit)
    scale = (w * dp * (g - g_mean)).sum() / var
    with np.errstate(over="ignore"):
        scale_out = scale * (g_unit / p_unit)
        shift_out = (g_mean - scale * p_mean) * g_unit
    if not (np.isfinite(scale_out) and np.isfinite(shift_out)):
        raise InputError(
            "the scale and shift mapping pred_disparity onto gt_disparity are beyond the float64 "
            f"range (magnitudes {p_unit:.3g} and {g_unit:.3g})"
        )
    return float(scale_out), float(shift_out)


def _unit(array: np.ndarray) -> float:
    """Largest magnitude of ``array`` (1 for an all-zero array)."""
    top = float(np.max(np.abs(array)))
    return top if top > 0 else 1.0


def _row_latitudes_deg(height: int) -> np.ndarray:
    return 90.0 - 180.0 * (np.arange(height, dtype=np.float64) + 0.5) / height


def depth_metrics(
    pred_disparity: np.ndarray,
    gt_depth: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    pole_cap_deg: float = 0.0,
    weighting: str = "uniform",
) -> dict[str, float]:
    """Scale/shift-aligned depth metrics of an ERP disparity prediction, as in the paper.

    Valid pixels: ground-truth depth finite and > 0, prediction finite, ``valid`` true (if given),
    and row-centre latitude within ``±(90° - pole_cap_deg)`` (rows follow the ERP convention
    of docs/conventions.md: row i has latitude ``90° - 180° (i + 0.5) / H``). Scale s and shift
    o are fitted by weighted least squares of ``s·pred + o`` against ``1/gt_depth`` over the valid
    pixels; the fitted disparity is clamped below at ``1e-3 x min(1/gt_depth)`` over the valid
    pixels (so a fitted value ≤ 0 becomes a very far but finite depth) and inverted to depth. Every
    metric then averages over the valid pixels with weights 1 (``"uniform"``) or cos(latitude)
    (``"solid_angle"``, each pixel weighted by the solid angle it covers).

    Parameters
    ----------
    pred_disparity : np.ndarray
        (H, W) float prediction, disparity up to an unknown scale and shift; NaN = no prediction.
    gt_depth : np.ndarray
        (H, W) float ground-truth radial depth; NaN, inf or ≤ 0 = invalid. W must equal 2H.
    valid : np.ndarray, optional
        (H, W) bool, extra mask (True = evaluate).
    pole_cap_deg : float
        Radius in degrees of latitude of the cap excluded around each pole, in [0, 90).
    weighting : str
        ``"uniform"`` (the paper) or ``"solid_angle"``.

    Returns
    -------
    dict[str, float]
        ``abs_rel`` mean |D-G|/G; ``mae`` mean |D-G|; ``rmse`` sqrt(mean (D-G)²); ``rmse_log10``
        sqrt(mean (log10 D - log10 G)²) (base 10 as the paper, ≈ ln-based value / 2.303);
        ``delta1``/``delta2``/``delta3`` fraction with max(D/G, G/D) < 1.25, 1.25², 1.25³;
        ``scale``, ``shift`` of the fit; ``n_valid`` (int) pixels evaluated; ``coverage`` fraction
        of ground-truth-valid pixels (valid GT, mask, outside the caps) with a finite prediction.
    """
    pred = as_array(pred_disparity, "pred_disparity")
    gt = as_array(gt_depth, "gt_depth")
    if pred.ndim != 2 or gt.ndim != 2:
        raise InputError(
            f"pred_disparity and gt_depth must be 2-D (H, W) ERP maps, got {pred.shape} and "
            f"{gt.shape}"
        )
    if pred.shape != gt.shape:
        raise InputError(f"shape mismatch: pred_disparity {pred.shape} vs gt_depth {gt.shape}")
    h, w = gt.shape
    if h < 1 or w != 2 * h:
        raise InputError(f"ERP maps must have W == 2H, got (H, W) = {gt.shape}")
    for name, arr in (("pred_disparity", pred), ("gt_depth", gt)):
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise InputError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    weighting = one_of(weighting, "weighting", WEIGHTINGS)
    try:
        cap = number(pole_cap_deg, "pole_cap_deg", low=0.0, high=90.0)
    except InputError:
        cap = 90.0
    if cap == 90.0:
        raise InputError(f"pole_cap_deg must be in [0, 90) degrees, got {pole_cap_deg!r}")

    pred = pred.astype(np.float64, copy=False)
    gt = gt.astype(np.float64, copy=False)
    lat = _row_latitudes_deg(h)
    rows_in = np.abs(lat) <= 90.0 - cap
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        # Depths below ~5.6e-309 have no finite disparity 1/depth: invalid like depth <= 0.
        gt_ok = np.isfinite(gt) & (gt > 0) & np.isfinite(1.0 / gt) & rows_in[:, None]
    if valid is not None:
        m = as_array(valid, "valid")
        if m.shape != gt.shape:
            raise InputError(f"valid must have shape {gt.shape}, got {m.shape}")
        if m.dtype != np.bool_:
            raise InputError(f"valid must be a bool array, got dtype {m.dtype}")
        gt_ok &= m
    n_gt = int(gt_ok.sum())
    if n_gt == 0:
        raise InputError("no valid ground-truth pixel: expected at least 1 (check mask and caps)")
    sel = gt_ok & np.isfinite(pred)
    n_valid = int(sel.sum())
    if n_valid == 0:
        raise InputError("no valid pixel: the prediction is NaN/inf wherever ground truth is valid")

    g = gt[sel]
    p = pred[sel]
    if weighting == "solid_angle":
        wts = np.broadcast_to(np.cos(np.deg2rad(lat))[:, None], gt.shape)[sel]
    else:
        wts = np.ones(n_valid)
    gd = 1.0 / g
    scale, shift = fit_scale_shift(p, gd, wts)
    wsum = wts.sum()

    def mean(x: np.ndarray) -> float:
        return float((wts * x).sum() / wsum)

    # Near float64's limits the fitted depths may overflow: the metrics are then inf, not NaN.
    with np.errstate(over="ignore", divide="ignore", under="ignore"):
        fitted = np.maximum(scale * p + shift, DISPARITY_FLOOR * gd.min())
        d = 1.0 / fitted
        err = d - g
        ratio = np.maximum(d / g, g / d)
        return {
            "abs_rel": mean(np.abs(err) / g),
            "mae": mean(np.abs(err)),
            "rmse": float(np.sqrt(mean(err * err))),
            "rmse_log10": float(np.sqrt(mean((np.log10(d) - np.log10(g)) ** 2))),
            "delta1": mean(ratio < 1.25),
            "delta2": mean(ratio < 1.25**2),
            "delta3": mean(ratio < 1.25**3),
            "scale": scale,
            "shift": shift,
            "n_valid": n_valid,
            "coverage": n_valid / n_gt,
        }


_FORMAT = (
    ("abs_rel", "AbsRel", "{:.4f}"),
    ("mae", "MAE", "{:.4f}"),
    ("rmse", "RMSE", "{:.4f}"),
    ("rmse_log10", "RMSElog10", "{:.4f}"),
    ("delta1", "d1", "{:.4f}"),
    ("delta2", "d2", "{:.4f}"),
    ("delta3", "d3", "{:.4f}"),
    ("n_valid", "n", "{:d}"),
    ("coverage", "cov", "{:.2%}"),
)


def format_metrics(metrics: Mapping[str, float]) -> str:
    """One-line summary of :func:`depth_metrics` output (keys that are absent are skipped).

    Parameters
    ----------
    metrics : Mapping[str, float]

    Returns
    -------
    str
        e.g. ``"AbsRel 0.0512  MAE 0.1200  RMSE 0.2100  RMSElog10 0.0300  d1 0.9600 ..."``.
    """
    parts = []
    for key, label, fmt in _FORMAT:
        if key in metrics:
            value = metrics[key]
            parts.append(f"{label} {fmt.format(int(value) if fmt == '{:d}' else float(value))}")
    return "  ".join(parts)


# --------------------------------------------------------------------------------------------
# Seams.

_SEAM_MASKS: OrderedDict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
_SEAM_LOCK = threading.Lock()


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Square dilation by ``radius`` px, wrapping in longitude, not across the top/bottom."""
    out = mask.copy()
    for dx in range(-radius, radius + 1):
        if dx:
            out |= np.roll(mask, dx, axis=1)
    grown = out.copy()
    for dy in range(1, radius + 1):
        grown[dy:] |= out[:-dy]
        grown[:-dy] |= out[dy:]
    return grown  # type: ignore[no-any-return]  # numpy stubs: Any


def _edges(labels: np.ndarray) -> np.ndarray:
    """Mark the pixels whose right or lower neighbour (right wraps) has another label.

    The neighbours are marked too.
    """
    right = labels != np.roll(labels, -1, axis=1)
    down = np.zeros_like(right)
    down[:-1] = labels[:-1] != labels[1:]
    edge = right | down
    edge |= np.roll(right, 1, axis=1)
    edge[1:] |= down[:-1]
    return edge  # type: ignore[no-any-return]  # numpy stubs: Any


def _seam_masks(layout: Layout, band: int) -> tuple[np.ndarray, np.ndarray]:
    from m360.geometry.layout import plan_for

    key = (layout.key, band)
    with _SEAM_LOCK:
        if key in _SEAM_MASKS:
            _SEAM_MASKS.move_to_end(key)
            return _SEAM_MASKS[key]
    plan = plan_for(layout)
    n = len(layout)
    h, w = layout.tangent_shape
    borders = np.zeros(layout.erp_shape, bool)
    nearest = {"method": "nn"}
    tangents = np.full((n, h, w), np.nan, np.float32)
    for k in range(n):
        tangents[k] = 1.0
        inside = np.isfinite(plan.blend(tangents, nearest, confidence=False)[0])
        tangents[k] = np.nan
        borders |= _edges(inside)
    ids = np.broadcast_to(np.arange(n, dtype=np.float32)[:, None, None], (n, h, w))
    owner = np.rint(plan.blend(np.ascontiguousarray(ids), nearest, confidence=False)[0])
    masks = (_dilate(borders, band), _dilate(_edges(owner), band))
    with _SEAM_LOCK:
        _SEAM_MASKS[key] = masks
        while len(_SEAM_MASKS) > 4:
            _SEAM_MASKS.popitem(last=False)
    return masks


def edge_band(depth: np.ndarray, band: int = 4, jump: float = 0.05) -> np.ndarray:
    """Pixels within ``band`` px of a true depth edge: an (H, W) bool mask.

    An edge is a relative jump of more than ``jump`` in disparity 1/depth between a pixel and
    its right neighbour (column W − 1's is column 0) or the one below; the edges are then
    dilated by a (2·band + 1)² square, which wraps in longitude (an edge at column 0 marks
    columns W − band … W − 1 too) and stops at the poles. This is the "4 px band around depth
    edges" of ``benches/bench_prior.py`` and ``benches/bench_edges.py``.
    """
    import cv2

    gt = as_array(depth, "depth")
    if gt.ndim != 2 or gt.dtype.kind != "f":
        raise InputError(f"depth must be a 2-D float map, got {gt.dtype} of shape {gt.shape}")
    band = integer(band, "band", 0, 1000)
    jump = number(jump, "jump", 0.0)
    disparity = 1.0 / gt
    right = np.abs(np.diff(disparity, axis=1, append=disparity[:, :1])) / disparity
    down = np.abs(np.diff(disparity, axis=0, append=disparity[-1:])) / disparity
    edges = ((right > jump) | (down > jump)).astype(np.uint8)
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    reach = min(band, edges.shape[1])
    wrapped = cv2.copyMakeBorder(edges, 0, 0, reach, reach, cv2.BORDER_WRAP)
    dilated = cv2.dilate(wrapped, kernel)
    return np.asarray(dilated[:, reach : reach + edges.shape[1]], dtype=bool)


def seam_score(
    pred_disparity: np.ndarray,
    gt_disparity: np.ndarray,
    layout: Layout,
    *,
    band: int = 2,
) -> dict[str, float]:
    """How much worse a stitch's gradients are along tangent seams than elsewhere.

    The prediction is first mapped onto the ground truth by the least-squares scale and shift
    (:func:`fit_scale_shift`, over pixels where both are finite). The gradient error of a pixel
    is ``|∇(s·pred + o) - ∇gt|`` with forward differences on the ERP grid (the horizontal one
    wraps from column W-1 to 0, the vertical one stops at the last row). It is averaged within
    ``band`` ERP pixels of the tangent-image borders, within ``band`` pixels of the face
    triangles (the boundaries of the nearest-face partition), and elsewhere (outside both).

    Parameters
    ----------
    pred_disparity : (H, W) float array
        Stitched disparity (any scale and shift); NaN = no prediction.
    gt_disparity : (H, W) float array
        Ground-truth disparity (1/depth); NaN = invalid.
    layout : Layout
        The layout of the stitch (``layout.erp_shape == (H, W)``).
    band : int
        Half-width of the seam bands in ERP pixels (default 2).

    Returns
    -------
    dict[str, float]
        ``borders`` and ``triangles``: mean gradient error in that band divided by the mean
        elsewhere (1 = no visible seam, larger = seams); ``elsewhere``: the mean gradient error
        away from both bands (in ground-truth disparity units).
    """
    from m360.geometry.layout import Layout

    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    pred = real_array(pred_disparity, "pred_disparity")
    gt = real_array(gt_disparity, "gt_disparity")
    if pred.shape != layout.erp_shape or gt.shape != layout.erp_shape:
        raise InputError(
            f"pred_disparity {pred.shape} and gt_disparity {gt.shape} must both have the "
            f"layout's ERP shape {layout.erp_shape}"
        )
    # A band as tall as the map already covers all of it (and its cost grows with the band).
    band = integer(band, "band", low=0, high=layout.erp_shape[0])
    both = np.isfinite(pred) & np.isfinite(gt)
    if not both.any():
        raise InputError("no pixel where both pred_disparity and gt_disparity are finite")
    scale, shift = fit_scale_shift(pred[both], gt[both])
    # Near float64's limits the gradient errors may overflow: the means are then inf (or NaN).
    with np.errstate(over="ignore", invalid="ignore"):
        diff = np.where(both, scale * pred + shift - gt, np.nan)
        ex = np.roll(diff, -1, axis=1) - diff
        ey = np.zeros_like(diff)
        ey[:-1] = diff[1:] - diff[:-1]
        err = np.hypot(ex, ey)
    ok = np.isfinite(err)
    borders, triangles = _seam_masks(layout, band)
    rest = ok & ~borders & ~triangles
    if not rest.any():
        raise InputError("no valid pixel away from the seams to compare with")
    with np.errstate(over="ignore", invalid="ignore"):
        elsewhere = float(err[rest].mean())

        def ratio(mask: np.ndarray) -> float:
            sel = ok & mask
            if not sel.any() or elsewhere == 0.0:
                return float("nan")
            return float(err[sel].mean()) / elsewhere

        return {"borders": ratio(borders), "triangles": ratio(triangles), "elsewhere": elsewhere}
