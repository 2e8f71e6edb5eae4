"""Alignment options of :func:`m360.stitch`: what they mean, their names and defaults.

The tangents are aligned with deformable scale/offset grids per tangent (paper §3.3;
docs/method.md says where m360 departs from it). Every name, default and limit below is read
from the compiled core, which owns them and checks every value (``_core.stitch_options``).

Options
-------
align
    ``"multiscale"`` (default): the energy's schedule :data:`SCHEDULES` of (cols, rows) grid
    nodes per tangent, coarse to fine — the paper's 4x3 → 8x7 → 16x14 with ``energy="paper"``,
    4x3 → 8x7 with the normalized energy (a third 16x14 level measured no more accurate on
    synthetic rooms, median AbsRel 0.0173 with and without it in benches/bench_align.py, while
    its Newton system costs several times the first two levels). ``(cols, rows)``: one level; a
    list of grids: that schedule (e.g. :data:`MULTISCALE`). Each level starts from identity
    fields on the maps as the previous level left them. ``"none"``: values pass through.
energy
    ``"normalized"`` (default): every term is resolution independent — the data term averaged
    over samples, the smoothness a Dirichlet energy of the fields per tangent, the scale term a
    mean of 1/s — so a level's answer depends neither on its grid size nor on when the solver
    stops. ``"paper"``: the paper's energy as printed, (1/z_a) Σ r² + 40/(N·m·n) Σ (Δs² + Δo²) +
    0.007 Σ 1/s; its 1/s term is summed over nodes while the others are averaged, so at fine
    grids it dominates (solved to convergence it degrades even exact tangents).
solver
    ``"newton"`` (default): exact Hessian, sparse Cholesky (faer), converges in a few
    iterations. ``"lbfgs"``: limited-memory BFGS, the paper's solver.
iterations
    Iteration cap per level (None: :data:`DEFAULT_ITERATIONS` of the solver — Newton converges
    long before its cap, L-BFGS stops after the paper's 50).
tolerance
    Converged when the gradient's max-norm ≤ tolerance · max(1, |energy|).
sample_fraction
    Fraction of overlap pixels used by the data term (paper: 1 %), chosen deterministically;
    tangents larger than a 2048-wide layout's (400 x 346) keep that layout's number of samples.
pole_cap_deg
    Leave out overlap samples within this many degrees of either pole.
smoothness, scale_weight
    Term weights (None: :data:`ENERGY_WEIGHTS` of the energy). The paper's are λ_s = 40,
    λ_c = 0.007; the normalized energy's were chosen by measurement (benches/bench_align.py).
offsets
    Where the offset field acts. A network's output is affine in *perspective* disparity and
    spherical = perspective/|q| (q the pixel's ray), so its shift becomes o/|q| in spherical
    disparity, which a spherical offset cannot represent exactly. ``"perspective"`` models
    D̃ = s·D + o/|q| (and standardises in perspective space); ``"spherical"`` is the paper's
    D̃ = s·D + o. None: perspective for the normalized energy, spherical for the paper's.
loss
    The loss on each overlap residual. ``"cauchy"`` (the normalized energy's default) and
    ``"huber"`` are robust: each level is solved, every sample reweighted from its residual
    (scale: 1.4826 × the median absolute residual) and solved again, three times, so a region
    one tangent got wrong (a content error its neighbours do not share) stops pulling the grids.
    ``"squared"``: least squares, the paper's (the paper energy's default). The weights are
    reported per sample (``sample_weights``, ``sample_pixels`` in each level's report).

prior_weight, prior_scale_deg, prior_fusion
    Used only with ``prior=`` (:mod:`m360.stitching.prior`): the weight λ of the prior term
    (default 1) and the frequency split in degrees (default 3): a prior-only level with grid
    nodes this far apart runs after the schedule, and the tangents are compared with the prior
    averaged over half this radius; finer detail stays the tangents'. Measured in
    benches/bench_prior.py (docs/method.md, "Global prior"). ``prior_fusion``: ``"auto"``
    (default) moves the prior's low frequencies towards the tangents' own consensus where the
    tangents agree with each other to better than 1.2 % (in full at 0.4 %), and further where
    the prior strays from that consensus by more than the consensus's own uncertainty explains
    (a prior worse than the tangents; with the default layout's deep overlaps); the stitch
    report's ``tangent_share`` says how far. With those deep overlaps and tangents that spread
    by at most 3 %, it also outvotes the prior samples far outside the consensus's uncertainty
    (``consensus_outvoted``), and where the tangents spread too widely to move the prior sample
    by sample, it corrects the prior's shape at the sphere's largest scales when it strays
    from their consensus there by more than 0.8 % (``low_order_share``: a prior bent as a
    whole). ``"off"`` does none of these, for a prior known to be more accurate than any
    tangent (a LiDAR scan).

When the tangents leave too few valid overlap samples for a level's grid (fewer than one per
four grid nodes: a noisy or featureless panorama), the level is left out; when none is left, one
per-tangent affine level runs if it can, else the tangents are only standardised. The stitch
report's ``align_fallback`` says which (``"none"``, ``"coarser_grid"``, ``"affine"``,
``"unaligned"``) and a warning is logged.
"""

