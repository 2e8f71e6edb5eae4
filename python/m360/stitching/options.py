"""One validated, canonical set of stitching options: :class:`StitchOptions`.

:func:`m360.stitch`, :func:`m360.estimate`, :func:`m360.batch.run` and ``m360 run`` take the same
stitching keywords (see :mod:`m360.align` and :mod:`m360.blend` for what each means) or a ready
``options=StitchOptions(...)``. Python only normalises the *types* of the keywords; the compiled
core fills in its defaults and judges every value (``_core.stitch_options``), so names, defaults
and limits live in one place.
"""

from __future__ import annotations

import argparse
import copy
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Annotated, Any, TypedDict

import numpy as np

from .. import _core
from .._keywords import Option, document, split
from .._validate import count, real, text
from ..errors import InputError
from .align import (
    ALIGN_MODES,
    DEFAULT_LOSS,
    DEFAULT_OFFSETS,
    ENERGY_WEIGHTS,
    AlignSolver,
    Energy,
    Loss,
    Offsets,
    PriorFusion,
)
from .blend import BlendMethod, Fidelity, PoissonSolver

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "AlignOptions",
    "AlignSpec",
    "BlendOptions",
    "StitchKeywords",
    "StitchOptions",
    "StitchTuning",
    "multiscale_levels",
    "parse_align",
]

#: What ``align`` may be: ``"multiscale"``, ``"none"``, a (cols, rows) grid or a list of grids.
AlignSpec = str | tuple[int, int] | Sequence[tuple[int, int]]


def parse_align(text: str) -> AlignSpec:
    """Read ``--align``: a mode name, or grids ``COLSxROWS[,COLSxROWS...]`` (e.g. ``4x3,8x7``)."""
    if text in ALIGN_MODES:
        return text
    try:
        grids = [tuple(int(v) for v in g.lower().split("x")) for g in text.split(",")]
    except ValueError:
        grids = []
    if not grids or any(len(g) != 2 for g in grids):
        raise argparse.ArgumentTypeError(
            f"{text!r}: use {' or '.join(ALIGN_MODES)}, or grids COLSxROWS[,COLSxROWS...] "
            "such as 4x3,8x7"
        )
    return [(g[0], g[1]) for g in grids]


# The help texts show the core's defaults (names, defaults and limits live in the core).
_ALIGN = _core.DEFAULTS["align"]
_POISSON = _core.DEFAULTS["poisson"]
_CHOICES = _core.CHOICES
_SCHEDULES = "; ".join(
    f"{energy}: {','.join(f'{c}x{r}' for c, r in levels)}"
    for energy, levels in _core.DEFAULTS["schedules"].items()
)
_PER_SOLVER = ", ".join(f"{k} {v}" for k, v in _core.DEFAULTS["iterations"].items())


def _per_energy(values: Mapping[str, Any]) -> str:
    return ", ".join(f"{energy} {value}" for energy, value in values.items())


