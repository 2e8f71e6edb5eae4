"""Depth estimators: what :func:`m360.estimate` runs on the tangent images (or the whole ERP).

An *estimator* is anything with ``predict(tangents) -> (N, h, w) float32`` and an
``output_kind`` (:data:`OUTPUT_KINDS`; docs/architecture.md): :class:`OnnxEstimator` (ONNX
Runtime, :mod:`m360.estimators.onnx`), :class:`SimulatedEstimator` (demo and tests) or a user's
own object. A *panoramic* estimator (``kind = "panoramic"``, :class:`PanoramicEstimator`) has
``predict(erp) -> (h, w) float32`` instead: the whole ERP in, one ERP map out at its own
resolution (:class:`PanoramicOnnxEstimator`). :func:`load_estimator` turns a registry name, an
``.onnx`` path or such an object into one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from ..errors import InputError
from . import registry as _models
from .kinds import (
    ESTIMATOR_KINDS,
    OUTPUT_KINDS,
    PANORAMIC_OUTPUT_KINDS,
    OutputKind,
    check_estimator_kind,
    check_output_kind,
    check_panoramic_output_kind,
    ray_norms,
    to_perspective_disparity,
    to_spherical_disparity,
)
from .onnx import (
    MAX_NETWORK_SIZE,
    RESIZE_MODES,
    OnnxEstimator,
    PanoramicOnnxEstimator,
    is_file,
    network_size,
)
from .options import ModelKeywords, ModelOptions
from .simulated import SimulatedEstimator

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "ESTIMATOR_KINDS",
    "MAX_NETWORK_SIZE",
    "OUTPUT_KINDS",
    "PANORAMIC_OUTPUT_KINDS",
    "RESIZE_MODES",
    "Estimator",
    "ModelKeywords",
    "ModelOptions",
    "OnnxEstimator",
    "OutputKind",
    "PanoramicEstimator",
    "PanoramicOnnxEstimator",
    "SimulatedEstimator",
    "check_output_kind",
    "estimator_kind",
    "load_estimator",
    "network_size",
    "ray_norms",
    "to_perspective_disparity",
    "to_spherical_disparity",
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


@runtime_checkable
class PanoramicEstimator(Protocol):
    """What :func:`estimate` needs from a panoramic estimator (ERP in, ERP out).

    Attributes
    ----------
    kind : str
        ``"panoramic"``.
    output_kind : str
        One of :data:`PANORAMIC_OUTPUT_KINDS`.
    """

    @property
    def kind(self) -> str:
        """``"panoramic"``."""
        ...

    @property
    def output_kind(self) -> str:
        """One of :data:`PANORAMIC_OUTPUT_KINDS`."""
        ...

    def predict(self, erp: np.ndarray) -> np.ndarray:
        """Predict one ERP map of the whole panorama.

        Parameters
        ----------
        erp : (H, W, 3) uint8
            RGB panorama (float RGB in [0, 1] is possible too).

        Returns
        -------
        numpy.ndarray
            (h, w) float32 of ``output_kind`` at the estimator's own resolution, covering the
            whole sphere (an ERP grid, best w == 2h); NaN where there is no estimate.
        """
        ...


def estimator_kind(estimator: Any) -> str:
    """The role of an estimator object: its ``kind`` attribute, ``"tangent"`` when it has none."""
    kind = getattr(estimator, "kind", "tangent")
    return check_estimator_kind(kind, f"estimator {type(estimator).__name__} kind")


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
        affine disparity, ImageNet normalisation unless the graph applies it, 384 px; with
        ``kind="panoramic"`` 512 x 1024) or an object with ``predict`` and ``output_kind``
        (returned as is; the options below are refused for it, but ``kind``, which is checked
        against the object's own ``kind`` attribute, default ``"tangent"``).
    model_options : ModelOptions, optional
        The model options at once (then give none of them as a keyword).
    **keywords
        The model options (:class:`ModelKeywords`): ``providers``, ``threads``,
        ``input_size`` (a model whose file fixes its input size refuses any other, naming the
        size it takes), ``kind`` (``"tangent"``, the default, or ``"panoramic"``: a
        :class:`PanoramicOnnxEstimator`), ``output_kind`` (:data:`OUTPUT_KINDS`; panoramic:
        :data:`PANORAMIC_OUTPUT_KINDS`, where ``"metric_depth"`` is refused), ``resize``,
        ``multiple_of``, ``normalize``, ``mean``, ``std``.

    Returns
    -------
    Estimator or PanoramicEstimator
        Ready to ``predict``.

    Examples
    --------
    >>> pano = m360.estimators.load_estimator(
    ...     "pano.onnx", kind="panoramic", output_kind="distance")
    >>> pano.predict(rgb).shape      # the network's own resolution, e.g. (512, 1024)

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
    kind = given.get("kind")
    if isinstance(model, (str, os.PathLike)):
        text = os.fspath(model)
        if text in _models.REGISTRY:
            entry = _models.get(text)
            if kind is not None and kind != entry.kind:
                raise InputError(
                    f"model {entry.name!r} is a {entry.kind} model; kind={kind!r} does not apply"
                )
            onnx_class = PanoramicOnnxEstimator if entry.kind == "panoramic" else OnnxEstimator
            path = _models.ensure(text)
            estimator = onnx_class(
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
            onnx_class = PanoramicOnnxEstimator if kind == "panoramic" else OnnxEstimator
            return onnx_class(
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
    if isinstance(model, (Estimator, PanoramicEstimator)):
        ignored = [k for k in given if k != "kind"]
        if ignored:
            raise InputError(
                f"{', '.join(ignored)} apply to ONNX models given by name or path; configure "
                f"the {type(model).__name__} object itself instead"
            )
        role = estimator_kind(model)
        if kind is not None and kind != role:
            raise InputError(
                f"kind={kind!r} but the {type(model).__name__} object is a {role} estimator "
                f"(its kind attribute{' is absent' if role == 'tangent' else ''})"
            )
        where = f"estimator {type(model).__name__} output_kind"
        if role == "panoramic":
            check_panoramic_output_kind(model.output_kind, where)
        else:
            check_output_kind(model.output_kind, where)
        return model
    raise InputError(
        f"model must be a registry name, a path to an .onnx file, or an object with "
        f"predict(tangents) and output_kind; got {type(model).__name__}"
    )
