"""The model options, written once: how an ONNX model is run (:class:`ModelOptions`).

:func:`m360.estimate`, :func:`m360.batch.run`, :func:`m360.estimators.load_estimator` and
``m360 run`` take them as keywords (:class:`ModelKeywords`) or as one :class:`ModelOptions`. They
apply to ONNX models given by registry name or path; an estimator object is configured itself.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Annotated, Any, TypedDict

from .._keywords import Option, checked, document, split
from .._validate import integer, size_pair
from .._validate import threads as check_threads
from ..errors import InputError
from .kinds import ALL_OUTPUT_KINDS, ESTIMATOR_KINDS, check_any_output_kind, check_estimator_kind
from .onnx import MAX_NETWORK_SIZE, RESIZE_POLICIES, check_triple
from .onnx_file import NORMALIZE_PRESETS

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["ModelKeywords", "ModelOptions"]


def _providers(value: Any, name: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, Sequence) or not value or not all(isinstance(p, str) for p in value):
        raise InputError(f"{name} must be a list of provider names, got {value!r}")
    return tuple(value)


def _comma_list(text: str) -> tuple[str, ...]:
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    if not names:
        raise argparse.ArgumentTypeError("give at least one provider name")
    return names


def _choice(choices: Sequence[str]) -> Any:
    def check(value: Any, name: str) -> str:
        if not isinstance(value, str) or value not in choices:
            known = ", ".join(choices)
            raise InputError(f"{name}={value!r} is not supported; choose one of {known}")
        return value

    return check


def _triple(value: Any, name: str) -> tuple[float, float, float]:
    r, g, b = (float(v) for v in check_triple(value, name))
    return (r, g, b)


@document
class ModelKeywords(TypedDict, total=False):
    """The model options as keywords; each is None or absent for the model's own default."""

    providers: Annotated[
        Sequence[str] | None,
        Option(
            "ONNX Runtime execution providers in order of preference, comma-separated on the "
            "command line (e.g. CUDAExecutionProvider,CPUExecutionProvider; default CPU)",
            check=_providers,
            parse=_comma_list,
        ),
    ]
    threads: Annotated[
        int | None,
        Option(
            "ONNX Runtime intra-op threads (m360 run with --workers > 1: also the core's "
            "threads per worker)",
            check=check_threads,
            parse=int,
        ),
    ]
    input_size: Annotated[
        tuple[int, int] | None,
        Option(
            "network input size (height, width) of a dynamic-size .onnx file (default: the "
            "model's); a file that fixes its size refuses any other",
            check=lambda v, n: size_pair(v, n, MAX_NETWORK_SIZE),
            parse=int,
            nargs=2,
            metavar=("H", "W"),
        ),
    ]
    kind: Annotated[
        str | None,
        Option(
            "the model's role: tangent (perspective tiles in, a map per tile out: the default) "
            "or panoramic (the whole ERP in, one ERP map out, run once at the network's size "
            "and upsampled along the photo's edges)",
            check=check_estimator_kind,
            choices=ESTIMATOR_KINDS,
            flag="--model-kind",
        ),
    ]
    output_kind: Annotated[
        str | None,
        Option(
            "what the model outputs (default: the registry's, or affine_disparity); tangent "
            "models: affine_disparity, metric_depth (z), distance, affine_depth, "
            "negated_affine_disparity; panoramic models: affine_disparity, disparity "
            "(1/metres), affine_depth, distance (radial metres), negated_affine_disparity",
            check=check_any_output_kind,
            choices=ALL_OUTPUT_KINDS,
        ),
    ]
    resize: Annotated[
        str | None,
        Option(
            "how a tangent is resized to a dynamic model's input size: keep-aspect (fit inside "
            "the input size, keeping the tangent's aspect ratio), cover (cover it, keeping the "
            "aspect ratio) or exact (exactly the input size); then rounded to --multiple-of "
            "(default: the registry's, or keep-aspect)",
            check=_choice(tuple(RESIZE_POLICIES)),
            choices=tuple(RESIZE_POLICIES),
        ),
    ]
    multiple_of: Annotated[
        int | None,
        Option(
            "the network's input height and width are rounded to a multiple of this (a dynamic "
            "model that needs it, e.g. 32; default: the registry's, or 1)",
            check=lambda v, n: integer(v, n, low=1, high=MAX_NETWORK_SIZE),
            parse=int,
            metavar="N",
        ),
    ]
    normalize: Annotated[
        str | None,
        Option(
            "input normalisation by name, instead of mean/std: imagenet (the ImageNet mean and "
            "std), unit (RGB in [0, 1] as is) or none (the raw 0-255 pixel values); wins over "
            "what the graph holds (default: the model's own)",
            check=_choice(tuple(NORMALIZE_PRESETS)),
            choices=tuple(NORMALIZE_PRESETS),
        ),
    ]
    mean: Annotated[
        Sequence[float] | None,
        Option(
            "input normalisation: mean per RGB channel of RGB in [0, 1], applied by m360 (wins "
            "over what the graph holds; default: the model's own)",
            check=_triple,
            parse=float,
            nargs=3,
            metavar=("R", "G", "B"),
        ),
    ]
    std: Annotated[
        Sequence[float] | None,
        Option(
            "input normalisation: standard deviation per RGB channel (see mean)",
            check=_triple,
            parse=float,
            nargs=3,
            metavar=("R", "G", "B"),
        ),
    ]


