"""Blending options of :func:`m360.stitch`: what they mean, their names and defaults.

How the tangents that see an ERP pixel are combined (paper §3.4; docs/method.md). Weights come
from each face's own geometry and are sampled at the pixel like the disparity. Every name,
default and limit below is read from the compiled core, which owns them and checks every value
(``_core.stitch_options``).

Methods
-------
``"consensus"`` (default)
    Disagreement-aware frustum blend: per ERP pixel an iteratively reweighted mean of the
    tangents that see it, the frustum weights as prior, each tangent's weight multiplied by the
    Cauchy weight 1/(1 + (e/c)²) of its distance e from the current consensus (c = 2.385·σ,
    σ = 1.4826 × the median distance of a tangent's value from its pixel's frustum blend, over
    a regular subsample of the pixels two or more tangents see), three times. Where three or
    more tangents see a pixel, one that disagrees with the others (a content error of the
    network, which the overlapping tangent does not share) loses its say; where two disagree
    the frustum weights decide as in ``"frustum"``. The ``confidence`` output is the
    disagreement left, √(Σ p·e²/(1 + (e/c)²) / Σ p) with p the frustum weights: a tangent
    voted down still marks its footprint there.
    Measured on synthetic rooms with content errors it beats ``"poisson"`` on AbsRel at about
    half the time (benches/bench_align.py ``--robust``; README).
``"poisson"``
    The paper's gradient-domain blend, minimising
    ``Σ_a Σ_x ω_a(x)‖∇B(x) - ∇D_a(x)‖² + λ Σ_x (B(x) - T(x))²`` with ω_a the frustum weights
    (taken at each difference's midpoint, the mean of its two ends, so both poles and both
    longitude directions are treated alike), forward differences on the
    ERP grid (periodic in longitude, no edge across a pole), λ = ``lam`` and T the fidelity
    target; solved (matrix-free, float64, warm-started from the target) to a relative residual
    ≤ ``tolerance``. A solve that does not reach it raises :class:`m360.SolverError`.
``"frustum"``
    Weights 1 in the centre of each tangent image, falling linearly to 0 at its border, the ramp
    starting 30 % of the way in from each corner along the diagonal; the fast seam-free choice.
``"median"``
    Where three or more tangents see a pixel, the median of their values weighted by the
    frustum weights (the smallest value whose cumulative weight, in increasing order, reaches
    half the total); the frustum blend elsewhere. A tangent that disagrees with the others has
    no pull at all, but the result jumps where the set of tangents changes.
``"radial"``
    Weights 1 within 15° of the optical axis, falling linearly to 0 at the image's inscribed half
    field of view (plain mean where every weight is 0).
``"mean"``
    Average of every tangent that sees the pixel.
``"nn"``
    The tangent whose un-padded face contains the pixel (falling back to the next nearest face
    where that one has no valid value).

Poisson options (``blend_options``; refused for another method)
----------------------------------------------------------------
fidelity
    The target T: ``"frustum"`` (default: the frustum blend, which measured best on AbsRel and
    seams together), ``"nn"`` (the nearest-face stitch, as in the paper), ``"mean"`` or
    ``"consensus"`` (the ``"consensus"`` blend; then ``confidence`` is that blend's).
lam
    λ > 0, the weight of the fidelity term (it anchors the solution).
tolerance
    Relative residual to reach, in [:data:`MIN_POISSON_TOLERANCE`, 1): a float64 conjugate
    gradient stalls near 1e-14, so a tighter request could only spin until ``iterations``.
iterations
    Iteration cap of the solve.
solver
    ``"multigrid"`` (default: conjugate gradients preconditioned by a multigrid V-cycle on the
    ERP grid), ``"fused"`` (fused-sweep Jacobi-preconditioned CG) or ``"faer"`` (faer's CG with
    the Jacobi preconditioner).
"""

from __future__ import annotations

from typing import Literal, TypedDict

from .. import _core

__all__ = [
    "BLEND_METHODS",
    "FIDELITY_TARGETS",
    "MIN_POISSON_TOLERANCE",
    "POISSON_DEFAULTS",
    "POISSON_SOLVERS",
    "WEIGHT_MAPS",
    "BlendMethod",
    "BlendReport",
    "Fidelity",
    "PoissonSolver",
]

#: Blend methods (the core's ``CHOICES["blend"]``; the first is the default).
BlendMethod = Literal["consensus", "poisson", "frustum", "median", "radial", "mean", "nn"]
#: Fidelity targets of the Poisson blend (the core's ``CHOICES["fidelity"]``).
Fidelity = Literal["frustum", "nn", "mean", "consensus"]
#: Solvers of the Poisson blend (the core's ``CHOICES["poisson_solver"]``).
PoissonSolver = Literal["multigrid", "fused", "faer"]

BLEND_METHODS: tuple[str, ...] = tuple(_core.CHOICES["blend"])
FIDELITY_TARGETS: tuple[str, ...] = tuple(_core.CHOICES["fidelity"])
POISSON_SOLVERS: tuple[str, ...] = tuple(_core.CHOICES["poisson_solver"])
#: Per-face weight maps ``Plan.blend_weights`` draws.
WEIGHT_MAPS: tuple[str, ...] = tuple(_core.CHOICES["weights"])
#: Smallest Poisson tolerance the core accepts.
MIN_POISSON_TOLERANCE: float = float(_core.LIMITS["min_poisson_tolerance"])
#: The Poisson options the core fills in (``method`` included).
POISSON_DEFAULTS: dict[str, object] = dict(_core.DEFAULTS["poisson"])


class _BlendReportBase(TypedDict):
    method: BlendMethod
    seconds: float


class BlendReport(_BlendReportBase, total=False):
    """The blend's report, ``StitchResult.report["blend"]``.

    ``method`` and ``seconds`` always; the rest for ``"poisson"`` only.
    """

    solver: PoissonSolver
    iterations: int
    relative_residual: float
    initial_residual: float
    tolerance: float
    converged: bool
    lam: float
    fidelity: Fidelity
    unknowns: int
    assemble_seconds: float
    solve_seconds: float
