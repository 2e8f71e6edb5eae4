"""The temporal term: frame t's depth kept consistent with frame t−1's where the image agrees.

Per-tangent networks make each frame's tangents wrong in a different way, so a video estimated
frame by frame flickers: the alignment's gauge (the global scale and offset of a relative
result) jumps, and each tile's content errors come and go. :class:`Temporal` carries a small
state from one frame to the next, a low-resolution copy of the previous frame's result and of
its grey image (:class:`TemporalState`, written next to each frame's outputs so a resumed run
makes the same bytes), and for each new frame:

1. **Scene cut?** The grey images are correlated (:func:`scene_cut`); after a cut, or without a
   previous frame, the frame is taken as it is and starts a new state.
2. **Where did the image change?** ``confidence = exp(−(|Δgrey| / CHANGE_SCALE)²)`` per
   state pixel: 1 where the image is the same, near 0 where something moved.
3. **Prior** (``Temporal(prior=True)``, where :func:`m360.estimate` takes one): the previous
   state, predicted with its trend, is handed to the stitch as a prior in the run's units with
   that confidence, so the alignment starts from the previous frame's solution
   (:meth:`Temporal.prior_keywords`). Off by default: measured, it added nothing to steps 4-5.
4. **Gauge**: a relative result is mapped by the affine map ``a·D + b`` that best fits the
   previous state where the confidence is high (weighted least squares, refitted once without
   the worst residuals), so the global scale does not jump.
5. **Smoothing**: at the state's resolution the result is pulled towards the previous state,
   ``S = D + STRENGTH·confidence·(S_prev − D)`` (an exponential moving average where the image
   did not change), and the full-resolution map takes the low-frequency correction ``S − D``
   (bilinearly upsampled); the frame's own detail above the state's resolution is kept.

The issue behind this asked for a term on the alignment's fields (each tangent's scale and
offset fields close to the previous frame's). Those fields legitimately change from frame to
frame, since they absorb each frame's own per-tile errors, and the stack is standardised per
tangent before the alignment, so fields of two frames are not comparable: the prior on the
result (steps 3–5) is the nearest sound formulation (docs/video.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError, ReadError
from ..io.files import save_npy

__all__ = [
    "CHANGE_SCALE",
    "CUT_CORRELATION",
    "STATE_WIDTH",
    "STRENGTH",
    "TEMPORAL_MODES",
    "Correction",
    "Temporal",
    "TemporalState",
    "scene_cut",
]

#: ``temporal=`` choices, the default first.
TEMPORAL_MODES = ("smooth", "none")
#: Width of the state's maps (height half of it): the per-tile errors are larger than a pixel of
#: it at any ERP width, and a state stays small (1 MB per frame).
STATE_WIDTH = 512
#: Weight of the previous state where the image did not change (the moving average's α).
STRENGTH = 0.7
#: Gain of the trend (the alpha-beta filter's β): how fast the state learns a steady change.
TREND = 0.1
#: Relative difference between frame and state at which the pull is halved (moved edges).
AGREEMENT = 0.1
#: Relative difference between a pixel and its state-resolution blur beyond which it is an edge.
EDGE_SCALE = 0.02
#: Grey-level change (0–1) at which a state pixel's confidence has fallen to 1/e.
CHANGE_SCALE = 0.06
#: A scene cut: two frames' grey images correlate less than this (at the best turn).
CUT_CORRELATION = 0.75
#: Least share of state pixels that must be confident for the gauge fit.
_MIN_FIT_SHARE = 0.05


@dataclass(frozen=True)
class TemporalState:
    """What a frame hands to the next: low-resolution disparity and grey image.

    Attributes
    ----------
    disparity : (h, w) float32
        The frame's output disparity at :data:`STATE_WIDTH` (NaN where none).
    grey : (h, w) float32
        Its grey image in [0, 1] at the same size (lightly blurred).
    """

    disparity: np.ndarray
    grey: np.ndarray
    velocity: np.ndarray | None = None

    def save(self, path: str | Path) -> Path:
        """Write the state as one ``.npy`` of shape (3, h, w) float32, atomically."""
        velocity = np.zeros_like(self.disparity) if self.velocity is None else self.velocity
        return save_npy(path, np.stack([self.disparity, self.grey, velocity]).astype(np.float32))

    @classmethod
    def load(cls, path: str | Path) -> TemporalState:
        """Read a state written by :meth:`save` (ReadError if missing or not one)."""
        try:
            array = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ReadError(f"temporal state {path} cannot be read: {exc}") from exc
        if array.ndim != 3 or array.shape[0] != 3 or array.dtype != np.float32:
            raise ReadError(f"temporal state {path} is not one (shape {array.shape})")
        return cls(*(np.ascontiguousarray(a) for a in array))


def _state_size(shape: tuple[int, int]) -> tuple[int, int]:
    """(width, height) of the state for an ERP of ``shape``: at most STATE_WIDTH wide."""
    width = min(STATE_WIDTH, shape[1])
    return width, max(1, width // 2)


def grey_of(rgb: np.ndarray) -> np.ndarray:
    """Give the state's grey image of an (H, W, 3) RGB frame: (h, w) float32 in [0, 1]."""
    size = _state_size(rgb.shape[:2])
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32)
    if rgb.dtype == np.uint8:
        grey /= 255.0
    blurred: np.ndarray = cv2.GaussianBlur(grey, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT)
    return blurred