class ModelOptions:
    """Frozen, checked model options: how an ONNX model is run.

    Built from the keywords of :class:`ModelKeywords` (``providers``, ``threads``,
    ``input_size``, ``kind``, ``output_kind``, ``resize``, ``multiple_of``, ``normalize``, ``mean``,
    ``std``); those not given are the model's defaults. ``normalize`` and ``mean``/``std`` are
    exclusive. Equal options compare equal and have the same :meth:`as_dict`.

    Examples
    --------
    >>> opts = m360.ModelOptions(multiple_of=32, normalize="unit", output_kind="metric_depth")
    >>> m360.estimate(rgb, "fastdepth.onnx", model_options=opts)

    Raises
    ------
    m360.InputError
        Naming the first unusable option.
    """

    __slots__ = ("_values",)
    _values: dict[str, Any]

    def __init__(self, **keywords: Unpack[ModelKeywords]) -> None:
        (given,) = split(keywords, ModelKeywords, where="ModelOptions")
        values = checked(given, ModelKeywords)
        if "normalize" in values and ("mean" in values or "std" in values):
            raise InputError(
                "give normalize (--normalize) or mean/std (--mean/--std), not both: "
                f"normalize={values['normalize']!r} already sets both"
            )
        object.__setattr__(self, "_values", values)

    @classmethod
    def build(cls, options: ModelOptions | None, **keywords: Unpack[ModelKeywords]) -> ModelOptions:
        """``options``, or the options the keywords describe (not both)."""
        given = {k: v for k, v in keywords.items() if v is not None}
        if options is None:
            return cls(**given)  # type: ignore[arg-type]  # mypy: a dict into a TypedDict
        if not isinstance(options, ModelOptions):
            raise InputError(
                f"model_options must be an m360.ModelOptions, got {type(options).__name__}"
            )
        if given:
            raise InputError(
                "give either model_options= or the model keywords, not both "
                f"(got {', '.join(given)})"
            )
        return options

    def keywords(self) -> dict[str, Any]:
        """Give the options given, as the keywords :func:`m360.estimators.load_estimator` takes."""
        return dict(self._values)

    def as_dict(self) -> dict[str, Any]:
        """Give the options given, JSON-able (tuples as lists): sidecars, resume fingerprints."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self._values.items()}

    def __getattr__(self, name: str) -> Any:
        if name in ModelKeywords.__annotations__:
            return self._values.get(name)
        raise AttributeError(f"ModelOptions has no option {name!r}")

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("ModelOptions is frozen; build a new one")

    def __reduce__(self) -> tuple[Any, ...]:
        return (_from_keywords, (self.keywords(),))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ModelOptions) and other._values == self._values

    def __hash__(self) -> int:
        return hash(repr(sorted(self._values.items())))

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v!r}" for k, v in self._values.items())
        return f"ModelOptions({inner})"


def _from_keywords(keywords: Mapping[str, Any]) -> ModelOptions:
    return ModelOptions(**keywords)
