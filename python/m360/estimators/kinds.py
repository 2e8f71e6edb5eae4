"""What an estimator outputs, and its conversion to the perspective disparity m360 stitches.

An estimator declares one ``output_kind`` (docs/architecture.md, estimators):

- ``"affine_disparity"``: perspective disparity 1/z up to an unknown scale and shift (MiDaS, DPT,
  Depth Anything relative models: the paper's assumption); passed through;
- ``"metric_depth"``: z-depth in metres (a metric model); perspective disparity = 1/z;
- ``"distance"``: radial distance |P| in metres; perspective disparity = |q| / distance with the
  pixel ray ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` (docs/conventions.md);
- ``"affine_depth"``: z-depth up to an unknown scale and shift (mobile PyDNet's raw output,
  Marigold, LeReS); per tangent the depth is shifted so that its robust minimum (1st
  percentile, lower values clamped to it) becomes :data:`AFFINE_DEPTH_FLOOR` times its robust
  range (1st to 99th percentile), then inverted;
- ``"negated_affine_disparity"``: an affine disparity with the sign flipped (an output that
  grows with depth); negated, then as ``"affine_disparity"``.

A *panoramic* estimator (ERP in, ERP out: :data:`ESTIMATOR_KINDS`) declares one of
:data:`PANORAMIC_OUTPUT_KINDS`, all of them about the ERP pixel's ray: ``"affine_disparity"``
(spherical disparity 1/|P| up to scale and shift), ``"disparity"`` (1/|P| in 1/metres),
``"affine_depth"`` (|P| up to scale and shift), ``"distance"`` (|P| in metres) and
``"negated_affine_disparity"`` (an affine spherical disparity with the sign flipped);
:func:`to_spherical_disparity` converts them. A z-depth (``"metric_depth"``) has no meaning for
an ERP output (there is no optical axis) and is refused.

After the conversion :func:`sanitise` checks each tangent (docs/method.md, "Checking the
network's output").
"""

from __future__ import annotations

import functools
import logging
import warnings
from typing import Any, Literal, TypedDict

import numpy as np

from .._validate import as_array
from ..errors import InputError, ModelError
from ..geometry.layout import Layout, plan_for

__all__ = [
    "AFFINE_DEPTH_FLOOR",
    "ALL_OUTPUT_KINDS",
    "DEPTH_KINDS",
    "ESTIMATOR_KINDS",
    "MIN_TANGENT_SHARE",
    "MIN_VALID_FRACTION",
    "OUTLIER_RATIO",
    "OUTPUT_KINDS",
    "PANORAMIC_METRIC_KINDS",
    "PANORAMIC_OUTPUT_KINDS",
    "OutputKind",
    "TangentDrop",
    "check_any_output_kind",
    "check_estimator_kind",
    "check_output_kind",
    "check_panoramic_output_kind",
    "ray_norms",
    "sanitise",
    "to_perspective_disparity",
    "to_spherical_disparity",
]

_log = logging.getLogger("m360")

#: What an estimator may declare it outputs.
OutputKind = Literal[
    "affine_disparity", "metric_depth", "distance", "affine_depth", "negated_affine_disparity"
]
OUTPUT_KINDS: tuple[str, ...] = (
    "affine_disparity",
    "metric_depth",
    "distance",
    "affine_depth",
    "negated_affine_disparity",
)
#: The kinds in metres whose values must be > 0 (the result keeps their scale).
DEPTH_KINDS: tuple[str, ...] = ("metric_depth", "distance")
#: The roles of an estimator: ``tangent`` (perspective tangent images in, one map per tangent
#: out: the paper's networks) or ``panoramic`` (the whole ERP in, one ERP map out).
ESTIMATOR_KINDS: tuple[str, ...] = ("tangent", "panoramic")
#: What a panoramic estimator may declare it outputs (per ERP pixel, along its ray).
PANORAMIC_OUTPUT_KINDS: tuple[str, ...] = (
    "affine_disparity",
    "disparity",
    "affine_depth",
    "distance",
    "negated_affine_disparity",
)
#: The panoramic kinds in metres (or 1/metres): their values must be > 0.
PANORAMIC_METRIC_KINDS: tuple[str, ...] = ("disparity", "distance")
#: Every output kind an option may name (tangent and panoramic).
ALL_OUTPUT_KINDS: tuple[str, ...] = (*OUTPUT_KINDS, "disparity")
#: ``affine_depth``: the robust minimum of a tangent's depth is shifted to this fraction of its
#: robust range (1st to 99th percentile) before 1/z (docs/method.md, "affine_depth").
AFFINE_DEPTH_FLOOR = 0.1
#: A tangent's disparity beyond this many times its median |disparity| is no estimate
#: (docs/method.md, "Checking the network's output").
OUTLIER_RATIO = 100.0
#: A tangent with fewer valid pixels than this share is dropped.
MIN_VALID_FRACTION = 0.05
#: Fewer tangents left than this share of the layout is a ModelError.
MIN_TANGENT_SHARE = 0.5
#: A tangent whose robust range (5th to 95th percentile) is below this share of its median
#: |value| has no dynamic range (a constant output).
_MIN_RANGE = 1e-4
#: Percentiles are read from at most this many samples per tangent (a regular subsample).
_MAX_SAMPLES = 1 << 16


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
        also = (
            " ('disparity' is for panoramic models, kind='panoramic')"
            if isinstance(kind, str) and kind == "disparity"
            else ""
        )
        raise InputError(f"{name}={kind!r} is not supported; choose one of {options}{also}")
    return kind  # type: ignore[return-value]


