"""The stitching core: per-tangent perspective disparity in, one ERP spherical disparity out."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._validate import MAX_ITERATIONS, as_array, check_shape, integer, number, one_of
from .errors import InputError
from .geometry import Layout, check_tiles, plan_for

__all__ = [
    "ALIGN_MODES",
    "BLEND_MODES",
    "ENERGIES",
    "FIDELITY_TARGETS",
    "MULTISCALE",
    "SCHEDULES",
    "SOLVERS",
    "StitchResult",
    "stitch",
]

#: Alignment modes by name; a (cols, rows) grid or a list of them gives an explicit schedule.
ALIGN_MODES = ("multiscale", "none")
#: The paper's multi-scale schedule of (cols, rows) grid nodes per tangent, coarse to fine.
MULTISCALE = ((4, 3), (8, 7), (16, 14))
#: What ``align="multiscale"`` runs for each energy. The paper's energy gets the paper's
#: schedule. With the normalized energy a third 16x14 level measured no more accurate on
#: synthetic rooms (median AbsRel 0.0173 with and without it, benches/bench_align.py) while
#: its Newton system (8,960 unknowns, heavy fill from overlapping tangents) costs several times
#: the first two levels, so its schedule stops at 8x7.
SCHEDULES = {"normalized": ((4, 3), (8, 7)), "paper": MULTISCALE}
#: Energies: "normalized" (well-posed, the default) or "paper" (the formula as printed).
ENERGIES = ("normalized", "paper")
#: Solvers: "newton" (exact Hessian, sparse Cholesky) or "lbfgs" (the paper's choice).
SOLVERS = ("newton", "lbfgs")
#: Term weights (smoothness, scale) of each energy. The paper's are λ_s = 40, λ_c = 0.007;
#: the normalized energy's were chosen by measurement on synthetic rooms (benches/bench_align.py).
ENERGY_WEIGHTS = {"paper": (40.0, 0.007), "normalized": (1.0, 0.01)}
#: Where the alignment offset acts: "perspective" (D̃ = s·D + o/|q|: a network's affine error
#: is exactly representable) or "spherical" (D̃ = s·D + o, the paper's formula).
OFFSETS = ("perspective", "spherical")
DEFAULT_OFFSETS = {"normalized": "perspective", "paper": "spherical"}
#: Iteration cap per level when `iterations` is None: Newton converges long before its cap;
#: L-BFGS stops after the paper's 50.
DEFAULT_ITERATIONS = {"newton": 100, "lbfgs": 50}
#: Blend modes implemented in this version.
BLEND_MODES = ("poisson", "frustum", "radial", "mean", "nn")
#: Fidelity targets of the Poisson blend; the first is the default (see ``blend_options``).
FIDELITY_TARGETS = ("frustum", "nn", "mean")
#: Poisson solvers: multigrid-preconditioned CG (default), Jacobi-preconditioned CG, faer's CG.
POISSON_SOLVERS = ("multigrid", "fused", "faer")
#: Smallest Poisson tolerance: a float64 conjugate gradient stalls near 1e-14 relative residual,
#: so a tighter request could only spin until ``max_iterations`` and fail.
MIN_POISSON_TOL = 1e-13
_PLANNED_ALIGN: tuple[str, ...] = ()
_PLANNED_BLEND: tuple[str, ...] = ()
_BLEND_OPTION_DEFAULTS: dict[str, Any] = {
    "fidelity": FIDELITY_TARGETS[0],
    "lam": 0.1,
    "tol": 1e-6,
    "max_iterations": 2000,
    "solver": POISSON_SOLVERS[0],
}


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
        Solver reports per stage. ``report["blend"]`` always has ``mode`` and ``seconds``; for
        ``blend="poisson"`` also ``iterations``, ``relative_residual`` (true ‖Ax - b‖/‖b‖ of the
        solution), ``initial_residual``, ``tolerance``, ``converged``, ``lambda``, ``fidelity``,
        ``unknowns``, ``assemble_seconds``, ``solve_seconds`` and ``solver``.
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
    align: str | tuple[int, int] | Sequence[tuple[int, int]] = "multiscale",
    blend: str = "poisson",
    *,
    mask: np.ndarray | None = None,
    energy: str = "normalized",
    solver: str = "newton",
    iterations: int | None = None,
    tolerance: float = 1e-6,
    sample_fraction: float = 0.01,
    pole_cap_deg: float = 0.0,
    smoothness: float | None = None,
    scale_weight: float | None = None,
    offsets: str | None = None,
    blend_options: Mapping[str, Any] | None = None,
    return_details: bool = False,
) -> np.ndarray | StitchResult:
    """Stitch per-tangent perspective disparity into one ERP spherical disparity map.

    Each tangent value is first converted from perspective disparity (1/z, what a monocular
    network predicts up to scale and shift) to spherical disparity (1/distance) with its own
    pixel's ray length; the tangents are then aligned (paper §3.3), mapped to the ERP grid
    (bilinear at the exact projected position) and blended.

    Parameters
    ----------
    tangent_disparity : (N, h, w) float32
        One perspective disparity map per camera of ``layout``; NaN marks pixels without an
        estimate. float64 is converted.
    layout : Layout
        The layout the tangents were made with.
    align : str, (cols, rows) or list of (cols, rows)
        ``"multiscale"``: the energy's schedule :data:`SCHEDULES` of grid nodes per tangent —
        the paper's 4x3 → 8x7 → 16x14 with ``energy="paper"``, 4x3 → 8x7 with the normalized
        energy (a 16x14 level measured no more accurate, at several times the cost). ``(cols,
        rows)``: one level; a list: that schedule (e.g. :data:`MULTISCALE`). Each level starts
        from identity fields on the maps as the previous level left them. ``"none"``: values
        pass through unchanged (no standardisation).
    blend : str
        How the tangents that see an ERP pixel are combined (paper §3.4). Weights come from each
        face's own geometry and are sampled at the pixel like the disparity:

        - ``"poisson"`` (default): gradient-domain blend, minimising
          ``Σ_a Σ_x ω_a(x)‖∇B(x) - ∇D_a(x)‖² + λ Σ_x (B(x) - T(x))²`` with ω_a the frustum
          weights (taken at each difference's midpoint, the mean of its two ends, so both poles
          and both longitude directions are treated alike), forward differences on the ERP grid
          (periodic in longitude, no edge across a pole), λ = 0.1 and T the fidelity target
          (``blend_options["fidelity"]``); solved to a relative residual ≤ 1e-6.
        - ``"frustum"``: weights 1 in the centre of each tangent image, falling linearly to 0 at
          its border, the ramp starting 30 % of the way in from each corner along the diagonal;
          the fast choice, seam-free.
        - ``"radial"``: weights 1 within 15° of the optical axis, falling linearly to 0 at the
          image's inscribed half field of view (plain mean where every weight is 0).
        - ``"mean"``: average of every tangent that sees the pixel.
        - ``"nn"``: the tangent whose un-padded face contains the pixel (falling back to the
          next nearest face where that one has no valid value).
    mask : (N, h, w) bool, optional
        False marks pixels with no estimate (sky, tripod). They never contribute, not even
        through a bilinear neighbour, and are left out of standardisation and overlaps.
    energy : {"normalized", "paper"}
        ``"paper"``: the paper's energy as printed, (1/z_a) Σ r² + 40/(N·m·n) Σ (Δs² + Δo²) +
        0.007 Σ 1/s. Its 1/s term is summed over nodes while the others are averaged, so at fine
        grids it dominates and the optimum depends on the grid (solved to convergence it degrades
        even exact tangents). ``"normalized"`` (default): every term is resolution independent —
        the data term averaged over samples, the smoothness a Dirichlet energy of the fields per
        tangent, the scale term a mean of 1/s — so each level's answer does not depend on its
        grid size or on when the solver stops.
    solver : {"newton", "lbfgs"}
        ``"newton"``: exact Hessian, sparse Cholesky (faer), converges in a few iterations.
        ``"lbfgs"``: limited-memory BFGS, the paper's solver.
    iterations : int, optional
        Iteration cap per level, at most 100,000; default 100 for Newton (it converges first)
        and 50 for L-BFGS (the paper's setting).
    tolerance : float
        Converged when the gradient's max-norm ≤ tolerance · max(1, |energy|).
    sample_fraction : float
        Fraction of overlap pixels used by the data term (paper: 1 %), chosen deterministically.
    pole_cap_deg : float
        Leave out overlap samples within this many degrees of either pole.
    smoothness, scale_weight : float, optional
        Term weights; default :data:`ENERGY_WEIGHTS` of the chosen energy.
    offsets : {"perspective", "spherical"}, optional
        Where the offset field acts. A network's output is affine in *perspective* disparity,
        and spherical = perspective/|q| (q the pixel's ray), so its shift becomes o/|q| in
        spherical disparity, which a spherical offset cannot represent exactly.
        ``"perspective"`` models D̃ = s·D + o/|q| (and standardises in perspective space);
        ``"spherical"`` is the paper's D̃ = s·D + o. Default: perspective for the normalized
        energy, spherical for ``energy="paper"``.
    blend_options : mapping, optional
        Options of ``blend="poisson"``: ``fidelity`` (``"frustum"``, the default: the frustum
        blend, which measured best on AbsRel and seams together; ``"nn"``: the nearest-face
        stitch, as in the paper; ``"mean"``), ``lam`` (λ > 0, default 0.1), ``tol`` (relative
        residual in (0, 1), default 1e-6), ``max_iterations`` (default 2000), ``solver``
        (``"multigrid"``, the default: conjugate gradients preconditioned by a multigrid
        V-cycle on the ERP grid; ``"fused"``: our fused-sweep Jacobi-preconditioned CG;
        ``"faer"``: faer's CG with the Jacobi preconditioner; all matrix-free, f64, warm-started
        from the target). A solve that does not reach ``tol`` raises :class:`m360.SolverError`.
    return_details : bool
        Return a :class:`StitchResult` instead of the disparity array.

    Returns
    -------
    (H, W) float32 spherical disparity, NaN where no tangent has a valid value; or a
    StitchResult. With alignment the result is in the input's range up to one global affine map.
    """
    t0 = time.perf_counter()
    tiles = check_tiles(tangent_disparity, layout, "tangent_disparity")
    energy = one_of(energy, "energy", ENERGIES)
    schedule = _schedule(align, layout, energy)
    blend = _mode(blend, "blend", BLEND_MODES, _PLANNED_BLEND)
    solver = one_of(solver, "solver", SOLVERS)
    max_iterations = DEFAULT_ITERATIONS[solver] if iterations is None else _count(iterations)
    tolerance = number(tolerance, "tolerance", low=0.0)
    sample_fraction = number(sample_fraction, "sample_fraction", low=0.0, high=1.0)
    pole_cap_deg = number(pole_cap_deg, "pole_cap_deg", low=0.0, high=89.0)
    default_smooth, default_scale = ENERGY_WEIGHTS[energy]
    smooth = default_smooth if smoothness is None else number(smoothness, "smoothness", low=0.0)
    scale = default_scale if scale_weight is None else number(scale_weight, "scale_weight")
    if scale <= 0:
        raise InputError(f"scale_weight={scale_weight!r} must be > 0 (it keeps the scales from 0)")
    offset_space = (
        DEFAULT_OFFSETS[energy] if offsets is None else one_of(offsets, "offsets", OFFSETS)
    )
    valid = None if mask is None else _check_mask(mask, layout)
    options = _blend_options(blend_options, blend)
    if not isinstance(return_details, bool):
        raise InputError(f"return_details must be True or False, got {return_details!r}")

    plan = plan_for(layout)
    spherical = plan.spherical_disparity(tiles, valid)
    t1 = time.perf_counter()
    grids: list[np.ndarray] = []
    report: dict[str, Any] = {}
    if schedule:
        spherical, levels, grids = plan.align(
            spherical, schedule, energy, smooth, scale, solver, max_iterations, tolerance,
            sample_fraction, pole_cap_deg, offset_space,
        )  # fmt: skip
        report["align"] = levels
    t2 = time.perf_counter()
    # The spread (returned as confidence) costs a second pass: only computed when returned.
    disparity, spread, blend_report = plan.blend(spherical, blend, spread=return_details, **options)
    t3 = time.perf_counter()
    blend_report["seconds"] = t3 - t2
    if not return_details:
        return disparity
    assert spread is not None  # asked for with return_details
    return StitchResult(
        disparity=disparity,
        confidence=spread,
        coverage=plan.coverage(),
        grids=grids,
        report={**report, "blend": blend_report},
        timings={"convert": t1 - t0, "align": t2 - t1, "blend": t3 - t2},
    )


def _schedule(align: object, layout: Layout, energy: str) -> list[tuple[int, int]]:
    """The list of (cols, rows) levels that ``align`` asks for ([] for "none")."""
    if isinstance(align, str):
        if align == "none":
            return []
        if align == "multiscale":
            return list(SCHEDULES[energy])
        _mode(align, "align", ALIGN_MODES, _PLANNED_ALIGN)
    levels: list[tuple[int, int]]
    if _is_grid(align):
        levels = [align]  # type: ignore[list-item]
    elif isinstance(align, (list, tuple)) and align and all(_is_grid(g) for g in align):
        levels = list(align)
    else:
        raise InputError(
            f"align={align!r} is not supported; use 'multiscale', 'none', a (cols, rows) grid "
            "or a list of grids such as [(4, 3), (8, 7)]"
        )
    h, w = layout.tangent_shape
    out = []
    for grid in levels:
        cols, rows = int(grid[0]), int(grid[1])
        if cols < 2 or rows < 2:
            raise InputError(f"alignment grid {grid!r} needs at least 2 x 2 nodes (cols, rows)")
        if cols > w or rows > h:
            raise InputError(
                f"alignment grid {grid!r} has more nodes than the tangent has pixels ({w}x{h})"
            )
        out.append((cols, rows))
    return out


def _is_grid(value: object) -> bool:
    return (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value)
    )


def _count(value: object) -> int:
    return integer(value, "iterations", low=0, high=MAX_ITERATIONS)


def _mode(value: object, name: str, available: tuple[str, ...], planned: tuple[str, ...]) -> str:
    if isinstance(value, str) and value in available:
        return value
    options = ", ".join(repr(v) for v in available)
    if isinstance(value, str) and value in planned:
        raise InputError(f"{name}={value!r} is not available in this version yet; use {options}")
    raise InputError(f"{name}={value!r} is not supported; choose one of {options}")


def _blend_options(options: Mapping[str, Any] | None, blend: str) -> dict[str, Any]:
    if options is None:
        return dict(_BLEND_OPTION_DEFAULTS) if blend == "poisson" else {}
    if not isinstance(options, Mapping):
        raise InputError(f"blend_options must be a mapping, got {type(options).__name__}")
    unknown = sorted(set(options) - set(_BLEND_OPTION_DEFAULTS), key=repr)
    if unknown:
        known = ", ".join(_BLEND_OPTION_DEFAULTS)
        raise InputError(f"unknown blend_options {unknown}; known: {known}")
    if options and blend != "poisson":
        raise InputError(f"blend_options apply to blend='poisson' only, got blend={blend!r}")
    out = {**_BLEND_OPTION_DEFAULTS, **options}
    if not isinstance(out["fidelity"], str) or out["fidelity"] not in FIDELITY_TARGETS:
        choices = ", ".join(repr(f) for f in FIDELITY_TARGETS)
        raise InputError(f"blend_options fidelity={out['fidelity']!r}: choose one of {choices}")
    lam = number(out["lam"], "blend_options lam", low=0.0)
    if lam == 0:
        raise InputError("blend_options lam=0 must be > 0 (it anchors the Poisson solution)")
    tol = number(out["tol"], "blend_options tol", low=MIN_POISSON_TOL, high=1.0)
    if tol == 1:
        raise InputError("blend_options tol=1 must be < 1")
    iters = integer(out["max_iterations"], "blend_options max_iterations", 1, MAX_ITERATIONS)
    if not isinstance(out["solver"], str) or out["solver"] not in POISSON_SOLVERS:
        raise InputError(
            f"blend_options solver={out['solver']!r}: choose 'multigrid', 'fused' or 'faer'"
        )
    return {
        "fidelity": out["fidelity"],
        "lam": lam,
        "tol": tol,
        "max_iterations": iters,
        "solver": out["solver"],
    }


def _check_mask(mask: np.ndarray, layout: Layout) -> np.ndarray:
    array = as_array(mask, "mask")
    h, w = layout.tangent_shape
    check_shape(array, "mask", ("N", "h", "w"), N=len(layout), h=h, w=w)
    if array.dtype != np.bool_:
        raise InputError(
            f"mask must be a bool array (False = no estimate), got dtype {array.dtype}"
        )
    return np.ascontiguousarray(array)
