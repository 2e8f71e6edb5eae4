"""The global prior of :func:`m360.estimate`: an ERP map, or a panoramic model run on the photo.

A prior is what a panoramic network (or any other source: another tool's output, a LiDAR map,
the previous video frame) says about the whole sphere at a low resolution; :func:`m360.stitch`
pulls the tangents' low frequencies toward it (docs/method.md). This module resolves what the
user gave (:func:`load_prior`), runs a prior model on the photo (:func:`prior_input`,
:func:`run_prior`), fits the map to the job (:func:`fit_to_job`: 2:1, masked, no larger than
the working ERP) and describes it for the sidecar and the resume fingerprint
(:func:`describe`).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .._keywords import checked
from .._validate import erp_map
from ..errors import InputError, M360Error, ModelError
from ..estimators import ModelKeywords, ModelOptions, OnnxEstimator, estimator_kind, load_estimator
from ..estimators.kinds import PANORAMIC_METRIC_KINDS, PANORAMIC_OUTPUT_KINDS

__all__ = [
    "PRIOR_KINDS",
    "PRIOR_MODEL_OPTIONS",
    "Prior",
    "as_keywords",
    "check_prior",
    "check_prior_confidence",
    "check_prior_options",
    "describe",
    "fit_to_job",
    "is_model",
    "load_prior",
    "prior_input",
    "run_prior",
]

#: What a prior map holds (per ERP pixel, along its ray): a panoramic model's output kinds.
PRIOR_KINDS: tuple[str, ...] = PANORAMIC_OUTPUT_KINDS
#: The prior kinds in metres (or 1/metres): with one, the result keeps the prior's scale.
METRIC_PRIOR_KINDS: tuple[str, ...] = PANORAMIC_METRIC_KINDS
#: A ``prior`` path with one of these suffixes is a prior map read from the file
#: (:func:`m360.io.read_map`: an m360 output's map, or an array file; a 16-bit PNG is what
#: other tools and LiDAR exports write most); any other path is a model.
MAP_SUFFIXES: tuple[str, ...] = (".npy", ".pfm", ".exr", ".png", ".tif", ".tiff")
#: The model options (:class:`m360.estimators.ModelKeywords`) a prior model given by path or
#: name takes in ``prior_options``: how it is fed. Its role is panoramic, its output kind is
#: ``prior_kind``, and it runs on the main model's providers and threads.
PRIOR_MODEL_OPTIONS: tuple[str, ...] = (
    "input_size",
    "resize",
    "multiple_of",
    "normalize",
    "mean",
    "std",
)
#: Where each other model option of a prior model comes from.
_PRIOR_OPTION_SOURCE = {
    "kind": "a prior model is always panoramic",
    "output_kind": "give prior_kind",
    "providers": "a prior model runs on the main model's providers",
    "threads": "a prior model runs on the main model's threads",
}


@dataclass(frozen=True)
class Prior:
    """A prior, resolved: a panoramic ``estimator`` to run on each photo, or a fixed ``array``.

    Attributes
    ----------
    kind : str
        One of :data:`PRIOR_KINDS` (a model's: its ``output_kind``).
    estimator : object or None
        A panoramic estimator (``kind == "panoramic"``), run on the photo at its own size.
    array : (Hp, Wp) float32 or None
        The prior map itself (Wp == 2 Hp, NaN = unknown), any resolution.
    confidence : (Hp, Wp) float32 or None
        How much each prior pixel is trusted, in [0, 1] (only with ``array``).
    """

    kind: str
    estimator: Any = None
    array: np.ndarray | None = None
    confidence: np.ndarray | None = None

    @property
    def metric(self) -> bool:
        """Whether the prior is in metres (``distance``, ``disparity``)."""
        return self.kind in METRIC_PRIOR_KINDS


def _erp_map(value: Any, name: str) -> np.ndarray:
    array = erp_map(value, name, integers=True, shape="(Hp, 2 Hp), any resolution")
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(array, dtype=np.float32)
    if np.isinf(out).any():
        raise InputError(f"{name} holds infinite values: mark unknown pixels NaN instead")
    if not np.isfinite(out).any():
        raise InputError(f"{name} has no finite value")
    out.flags.writeable = False
    return out


def check_prior(value: Any, name: str = "prior") -> Any:
    """Check a ``prior`` option: an ERP map, a path or registry name, or a panoramic estimator.

    Returns the map as a read-only float32 array, the path as a str, or the object.
    """
    if value is None:
        return None
    if isinstance(value, (str, os.PathLike)):
        return os.fspath(value)
    if isinstance(value, np.ndarray):
        return _erp_map(value, name)
    if hasattr(value, "predict") and hasattr(value, "output_kind"):
        if estimator_kind(value) != "panoramic":
            raise InputError(
                f"{name} is a {type(value).__name__}, a tangent estimator: a prior model must be "
                "panoramic (kind='panoramic': the whole ERP in, one ERP map out); load one with "
                "m360.estimators.load_estimator(path, kind='panoramic', output_kind=...)"
            )
        return value
    raise InputError(
        f"{name} must be an ERP map (Hp, 2 Hp), a panoramic model (a path, a registry name or a "
        f"panoramic estimator), or None; got {type(value).__name__}"
    )


def check_prior_confidence(value: Any, name: str = "prior_confidence") -> Any:
    """Check a ``prior_confidence`` map: (Hp, 2 Hp) in [0, 1] (NaN: 0, unknown).

    A path is read as a map file (:func:`m360.io.read_map`: .npy, .pfm, .exr, .tif, or a
    16-bit .png).
    """
    if value is None:
        return None
    if isinstance(value, (str, os.PathLike)):
        from ..io import read_map

        value = read_map(value)
    array = _erp_map(value, name).copy()
    finite = array[np.isfinite(array)]
    if finite.size and (finite.min() < 0 or finite.max() > 1):
        raise InputError(
            f"{name} must be in [0, 1], got values from {finite.min():.3g} to {finite.max():.3g}"
        )
    array[~np.isfinite(array)] = 0.0
    array.flags.writeable = False
    return array


def check_prior_options(value: Any, name: str = "prior_options") -> dict[str, Any] | None:
    """Check a ``prior_options`` option: how a prior model given by path or name is fed.

    An :class:`m360.ModelOptions` or a mapping of :data:`PRIOR_MODEL_OPTIONS` (``input_size``,
    ``resize``, ``multiple_of``, ``normalize``, ``mean``, ``std``), each checked as the model
    option of that name. Returns the options given, as keywords (None for none).
    """
    if value is None:
        return None
    if isinstance(value, ModelOptions):
        value = value.keywords()
    if not isinstance(value, Mapping):
        raise InputError(
            f"{name} must be an m360.ModelOptions or a dict of model options, got "
            f"{type(value).__name__}"
        )
    for key in value:
        if key in _PRIOR_OPTION_SOURCE:
            raise InputError(f"{name} cannot set {key!r}: {_PRIOR_OPTION_SOURCE[key]}")
        if key not in PRIOR_MODEL_OPTIONS:
            raise InputError(
                f"{name} has no option {key!r}; choose from {', '.join(PRIOR_MODEL_OPTIONS)}"
            )
    given = checked({k: v for k, v in value.items() if v is not None}, ModelKeywords)
    return given or None


def load_prior(
    prior: Any,
    prior_kind: str | None = None,
    prior_confidence: Any = None,
    *,
    prior_options: Any = None,
    providers: Any = None,
    threads: int | None = None,
) -> Prior | None:
    """Resolve the prior options of :func:`m360.estimate` (checked, a model loaded).

    Parameters
    ----------
    prior : None, (Hp, Wp) array, path, registry name or panoramic estimator
        The prior; a path or name is loaded with ``kind="panoramic"`` and ``output_kind=
        prior_kind`` (:func:`m360.estimators.load_estimator`), but a path ending in ``.npy``,
        ``.pfm`` or ``.exr`` is read as a prior map (:func:`m360.io.read_array`).
    prior_kind : str, optional
        What the prior holds (:data:`PRIOR_KINDS`): required for an array; for a model, its
        output kind (default: the registry's, or ``"affine_disparity"``; an estimator object's
        own, which a different ``prior_kind`` contradicts).
    prior_confidence : (Hp, Wp) array in [0, 1], optional
        Per-pixel trust in an array prior (same shape).
    prior_options : ModelOptions or dict, optional
        How a prior model given by path or name is fed (:func:`check_prior_options`: its
        input size, resize, multiple_of, normalize, mean, std); refused for a map or an
        estimator object (load that one with its options).
    providers, threads : optional
        ONNX Runtime's providers and threads for a prior model given by path or name (the
        main model's, so that a GPU run runs both on the GPU).

    Returns
    -------
    Prior or None
        None when ``prior`` is None.

    Raises
    ------
    m360.InputError
        For unusable options (naming which).
    m360.ModelError
        For a prior model that cannot be loaded (missing, corrupt, not ONNX …).
    """
    value = check_prior(prior)
    if prior_kind is not None and prior_kind not in PRIOR_KINDS:
        extra = (
            " (a z-depth has no meaning for an ERP map: use 'distance')"
            if prior_kind == "metric_depth"
            else ""
        )
        raise InputError(
            f"prior_kind={prior_kind!r} is not supported; choose one of "
            f"{', '.join(PRIOR_KINDS)}{extra}"
        )
    confidence = check_prior_confidence(prior_confidence)
    feed = check_prior_options(prior_options)
    if value is None:
        if prior_kind is not None or confidence is not None or feed is not None:
            raise InputError("prior_kind, prior_confidence and prior_options need a prior")
        return None
    named_model = isinstance(value, str) and os.path.splitext(value)[1].lower() not in MAP_SUFFIXES
    if feed is not None and not named_model:
        raise InputError(
            "prior_options go with a prior model given by path or name; a map is not run, "
            "and an estimator object is loaded with its own options"
        )
    if isinstance(value, str) and os.path.splitext(value)[1].lower() in MAP_SUFFIXES:
        from ..io import read_map

        value = _erp_map(read_map(value), f"prior map {value}")
    if isinstance(value, np.ndarray):
        if prior_kind is None:
            raise InputError(
                "say what the prior map holds: prior_kind= one of " + ", ".join(PRIOR_KINDS)
            )
        if confidence is not None and confidence.shape != value.shape:
            raise InputError(
                f"prior_confidence has shape {confidence.shape} but the prior {value.shape}"
            )
        return Prior(prior_kind, array=value, confidence=confidence)
    if confidence is not None:
        raise InputError(
            "prior_confidence goes with a prior map (an array); a prior model's trust is "
            "decided by the alignment"
        )
    if isinstance(value, str):
        try:
            estimator = load_estimator(
                value,
                kind="panoramic",
                output_kind=prior_kind,
                providers=providers,
                threads=threads,
                **(feed or {}),
            )
        except ModelError as exc:
            raise ModelError(f"the prior model cannot be used: {exc}") from exc
        if isinstance(estimator, OnnxEstimator):
            estimator.role = "prior"  # its error hints name the prior's own options
    else:
        estimator = load_estimator(value, kind="panoramic")
        if prior_kind is not None and prior_kind != estimator.output_kind:
            raise InputError(
                f"prior_kind={prior_kind!r} but the prior estimator outputs "
                f"{estimator.output_kind!r}; leave prior_kind out for an estimator object"
            )
    return Prior(estimator.output_kind, estimator=estimator)


def is_model(prior: Any) -> bool:
    """Whether a ``prior`` option names a model (a path or name, or an estimator), not a map."""
    if prior is None or isinstance(prior, np.ndarray):
        return False
    if isinstance(prior, (str, os.PathLike)):
        return os.path.splitext(os.fspath(prior))[1].lower() not in MAP_SUFFIXES
    return True


def as_keywords(prior: Prior | None) -> dict[str, Any]:
    """Give the keywords of :func:`m360.estimate` that pass ``prior`` as it is (loaded)."""
    if prior is None:
        return {}
    if prior.array is not None:
        return {
            "prior": prior.array,
            "prior_kind": prior.kind,
            "prior_confidence": prior.confidence,
        }
    return {"prior": prior.estimator}


def prior_input(estimator: Any, rgb: np.ndarray) -> np.ndarray:
    """Give what a panoramic ``estimator`` is fed for the photo ``rgb``.

    An ONNX model: the photo resized to its network size here (``cv2.INTER_AREA``, uint8), so
    that the engine that runs the network elsewhere (the Ray engine's model actors) ships the
    small image and makes the same bytes; another estimator: the photo as it is.
    """
    if isinstance(estimator, OnnxEstimator):
        h, w = estimator.network_size(rgb.shape[:2])
        if (h, w) != rgb.shape[:2]:
            flag = cv2.INTER_AREA if h <= rgb.shape[0] and w <= rgb.shape[1] else cv2.INTER_LINEAR
            return np.ascontiguousarray(cv2.resize(rgb, (w, h), interpolation=flag))
    return rgb


def run_prior(estimator: Any, image: np.ndarray, what: str = "prior model") -> np.ndarray:
    """Run a panoramic ``estimator`` on ``image`` (:func:`prior_input`); any failure a ModelError.

    Returns its (h, w) float32 output as it is (NaN kept), checked to be one 2-D float map.
    """
    try:
        raw = estimator.predict(image)
    except ModelError as exc:
        if what == "prior model":  # say whose options to change
            raise ModelError(f"{what}: {exc}") from exc
        raise
    except M360Error:
        raise
    except Exception as exc:  # a user estimator may raise anything; a batch needs M360Error
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(f"{what} {name} failed: {type(exc).__name__}: {exc}") from exc
    out = np.asarray(raw)
    if out.ndim != 2 or out.dtype.kind != "f" or min(out.shape) < 2:
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(
            f"{what} {name} returned {out.dtype} of shape {out.shape}; a panoramic estimator "
            "returns one float (h, w) ERP map"
        )
    values = np.asarray(out, dtype=np.float32)
    if not np.isfinite(values).any():
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(f"{what} {name} returned no finite value")
    return values


def _resize_masked(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resize a map with NaN to (h, w): area when shrinking, bilinear else, over valid pixels."""
    h, w = shape
    if values.shape == shape:
        return values
    shrink = h <= values.shape[0] and w <= values.shape[1]
    flag = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    valid = np.isfinite(values)
    weight = cv2.resize(valid.astype(np.float32), (w, h), interpolation=flag)
    total = cv2.resize(np.where(valid, values, np.float32(0)), (w, h), interpolation=flag)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = total / weight
    out[~(weight >= 0.5)] = np.nan
    result: np.ndarray = out.astype(np.float32, copy=False)
    return result


def fit_to_job(
    values: np.ndarray,
    confidence: np.ndarray | None,
    working_shape: tuple[int, int],
    erp_valid: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Fit a prior map to one job: an ERP grid (w == 2h), masked, no larger than the work.

    A model's output that is not 2:1 is resized to (h, 2h); a map larger than the working ERP
    ``working_shape`` is shrunk to it (the stitch runs there; the tangents give the detail);
    pixels whose share of the output-sized ERP mask ``erp_valid`` is not all valid are NaN
    (masked pixels take no part, as in the tangents). The confidence follows the same resizing
    (bilinear/area; no mask: the prior's NaN already say it).
    """
    prior = np.asarray(values, dtype=np.float32)
    h = prior.shape[0]
    if prior.shape[1] != 2 * h:
        h = max(2, (prior.shape[0] + prior.shape[1] // 2) // 2)
    if h > working_shape[0]:
        h = working_shape[0]
    shape = (h, 2 * h)
    prior = _resize_masked(prior, shape).copy() if prior.shape != shape else prior.copy()
    conf: np.ndarray | None = None
    if confidence is not None:
        trust = np.asarray(confidence, dtype=np.float32)
        if trust.shape != shape:
            flag = cv2.INTER_AREA if shape[0] <= trust.shape[0] else cv2.INTER_LINEAR
            trust = np.asarray(cv2.resize(trust, (shape[1], shape[0]), interpolation=flag))
        conf = np.clip(trust, 0.0, 1.0).astype(np.float32)
    if erp_valid is not None:
        area = cv2.resize(
            erp_valid.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA
        )
        prior[~(area >= 1.0 - 1e-6)] = np.nan
    return prior, conf


def describe(prior: Prior) -> dict[str, Any]:
    """Describe a prior as JSON: the sidecar's record and the resume fingerprint's.

    An array: ``source="array"``, its shape and the sha256 of its float32 bytes (and its
    confidence's); a model: its name, sha256, output kind and, for ONNX models, what feeds it.
    """
    if prior.array is not None:
        record: dict[str, Any] = {
            "kind": prior.kind,
            "source": "array",
            "shape": list(prior.array.shape),
            "sha256": hashlib.sha256(np.ascontiguousarray(prior.array).tobytes()).hexdigest(),
        }
        if prior.confidence is not None:
            record["confidence_sha256"] = hashlib.sha256(
                np.ascontiguousarray(prior.confidence).tobytes()
            ).hexdigest()
        return record
    est = prior.estimator
    record = {
        "kind": prior.kind,
        "source": "model",
        "name": getattr(est, "name", type(est).__name__),
        "sha256": getattr(est, "sha256", None),
    }
    if isinstance(est, OnnxEstimator):
        record.update(
            input_size=None if est.input_size is None else list(est.input_size),
            multiple_of=est.multiple_of,
            resize=est.resize_policy,
            mean=[float(v) for v in est.mean],
            std=[float(v) for v in est.std],
        )
    return record