def check_any_output_kind(kind: Any, name: str = "output_kind") -> str:
    """``kind`` if some estimator role takes it (:data:`ALL_OUTPUT_KINDS`), else InputError."""
    if not isinstance(kind, str) or kind not in ALL_OUTPUT_KINDS:
        options = ", ".join(repr(k) for k in ALL_OUTPUT_KINDS)
        raise InputError(f"{name}={kind!r} is not supported; choose one of {options}")
    return kind


def check_estimator_kind(kind: Any, name: str = "kind") -> str:
    """``kind`` if it is one of :data:`ESTIMATOR_KINDS`, else :class:`m360.InputError`."""
    if not isinstance(kind, str) or kind not in ESTIMATOR_KINDS:
        options = ", ".join(repr(k) for k in ESTIMATOR_KINDS)
        raise InputError(
            f"{name}={kind!r} is not an estimator kind; choose one of {options} (tangent: "
            "perspective tiles in, panoramic: the whole ERP in and out)"
        )
    return kind


def check_panoramic_output_kind(kind: Any, name: str = "output_kind") -> str:
    """``kind`` if a panoramic estimator may output it (:data:`PANORAMIC_OUTPUT_KINDS`).

    ``"metric_depth"`` gets its own message: a z-depth needs an optical axis, which an ERP map
    has not; a metric panoramic network outputs ``"distance"`` (radial metres).
    """
    if isinstance(kind, str) and kind == "metric_depth":
        raise InputError(
            f"{name}='metric_depth' (z-depth) has no meaning for a panoramic (ERP) output: an ERP "
            "pixel has no optical axis to measure z along. A metric panoramic network outputs "
            "the radial distance: use output_kind='distance' (metres) or 'disparity' (1/metres)"
        )
    if not isinstance(kind, str) or kind not in PANORAMIC_OUTPUT_KINDS:
        options = ", ".join(repr(k) for k in PANORAMIC_OUTPUT_KINDS)
        raise InputError(
            f"{name}={kind!r} is not supported for a panoramic model; choose one of {options}"
        )
    return kind