@document
class StitchTuning(TypedDict, total=False):
    """The stitching options beyond ``align`` and ``blend`` (:mod:`m360.align`, :mod:`m360.blend`).

    Each is None or absent for the core's default.
    """

    energy: Annotated[
        Energy | None,
        Option(f"alignment energy (default {_ALIGN['energy']})", choices=_CHOICES["energy"]),
    ]
    solver: Annotated[
        AlignSolver | None,
        Option(f"alignment solver (default {_ALIGN['solver']})", choices=_CHOICES["solver"]),
    ]
    iterations: Annotated[
        int | None,
        Option(f"alignment iteration cap per level (default per solver: {_PER_SOLVER})", parse=int),
    ]
    tolerance: Annotated[
        float | None,
        Option(f"alignment gradient tolerance (default {_ALIGN['tolerance']:g})", parse=float),
    ]
    sample_fraction: Annotated[
        float | None,
        Option(
            f"fraction of overlap pixels in the data term (default {_ALIGN['sample_fraction']:g})",
            parse=float,
        ),
    ]
    pole_cap_deg: Annotated[
        float | None,
        Option(
            f"leave out samples this close to the poles (default {_ALIGN['pole_cap_deg']:g})",
            parse=float,
        ),
    ]
    smoothness: Annotated[
        float | None,
        Option(
            "smoothness weight (default per energy: "
            f"{_per_energy({e: f'{w[0]:g}' for e, w in ENERGY_WEIGHTS.items()})})",
            parse=float,
        ),
    ]
    scale_weight: Annotated[
        float | None,
        Option(
            "scale term weight (default per energy: "
            f"{_per_energy({e: f'{w[1]:g}' for e, w in ENERGY_WEIGHTS.items()})})",
            parse=float,
        ),
    ]
    offsets: Annotated[
        Offsets | None,
        Option(
            f"where the offset acts (default per energy: {_per_energy(DEFAULT_OFFSETS)})",
            choices=_CHOICES["offsets"],
        ),
    ]
    loss: Annotated[
        Loss | None,
        Option(
            f"data-term loss (default per energy: {_per_energy(DEFAULT_LOSS)})",
            choices=_CHOICES["loss"],
        ),
    ]
    prior_weight: Annotated[
        float | None,
        Option(
            f"weight of the global prior's term, used with a prior (default "
            f"{_ALIGN['prior_weight']:g})",
            parse=float,
        ),
    ]
    prior_scale_deg: Annotated[
        float | None,
        Option(
            "frequency split of the prior, degrees: the tangents are compared with the prior "
            f"averaged over this radius (default {_ALIGN['prior_scale_deg']:g})",
            parse=float,
        ),
    ]
    prior_fusion: Annotated[
        PriorFusion | None,
        Option(
            "whether the prior's low frequencies move towards the tangents' own where they "
            "agree with each other (auto: by their measured spread and the prior's measured "
            "disagreement with them; prior samples far outside their consensus are outvoted, "
            "and a prior bent as a whole is straightened at the sphere's largest scales; off: "
            "none of these, for a prior more accurate than any network; "
            f"default {_ALIGN['prior_fusion']})",
            choices=_CHOICES["prior_fusion"],
        ),
    ]
    blend_options: Annotated[
        Mapping[str, Any] | None,
        Option(
            "Poisson blend options fidelity, lam, tolerance, iterations, solver (they select "
            "the Poisson blend when blend is not given)",
            parts={
                "fidelity": Option(
                    f"Poisson fidelity target (default {_POISSON['fidelity']})",
                    choices=_CHOICES["fidelity"],
                    flag="--poisson-fidelity",
                    aliases=("--fidelity",),
                ),
                "lam": Option(
                    f"Poisson fidelity weight λ (default {_POISSON['lam']:g})",
                    parse=float,
                    flag="--poisson-lam",
                ),
                "tolerance": Option(
                    f"Poisson relative residual (default {_POISSON['tolerance']:g})",
                    parse=float,
                    flag="--poisson-tolerance",
                ),
                "iterations": Option(
                    f"Poisson iteration cap (default {_POISSON['iterations']})",
                    parse=int,
                    flag="--poisson-iterations",
                ),
                "solver": Option(
                    f"Poisson solver (default {_POISSON['solver']})",
                    choices=_CHOICES["poisson_solver"],
                    flag="--poisson-solver",
                ),
            },
        ),
    ]


@document
class StitchKeywords(StitchTuning, total=False):
    """Every stitching option as a keyword: what ``stitch``, ``estimate``, ``batch.run`` take."""

    align: Annotated[
        AlignSpec | None,
        Option(
            f"alignment: multiscale (default; the energy's schedule, {_SCHEDULES}, with half "
            "the nodes per side on a subdivided layout's tiles), none, or grids "
            "COLSxROWS[,COLSxROWS...]",
            parse=parse_align,
        ),
    ]
    blend: Annotated[
        BlendMethod | None,
        Option(
            f"blending (default {_core.DEFAULTS['blend']['method']})", choices=_CHOICES["blend"]
        ),
    ]


_LIMIT_ITERATIONS = int(_core.LIMITS["max_iterations"])
#: The real-valued alignment options.
_REAL_KEYS = (
    "tolerance",
    "sample_fraction",
    "pole_cap_deg",
    "smoothness",
    "scale_weight",
    "prior_weight",
    "prior_scale_deg",
)
#: The Poisson keys of ``blend_options``, named by the core.
_POISSON_KEYS = tuple(k for k in _core.DEFAULTS["poisson"] if k != "method")
#: Old spellings of ``blend_options`` keys, still accepted with a DeprecationWarning.
_RENAMED_BLEND_KEYS = {"tol": "tolerance", "max_iterations": "iterations"}


