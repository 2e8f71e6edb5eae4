"""The stitching core: per-tangent perspective disparity in, one ERP spherical disparity out.

The options are documented in :mod:`m360.align` and :mod:`m360.blend` and collected in one
:class:`m360.StitchOptions`; the method and where m360 departs from the paper are in
docs/method.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, TypedDict, overload

import numpy as np

from .._compat import moved, renamed
from .._keywords import split
from .._validate import as_array, check_shape, flag
from ..errors import InputError
from ..geometry.layout import Layout, check_tangents, plan_for
from . import align as _align
from . import blend as _blend
from .align import AlignLevelReport
from .blend import BlendMethod, BlendReport
from .options import AlignSpec, StitchOptions, StitchTuning, build
from .prior import PriorKind, PriorReport, check_prior

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["StitchReport", "StitchResult", "stitch"]

_log = logging.getLogger("m360")

#: Module constants that moved to :mod:`m360.align` / :mod:`m360.blend` (old name → new home).
_MOVED = {
    "ALIGN_MODES": (_align, "ALIGN_MODES"),
    "MULTISCALE": (_align, "MULTISCALE"),
    "SCHEDULES": (_align, "SCHEDULES"),
    "ENERGIES": (_align, "ENERGIES"),
    "SOLVERS": (_align, "SOLVERS"),
    "ENERGY_WEIGHTS": (_align, "ENERGY_WEIGHTS"),
    "OFFSETS": (_align, "OFFSETS"),
    "DEFAULT_OFFSETS": (_align, "DEFAULT_OFFSETS"),
    "DEFAULT_ITERATIONS": (_align, "DEFAULT_ITERATIONS"),
    "BLEND_MODES": (_blend, "BLEND_METHODS"),
    "FIDELITY_TARGETS": (_blend, "FIDELITY_TARGETS"),
    "POISSON_SOLVERS": (_blend, "POISSON_SOLVERS"),
    "MIN_POISSON_TOL": (_blend, "MIN_POISSON_TOLERANCE"),
}


__getattr__ = moved(__name__, _MOVED)


class _StitchReportBase(TypedDict):
    blend: BlendReport


class StitchReport(_StitchReportBase, total=False):
    """Solver reports of one stitch.

    ``blend`` always; with alignment ``align`` (per level) and ``align_fallback`` (what the
    overlap samples allowed, see :mod:`m360.align`); with a prior ``prior``, what the alignment
    fitted to it (:class:`m360.stitching.prior.PriorReport`; None when no level ran).
    """

    align: list[AlignLevelReport]
    align_fallback: str
    prior: PriorReport | None


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
        pixel, 0 where one tangent sees it, NaN where none does; with ``blend="consensus"`` the
        disagreement left after the vote (:mod:`m360.blend`); with a prior, combined (root sum
        of squares) with the disagreement |disparity − prior| of the prior fitted to the result
        (NaN-free where the prior is unknown: the tangents' alone). Lower means more consistent.
    coverage : (H, W) uint8
        Number of tangents whose image contains each pixel.
    grids : list of (N, rows, cols, 2) float64
        Alignment grids (scale, offset per node) per level; empty with ``align="none"``.
    report : StitchReport
        Solver reports per stage: ``report["align"]``, one :class:`m360.align.AlignLevelReport`
        per level (only with alignment); ``report["blend"]``, a :class:`m360.blend.BlendReport`
        (``method`` and ``seconds``; for ``"poisson"`` also ``iterations``,
        ``relative_residual`` (true ‖Ax - b‖/‖b‖ of the solution), ``initial_residual``,
        ``tolerance``, ``converged``, ``lam``, ``fidelity``, ``unknowns``,
        ``assemble_seconds``, ``solve_seconds`` and ``solver``).
    timings : dict
        Seconds per stage: ``convert``, ``align``, ``blend``.
    options : StitchOptions or None
        The options the stitch ran with.
    """

    disparity: np.ndarray
    confidence: np.ndarray
    coverage: np.ndarray
    grids: list[np.ndarray] = field(default_factory=list)
    report: StitchReport = field(default_factory=dict)  # type: ignore[assignment]
    timings: dict[str, float] = field(default_factory=dict)
    options: StitchOptions | None = None


@overload
def stitch(
    tangents: np.ndarray,
    layout: Layout,
    align: AlignSpec = ...,
    blend: BlendMethod | None = ...,
    *,
    mask: np.ndarray | None = ...,
    prior: np.ndarray | None = ...,
    prior_kind: PriorKind = ...,
    prior_confidence: np.ndarray | None = ...,
    options: StitchOptions | None = ...,
    return_details: Literal[False] = ...,
    **keywords: Unpack[StitchTuning],
) -> np.ndarray: ...


