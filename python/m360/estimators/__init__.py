"""Depth estimators: what :func:`m360.estimate` runs on the tangent images.

An *estimator* is anything with ``predict(tangents) -> (N, h, w) float32`` and an
``output_kind`` (:data:`OUTPUT_KINDS`; docs/architecture.md): :class:`OnnxEstimator` (ONNX
Runtime, :mod:`m360.estimators.onnx`), :class:`SimulatedEstimator` (demo and tests) or a user's
own object. :func:`load_estimator` turns a registry name, an ``.onnx`` path or such an object
into one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from ..errors import InputError
from . import registry as _models
from .kinds import OUTPUT_KINDS, OutputKind, check_output_kind, ray_norms, to_perspective_disparity
from .onnx import MAX_NETWORK_SIZE, RESIZE_MODES, OnnxEstimator, is_file, network_size
from .options import ModelKeywords, ModelOptions
from .simulated import SimulatedEstimator

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "MAX_NETWORK_SIZE",
    "OUTPUT_KINDS",
    "RESIZE_MODES",
    "Estimator",
    "ModelKeywords",
    "ModelOptions",
    "OnnxEstimator",
    "OutputKind",
    "SimulatedEstimator",
    "check_output_kind",
    "load_estimator",
    "network_size",
    "ray_norms",
    "to_perspective_disparity",
]


@runtime_checkable
class Estimator(Protocol):
    """What :func:`estimate` needs from a depth estimator.

    Attributes
    ----------
    output_kind : str
        One of :data:`OUTPUT_KINDS`.
    """

    @property
    def output_kind(self) -> str:
        """One of :data:`OUTPUT_KINDS`."""
        ...

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        """Predict one map per tangent image.

        Parameters
        ----------
        tangents : (N, h, w, 3) uint8
            RGB tangent images (float RGB in [0, 1] is possible too).

        Returns
        -------
        numpy.ndarray
            (N, h, w) float32 of ``output_kind``; NaN where there is no estimate.
        """
        ...


def load_estimator(
    model: str | os.PathLike[str] | Estimator = _models.DEFAULT_MODEL,
    *,
    model_options: ModelOptions | None = None,
    **keywords: Unpack[ModelKeywords],
) -> Estimator:
    """Resolve ``model`` to an estimator.

    Parameters
    ----------
    model : str, path or Estimator
        A registry name (``m360.models.names()``: fetched, verified and loaded with its own
        preprocessing), a path to an ``.onnx`` file (loaded with the options below; defaults:
        affine disparity, ImageNet normalisation unless the graph applies it, 384 px) or an
        object with ``predict`` and ``output_kind`` (returned as is; the options below are
        refused for it).
    model_options : ModelOptions, optional
        The model options at once (then give none of them as a keyword).
    **keywords
        The model options (:class:`ModelKeywords`): ``providers``, ``threads``,
        ``input_size`` (a model whose file fixes its input size refuses any other, naming the
        size it takes), ``output_kind`` (:data:`OUTPUT_KINDS`), ``resize``, ``multiple_of``,
        ``normalize``, ``mean``, ``std``.

    Returns
    -------
    Estimator
        Ready to ``predict``.

    Raises
    ------
    m360.ModelError
        For an unknown, missing, corrupt or unverifiable model.
    m360.InputError
        For unusable options.
    """
    given = ModelOptions.build(model_options, **keywords).keywords()
    providers, threads = given.get("providers"), given.get("threads")
    input_size, output_kind = given.get("input_size"), given.get("output_kind")
    mean, std = given.get("mean"), given.get("std")
    multiple_of = given.get("multiple_of")
    normalize, resize = given.get("normalize"), given.get("resize")
    if isinstance(model, (str, os.PathLike)):
        text = os.fspath(model)
        if text in _models.REGISTRY:
            entry = _models.get(text)
            path = _models.ensure(text)
            estimator = OnnxEstimator(
                path,
                output_kind=entry.output_kind if output_kind is None else output_kind,
                input_size=input_size,
                mean=mean,
                std=std,
                normalize=normalize,
                expected_normalization=(entry.mean, entry.std),
                multiple_of=entry.multiple_of if multiple_of is None else multiple_of,
                resize=entry.resize if resize is None else resize,
                providers=providers,
                threads=threads,
                name=entry.name,
                sha256=entry.sha256,
            )
            if input_size is None:
                # The registry's size is a default (a file's own fixed size wins), not a request.
                estimator.input_size = entry.input_size
            return estimator
        if text.endswith(".onnx") or is_file(Path(text)):
            return OnnxEstimator(
                text,
                output_kind="affine_disparity" if output_kind is None else output_kind,
                input_size=input_size,
                mean=mean,
                std=std,
                normalize=normalize,
                multiple_of=1 if multiple_of is None else multiple_of,
                resize="upper_bound" if resize is None else resize,
                providers=providers,
                threads=threads,
            )
        _models.get(text)  # raises ModelError naming the registered models
    if isinstance(model, Estimator):
        ignored = list(given)
        if ignored:
            raise InputError(
                f"{', '.join(ignored)} apply to ONNX models given by name or path; configure "
                f"the {type(model).__name__} object itself instead"
            )
        check_output_kind(model.output_kind, f"estimator {type(model).__name__} output_kind")
        return model
    raise InputError(
        f"model must be a registry name, a path to an .onnx file, or an object with "
        f"predict(tangents) and output_kind; got {type(model).__name__}"
    )