def to_spherical_disparity(values: np.ndarray, kind: str) -> np.ndarray:
    """Convert a panoramic estimator's ERP output of ``kind`` to spherical disparity 1/|P|.

    Parameters
    ----------
    values : (h, w) float array
        The ERP map at the network's own resolution; NaN = no estimate.
    kind : str
        One of :data:`PANORAMIC_OUTPUT_KINDS`: ``"affine_disparity"`` and ``"disparity"`` pass
        through; ``"negated_affine_disparity"`` is negated; ``"distance"`` is inverted;
        ``"affine_depth"`` is shifted as a tangent's is (its robust minimum to
        :data:`AFFINE_DEPTH_FLOOR` of its robust range), then inverted.

    Returns
    -------
    (h, w) float32
        Spherical disparity; NaN where the input is not finite and, for ``"disparity"`` and the
        depths, where the value (shifted) is not > 0 or its inverse overflows float32.
    """
    check_panoramic_output_kind(kind)
    array = as_array(values, "panoramic output")
    if array.ndim != 2 or min(array.shape) < 1:
        raise InputError(f"a panoramic output must be one (h, w) map, got shape {array.shape}")
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(array, dtype=np.float32)
    out[~np.isfinite(out)] = np.nan
    if kind == "affine_disparity":
        return out
    if kind == "negated_affine_disparity":
        return np.negative(out, out=out)
    if kind == "disparity":
        with np.errstate(invalid="ignore"):
            out[~(out > 0)] = np.nan
        return out
    depth = out.astype(np.float64)
    if kind == "affine_depth":
        lo, hi = _percentiles(depth[None], (1.0, 99.0))
        # A constant map still has a floor above 0 (its inverse, a constant, not NaN).
        span = max(float(hi[0] - lo[0]), 1e-12 * max(abs(float(hi[0])), 1.0))
        depth = np.maximum(depth - lo[0], 0.0) + AFFINE_DEPTH_FLOOR * span
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        result = np.where(depth > 0, 1.0 / depth, np.nan).astype(np.float32)
    result[np.isinf(result)] = np.nan
    return result


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
        ``"affine_disparity"`` (returned as float32 unchanged), ``"negated_affine_disparity"``
        (negated), ``"metric_depth"`` (z-depth: 1/z), ``"distance"`` (radial: |q| / distance)
        or ``"affine_depth"`` (shifted per tangent, see the module's docstring, then 1/z).
    layout : Layout

    Returns
    -------
    (N, h, w) float32 perspective disparity; NaN where the input is not finite, and for depths
    where the (shifted) value is not > 0 or its disparity overflows float32.
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
    if kind in ("affine_disparity", "negated_affine_disparity"):
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf -> NaN below
            out = np.array(array, dtype=np.float32)
        if kind == "negated_affine_disparity":
            np.negative(out, out=out)
        out[~np.isfinite(out)] = np.nan
        return out
    depth = array.astype(np.float64)
    if kind == "affine_depth":
        depth[~np.isfinite(depth)] = np.nan
        lo, hi = _percentiles(depth, (1.0, 99.0))
        # Shift so the robust minimum sits at AFFINE_DEPTH_FLOOR of the robust range, values
        # below it clamped there (the nearest 1 %): positive depths whose disparity ratio over
        # the tangent is at most (hi - lo)/(F (hi - lo)) + 1 = 1/F + 1 at the 99th percentile.
        lo3, span3 = lo[:, None, None], (hi - lo)[:, None, None]
        depth = np.maximum(depth - lo3, 0.0) + AFFINE_DEPTH_FLOOR * span3
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        numerator = ray_norms(layout) if kind == "distance" else 1.0
        out = np.where(depth > 0, numerator / depth, np.nan).astype(np.float32)
    # A depth so small that its disparity overflows float32 is no estimate either.
    out[np.isinf(out)] = np.nan
    return out


def _percentiles(
    values: np.ndarray, qs: tuple[float, ...], *, absolute: bool = False
) -> tuple[np.ndarray, ...]:
    """Per-tangent NaN-ignoring percentiles of (N, h, w) ``values`` (|values| if ``absolute``).

    NaN for an empty tangent.
    """
    flat = values.reshape(values.shape[0], -1)
    step = max(1, flat.shape[1] // _MAX_SAMPLES)
    sample = np.abs(flat[:, ::step]) if absolute else flat[:, ::step]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN tangents give NaN
        result = np.nanpercentile(sample, qs, axis=1)
    return tuple(np.asarray(r, dtype=np.float64) for r in result)


class TangentDrop(TypedDict):
    """One tangent :func:`sanitise` dropped: its index in the layout and why."""

    tangent: int
    reason: str


def sanitise(
    perspective: np.ndarray,
    kind: str,
    *,
    raw: np.ndarray | None = None,
    outlier_ratio: float = OUTLIER_RATIO,
    min_valid_fraction: float = MIN_VALID_FRACTION,
    min_tangent_share: float = MIN_TANGENT_SHARE,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Check each tangent's perspective disparity before anything trusts it (in place).

    Pixels: not finite, or beyond ``outlier_ratio`` times the tangent's median |disparity|
    (a near-zero depth's spike), become NaN (the depth kinds' values ≤ 0 are already NaN after
    :func:`to_perspective_disparity`). Tangents: one with fewer than ``min_valid_fraction``
    valid pixels, without dynamic range (a constant output), or of the wrong sign for ``kind``
    (a depth mostly ≤ 0 in ``raw``; an affine disparity mostly < 0) is dropped, all NaN, with a
    logged warning (logger ``m360``) naming it and why; the others go on.

    Parameters
    ----------
    perspective : (N, h, w) float32
        Output of :func:`to_perspective_disparity`; changed in place.
    kind : str
        The estimator's declared output kind.
    raw : (N, h, w) float array, optional
        The estimator's output before the conversion (for the sign of a depth).
    outlier_ratio, min_valid_fraction : float
        The thresholds (defaults :data:`OUTLIER_RATIO`, :data:`MIN_VALID_FRACTION`).
    min_tangent_share : float
        Fewer tangents left than this share of N raises :class:`m360.ModelError`.

    Returns
    -------
    perspective : (N, h, w) float32
        The same array, sanitised.
    checks : dict
        ``dropped`` (list of :class:`TangentDrop`), ``outlier_pixels`` (pixels made NaN by the
        range rule), ``valid_fraction`` (per tangent, after the checks).

    Raises
    ------
    m360.ModelError
        When fewer than ``min_tangent_share`` of the tangents are left, naming the reasons.
    """
    check_output_kind(kind)
    if perspective.ndim != 3:
        raise InputError(f"perspective must be (N, h, w), got shape {perspective.shape}")
    n = perspective.shape[0]
    flat = perspective.reshape(n, -1)
    flat[~np.isfinite(flat)] = np.nan
    (median,) = _percentiles(perspective, (50.0,), absolute=True)
    outlier_pixels = 0
    for k in range(n):  # one tangent at a time: no stack-sized temporary
        with np.errstate(invalid="ignore"):
            outliers = np.abs(flat[k]) > outlier_ratio * median[k]
        outlier_pixels += int(outliers.sum())
        flat[k, outliers] = np.nan
    valid = np.isfinite(flat)
    share = valid.mean(axis=1)
    lo, mid, hi = _percentiles(perspective, (5.0, 50.0, 95.0))
    negative_raw = None
    if raw is not None and kind in DEPTH_KINDS:
        raw_flat = np.asarray(raw).reshape(n, -1)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(raw_flat)
            negative_raw = (finite & (raw_flat <= 0)).sum(axis=1) / np.maximum(finite.sum(1), 1)
    dropped: list[TangentDrop] = []
    for k in range(n):
        reason = None
        if negative_raw is not None and negative_raw[k] > 0.5:
            reason = (
                f"wrong sign: {negative_raw[k]:.0%} of its {kind} output is <= 0 (a depth "
                "must be > 0; is the output a disparity or negated?)"
            )
        elif share[k] < min_valid_fraction:
            reason = f"too few valid pixels ({share[k]:.1%} < {min_valid_fraction:.0%})"
        elif kind in ("affine_disparity", "negated_affine_disparity") and mid[k] < 0:
            other = "negated_affine_disparity" if kind == "affine_disparity" else "affine_disparity"
            reason = (
                f"wrong sign: its {kind} is mostly negative (median {mid[k]:.3g}); an output "
                f"that grows with depth needs output_kind={other!r} or 'affine_depth'"
            )
        elif not hi[k] - lo[k] > _MIN_RANGE * abs(mid[k]) or hi[k] == lo[k]:
            reason = f"no dynamic range (5th to 95th percentile {lo[k]:.6g} to {hi[k]:.6g})"
        if reason is not None:
            flat[k] = np.nan
            share[k] = 0.0
            dropped.append(TangentDrop(tangent=k, reason=reason))
            _log.warning("tangent %d dropped: %s", k, reason)
    left = n - len(dropped)
    if left < max(1, min_tangent_share * n):
        reasons = "; ".join(f"tangent {d['tangent']}: {d['reason']}" for d in dropped[:5])
        more = f" (and {len(dropped) - 5} more)" if len(dropped) > 5 else ""
        raise ModelError(
            f"only {left} of {n} tangents have a usable {kind} output (at least "
            f"{min_tangent_share:.0%} needed): {reasons}{more}"
        )
    checks = {
        "dropped": dropped,
        "outlier_pixels": outlier_pixels,
        "valid_fraction": [round(float(v), 4) for v in share],
    }
    return perspective, checks
