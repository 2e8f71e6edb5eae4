"""The options of the end-to-end job, written once: :class:`EstimateKeywords`.

Every keyword :func:`m360.estimate` and :func:`m360.batch.run` take beyond their named
parameters: the stitching options (:class:`m360.stitching.options.StitchKeywords`), the model
options (:class:`m360.estimators.ModelKeywords`), the job's own (:class:`JobKeywords`) and the
global prior (:class:`PriorKeywords`). ``m360 run`` builds one flag per entry from the same
lists (m360._keywords).
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Annotated, Any, TypedDict

from .. import _core
from .._keywords import Option, definition, document, resolved
from .._validate import integer, one_of
from ..errors import InputError
from ..estimators.options import ModelKeywords
from ..geometry.layout import DEFAULT_PADDING, PAPER_PADDING, Layout, default_layout
from ..stitching.edges import EDGE_MODES
from ..stitching.options import StitchKeywords
from ..stitching.upsample import UPSAMPLE_METHODS
from .masks import SKY_MODES, SKY_THRESHOLD
from .memory import DEFAULT_WORKING_WIDTH, NATIVE_WIDTH_LIMIT, check_working_width
from .prior import (
    PRIOR_KINDS,
    PRIOR_MODEL_OPTIONS,
    check_prior,
    check_prior_confidence,
    check_prior_options,
)

__all__ = [
    "EstimateKeywords",
    "JobKeywords",
    "PriorKeywords",
    "job_fingerprint",
    "job_layout",
    "refuse_layout_options",
    "resolve_job",
]


def _working_width(value: Any, name: str) -> int | str | None:
    check_working_width(value)
    return value  # type: ignore[no-any-return]  # checked: None, "native" or an even int


def _parse_working_width(text: str) -> int | str:
    if text == "native":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a width or 'native', got {text!r}") from None


def _padding(value: Any, name: str) -> float:
    # The core judges the value (the layout it allows), once here rather than per image; with
    # subdivisions the pair is judged again (resolve_job).
    padding = default_layout(2048, value).padding
    assert padding is not None  # an icosahedron layout has one
    return padding


def _parse_padding(text: str) -> float | str:
    if text == "paper":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or 'paper', got {text!r}") from None


@document
class JobKeywords(TypedDict, total=False):
    """The job's own options: which layout, at which width, what to do with the sky."""

    working_width: Annotated[
        int | str | None,
        Option(
            "ERP width the method runs at, the result upsampled to the image's resolution "
            f"along its edges (default: the image's width up to {NATIVE_WIDTH_LIMIT}, above it "
            f"{DEFAULT_WORKING_WIDTH}; native: always the image's)",
            check=_working_width,
            parse=_parse_working_width,
            metavar="W|native",
        ),
    ]
    upsample: Annotated[
        str | None,
        Option(
            "how a working-width result reaches the image's resolution: guided follows the "
            "photo's edges at depth discontinuities, bilinear does not",
            check=lambda v, n: one_of(v, n, UPSAMPLE_METHODS),
            choices=UPSAMPLE_METHODS,
            default="guided",
        ),
    ]
    edges: Annotated[
        str | None,
        Option(
            "photo: depth edges smeared by the network are made sharp along the photo's "
            "(m360.stitching.refine_edges, at the output's resolution); network: as the "
            "network gave them; auto: photo for a tangent network that sees its tile 4 or "
            "more times smaller, network otherwise",
            check=lambda v, n: one_of(v, n, EDGE_MODES),
            choices=EDGE_MODES,
            default="auto",
        ),
    ]
    padding: Annotated[
        float | str | None,
        Option(
            f"padding of the tangent layout in gnomonic units (default {DEFAULT_PADDING}: more "
            f"tangents vote on each pixel, lower error under network content errors; paper: "
            f"the paper's {PAPER_PADDING})",
            check=_padding,
            parse=_parse_padding,
            metavar="P|paper",
        ),
    ]
    subdivisions: Annotated[
        int | None,
        Option(
            "times each icosahedron face of the default layout is split into 4: 1 gives 80 "
            "tangents half as wide in angle, which a network of a fixed input size sees at "
            "twice the angular resolution (sharper depth edges) for 4x the network calls; "
            f"their padding defaults to the paper's {PAPER_PADDING} (at most 16 tangents may "
            "see one direction)",
            check=lambda v, n: integer(v, n, low=0, high=_core.LIMITS["max_subdivisions"]),
            parse=int,
            metavar="N",
            default=0,
        ),
    ]
    sky: Annotated[
        str | None,
        Option(
            f"nan: the sky (disparity at or below {SKY_THRESHOLD:.0%} of its 90th percentile) "
            "gets no depth, instead of a huge fake distance",
            check=lambda v, n: one_of(v, n, SKY_MODES),
            choices=SKY_MODES,
            default="keep",
        ),
    ]