def shrink(disparity: np.ndarray) -> np.ndarray:
    """Shrink an (H, W) map to the state's size, NaN-aware (area average of finite pixels)."""
    size = _state_size(disparity.shape)
    # One pass when every pixel is finite (the usual frame): an area average has no NaN then.
    quick: np.ndarray = cv2.resize(
        np.asarray(disparity, np.float32), size, interpolation=cv2.INTER_AREA
    )
    if np.isfinite(quick).all():
        return quick
    finite = np.isfinite(disparity)
    filled = np.where(finite, disparity, 0).astype(np.float32)
    total = cv2.resize(filled, size, interpolation=cv2.INTER_AREA)
    weight = cv2.resize(finite.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 0.5, total / weight, np.nan).astype(np.float32)


def _grow(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of a state-sized map to ``shape`` (H, W), wrapping in longitude.

    Pixel centres as everywhere in m360; rows clamp at the poles. Exact float interpolation
    (cv2.remap's fixed-point weights were off by up to 1/32 of a step).
    """
    height, width = shape
    w = values.shape[1]
    if width % w == 0:
        # An integer ratio r: one wrapped column on each side, resized to W + 2r, is the
        # same map without full-size coordinate maps (12x faster than a remap at 1K-4K).
        r = width // w
        padded = np.concatenate([values[:, -1:], values, values[:, :1]], axis=1)
        big = cv2.resize(padded, (width + 2 * r, height), interpolation=cv2.INTER_LINEAR)
        grown: np.ndarray = big[:, r : r + width]
        return grown
    rows: np.ndarray = cv2.resize(values, (w, height), interpolation=cv2.INTER_LINEAR)  # rows
    col = (np.arange(width) + 0.5) * (w / width) - 0.5
    c0 = np.floor(col).astype(np.intp)
    fx = (col - c0).astype(np.float32).reshape((1, width) + (1,) * (values.ndim - 2))
    left: np.ndarray = rows[:, c0 % w]
    right: np.ndarray = rows[:, (c0 + 1) % w]
    right -= left
    right *= fx
    right += left
    return right


def scene_cut(grey: np.ndarray, previous: np.ndarray) -> tuple[bool, float]:
    """Tell whether two frames' grey images (:func:`grey_of`) are a scene cut.

    The correlation of the two standardised images, at the best circular shift in longitude
    (a 360° camera that turns about its vertical axis shifts its columns; found for all
    shifts at once by FFT along the rows). Measured on the synthetic walks (8 rooms, 256 px):
    at least 0.987 between consecutive frames of one walk, at most 0.55 between two rooms;
    a cut is below :data:`CUT_CORRELATION`.

    Returns
    -------
    (bool, float)
        Whether it is a cut, and the correlation.
    """
    a = (grey - grey.mean()) / max(float(grey.std()), 1e-6)
    b = (previous - previous.mean()) / max(float(previous.std()), 1e-6)
    spectrum = np.fft.rfft(a, axis=1) * np.conj(np.fft.rfft(b, axis=1))
    correlation = float(np.fft.irfft(spectrum, n=a.shape[1], axis=1).sum(axis=0).max() / a.size)
    return correlation < CUT_CORRELATION, correlation


def _fit_gauge(
    current: np.ndarray, target: np.ndarray, weight: np.ndarray
) -> tuple[float, float] | None:
    """Affine (a, b) with a·current + b ≈ target, weighted; refitted without the worst 20 %."""
    keep = np.isfinite(current) & np.isfinite(target) & (weight > 0.5)
    if keep.mean() < _MIN_FIT_SHARE:
        return None
    x, y, w = current[keep].astype(np.float64), target[keep].astype(np.float64), weight[keep]
    fit = None
    for _ in range(2):
        # The weighted least squares of two unknowns by its 2x2 normal equations (a dense
        # lstsq of the (n, 2) design took half the temporal term's time).
        # numpy's pairwise sums, not BLAS dots: those split by the BLAS's thread count, and the
        # same frame must give the same gauge in every process (a Ray worker's included).
        wx = w * x
        sw, sx, sy = w.sum(), wx.sum(), (w * y).sum()
        sxx, sxy = (wx * x).sum(), (wx * y).sum()
        det = sw * sxx - sx * sx
        if not det > 1e-12 * max(sw * sxx, 1e-300):
            return None
        fit = ((sw * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det)
        fit = (float(fit[0]), float(fit[1]))
        residual = np.abs(fit[0] * x + fit[1] - y)
        inliers = residual <= np.quantile(residual, 0.8)
        x, y, w = x[inliers], y[inliers], w[inliers]
        if x.size < 16:
            break
    if fit is None or not (fit[0] > 0 and math.isfinite(fit[0]) and math.isfinite(fit[1])):
        return None
    return fit


class Temporal:
    """The temporal term of a video run: one instance per run, frames in order.

    Parameters
    ----------
    mode : {"smooth", "none"}
        ``"none"``: every frame on its own (today's still pipeline); ``"smooth"``: the steps of
        this module.
    prior : bool
        Also hand the previous state to the stitch as a prior where :func:`m360.estimate`
        takes one and the alignment runs (step 3). Default False: measured on the synthetic
        walks it gave the same flicker as steps 4-5 alone and AbsRel within ±0.0012 either
        way (docs/video.md), for the prior's extra alignment work.
    """

    def __init__(self, mode: str = "smooth", *, prior: bool = False) -> None:
        if mode not in TEMPORAL_MODES:
            raise InputError(f"temporal must be one of {', '.join(TEMPORAL_MODES)}, got {mode!r}")
        if not isinstance(prior, bool):
            raise InputError(f"prior must be True or False, got {prior!r}")
        self.mode = mode
        self.prior = prior

    def describe(self) -> dict[str, Any]:
        """Describe what decides the outputs (for the resume fingerprint)."""
        return {"mode": self.mode, "prior": self.prior and self.mode != "none"}

    def prepare(
        self, rgb: np.ndarray, previous: TemporalState | None, *, missing: str = "first frame"
    ) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
        """Before the frame's estimate: its grey image, the confidence map, and what was found.

        ``missing`` says why there is no ``previous`` state (recorded as the ``reset``).

        Returns
        -------
        grey : (h, w) float32
        confidence : (h, w) float32 or None
            None when the frame starts afresh (first frame, scene cut, mode ``"none"``).
        record : dict
            ``cut`` (bool), ``correlation``, ``reset`` (why there is no term, or None).
        """
        grey = grey_of(rgb)
        if self.mode == "none":
            return grey, None, {"reset": "temporal none"}
        if previous is None:
            return grey, None, {"cut": False, "reset": missing}
        if previous.grey.shape != grey.shape:
            return grey, None, {"cut": True, "reset": "frame size changed"}
        cut, correlation = scene_cut(grey, previous.grey)
        record: dict[str, Any] = {"cut": cut, "correlation": round(correlation, 6)}
        if cut:
            return grey, None, {**record, "reset": "scene cut"}
        confidence = np.exp(-np.square((grey - previous.grey) / CHANGE_SCALE)).astype(np.float32)
        record["confidence_mean"] = round(float(confidence.mean()), 6)
        return grey, confidence, {**record, "reset": None}

    def prior_keywords(
        self,
        previous: TemporalState | None,
        confidence: np.ndarray | None,
        accepted: Any,
    ) -> dict[str, Any]:
        """Give the keywords that hand the previous state to the stitch as a prior (step 3).

        Empty when there is nothing to hand over (first frame, cut, mode ``"none"``), or when
        ``accepted`` (the keyword names :func:`m360.estimate` takes) has no ``prior``. The
        prior is the state predicted to this frame (value plus trend), in the run's units
        (``prior_kind="disparity"``: the result takes them, so the gauge does not jump), with
        the image-change confidence.
        """
        if self.mode == "none" or not self.prior or previous is None or confidence is None:
            return {}
        if not {"prior", "prior_kind", "prior_confidence"} <= set(accepted):
            return {}
        predicted = previous.disparity
        if previous.velocity is not None:
            predicted = predicted + previous.velocity
        return {
            "prior": predicted.astype(np.float32),
            "prior_kind": "disparity",
            "prior_confidence": confidence,
        }

    def apply(
        self,
        disparity: np.ndarray,
        grey: np.ndarray,
        confidence: np.ndarray | None,
        previous: TemporalState | None,
        *,
        relative: bool = True,
    ) -> tuple[np.ndarray, TemporalState, dict[str, Any]]:
        """After the frame's estimate: the smoothed disparity and the state for the next frame.

        :meth:`advance` then its :class:`Correction` (the state the next frame needs first,
        the full-resolution map after; a video run applies the correction while it writes).

        Parameters
        ----------
        disparity : (H, W) float32
            The frame's result (not changed).
        grey, confidence :
            From :meth:`prepare`.
        previous : TemporalState or None
        relative : bool
            The result is up to scale and shift (fit the gauge); False for metric results.

        Returns
        -------
        disparity : (H, W) float32
        state : TemporalState
        record : dict
            ``gauge`` ([a, b] or None), ``strength``.
        """
        state, correction, record = self.advance(
            disparity, grey, confidence, previous, relative=relative
        )
        out = disparity if correction is None else correction.apply(disparity)
        return out, state, record

    def advance(
        self,
        disparity: np.ndarray,
        grey: np.ndarray,
        confidence: np.ndarray | None,
        previous: TemporalState | None,
        *,
        relative: bool = True,
    ) -> tuple[TemporalState, Correction | None, dict[str, Any]]:
        """Give the state for the next frame, this one's correction (None: unchanged), a record.

        Works on the state-sized maps only; :meth:`Correction.apply` does the full-size work.
        Arguments as :meth:`apply`.
        """
        small = shrink(disparity)
        if confidence is None or previous is None or self.mode == "none":
            return TemporalState(small, grey), None, {"gauge": None, "strength": 0.0}
        gauge = _fit_gauge(small, previous.disparity, confidence) if relative else (1.0, 0.0)
        if gauge is None:  # too little agrees with the previous frame: start afresh
            return TemporalState(small, grey), None, {"gauge": None, "strength": 0.0}
        a, b = gauge
        small = small * np.float32(a) + np.float32(b)
        velocity = np.zeros_like(small) if previous.velocity is None else previous.velocity
        predicted = previous.disparity + velocity
        pull = np.float32(STRENGTH) * confidence
        pull[~np.isfinite(predicted) | ~np.isfinite(small)] = 0
        innovation = np.nan_to_num(small - predicted).astype(np.float32)
        with np.errstate(invalid="ignore", divide="ignore"):
            relative_change = np.nan_to_num(np.abs(innovation / small), nan=1.0)
        pull *= 1 / (1 + np.square(relative_change / AGREEMENT))
        correction = np.nan_to_num(pull * (predicted - small)).astype(np.float32)
        velocity = (confidence * (velocity + np.float32(TREND) * innovation)).astype(np.float32)
        velocity[pull == 0] = 0
        state = TemporalState((small + correction).astype(np.float32), grey, velocity)
        record = {"gauge": [a, b], "strength": STRENGTH}
        return state, Correction(a, b, small, correction), record


@dataclass(frozen=True)
class Correction:
    """What the temporal term does to one frame at full resolution (:meth:`Temporal.advance`).

    The gauge ``a·D + b`` and the state-sized corrected-minus-current map, grown to the frame
    where the frame is smooth at the state's scale.
    """

    a: float
    b: float
    small: np.ndarray
    correction: np.ndarray

    def apply(self, disparity: np.ndarray) -> np.ndarray:
        """Give the frame's (H, W) disparity in the gauge, with the correction (a new array)."""
        out: np.ndarray = disparity * np.float32(self.a) + np.float32(self.b)
        # Near depth edges the low-resolution maps mix both sides and a moving camera shifts
        # the edge: the correction is kept only where the frame is smooth at the state's scale.
        # One two-channel upsampling for both maps; the weight in place, one temporary.
        grown = _grow(np.dstack([self.small, self.correction]), disparity.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            weight = np.divide(out, grown[..., 0])
        weight -= 1
        weight *= np.float32(1 / EDGE_SCALE)
        np.square(weight, out=weight)
        np.negative(weight, out=weight)
        np.exp(weight, out=weight)
        weight[~np.isfinite(weight)] = 0  # no state there: no correction
        weight *= grown[..., 1]
        out += weight
        return out