@overload
def stitch(
    tangents: np.ndarray,
    layout: Layout,
    align: AlignSpec = ...,
    blend: BlendMethod | None = ...,
    *,
    mask: np.ndarray | None = ...,
    prior: np.ndarray | None = ...,
    prior_kind: PriorKind = ...,
    prior_confidence: np.ndarray | None = ...,
    options: StitchOptions | None = ...,
    return_details: Literal[True],
    **keywords: Unpack[StitchTuning],
) -> StitchResult: ...


@renamed(tangent_disparity="tangents")
def stitch(
    tangents: np.ndarray,
    layout: Layout,
    align: AlignSpec = "multiscale",
    blend: BlendMethod | None = None,
    *,
    mask: np.ndarray | None = None,
    prior: np.ndarray | None = None,
    prior_kind: PriorKind = "affine_disparity",
    prior_confidence: np.ndarray | None = None,
    options: StitchOptions | None = None,
    return_details: bool = False,
    **keywords: Unpack[StitchTuning],
) -> np.ndarray | StitchResult:
    """Stitch per-tangent perspective disparity into one ERP spherical disparity map.

    Each tangent value is first converted from perspective disparity (1/z, what a monocular
    network predicts up to scale and shift) to spherical disparity (1/distance) with its own
    pixel's ray length; the tangents are then aligned (paper §3.3, :mod:`m360.align`), mapped to
    the ERP grid (bilinear at the exact projected position, but not across a depth edge: where
    the four neighbours span a jump of more than 5 %, the side with most of the weight; ``nn``
    is plain bilinear) and blended (paper §3.4, :mod:`m360.blend`).

    Parameters
    ----------
    tangents : (N, h, w) float32
        One perspective disparity map per camera of ``layout``; NaN marks pixels without an
        estimate. float64 is converted.
    layout : Layout
        The layout the tangents were made with.
    align : str, (cols, rows) or list of (cols, rows)
        ``"multiscale"`` (default: the energy's schedule, :data:`m360.align.SCHEDULES`), one
        grid of (cols, rows) nodes per tangent, a list of grids, or ``"none"`` (values pass
        through unchanged).
    blend : str, optional
        ``"consensus"`` (the core's default), ``"poisson"``, ``"frustum"``, ``"radial"``,
        ``"mean"``, ``"median"`` or ``"nn"``.
    mask : (N, h, w) bool, optional
        False marks pixels with no estimate (sky, tripod). They never contribute, not even
        through a bilinear neighbour, and are left out of standardisation and overlaps.
    prior : (Hp, 2·Hp) float array, optional
        A global prior ERP map of any resolution (a panoramic network's output, another tool's,
        the previous video frame), NaN = unknown: the alignment follows its low frequencies
        while the blend keeps the tangents' detail (:mod:`m360.stitching.prior`; the weight
        and frequency split are ``prior_weight`` and ``prior_scale_deg``, its fusion with the
        tangents' own low frequencies ``prior_fusion``). Needs alignment.
        None (default): no prior, the result is exactly that of a stitch without one.
    prior_kind : str
        What the prior holds: ``"affine_disparity"`` (default; spherical disparity up to scale
        and shift), ``"disparity"`` (1/m: the result takes its units), ``"affine_depth"``
        (radial depth up to scale and shift) or ``"distance"`` (radial metres: the result is
        then spherical disparity in 1/m).
    prior_confidence : (Hp, 2·Hp) float array in [0, 1], optional
        Per-pixel trust in the prior (e.g. lower where a video frame changed).
    options : StitchOptions, optional
        Every stitching option at once (then give none of them as a keyword).
    return_details : bool
        Return a :class:`StitchResult` instead of the disparity array.
    **keywords
        The other stitching options, :class:`m360.stitching.options.StitchTuning` (``energy``,
        ``solver``, ``iterations``, ``tolerance``, ``sample_fraction``, ``pole_cap_deg``,
        ``smoothness``, ``scale_weight``, ``offsets``, ``loss``, ``prior_weight``,
        ``prior_scale_deg``, ``prior_fusion``, ``blend_options``; see
        :mod:`m360.align` and :mod:`m360.blend`); None or absent takes the core's default. A
        Poisson solve that does not reach its tolerance raises :class:`m360.SolverError`.

    Returns
    -------
    numpy.ndarray or StitchResult
        (H, W) float32 spherical disparity, NaN where no tangent has a valid value; or a
        :class:`StitchResult`. With alignment the result is in the input's range up to one
        global affine map.

    Raises
    ------
    m360.InputError
        For unusable tangents, layout, mask or options (naming which).
    m360.SolverError
        For a Poisson solve that does not converge.
    """
    t0 = time.perf_counter()
    data = check_tangents(tangents, layout, "tangents")
    (tuning,) = split(keywords, StitchTuning, where="stitch")
    opts = build(options, layout.subdivisions or 0, align=align, blend=blend, **tuning).checked_for(
        layout.tangent_shape
    )
    valid = None if mask is None else _check_mask(mask, layout)
    flag(return_details, "return_details")
    prior_map: np.ndarray | None = None
    if prior is not None:
        prior_map, prior_conf, absolute = check_prior(prior, prior_kind, prior_confidence)
        if opts.align is None:
            raise InputError("a prior needs alignment: give align other than 'none'")
    elif prior_confidence is not None:
        raise InputError("prior_confidence was given without a prior")

    plan = plan_for(layout)
    spherical = plan.spherical_disparity(data, valid)
    t1 = time.perf_counter()
    grids: list[np.ndarray] = []
    levels: list[AlignLevelReport] = []
    align_options = opts.align
    fit: dict[str, Any] | None = None
    if align_options is not None:
        # In place: `spherical` is this call's own array (no second stack-sized array).
        if prior_map is None:
            spherical, reports, grids, fallback = plan.align(
                spherical, dict(align_options), in_place=True
            )
        else:
            spherical, reports, grids, fallback, fit = plan.align_with_prior(
                spherical, dict(align_options), prior_map, prior_conf, absolute, in_place=True
            )
        levels = [_level_report(r) for r in reports]
        if fallback != "none":
            _log.warning(
                "too few overlap samples for the alignment schedule: fell back to %s (%s)",
                fallback,
                ", ".join(f"{c}x{r}" for c, r in (lv["grid"] for lv in levels)) or "no level",
            )
    t2 = time.perf_counter()
    # The confidence costs a second pass: only computed when returned.
    vote: dict[str, Any] = {}
    if fit is not None:
        # The prior votes among the faces where they disagree, and the confidence includes the
        # disagreement with it (docs/method.md, "Global prior").
        vote = {"prior": prior_map, "prior_confidence": prior_conf}
        vote["prior_affine"] = (float(fit["affine"][0]), float(fit["affine"][1]))
    disparity, confidence, raw_blend = plan.blend(
        spherical, dict(opts.blend), confidence=return_details, **vote
    )
    t3 = time.perf_counter()
    blend_report: BlendReport = {**raw_blend, "seconds": t3 - t2}  # type: ignore[typeddict-item]
    if not return_details:
        return disparity
    if confidence is None:  # asked for with return_details
        raise RuntimeError("the core returned no confidence although it was asked for")
    report = StitchReport(blend=blend_report)
    if align_options is not None:
        report["align"] = levels
        report["align_fallback"] = fallback
    if prior_map is not None:
        report["prior"] = None
        if fit is not None:
            affine = (float(fit["affine"][0]), float(fit["affine"][1]))
            report["prior"] = PriorReport(
                kind=str(prior_kind),
                affine=affine,
                samples=int(fit["samples"]),
                outvoted=float(fit["outvoted"]),
                weight=float(fit["weight"]),
                residual=float(fit["residual"]),
                tangent_spread=(
                    None if fit["tangent_spread"] is None else float(fit["tangent_spread"])
                ),
                tangent_share=float(fit["tangent_share"]),
                consensus_outvoted=float(fit["consensus_outvoted"]),
                low_order_gap=float(fit["low_order_gap"]),
                low_order_share=float(fit["low_order_share"]),
            )
    return StitchResult(
        disparity=disparity,
        confidence=confidence,
        coverage=plan.coverage(),
        grids=grids,
        report=report,
        timings={"convert": t1 - t0, "align": t2 - t1, "blend": t3 - t2},
        options=opts,
    )


def _level_report(raw: Mapping[str, Any]) -> AlignLevelReport:
    report: AlignLevelReport = {**raw}  # type: ignore[typeddict-item]
    report["grid"] = (int(raw["grid"][0]), int(raw["grid"][1]))
    return report


def _check_mask(mask: np.ndarray, layout: Layout) -> np.ndarray:
    array = as_array(mask, "mask")
    h, w = layout.tangent_shape
    check_shape(array, "mask", ("N", "h", "w"), N=len(layout), h=h, w=w)
    if array.dtype != np.bool_:
        raise InputError(
            f"mask must be a bool array (False = no estimate), got dtype {array.dtype}"
        )
    return np.ascontiguousarray(array)