def _prior_model_flags() -> dict[str, Option]:
    """Give the flags of ``prior_options``: the model options' own, named ``--prior-...``."""
    flags = {}
    for key in PRIOR_MODEL_OPTIONS:
        option = definition(ModelKeywords)[key]
        flags[key] = dataclasses.replace(
            option,
            flag="--prior-" + key.replace("_", "-"),
            aliases=(),
            help=f"as {option.flag_name(key)}, for a prior model given by path or name",
        )
    return flags


def resolve_job(values: Any) -> dict[str, Any]:
    """Check the given :class:`JobKeywords` (padding with subdivisions); default the rest."""
    job = resolved(values, JobKeywords)
    if job["subdivisions"]:
        job_layout(2048, job)  # the core refuses a padding too wide for the smaller tangents
    return job


def refuse_layout_options(job: dict[str, Any]) -> None:
    """Refuse the layout's options for a panoramic model (one pass over the whole ERP)."""
    if job["padding"] is not None or job["subdivisions"]:
        raise InputError(
            "a panoramic model runs once on the whole ERP: padding and subdivisions do not apply"
        )


def job_layout(erp_width: int, job: dict[str, Any]) -> Layout:
    """Make the default layout at ``erp_width`` with the job's ``padding`` and ``subdivisions``."""
    return default_layout(erp_width, job["padding"], job["subdivisions"])


def job_fingerprint(job: dict[str, Any]) -> dict[str, Any]:
    """Describe the job for a resume fingerprint: the options that differ from their defaults.

    And always the padding the layout takes and the edges mode: their defaults changed (padding
    0.3 → 0.7, edges "network" → "auto"), so an image written before under a default (no key)
    is redone, and one written with the new value given is kept.
    """
    defaults = {name: o.default for name, o in definition(JobKeywords).items()}
    described = {k: v for k, v in job.items() if v != defaults[k]}
    described["padding"] = job_layout(2048, job).padding
    described["edges"] = job["edges"]
    return described


@document
class PriorKeywords(TypedDict, total=False):
    """The global prior: what the whole sphere looks like at a low resolution (docs/method.md)."""

    prior: Annotated[
        Any,
        Option(
            "a global prior the alignment pulls the tangents' low frequencies toward: a "
            "panoramic model (an .onnx path or registry name, loaded with kind panoramic and "
            "run on each photo at its own size) or an ERP map (Hp, 2 Hp) of any resolution, "
            "NaN = unknown (on the command line a .npy, .pfm, .exr, .tif or 16-bit .png file; "
            "an m360 output's is read with its sidecar); needs alignment",
            check=lambda v, n: check_prior(v, n),
            parse=str,
            metavar="MODEL|MAP",
        ),
    ]
    prior_kind: Annotated[
        str | None,
        Option(
            "what the prior holds: affine_disparity, disparity (1/metres), affine_depth, "
            "distance (radial metres) or negated_affine_disparity (grows with depth); a prior "
            "model's output kind (default: the registry's, or affine_disparity); required for "
            "a map",
            check=lambda v, n: one_of(v, n, PRIOR_KINDS),
            choices=PRIOR_KINDS,
        ),
    ]
    prior_confidence: Annotated[
        Any,
        Option(
            "per-pixel trust in a prior map, (Hp, Wp) in [0, 1] (on the command line a .npy, "
            ".pfm, .exr, .tif or 16-bit .png file)",
            check=lambda v, n: check_prior_confidence(v, n),
            parse=str,
            metavar="MAP",
        ),
    ]
    prior_options: Annotated[
        Any,
        Option(
            "how a prior model given by path or name is fed: an m360.ModelOptions or a dict "
            "of its input_size, resize, multiple_of, normalize, mean and std (on the command "
            "line --prior-input-size, --prior-normalize …); its providers and threads are the "
            "main model's",
            check=lambda v, n: check_prior_options(v, n),
            parts=_prior_model_flags(),
        ),
    ]


@document
class EstimateKeywords(StitchKeywords, ModelKeywords, JobKeywords, PriorKeywords, total=False):
    """Every keyword of :func:`m360.estimate` and :func:`m360.batch.run` beyond their named ones.

    The stitching options (``align``, ``blend``, ``energy`` …; :mod:`m360.align`,
    :mod:`m360.blend`), the model options (``providers``, ``threads``, ``input_size``,
    ``kind``, ``output_kind``, ``mean``, ``std``), the job's own (``working_width``,
    ``upsample``, ``padding``, ``sky``) and the global prior (``prior``, ``prior_kind``,
    ``prior_confidence``, ``prior_options``). None or absent: the default.
    """
