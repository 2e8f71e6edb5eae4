"""The stitching core: per-tangent perspective disparity in, one ERP spherical disparity out."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._validate import as_array, check_shape
from .errors import InputError
from .geometry import Layout, check_tiles, plan_for

__all__ = ["ALIGN_MODES", "BLEND_MODES", "FIDELITY_TARGETS", "StitchResult", "stitch"]

#: Alignment modes implemented in this version.
ALIGN_MODES = ("none",)
#: Blend modes implemented in this version.
BLEND_MODES = ("poisson", "frustum", "radial", "mean", "nn")
#: Fidelity targets of the Poisson blend; the first is the default (see ``blend_options``).
FIDELITY_TARGETS = ("frustum", "nn", "mean")
_PLANNED_ALIGN = ("multiscale",)
_PLANNED_BLEND: tuple[str, ...] = ()
_BLEND_OPTION_DEFAULTS: dict[str, Any] = {
    "fidelity": FIDELITY_TARGETS[0],
    "lam": 0.1,
    "tol": 1e-6,
    "max_iterations": 2000,
    "solver": "fused",
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
    align: str = "multiscale",
    blend: str = "poisson",
    *,
    mask: np.ndarray | None = None,
    blend_options: Mapping[str, Any] | None = None,
    return_details: bool = False,
) -> np.ndarray | StitchResult:
    """Stitch per-tangent perspective disparity into one ERP spherical disparity map.

    Each tangent value is first converted from perspective disparity (1/z, what a monocular
    network predicts up to scale and shift) to spherical disparity (1/distance) with its own
    pixel's ray length, then mapped to the ERP grid (bilinear at the exact projected position)
    and blended.

    Parameters
    ----------
    tangent_disparity : (N, h, w) float32
        One perspective disparity map per camera of ``layout``; NaN marks pixels without an
        estimate. float64 is converted.
    layout : Layout
        The layout the tangents were made with.
    align : str
        ``"none"``: values pass through unchanged (no standardisation). ``"multiscale"`` (the
        default of the method) comes with the alignment module; until then it raises InputError.
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
        through a bilinear neighbour.
    blend_options : mapping, optional
        Options of ``blend="poisson"``: ``fidelity`` (``"frustum"``, the default: the frustum
        blend, which measured best on AbsRel and seams together; ``"nn"``: the nearest-face
        stitch, as in the paper; ``"mean"``), ``lam`` (λ > 0, default 0.1), ``tol`` (relative
        residual in (0, 1), default 1e-6), ``max_iterations`` (default 2000), ``solver``
        (``"fused"``, the default, our fused-sweep conjugate gradient, or ``"faer"``, faer's
        conjugate gradient on the same operator; both matrix-free, Jacobi-preconditioned, f64,
        warm-started from the target). A solve that does not reach ``tol`` raises
        :class:`m360.SolverError`.
    return_details : bool
        Return a :class:`StitchResult` instead of the disparity array.

    Returns
    -------
    (H, W) float32 spherical disparity, NaN where no tangent has a valid value; or a
    StitchResult.
    """
    t0 = time.perf_counter()
    tiles = check_tiles(tangent_disparity, layout, "tangent_disparity")
    align = _mode(align, "align", ALIGN_MODES, _PLANNED_ALIGN)
    blend = _mode(blend, "blend", BLEND_MODES, _PLANNED_BLEND)
    valid = None if mask is None else _check_mask(mask, layout)
    options = _blend_options(blend_options, blend)
    if not isinstance(return_details, bool):
        raise InputError(f"return_details must be True or False, got {return_details!r}")

    plan = plan_for(layout)
    spherical = plan.spherical_disparity(tiles, valid)
    t1 = time.perf_counter()
    t2 = t1  # alignment: "none" passes the values through
    disparity, spread, blend_report = plan.blend(spherical, blend, **options)
    t3 = time.perf_counter()
    blend_report["seconds"] = t3 - t2
    if not return_details:
        return disparity
    return StitchResult(
        disparity=disparity,
        confidence=spread,
        coverage=plan.coverage(),
        report={"blend": blend_report},
        timings={"convert": t1 - t0, "align": t2 - t1, "blend": t3 - t2},
    )


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
    unknown = sorted(set(options) - set(_BLEND_OPTION_DEFAULTS))
    if unknown:
        known = ", ".join(_BLEND_OPTION_DEFAULTS)
        raise InputError(f"unknown blend_options {unknown}; known: {known}")
    if options and blend != "poisson":
        raise InputError(f"blend_options apply to blend='poisson' only, got blend={blend!r}")
    out = {**_BLEND_OPTION_DEFAULTS, **options}
    if out["fidelity"] not in FIDELITY_TARGETS:
        choices = ", ".join(repr(f) for f in FIDELITY_TARGETS)
        raise InputError(f"blend_options fidelity={out['fidelity']!r}: choose one of {choices}")
    lam, tol, iters = out["lam"], out["tol"], out["max_iterations"]
    if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not (0 < lam < np.inf):
        raise InputError(f"blend_options lam={lam!r} must be a finite number > 0")
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (0 < tol < 1):
        raise InputError(f"blend_options tol={tol!r} must be a number in (0, 1)")
    if isinstance(iters, bool) or not isinstance(iters, (int, np.integer)) or iters < 1:
        raise InputError(f"blend_options max_iterations={iters!r} must be an integer >= 1")
    if out["solver"] not in ("fused", "faer"):
        raise InputError(f"blend_options solver={out['solver']!r}: choose 'fused' or 'faer'")
    return {
        "fidelity": out["fidelity"],
        "lam": float(lam),
        "tol": float(tol),
        "max_iterations": int(iters),
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