class AlignOptions(TypedDict):
    """The alignment options as the core resolved them (every default filled in)."""

    levels: list[tuple[int, int]]
    energy: Energy
    solver: AlignSolver
    iterations: int
    tolerance: float
    sample_fraction: float
    pole_cap_deg: float
    smoothness: float
    scale_weight: float
    offsets: Offsets
    loss: Loss
    prior_weight: float
    prior_scale_deg: float
    prior_fusion: PriorFusion


class _BlendMethodOnly(TypedDict):
    method: BlendMethod


class BlendOptions(_BlendMethodOnly, total=False):
    """The blend options as the core resolved them.

    ``method``, and for ``"poisson"`` every Poisson option.
    """

    fidelity: Fidelity
    lam: float
    tolerance: float
    iterations: int
    solver: PoissonSolver


class StitchOptions:
    """Frozen, validated stitching options: the alignment schedule and solver, the blend.

    Built from the keywords :func:`m360.stitch` takes; every value is checked and every default
    filled in by the core, so two option sets that stitch alike compare equal and have the same
    :meth:`as_dict`.

    Parameters
    ----------
    align : str, (cols, rows) or list of (cols, rows)
        ``"multiscale"`` (default: the energy's schedule), ``"none"`` (no alignment), one grid
        or a schedule of grids (see :mod:`m360.align`).
    blend : str, optional
        Blend method (default: the core's, ``"consensus"``; see :mod:`m360.blend`).
    energy, solver, iterations, tolerance, sample_fraction : optional
        Alignment options; None takes the core's default (see :mod:`m360.align`).
    pole_cap_deg, smoothness, scale_weight, offsets, loss : optional
        Alignment options; None takes the core's default (see :mod:`m360.align`). Ignored with
        ``align="none"``.
    prior_weight, prior_scale_deg, prior_fusion : optional
        The global prior's term weight, frequency split and fusion with the tangents' own low
        frequencies (see :mod:`m360.stitching.prior`); used only when a prior is given.
    blend_options : mapping, optional
        Poisson options ``fidelity``, ``lam``, ``tolerance``, ``iterations``, ``solver`` (see
        :mod:`m360.blend`); refused for another method; given without ``blend``, they select
        ``"poisson"``.

    Raises
    ------
    m360.InputError
        Naming the first option that is unusable.

    Examples
    --------
    >>> opts = m360.StitchOptions(energy="paper", blend_options={"lam": 0.2})
    >>> opts.align["levels"], opts.blend["lam"]
    ([(4, 3), (8, 7), (16, 14)], 0.2)
    """

    __slots__ = ("_align", "_blend")
    _align: AlignOptions | None
    _blend: BlendOptions

    def __init__(
        self,
        align: AlignSpec = "multiscale",
        blend: BlendMethod | None = None,
        **keywords: Unpack[StitchTuning],
    ) -> None:
        (given,) = split(keywords, StitchTuning, where="StitchOptions")
        energy, solver, loss, offsets = (
            given.get(k) for k in ("energy", "solver", "loss", "offsets")
        )
        blend_options = given.get("blend_options")
        levels = _levels(align)
        raw_align: dict[str, Any] | None = None
        if levels is not False:
            raw_align = {
                "levels": levels,
                "energy": _choice(energy, "energy", "energy"),
                "solver": _choice(solver, "solver", "solver"),
                "iterations": _count(given.get("iterations"), "iterations"),
                **{k: _real(given.get(k), k) for k in _REAL_KEYS},
                "offsets": _choice(offsets, "offsets", "offsets"),
                "loss": _choice(loss, "loss", "loss"),
                "prior_fusion": _choice(given.get("prior_fusion"), "prior_fusion", "prior_fusion"),
            }
            raw_align = {k: v for k, v in raw_align.items() if v is not None}
        if blend is not None:
            method = text(blend, "blend", _core.CHOICES["blend"])
        elif blend_options:  # Poisson options without a method ask for the Poisson blend
            method = "poisson"
        else:
            method = _core.CHOICES["blend"][0]
        raw_blend = {"method": method, **_blend_options(blend_options)}
        resolved_align, resolved_blend = _core.stitch_options(raw_align, raw_blend)
        self._set(resolved_align, resolved_blend)

    def _set(self, align: Any, blend: Any) -> None:
        if align is not None:
            align = {**align, "levels": [(int(c), int(r)) for c, r in align["levels"]]}
        object.__setattr__(self, "_align", align)
        object.__setattr__(self, "_blend", dict(blend))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> StitchOptions:
        """Options from their :meth:`as_dict` form (e.g. a sidecar's), checked again by the core.

        Parameters
        ----------
        data : mapping
            ``{"align": {...} or None, "blend": {...}}``.

        Returns
        -------
        StitchOptions
        """
        if not isinstance(data, Mapping) or set(data) != {"align", "blend"}:
            raise InputError(f"stitch options must be {{'align': ..., 'blend': ...}}, got {data!r}")
        align, blend = data["align"], data["blend"]
        if align is not None and not isinstance(align, Mapping):
            raise InputError(f"stitch options 'align' must be a mapping or None, got {align!r}")
        if not isinstance(blend, Mapping):
            raise InputError(f"stitch options 'blend' must be a mapping, got {blend!r}")
        raw_align = None
        if align is not None:
            raw_align = dict(align)
            if "levels" in raw_align and raw_align["levels"] is not None:
                levels = _levels(raw_align["levels"])
                if levels is False or levels is None:
                    raise InputError(f"stitch options levels={raw_align['levels']!r} is unusable")
                raw_align["levels"] = levels
        options = cls.__new__(cls)
        options._set(*_core.stitch_options(raw_align, dict(blend)))
        return options

    def checked_for(self, tangent_shape: tuple[int, int]) -> StitchOptions:
        """``self``, after the core checked the grids against a tangent size (h, w).

        Raises
        ------
        m360.InputError
            If a grid has more nodes than the tangent has pixels.
        """
        align = None if self._align is None else dict(self._align)
        _core.stitch_options(align, dict(self._blend), tangent_shape)
        return self

    @property
    def align(self) -> AlignOptions | None:
        """The resolved alignment options (a copy), None without alignment."""
        return copy.deepcopy(self._align)

    @property
    def blend(self) -> BlendOptions:
        """The resolved blend options (a copy): ``method`` and its options."""
        return copy.deepcopy(self._blend)

    @property
    def method(self) -> BlendMethod:
        """The blend method."""
        return self._blend["method"]

    def as_dict(self) -> dict[str, Any]:
        """Give the canonical JSON-able form: ``{"align": {...} or None, "blend": {...}}``.

        Every default is filled in and grids are ``[cols, rows]`` lists, so equal options give
        equal dicts (the batch resume fingerprint hashes this).
        """
        align: dict[str, Any] | None = None
        if self._align is not None:
            align = {**self._align, "levels": [[c, r] for c, r in self._align["levels"]]}
        return {"align": align, "blend": dict(self._blend)}

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("StitchOptions is frozen; build a new one")

    def __delattr__(self, name: str) -> None:
        raise AttributeError("StitchOptions is frozen")

    def __reduce__(self) -> tuple[Any, ...]:
        return (StitchOptions.from_dict, (self.as_dict(),))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StitchOptions) and other.as_dict() == self.as_dict()

    def __hash__(self) -> int:
        return hash(repr(self.as_dict()))

    def __repr__(self) -> str:
        return f"StitchOptions(align={self._align!r}, blend={self._blend!r})"