from __future__ import annotations

from typing import Literal, TypedDict

import numpy as np

from .. import _core

__all__ = [
    "ALIGN_MODES",
    "DEFAULT_ITERATIONS",
    "DEFAULT_LOSS",
    "DEFAULT_OFFSETS",
    "ENERGIES",
    "ENERGY_WEIGHTS",
    "LOSSES",
    "MULTISCALE",
    "OFFSETS",
    "SCHEDULES",
    "SOLVERS",
    "AlignLevelReport",
    "AlignMode",
    "AlignSolver",
    "Energy",
    "Loss",
    "Offsets",
    "PriorFusion",
]

#: Alignment modes by name; a (cols, rows) grid or a list of them gives an explicit schedule.
AlignMode = Literal["multiscale", "none"]
#: Alignment energies (the core's ``CHOICES["energy"]``; the first is the default).
Energy = Literal["normalized", "paper"]
#: Alignment solvers (the core's ``CHOICES["solver"]``).
AlignSolver = Literal["newton", "lbfgs"]
#: Where the offset acts (the core's ``CHOICES["offsets"]``).
Offsets = Literal["perspective", "spherical"]
#: Losses of the data term (the core's ``CHOICES["loss"]``).
Loss = Literal["cauchy", "huber", "squared"]
#: Whether a prior is fused with the tangents' own low frequencies (``CHOICES["prior_fusion"]``).
PriorFusion = Literal["auto", "off"]

ALIGN_MODES: tuple[str, ...] = ("multiscale", "none")
ENERGIES: tuple[str, ...] = tuple(_core.CHOICES["energy"])
SOLVERS: tuple[str, ...] = tuple(_core.CHOICES["solver"])
OFFSETS: tuple[str, ...] = tuple(_core.CHOICES["offsets"])
LOSSES: tuple[str, ...] = tuple(_core.CHOICES["loss"])
#: What ``align="multiscale"`` runs for each energy: (cols, rows) nodes per level.
SCHEDULES: dict[str, tuple[tuple[int, int], ...]] = {
    energy: tuple((int(c), int(r)) for c, r in levels)
    for energy, levels in _core.DEFAULTS["schedules"].items()
}
#: The paper's multi-scale schedule, coarse to fine.
MULTISCALE: tuple[tuple[int, int], ...] = SCHEDULES["paper"]
#: Iteration cap per level of each solver when ``iterations`` is None.
DEFAULT_ITERATIONS: dict[str, int] = {k: int(v) for k, v in _core.DEFAULTS["iterations"].items()}


#: Term weights (smoothness, scale_weight) of each energy.
ENERGY_WEIGHTS: dict[str, tuple[float, float]] = {
    energy: (float(weights[0]), float(weights[1]))
    for energy, weights in _core.DEFAULTS["weights"].items()
}
#: Where the offset acts by default for each energy.
DEFAULT_OFFSETS: dict[str, str] = {
    energy: str(offsets) for energy, offsets in _core.DEFAULTS["offsets"].items()
}


#: The data-term loss by default for each energy.
DEFAULT_LOSS: dict[str, str] = {
    energy: str(loss) for energy, loss in _core.DEFAULTS["losses"].items()
}


class AlignLevelReport(TypedDict):
    """The solver's report of one alignment level (``StitchResult.report["align"][k]``)."""

    grid: tuple[int, int]
    iterations: int
    initial_energy: float
    energy: float
    gradient_norm: float
    converged: bool
    samples: int
    build_seconds: float
    solve_seconds: float
    #: The data term's loss and, for a robust one, the residual scale of the last reweighting.
    loss: str
    robust_scale: float
    #: (K,) float32 weight of each valid overlap sample after the last reweighting, and (K, 3)
    #: int64 where it is: (tangent a, pixel index row·w + col in a, tangent b).
    sample_weights: np.ndarray
    sample_pixels: np.ndarray
