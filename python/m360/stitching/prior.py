"""A global prior for :func:`m360.stitch`: an ERP map (any resolution) that the alignment follows.

A panoramic network (or another tool, a LiDAR map, the previous video frame) gives a globally
consistent but coarse ERP map; the tangents give the detail. With ``prior=`` the alignment gets
one more term (docs/method.md, "Global prior"): at deterministic sample pixels of every tangent
its aligned disparity, averaged over ``prior_scale_deg`` degrees (the frequency split: finer
detail stays the tangents'), is pulled towards α·P + β, with (α, β) solved jointly with the
fields; each prior sample is judged against the tangents that see its direction (a Cauchy
weight, capped by its neighbourhood's and 0 below 0.8: trusted or not) and weighs that times its
``prior_confidence``, so prior regions that the tangents all contradict (windows, mirrors, sky)
lose their pull, and ``prior_weight`` sets the term's weight against the overlaps'. Where the
tangents agree closely with each other (a relative spread under 1.2 %), the prior's low
frequencies are first moved towards theirs, since a smooth error of the prior is invisible to
their overlaps; the more so where the prior strays from their consensus by more than its
uncertainty explains (``prior_fusion="auto"``, the default; ``"off"`` keeps the prior's as they
are).

Kinds (``prior_kind``), mirroring the estimators' output kinds (:mod:`m360.estimators.kinds`):

- ``"affine_disparity"`` (default): spherical disparity up to an unknown scale and shift;
- ``"disparity"``: spherical disparity 1/distance in 1/m; the result is in its units;
- ``"affine_depth"``: radial depth up to scale and shift; shifted so its robust minimum (1st
  percentile) sits at ``AFFINE_DEPTH_FLOOR`` of its robust range, then inverted (as the
  estimators do), then as ``"affine_disparity"``;
- ``"distance"``: radial distance in metres; inverted, then as ``"disparity"``;
- ``"negated_affine_disparity"``: an affine disparity with the sign flipped (a map that grows
  with depth, e.g. a network's pre-sigmoid output); negated, then as ``"affine_disparity"``.
"""

from __future__ import annotations

from typing import Any, Literal, TypedDict

import numpy as np

from .._validate import as_array, erp_map
from ..errors import InputError
from ..estimators.kinds import PANORAMIC_OUTPUT_KINDS, to_spherical_disparity

__all__ = [
    "PRIOR_KINDS",
    "PriorKind",
    "PriorReport",
    "check_prior",
]

#: What a prior map holds.
PriorKind = Literal[
    "affine_disparity", "disparity", "affine_depth", "distance", "negated_affine_disparity"
]
PRIOR_KINDS: tuple[str, ...] = PANORAMIC_OUTPUT_KINDS
#: The kinds whose units the result takes.
_ABSOLUTE = ("disparity", "distance")


class PriorReport(TypedDict):
    """What the alignment fitted to the prior (``StitchResult.report["prior"]``)."""

    #: The prior's kind.
    kind: str
    #: (a, b): the prior (as spherical disparity) in the result's units is a·P + b; (1, 0) for
    #: an absolute kind (the result is in its units).
    affine: tuple[float, float]
    #: Prior samples the last level used.
    samples: int
    #: Share of the prior's (confidence-weighted) pull its robust weights took away (samples
    #: with weight below ½): the regions where the tangents outvoted it.
    outvoted: float
    #: The prior term's weight (``prior_weight``).
    weight: float
    #: Median |residual| at the prior samples, in standardised units (1 = the prior's mean
    #: absolute deviation).
    residual: float
    #: The tangents' relative spread (std/mean) where two or more see a prior sample, after
    #: the first alignment level; None when not measured (a one-level schedule, or
    #: ``prior_fusion="off"``).
    tangent_spread: float | None
    #: Share (0-1) of the tangents' low-frequency disagreement with the prior that moved the
    #: prior before it joined: 1 where the tangents agree to 0.4 %, 0 from 1.2 % (real
    #: networks: 5-16 %). docs/method.md, "The tangents' own low frequencies".
    tangent_share: float
    #: Share of the prior samples the tangents' consensus outvoted before the prior joined:
    #: where the prior strays from it by more than three of its standard errors and 6 % of the
    #: disparity (docs/method.md, "Outvoted by the consensus"); 0 with fewer than 5 views or
    #: tangents that spread by more than 3 %.
    consensus_outvoted: float
    #: The prior's disagreement with the tangents' consensus at the sphere's largest scales
    #: (relative RMS over spherical harmonics of degree ≤ 2: a prior bent as a whole); 0 when
    #: not measured (where ``consensus_outvoted`` is not, where ``tangent_share`` > 0, or beside
    #: a regional error outvoted in bulk: over 3 % of the samples, all or nearly all one way).
    low_order_gap: float
    #: Share (0-1) of that disagreement that moved the prior before it joined: 1 − (0.008 /
    #: gap)², none up to 0.8 % (docs/method.md, "The sphere's largest scales").
    low_order_share: float


def check_prior(
    prior: Any, kind: Any, confidence: Any = None
) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """Check a prior and convert it to spherical disparity for the core.

    Parameters
    ----------
    prior : (Hp, 2·Hp) float array
        The prior ERP map, any resolution; NaN = unknown.
    kind : str
        One of :data:`PRIOR_KINDS`.
    confidence : (Hp, 2·Hp) float array in [0, 1], optional
        Per-pixel trust in the prior (0 = ignore there).

    Returns
    -------
    (values, confidence, absolute)
        float32 C-contiguous spherical disparity (NaN where unknown or unusable), the
        confidence as float32 or None, and whether the result takes the prior's units.

    Raises
    ------
    m360.InputError
        Naming the problem: shape, aspect, dtype, a kind not in :data:`PRIOR_KINDS`, a prior
        without a usable value, a confidence of another shape or outside [0, 1].
    """
    if not isinstance(kind, str) or kind not in PRIOR_KINDS:
        choices = ", ".join(repr(k) for k in PRIOR_KINDS)
        raise InputError(f"prior_kind={kind!r} is not supported; choose one of {choices}")
    array = erp_map(prior, "prior", integers=True)
    # The same conversion as a panoramic model's output (one definition of the kinds).
    out = to_spherical_disparity(array, kind)
    if not np.isfinite(out).any():
        raise InputError(f"prior has no usable value for prior_kind={kind!r} (all NaN or invalid)")
    conf = None
    if confidence is not None:
        c = as_array(confidence, "prior_confidence")
        if c.shape != array.shape:
            raise InputError(
                f"prior_confidence has shape {c.shape}, the prior {array.shape}: they must match"
            )
        conf = np.ascontiguousarray(c, dtype=np.float32)
        if not np.all((conf >= 0) & (conf <= 1)):
            raise InputError("prior_confidence must lie in [0, 1] everywhere (no NaN)")
    return np.ascontiguousarray(out), conf, kind in _ABSOLUTE