def multiscale_levels(energy: str, subdivisions: int) -> list[tuple[int, int]]:
    """Give ``align="multiscale"``'s grids for tangents of a layout split ``subdivisions`` times.

    The energy's schedule (``_core.DEFAULTS["schedules"]``) is for the 20 faces; a subdivided
    layout's tiles are 2^n times narrower in angle, so its grids have 2^n times fewer nodes per
    side (at least 2), about as far apart on the sphere: 4x3 → 8x7 becomes 2x2 → 4x4 at n = 1,
    which measured the same AbsRel as 4x3 → 8x7 on those tiles in less than half the time
    (docs/method.md, "Where the detail comes from").
    """
    schedule = _core.DEFAULTS["schedules"][energy]
    step = 2**subdivisions
    return [(max(2, -(-c // step)), max(2, -(-r // step))) for c, r in schedule]


def build(
    options: StitchOptions | None, subdivisions: int = 0, **keywords: Unpack[StitchKeywords]
) -> StitchOptions:
    """``options``, or the options the stitching keywords describe (not both).

    The one place the callers of :class:`StitchOptions` (``stitch``, ``estimate``,
    ``batch.run``) turn their keywords into options; keywords given as None count as absent.
    ``subdivisions``: the layout's, whose tiles ``align="multiscale"`` (the default) is scaled
    to (:func:`multiscale_levels`).
    """
    given = {k: v for k, v in keywords.items() if v is not None}
    if options is None:
        if subdivisions and given.get("align", "multiscale") == "multiscale":
            energy = given.get("energy", _ALIGN["energy"])
            if isinstance(energy, str) and energy in _core.DEFAULTS["schedules"]:
                # (another energy: StitchOptions names the problem)
                given["align"] = multiscale_levels(energy, subdivisions)
        return StitchOptions(**given)  # type: ignore[arg-type]  # mypy: one TypedDict into another
    if not isinstance(options, StitchOptions):
        raise InputError(f"options must be an m360.StitchOptions, got {type(options).__name__}")
    if given.get("align") == "multiscale":
        del given["align"]  # the default, spelt out
    if not given:
        return options
    named = ", ".join(given)
    raise InputError(f"give either options= or the stitching keywords, not both (got {named})")


def _levels(align: Any) -> list[tuple[int, int]] | bool | None:
    """Read the levels of ``align``.

    A list of grids, None (the energy's schedule) or False (no alignment).
    """
    if isinstance(align, str):
        if align == "none":
            return False
        if align == "multiscale":
            return None
    elif _is_grid(align):
        return [(int(align[0]), int(align[1]))]
    elif isinstance(align, (list, tuple)) and align and all(_is_grid(g) for g in align):
        return [(int(g[0]), int(g[1])) for g in align]
    raise InputError(
        f"align={align!r} is not supported; use 'multiscale', 'none', a (cols, rows) grid or a "
        "list of grids such as [(4, 3), (8, 7)]"
    )


def _is_grid(value: object) -> bool:
    return (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(
            isinstance(v, (int, np.integer))
            and not isinstance(v, bool)
            and abs(int(v)) < 1 << 62  # beyond it the core's counters overflow; within, it judges
            for v in value
        )
    )


def _choice(value: Any, name: str, kind: str) -> str | None:
    return None if value is None else text(value, name, _core.CHOICES[kind])


def _real(value: Any, name: str) -> float | None:
    return None if value is None else real(value, name)


def _count(value: Any, name: str) -> int | None:
    return None if value is None else count(value, name, _LIMIT_ITERATIONS)


def _blend_options(options: Mapping[str, Any] | None) -> dict[str, Any]:
    """``blend_options`` with types normalised and old key spellings renamed (with a warning)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InputError(f"blend_options must be a mapping, got {type(options).__name__}")
    out: dict[str, Any] = {}
    for key, value in options.items():
        name = _RENAMED_BLEND_KEYS.get(key, key) if isinstance(key, str) else key
        if name != key:
            warnings.warn(
                f"blend_options key {key!r} is deprecated; use {name!r}",
                DeprecationWarning,
                stacklevel=4,
            )
            if name in options:
                raise InputError(f"blend_options has both {key!r} and {name!r}")
        if name not in _POISSON_KEYS:
            known = ", ".join(_POISSON_KEYS)
            raise InputError(f"unknown blend_options {key!r}; known: {known}")
        if name in ("fidelity", "solver"):
            kind = "fidelity" if name == "fidelity" else "poisson_solver"
            out[name] = text(value, f"blend_options {name}", _core.CHOICES[kind])
        elif name == "iterations":
            out[name] = count(value, f"blend_options {name}", _LIMIT_ITERATIONS)
        else:
            out[name] = real(value, f"blend_options {name}")
    return out
