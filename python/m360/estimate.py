"""Depth estimators and the end-to-end job: ERP image in, ERP disparity and depth out.

An *estimator* is anything with ``predict(tiles) -> (N, h, w) float32`` and an ``output_kind``
(DESIGN.md §8):

- ``"affine_disparity"``: perspective disparity 1/z up to an unknown scale and shift (MiDaS, DPT,
  Depth Anything relative models: the paper's assumption); passed through;
- ``"metric_depth"``: z-depth in metres (a metric model); perspective disparity = 1/z;
- ``"distance"``: radial distance |P| in metres; perspective disparity = |q| / distance with the
  pixel ray ``q = ((x - cx)/fx, (y - cy)/fy, 1)``.

:class:`OnnxEstimator` runs an ONNX graph with ONNX Runtime, one tangent at a time by default
(on a few CPU cores batching gains nothing and multiplies the activation memory), with the
model's own resize and normalisation, and resizes the prediction back to the tangent size.
:func:`estimate` projects the panorama onto the layout's tangents, runs the estimator, converts
its output to perspective disparity and stitches (:func:`m360.stitch`).
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from . import models as _models
from ._validate import MAX_THREADS, as_array, check_erp_shape, integer
from .errors import InputError, M360Error, ModelError
from .geometry import Layout, erp_to_tangents
from .stitch import StitchResult, stitch

__all__ = [
    "OUTPUT_KINDS",
    "EstimateResult",
    "Estimator",
    "OnnxEstimator",
    "SimulatedEstimator",
    "estimate",
    "load_estimator",
    "ray_norms",
    "to_perspective_disparity",
]

#: What an estimator may declare it outputs.
OUTPUT_KINDS = ("affine_disparity", "metric_depth", "distance")
RESIZE_MODES = ("upper_bound", "lower_bound", "exact")
#: Largest network input side (and rounding multiple) accepted: depth networks run at ≤ 1536 px,
#: and one 4096² float32 RGB input is already 200 MB.
MAX_NETWORK_SIZE = 4096
#: Largest |mean| and std of the input normalisation, and smallest std: beyond them the
#: float32 network input would overflow.
_NORMALISATION_LIMIT = 1e6


@runtime_checkable
class Estimator(Protocol):
    """What :func:`estimate` needs from a depth estimator.

    Attributes
    ----------
    output_kind : str
        One of :data:`OUTPUT_KINDS`.
    """

    output_kind: str

    def predict(self, tiles: np.ndarray) -> np.ndarray:
        """(N, h, w, 3) uint8 RGB tangents → (N, h, w) float32 of ``output_kind``; NaN = none."""
        ...


# --------------------------------------------------------------------------------------------
# Kind conversion.


@functools.lru_cache(maxsize=8)
def _ray_norms_cached(layout: Layout) -> np.ndarray:
    h, w = layout.tangent_shape
    x = np.arange(w, dtype=np.float64)
    y = np.arange(h, dtype=np.float64)
    out = np.empty((len(layout), h, w), dtype=np.float64)
    for k, cam in enumerate(layout.cameras):
        qx = (x - cam.cx) / cam.fx
        qy = (y - cam.cy) / cam.fy
        out[k] = np.sqrt(1.0 + qx[None, :] ** 2 + qy[:, None] ** 2)
    out.flags.writeable = False
    return out


def ray_norms(layout: Layout) -> np.ndarray:
    """|q| of every tangent pixel: (N, h, w) float64, read-only, ≥ 1.

    ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` for the pixel centre (x = column, y = row) of each
    camera (DESIGN.md §1); perspective disparity 1/z equals ``|q| / distance``.
    """
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    return _ray_norms_cached(layout)


def to_perspective_disparity(values: np.ndarray, kind: str, layout: Layout) -> np.ndarray:
    """Convert an estimator's output of the declared ``kind`` to perspective disparity.

    Parameters
    ----------
    values : (N, h, w) float array
        One map per camera of ``layout``; NaN = no estimate.
    kind : str
        ``"affine_disparity"`` (returned as float32 unchanged), ``"metric_depth"`` (z-depth:
        1/z) or ``"distance"`` (radial: |q| / distance).
    layout : Layout

    Returns
    -------
    (N, h, w) float32 perspective disparity; NaN where the input is NaN, and for depths where
    the value is not > 0.
    """
    if not isinstance(kind, str) or kind not in OUTPUT_KINDS:
        options = ", ".join(repr(k) for k in OUTPUT_KINDS)
        raise InputError(f"output_kind={kind!r} is not supported; choose one of {options}")
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    array = as_array(values, "estimator output")
    h, w = layout.tangent_shape
    if array.shape != (len(layout), h, w):
        raise InputError(
            f"estimator output has shape {array.shape}, expected {(len(layout), h, w)} (N, h, w)"
        )
    if kind == "affine_disparity":
        with np.errstate(over="ignore"):  # beyond float32: inf, which stitch() refuses
            return np.ascontiguousarray(array, dtype=np.float32)
    depth = array.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        numerator = 1.0 if kind == "metric_depth" else ray_norms(layout)
        out = np.where(depth > 0, numerator / depth, np.nan).astype(np.float32)
    # A depth so small that its disparity overflows float32 is no estimate either.
    out[np.isinf(out)] = np.nan
    return out


# --------------------------------------------------------------------------------------------
# ONNX Runtime.


@dataclass(frozen=True)
class _InputSpec:
    name: str
    layout: str  # "NCHW" or "NHWC"
    batch: int | None  # fixed batch size or None (dynamic)
    size: tuple[int, int] | None  # fixed (H, W) or None (dynamic)


@functools.lru_cache(maxsize=4)
def _session(
    path: str, size: int, mtime_ns: int, providers: tuple[str, ...], threads: int | None
) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    if threads is not None:
        options.intra_op_num_threads = threads
    try:
        return ort.InferenceSession(path, sess_options=options, providers=list(providers))
    except Exception as exc:  # onnxruntime raises its own exception types per failure
        reason = _models.sniff_onnx(path)
        detail = reason if reason else f"ONNX Runtime says: {str(exc).strip()[:300]}"
        raise ModelError(f"cannot load {path} as an ONNX model: {detail}") from exc


def _pick_providers(providers: Sequence[str] | None) -> tuple[str, ...]:
    import onnxruntime as ort

    available = ort.get_available_providers()
    if providers is None:
        return ("CPUExecutionProvider",)
    if isinstance(providers, str):
        providers = [providers]
    if not isinstance(providers, (Sequence, set, frozenset)) or not all(
        isinstance(p, str) for p in providers
    ):
        raise InputError(f"providers must be a list of provider names, got {providers!r}")
    chosen = tuple(p for p in providers if p in available)
    if not chosen:
        raise InputError(
            f"none of providers={list(providers)} is available in this onnxruntime build; "
            f"available: {', '.join(available)} (GPU providers need onnxruntime-gpu)"
        )
    return chosen


def _check_threads(threads: int | None) -> int | None:
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)):
        raise InputError(f"threads must be a positive integer or None, got {threads!r}")
    if not 1 <= threads <= MAX_THREADS:
        raise InputError(f"threads must be a positive integer up to {MAX_THREADS}, got {threads!r}")
    return int(threads)


def _fixed(dim: Any) -> int | None:
    return int(dim) if isinstance(dim, (int, np.integer)) and dim > 0 else None


def _round_to(value: float, multiple: int, mode: str) -> int:
    if mode == "lower_bound":
        n = math.ceil(value / multiple - 1e-9)
    elif mode == "upper_bound":
        n = math.floor(value / multiple + 1e-9)
    else:
        n = round(value / multiple)
    return max(multiple, int(n) * multiple)


def network_size(
    tile_shape: tuple[int, int],
    input_size: tuple[int, int],
    *,
    multiple_of: int = 1,
    resize: str = "upper_bound",
) -> tuple[int, int]:
    """Network input (height, width) for a tile of ``tile_shape`` and a dynamic-size model.

    ``"upper_bound"`` scales the tile to fit inside ``input_size`` keeping its aspect ratio and
    rounds down to ``multiple_of`` (MiDaS); ``"lower_bound"`` scales it to cover ``input_size``
    and rounds up (Depth Anything); ``"exact"`` uses ``input_size`` rounded to ``multiple_of``.
    """
    h, w = tile_shape
    th, tw = input_size
    if resize == "exact":
        return _round_to(th, multiple_of, "nearest"), _round_to(tw, multiple_of, "nearest")
    scale = min(th / h, tw / w) if resize == "upper_bound" else max(th / h, tw / w)
    return _round_to(h * scale, multiple_of, resize), _round_to(w * scale, multiple_of, resize)


class OnnxEstimator:
    """A depth network in an ONNX file, run with ONNX Runtime.

    Parameters
    ----------
    path : str or PathLike
        The .onnx file. Its first input must be a 4-D float image, NCHW (1, 3, H, W) or NHWC
        (1, H, W, 3); its first output (B, H', W') or (B, 1, H', W').
    output_kind : str
        What the network outputs (:data:`OUTPUT_KINDS`).
    input_size : (int, int), optional
        Network (height, width) for models whose input size is dynamic; ignored (with the
        file's size used instead) when the file fixes it. Default 384 x 384.
    mean, std : 3 floats
        Normalisation ``(rgb / 255 - mean) / std`` per RGB channel. Default ImageNet's.
    multiple_of : int
        Round dynamic network sizes to a multiple of this (32 for CNN/DPT, 14 for ViT-14).
    resize : str
        How a dynamic size follows the tile's aspect: ``"upper_bound"``, ``"lower_bound"`` or
        ``"exact"`` (see :func:`network_size`).
    providers : list of str, optional
        ONNX Runtime execution providers in order of preference (e.g. ``["CUDAExecutionProvider",
        "CPUExecutionProvider"]``); unavailable ones are skipped. Default CPU.
    threads : int, optional
        Intra-op threads of the session (default: ONNX Runtime's choice, all cores).
    batch_size : int
        Tangents per network call (1: one at a time, the default; larger only when the model's
        batch dimension is dynamic).
    name : str, optional
        Name for reports (default: the file name).
    sha256 : str, optional
        The file's sha256 if already known (registry models); computed lazily otherwise.

    Notes
    -----
    Sessions are cached per process by (file, size, mtime, providers, threads). Tiles are
    resized to the network size with ``cv2.INTER_AREA`` when shrinking and ``cv2.INTER_LINEAR``
    when enlarging, and predictions back to the tile size with ``cv2.INTER_LINEAR`` (no
    overshoot at depth edges). uint8 tiles are divided by 255; float tiles are taken as RGB in
    [0, 1].
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        output_kind: str = "affine_disparity",
        input_size: tuple[int, int] | None = None,
        mean: Sequence[float] = _models.IMAGENET_MEAN,
        std: Sequence[float] = _models.IMAGENET_STD,
        multiple_of: int = 1,
        resize: str = "upper_bound",
        providers: Sequence[str] | None = None,
        threads: int | None = None,
        batch_size: int = 1,
        name: str | None = None,
        sha256: str | None = None,
    ) -> None:
        if not isinstance(path, (str, os.PathLike)):
            raise InputError(f"path must be a str or os.PathLike, got {type(path).__name__}")
        self.path = Path(path)
        if not _is_file(self.path):
            raise ModelError(f"model file {self.path} does not exist (or is not a file)")
        if not isinstance(output_kind, str) or output_kind not in OUTPUT_KINDS:
            options = ", ".join(repr(k) for k in OUTPUT_KINDS)
            raise InputError(
                f"output_kind={output_kind!r} is not supported; choose one of {options}"
            )
        self.output_kind = output_kind
        self.input_size = _check_size_pair(input_size, "input_size") if input_size else None
        self.mean = _check_triple(mean, "mean")
        self.std = _check_triple(std, "std")
        if np.any(np.abs(self.mean) > _NORMALISATION_LIMIT):
            raise InputError(f"mean must be at most {_NORMALISATION_LIMIT:g} in magnitude")
        if np.any(self.std < 1 / _NORMALISATION_LIMIT) or np.any(self.std > _NORMALISATION_LIMIT):
            raise InputError(
                f"std must be > 0 per channel (within [1e-6, 1e6]), got {tuple(self.std)}"
            )
        self.multiple_of = integer(multiple_of, "multiple_of", low=1, high=MAX_NETWORK_SIZE)
        if not isinstance(resize, str) or resize not in RESIZE_MODES:
            raise InputError(f"resize={resize!r} is not supported; choose one of {RESIZE_MODES}")
        self.resize = resize
        self.batch_size = integer(batch_size, "batch_size", low=1, high=1 << 16)
        if name is not None and not isinstance(name, str):
            raise InputError(f"name must be a str, got {type(name).__name__}")
        if sha256 is not None and not isinstance(sha256, str):
            raise InputError(f"sha256 must be a hex str, got {type(sha256).__name__}")
        self.threads = _check_threads(threads)
        self.requested_providers = _pick_providers(providers)
        self.name = name or self.path.name
        self._sha256 = sha256
        stat = self.path.stat()
        self.session = _session(
            str(self.path.resolve()),
            stat.st_size,
            stat.st_mtime_ns,
            self.requested_providers,
            self.threads,
        )
        self.providers = tuple(self.session.get_providers())
        self._input = self._inspect_input()
        self._output_name = self.session.get_outputs()[0].name
        if self._input.batch is not None and self._input.batch != 1 and self.batch_size == 1:
            raise ModelError(
                f"{self.name}: input {self._input.name!r} has a fixed batch of "
                f"{self._input.batch}; m360 runs one tangent at a time and needs batch 1 "
                "(or a dynamic batch dimension)"
            )

    def _inspect_input(self) -> _InputSpec:
        inputs = self.session.get_inputs()
        first = inputs[0]
        shape = list(first.shape)
        if len(inputs) != 1:
            raise ModelError(
                f"{self.name} has {len(inputs)} inputs ({', '.join(i.name for i in inputs)}); "
                "m360 can feed models with exactly one image input"
            )
        if len(shape) != 4:
            raise ModelError(
                f"{self.name}: input {first.name!r} has rank {len(shape)} (shape {shape}); m360 "
                "needs a 4-D image input, NCHW (1, 3, H, W) or NHWC (1, H, W, 3)"
            )
        if first.type != "tensor(float)":
            raise ModelError(
                f"{self.name}: input {first.name!r} has type {first.type}; m360 feeds float32 "
                "images (tensor(float))"
            )
        if _fixed(shape[1]) == 3:
            layout, hw = "NCHW", (shape[2], shape[3])
        elif _fixed(shape[3]) == 3:
            layout, hw = "NHWC", (shape[1], shape[2])
        elif _fixed(shape[1]) is None and _fixed(shape[3]) is None:
            layout, hw = "NCHW", (shape[2], shape[3])
        else:
            raise ModelError(
                f"{self.name}: input {first.name!r} has shape {shape}: neither dimension 1 "
                "(NCHW) nor dimension 3 (NHWC) is 3 RGB channels"
            )
        fixed_hw = (_fixed(hw[0]), _fixed(hw[1]))
        size = (fixed_hw[0], fixed_hw[1]) if None not in fixed_hw else None
        return _InputSpec(first.name, layout, _fixed(shape[0]), size)  # type: ignore[arg-type]

    @property
    def sha256(self) -> str:
        """sha256 of the model file (computed on first access for non-registry files)."""
        if self._sha256 is None:
            self._sha256 = _file_sha256(str(self.path.resolve()), *_stat_key(self.path))
        return self._sha256

    def network_size(self, tile_shape: tuple[int, int]) -> tuple[int, int]:
        """Network input (height, width) used for tiles of ``tile_shape``."""
        if self._input.size is not None:
            return self._input.size
        target = self.input_size or (384, 384)
        return network_size(tile_shape, target, multiple_of=self.multiple_of, resize=self.resize)

    def preprocess(self, tiles: np.ndarray) -> np.ndarray:
        """(B, h, w, 3) uint8/float RGB → network input (B, 3, H, W) or (B, H, W, 3) float32."""
        b, h, w = tiles.shape[:3]
        nh, nw = self.network_size((h, w))
        out = np.empty((b, nh, nw, 3), dtype=np.float32)
        scale = 1.0 / 255.0 if tiles.dtype == np.uint8 else 1.0
        flag = cv2.INTER_AREA if nh <= h and nw <= w else cv2.INTER_LINEAR
        for k in range(b):
            tile = tiles[k].astype(np.float32) * np.float32(scale)
            out[k] = tile if (nh, nw) == (h, w) else cv2.resize(tile, (nw, nh), interpolation=flag)
        out -= self.mean.astype(np.float32)
        out /= self.std.astype(np.float32)
        if self._input.layout == "NCHW":
            out = out.transpose(0, 3, 1, 2)
        return np.ascontiguousarray(out)

    def _run(self, batch: np.ndarray) -> np.ndarray:
        result = self.session.run([self._output_name], {self._input.name: batch})[0]
        pred = np.asarray(result)
        b = batch.shape[0]
        if pred.ndim == 4 and pred.shape[0] == b and pred.shape[1] == 1:
            pred = pred[:, 0]
        if pred.ndim != 3 or pred.shape[0] != b or min(pred.shape[1:]) < 1:
            raise ModelError(
                f"{self.name}: output {self._output_name!r} has shape {tuple(pred.shape)} for an "
                f"input of shape {tuple(batch.shape)}; m360 needs one depth map per image, "
                f"shape ({b}, H, W) or ({b}, 1, H, W)"
            )
        return pred.astype(np.float32, copy=False)

    def predict(self, tiles: np.ndarray) -> np.ndarray:
        """Run the network on each tangent.

        Parameters
        ----------
        tiles : (N, h, w, 3) uint8 RGB (or float RGB in [0, 1])

        Returns
        -------
        (N, h, w) float32 in the model's ``output_kind``, NaN where the output is not finite.
        """
        array = as_array(tiles, "tiles")
        if array.ndim != 4 or array.shape[3] != 3 or min(array.shape[1:3]) < 1:
            raise InputError(
                f"tiles must have shape (N, h, w, 3) RGB with h, w > 0, got {array.shape}"
            )
        n, h, w = array.shape[:3]
        out = np.empty((n, h, w), dtype=np.float32)
        step = self.batch_size if self._input.batch is None else 1
        for start in range(0, n, step):
            pred = self._run(self.preprocess(array[start : start + step]))
            for k in range(pred.shape[0]):
                p = pred[k]
                out[start + k] = (
                    p
                    if p.shape == (h, w)
                    else cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR)
                )
        out[~np.isfinite(out)] = np.nan
        return out

    def __repr__(self) -> str:
        return (
            f"OnnxEstimator({self.name!r}, output_kind={self.output_kind!r}, "
            f"providers={list(self.providers)}, threads={self.threads})"
        )


def _stat_key(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


@functools.lru_cache(maxsize=16)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    return _models.sha256_of(path)


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False for names the OS refuses (too long, NUL bytes)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def _check_triple(value: Sequence[float], name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be 3 numbers (R, G, B), got {value!r}") from exc
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise InputError(f"{name} must be 3 finite numbers (R, G, B), got {value!r}")
    return array


def _check_size_pair(value: Any, name: str) -> tuple[int, int]:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        value = (value, value)
    try:
        h, w = value
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be (height, width), got {value!r}") from exc
    for v in (h, w):
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, np.integer))
            or not 1 <= v <= MAX_NETWORK_SIZE
        ):
            raise InputError(
                f"{name} must be two integers in [1, {MAX_NETWORK_SIZE}] (height, width), "
                f"got {value!r}"
            )
    return int(h), int(w)


def load_estimator(
    model: str | os.PathLike[str] | Estimator = _models.DEFAULT_MODEL,
    *,
    providers: Sequence[str] | None = None,
    threads: int | None = None,
    input_size: tuple[int, int] | None = None,
    output_kind: str | None = None,
    mean: Sequence[float] | None = None,
    std: Sequence[float] | None = None,
) -> Estimator:
    """Resolve ``model`` to an estimator.

    A registry name (``m360.models.names()``) is fetched/verified and loaded with its own
    preprocessing (``input_size``/``output_kind``/``mean``/``std`` override it); a path to an
    ``.onnx`` file is loaded with the given options (defaults: affine disparity, ImageNet
    normalisation, 384 px); an object with ``predict`` and ``output_kind`` is returned as is.
    """
    if isinstance(model, (str, os.PathLike)):
        text = os.fspath(model)
        if text in _models.REGISTRY:
            entry = _models.get(text)
            path = _models.ensure(text)
            return OnnxEstimator(
                path,
                output_kind=output_kind or entry.output_kind,
                input_size=input_size or entry.input_size,
                mean=entry.mean if mean is None else mean,
                std=entry.std if std is None else std,
                multiple_of=entry.multiple_of,
                resize=entry.resize,
                providers=providers,
                threads=threads,
                name=entry.name,
                sha256=entry.sha256,
            )
        if text.endswith(".onnx") or _is_file(Path(text)):
            return OnnxEstimator(
                text,
                output_kind=output_kind or "affine_disparity",
                input_size=input_size,
                mean=_models.IMAGENET_MEAN if mean is None else mean,
                std=_models.IMAGENET_STD if std is None else std,
                providers=providers,
                threads=threads,
            )
        _models.get(text)  # raises ModelError naming the registered models
    if isinstance(model, Estimator):
        given = {
            "providers": providers,
            "threads": threads,
            "input_size": input_size,
            "output_kind": output_kind,
            "mean": mean,
            "std": std,
        }
        ignored = [k for k, v in given.items() if v is not None]
        if ignored:
            raise InputError(
                f"{', '.join(ignored)} apply to ONNX models given by name or path; configure "
                f"the {type(model).__name__} object itself instead"
            )
        kind = model.output_kind
        if kind not in OUTPUT_KINDS:
            options = ", ".join(repr(k) for k in OUTPUT_KINDS)
            raise InputError(
                f"estimator {type(model).__name__} declares output_kind={kind!r}; "
                f"choose one of {options}"
            )
        return model
    raise InputError(
        f"model must be a registry name, a path to an .onnx file, or an object with "
        f"predict(tiles) and output_kind; got {type(model).__name__}"
    )


# --------------------------------------------------------------------------------------------
# Simulated network (demo, tests).


class SimulatedEstimator:
    """NOT a network: exact tangent disparity of a synthetic scene, distorted per tangent.

    It returns what a *perfect* affine-invariant network would give on
    :mod:`m360.synthetic` scenes: the ray-cast perspective disparity of each tangent, with a
    random scale and shift per tangent and optional gaussian noise
    (:func:`m360.synthetic.distort`). The tiles it is given are only checked for shape. Used by
    ``m360 demo`` and the tests; never by ``m360 run``.

    Parameters
    ----------
    scene : m360.synthetic.Scene
    layout : Layout
        The layout :func:`estimate` will use (its cameras are ray cast).
    seed : int
        Seed of the distortion.
    scale : (float, float)
        Range of the log-uniform scale per tangent.
    shift : float
        Shift amplitude relative to each tangent's median disparity.
    noise : float
        Relative gaussian noise std.
    """

    output_kind = "affine_disparity"

    def __init__(
        self,
        scene: Any,
        layout: Layout,
        *,
        seed: int = 0,
        scale: tuple[float, float] = (0.5, 2.0),
        shift: float = 0.3,
        noise: float = 0.0,
    ) -> None:
        from . import synthetic

        if not isinstance(layout, Layout):
            raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
        self.layout = layout
        self.exact = synthetic.tangent_perspective_disparity(scene, layout.cameras)
        self._tiles = synthetic.distort(self.exact, seed, scale=scale, shift=shift, noise=noise)
        self.name = f"simulated (exact disparity, per-tangent affine, noise {noise:g})"

    def predict(self, tiles: np.ndarray) -> np.ndarray:
        """The distorted exact disparities (N, h, w) float32 of the layout's tangents."""
        shape = (len(self.layout), *self.layout.tangent_shape)
        if tuple(np.shape(tiles)[:3]) != shape:
            raise InputError(
                f"SimulatedEstimator was built for tiles of shape {shape}, got {np.shape(tiles)}"
            )
        return self._tiles.copy()


# --------------------------------------------------------------------------------------------
# End to end.


@dataclass
class EstimateResult:
    """Everything :func:`estimate` produced for one panorama.

    Attributes
    ----------
    disparity : (H, W) float32
        Spherical disparity 1/distance (relative: up to a global scale and shift, unless the
        model is metric and ``align="none"``); NaN where no tangent has an estimate.
    depth : (H, W) float32
        Radial depth 1/disparity where disparity > 0, NaN elsewhere (relative unless metric).
    confidence : (H, W) float32
        Overlap disagreement from :func:`m360.stitch` (lower = more consistent).
    tangents : (N, h, w) float32
        Per-tangent perspective disparity given to the stitcher (after kind conversion).
    timings : dict
        Seconds per stage: ``load`` (model), ``project``, ``network``, ``convert``, ``align``,
        ``blend``, ``total``.
    model : dict
        ``name``, ``sha256``, ``output_kind``, ``providers``, ``threads`` (what ran).
    units : str
        ``"relative"`` or ``"metres"`` (for depth; disparity is in 1/units).
    options : dict
        The stitching options used (align, blend, layout).
    layout : Layout
    stitch : StitchResult
        The stitcher's full report.
    """

    disparity: np.ndarray
    depth: np.ndarray
    confidence: np.ndarray
    tangents: np.ndarray
    timings: dict[str, float]
    model: dict[str, Any]
    units: str
    options: dict[str, Any]
    layout: Layout
    stitch: StitchResult = field(repr=False)


def _check_erp_rgb(erp: Any) -> np.ndarray:
    array = as_array(erp, "erp")
    if array.ndim != 3 or array.shape[2] != 3:
        raise InputError(
            f"erp must be an RGB panorama of shape (H, W, 3), got {array.shape}"
            + (" (grey images: stack the channel three times)" if array.ndim == 2 else "")
        )
    check_erp_shape(array.shape[0], array.shape[1], "erp")
    if array.dtype == np.uint8:
        return array
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all() or array.min() < 0 or array.max() > 1:
            raise InputError(
                "a float erp must be RGB in [0, 1] without NaN (uint8 is the usual input)"
            )
        return np.ascontiguousarray(array, dtype=np.float32)
    raise InputError(f"erp has dtype {array.dtype}; use uint8 RGB (or float RGB in [0, 1])")


def estimate(
    erp: np.ndarray,
    model: str | os.PathLike[str] | Estimator = _models.DEFAULT_MODEL,
    *,
    align: str = "multiscale",
    blend: str = "poisson",
    layout: Layout | None = None,
    mask: np.ndarray | None = None,
    providers: Sequence[str] | None = None,
    threads: int | None = None,
    input_size: tuple[int, int] | None = None,
    output_kind: str | None = None,
    mean: Sequence[float] | None = None,
    std: Sequence[float] | None = None,
) -> EstimateResult:
    """Estimate the depth of an equirectangular panorama (the paper's pipeline, end to end).

    Parameters
    ----------
    erp : (H, W, 3) uint8 RGB, W == 2H
        The panorama (ERP convention of DESIGN.md §1: column 0 at longitude −π, row 0 at the
        top). float RGB in [0, 1] is accepted too.
    model : str, path or estimator
        A registry name (default ``"midas-v21-small"``, downloaded and verified on first use;
        see ``m360 models``), a path to an ``.onnx`` file, or any object with
        ``predict(tiles) -> (N, h, w)`` and ``output_kind``.
    align, blend : str
        Passed to :func:`m360.stitch` (defaults: the method's ``"multiscale"`` and
        ``"poisson"``).
    layout : Layout, optional
        Tangent layout; default ``Layout.icosahedron(W)``.
    mask : (N, h, w) bool, optional
        False marks tangent pixels without an estimate (passed to :func:`m360.stitch`).
    providers, threads : optional
        ONNX Runtime execution providers and intra-op threads (ONNX models only).
    input_size, output_kind, mean, std : optional
        Override the model's preprocessing / declared output (ONNX models).

    Returns
    -------
    EstimateResult
        ``disparity`` (H, W) spherical disparity, ``depth`` (H, W) radial depth,
        ``confidence``, ``tangents``, ``timings`` per stage and what ran.
    """
    t_start = time.perf_counter()
    rgb = _check_erp_rgb(erp)
    height, width = rgb.shape[:2]
    if layout is None:
        layout = Layout.icosahedron(width)
    elif not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    estimator = load_estimator(
        model,
        providers=providers,
        threads=threads,
        input_size=input_size,
        output_kind=output_kind,
        mean=mean,
        std=std,
    )
    kind = estimator.output_kind
    t_load = time.perf_counter()
    tiles = erp_to_tangents(rgb, layout)
    t_project = time.perf_counter()
    try:
        raw = estimator.predict(tiles)
    except M360Error:
        raise
    except Exception as exc:  # a user estimator may raise anything; a batch loop needs M360Error
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(f"estimator {name} failed: {type(exc).__name__}: {exc}") from exc
    t_network = time.perf_counter()
    h, w = layout.tangent_shape
    raw_array = np.asarray(raw)
    if raw_array.shape != (len(layout), h, w) or raw_array.dtype.kind != "f":
        raise ModelError(
            f"estimator {getattr(estimator, 'name', type(estimator).__name__)} returned "
            f"{raw_array.dtype} of shape {raw_array.shape}; expected float (N, h, w) = "
            f"{(len(layout), h, w)}"
        )
    perspective = to_perspective_disparity(raw_array, kind, layout)
    t_convert = time.perf_counter()
    details = stitch(perspective, layout, align=align, blend=blend, mask=mask, return_details=True)
    assert isinstance(details, StitchResult)
    disparity = details.disparity
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(disparity > 0, 1.0 / disparity, np.nan).astype(np.float32)
    t_end = time.perf_counter()
    st = details.timings
    metric = kind != "affine_disparity" and align == "none"
    return EstimateResult(
        disparity=disparity,
        depth=depth,
        confidence=details.confidence,
        tangents=perspective,
        timings={
            "load": t_load - t_start,
            "project": t_project - t_load,
            "network": t_network - t_project,
            "convert": t_convert - t_network + st.get("convert", 0.0),
            "align": st.get("align", 0.0),
            "blend": st.get("blend", 0.0),
            "total": t_end - t_start,
        },
        model=_model_info(estimator, layout),
        units="metres" if metric else "relative",
        options={
            "align": align,
            "blend": blend,
            "layout": repr(layout),
            "erp_shape": [height, width],
        },
        layout=layout,
        stitch=details,
    )


def _model_info(estimator: Any, layout: Layout) -> dict[str, Any]:
    info: dict[str, Any] = {
        "name": getattr(estimator, "name", type(estimator).__name__),
        "output_kind": estimator.output_kind,
    }
    if isinstance(estimator, OnnxEstimator):
        info.update(
            sha256=estimator.sha256,
            path=str(estimator.path),
            providers=list(estimator.providers),
            threads=estimator.threads,
            network_size=list(estimator.network_size(layout.tangent_shape)),
            mean=[float(v) for v in estimator.mean],
            std=[float(v) for v in estimator.std],
        )
    else:
        info["sha256"] = None
    return info
