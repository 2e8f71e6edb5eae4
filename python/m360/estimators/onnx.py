"""ONNX Runtime estimators: a depth network in an ``.onnx`` file, run one tangent at a time.

:class:`OnnxEstimator` runs an ONNX graph with ONNX Runtime, one tangent at a time by default
(on a few CPU cores batching gains nothing and multiplies the activation memory), with the
model's own resize and normalisation, and resizes the prediction back to the tangent size.
:class:`PanoramicOnnxEstimator` runs a panoramic network (the whole ERP in, one ERP map out)
once, with the same size rules, normalisation and checks, and returns the map at the network's
own resolution (its callers upsample it).
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .._compat import renamed
from .._validate import as_array, integer, size_pair
from .._validate import threads as check_threads
from ..errors import InputError, ModelError
from . import onnx_file
from .kinds import (
    DEPTH_KINDS,
    PANORAMIC_METRIC_KINDS,
    check_output_kind,
    check_panoramic_output_kind,
)

__all__ = [
    "MAX_NETWORK_SIZE",
    "RESIZE_MODES",
    "OnnxEstimator",
    "PanoramicOnnxEstimator",
    "is_file",
    "network_size",
    "resize_valid",
]

RESIZE_MODES = ("upper_bound", "lower_bound", "exact")
#: The resize policies by the names users give (``resize=``, ``--resize``) → :data:`RESIZE_MODES`:
#: ``keep-aspect`` fits the tangent inside the input size keeping its aspect ratio, ``cover``
#: covers the input size keeping the aspect ratio, ``exact`` uses the input size as given.
RESIZE_POLICIES = {"keep-aspect": "upper_bound", "cover": "lower_bound", "exact": "exact"}
#: Multiples a dynamic input size is probed at when ONNX Runtime refuses a size (a CNN with
#: skip connections needs 2^downsamplings, a ViT its patch size), smallest first.
SIZE_MULTIPLES = (1, 2, 4, 8, 16, 32, 64, 128)
#: ViT patch sizes, tried when no power of two works.
PATCH_MULTIPLES = (14, 28)
#: Largest network input side (and rounding multiple) accepted: depth networks run at ≤ 1536 px,
#: and one 4096² float32 RGB input is already 200 MB.
MAX_NETWORK_SIZE = 4096
#: Largest |mean| and std of the input normalisation, and smallest std: beyond them the
#: float32 network input would overflow.
_NORMALISATION_LIMIT = 1e6


@dataclass(frozen=True)
class _InputSpec:
    name: str
    layout: str  # "NCHW" or "NHWC"
    batch: int | None  # fixed batch size or None (dynamic)
    size: tuple[int, int] | None  # fixed (H, W) or None (dynamic)


#: Sessions per (sha256 of the model bytes, folder, providers, threads): keyed by content, so a
#: file changed in place can never be served a session of its old bytes (the folder: where
#: external weights are looked for).
_SESSIONS: OrderedDict[tuple[str, str, tuple[str, ...], int | None], Any] = OrderedDict()
_SESSIONS_MAX = 4
_SESSIONS_LOCK = threading.Lock()


def _read_model(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except (OSError, ValueError) as exc:
        raise ModelError(f"cannot read model file {path}: {exc}") from exc


def _session(
    path: Path, data: bytes, digest: str, providers: tuple[str, ...], threads: int | None
) -> Any:
    """Make (or reuse) the ONNX Runtime session of ``data``, the bytes that were hashed."""
    import onnxruntime as ort

    folder = str(path.resolve().parent)
    key = (digest, folder, providers, threads)
    with _SESSIONS_LOCK:
        if key in _SESSIONS:
            _SESSIONS.move_to_end(key)
            return _SESSIONS[key]
    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    if threads is not None:
        options.intra_op_num_threads = threads
    # ONNX Runtime's threads spin after each call, waiting for the next; m360's own work runs
    # between and beside the calls (the stitch, the next video frame's), and the spinning takes
    # its cores: a video run went from 1.06x to 1.38x the loop with it off, while a loop of
    # m360.estimate kept its time (benches/bench_video.py, FastDepth, 2 cores).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    # Loaded from bytes, a model with external weights finds them next to its file.
    options.add_session_config_entry("session.model_external_initializers_file_folder_path", folder)
    try:
        session = ort.InferenceSession(data, sess_options=options, providers=list(providers))
    except Exception as exc:  # onnxruntime raises its own exception types per failure
        reason = onnx_file.sniff_onnx(path)
        detail = reason if reason else f"ONNX Runtime says: {str(exc).strip()[:300]}"
        raise ModelError(f"cannot load {path} as an ONNX model: {detail}") from exc
    with _SESSIONS_LOCK:
        _SESSIONS[key] = session
        while len(_SESSIONS) > _SESSIONS_MAX:
            _SESSIONS.popitem(last=False)
    return session


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


@renamed(tile_shape="tangent_shape")
def network_size(
    tangent_shape: tuple[int, int],
    input_size: tuple[int, int],
    *,
    multiple_of: int = 1,
    resize: str = "upper_bound",
) -> tuple[int, int]:
    """Network input (height, width) for a tangent of ``tangent_shape`` and a dynamic-size model.

    ``"upper_bound"`` scales the tangent to fit inside ``input_size`` keeping its aspect ratio and
    rounds down to ``multiple_of`` (MiDaS); ``"lower_bound"`` scales it to cover ``input_size``
    and rounds up (Depth Anything); ``"exact"`` uses ``input_size`` rounded to ``multiple_of``.
    """
    h, w = tangent_shape
    th, tw = input_size
    if resize == "exact":
        return _round_to(th, multiple_of, "nearest"), _round_to(tw, multiple_of, "nearest")
    scale = min(th / h, tw / w) if resize == "upper_bound" else max(th / h, tw / w)
    return _round_to(h * scale, multiple_of, resize), _round_to(w * scale, multiple_of, resize)


class OnnxEstimator:
    """A depth network in an ONNX file, run with ONNX Runtime, one tangent image at a time.

    Parameters
    ----------
    path : str or PathLike
        The .onnx file. Its first input must be a 4-D float image, NCHW (1, 3, H, W) or NHWC
        (1, H, W, 3); its first output (B, H', W') or (B, 1, H', W').
    output_kind : str
        What the network outputs (:data:`m360.estimators.OUTPUT_KINDS`).
    input_size : (int, int), optional
        Network (height, width) for models whose input size is dynamic. Default 384 x 384. A
        file that fixes its input size runs at that size; another ``input_size`` is an
        :class:`m360.InputError`.
    mean, std : 3 floats, optional
        Explicit normalisation ``(rgb / 255 - mean) / std`` per RGB channel; wins over what the
        graph holds. Default: ``expected_normalization``, applied only if the graph does not
        normalise its input itself (:func:`m360.models.input_normalization`; the finding is
        in ``normalization`` and ``normalization_source``).
    normalize : {"imagenet", "unit", "none"}, optional
        A named explicit normalisation instead of ``mean``/``std`` (not with them):
        ``imagenet``, ``unit`` (RGB in [0, 1] as is) or ``none`` (raw 0-255 values).
    multiple_of : int
        Round dynamic network sizes to a multiple of this (32 for CNN/DPT, 14 for ViT-14).
    resize : str
        How a dynamic size follows the tangent's aspect: ``"upper_bound"`` (alias
        ``"keep-aspect"``), ``"lower_bound"`` (``"cover"``) or ``"exact"`` (see
        :func:`network_size`).
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
        The file's expected sha256 (registry models): the bytes loaded must have it, else
        :class:`m360.ModelError`. The session is made from the bytes that were hashed.
    expected_normalization : (mean, std), optional
        The normalisation the network was trained with (default ImageNet's).

    Attributes
    ----------
    role : {"model", "prior"}
        What the job uses it as; a prior's error hints name the prior's own options
        (``--prior-multiple-of``, ``prior_options``). Set by
        :func:`m360.pipeline.prior.load_prior`.

    Notes
    -----
    Sessions are cached per process by (sha256 of the bytes, folder, providers, threads); the
    file is read once per estimator, hashed, and the session made from those bytes. Tangents are
    resized to the network size with ``cv2.INTER_AREA`` when shrinking and ``cv2.INTER_LINEAR``
    when enlarging, and predictions back to the tangent size with ``cv2.INTER_LINEAR`` (no
    overshoot at depth edges). uint8 tangents are divided by 255; float tangents are taken as RGB in
    [0, 1].
    """

    role: str = "model"

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        output_kind: str = "affine_disparity",
        input_size: tuple[int, int] | None = None,
        mean: Sequence[float] | None = None,
        std: Sequence[float] | None = None,
        normalize: str | None = None,
        multiple_of: int = 1,
        resize: str = "upper_bound",
        providers: Sequence[str] | None = None,
        threads: int | None = None,
        batch_size: int = 1,
        name: str | None = None,
        sha256: str | None = None,
        expected_normalization: tuple[Sequence[float], Sequence[float]] | None = None,
    ) -> None:
        if not isinstance(path, (str, os.PathLike)):
            raise InputError(f"path must be a str or os.PathLike, got {type(path).__name__}")
        self.path = Path(path)
        self.output_kind: str = self._check_output_kind(output_kind)
        if not is_file(self.path):
            raise ModelError(f"model file {self.path} does not exist (or is not a file)")
        self.input_size = (
            None if input_size is None else size_pair(input_size, "input_size", MAX_NETWORK_SIZE)
        )
        if normalize is not None:
            if not isinstance(normalize, str) or normalize not in onnx_file.NORMALIZE_PRESETS:
                choices = ", ".join(onnx_file.NORMALIZE_PRESETS)
                raise InputError(
                    f"normalize={normalize!r} is not supported; choose one of {choices}"
                )
            if mean is not None or std is not None:
                raise InputError("give normalize or mean/std, not both")
            mean, std = onnx_file.NORMALIZE_PRESETS[normalize]
        self.normalize = normalize
        expected = expected_normalization or (onnx_file.IMAGENET_MEAN, onnx_file.IMAGENET_STD)
        if not isinstance(expected, (tuple, list)) or len(expected) != 2:
            raise InputError(
                f"expected_normalization must be (mean, std), got {expected_normalization!r}"
            )
        self.mean = check_triple(expected[0] if mean is None else mean, "mean")
        self.std = check_triple(expected[1] if std is None else std, "std")
        if np.any(np.abs(self.mean) > _NORMALISATION_LIMIT):
            raise InputError(f"mean must be at most {_NORMALISATION_LIMIT:g} in magnitude")
        if np.any(self.std < 1 / _NORMALISATION_LIMIT) or np.any(self.std > _NORMALISATION_LIMIT):
            raise InputError(
                f"std must be > 0 per channel (within [1e-6, 1e6]), got {tuple(self.std)}"
            )
        self.multiple_of = integer(multiple_of, "multiple_of", low=1, high=MAX_NETWORK_SIZE)
        if isinstance(resize, str):
            resize = RESIZE_POLICIES.get(resize, resize)
        if not isinstance(resize, str) or resize not in RESIZE_MODES:
            policies = ", ".join((*RESIZE_POLICIES, *RESIZE_MODES[:2]))
            raise InputError(f"resize={resize!r} is not supported; choose one of {policies}")
        self.resize = resize
        self._size_rules: dict[tuple[int, int], int | None] = {}
        self.batch_size = integer(batch_size, "batch_size", low=1, high=1 << 16)
        if name is not None and not isinstance(name, str):
            raise InputError(f"name must be a str, got {type(name).__name__}")
        if sha256 is not None and not isinstance(sha256, str):
            raise InputError(f"sha256 must be a hex str, got {type(sha256).__name__}")
        self.threads = check_threads(threads)
        self.requested_providers = _pick_providers(providers)
        self.name = name or self.path.name
        # Hash the bytes that are loaded (not the file, which may change after a check).
        data = _read_model(self.path)
        self._sha256 = hashlib.sha256(data).hexdigest()
        if sha256 is not None and sha256.lower() != self._sha256:
            raise ModelError(
                f"model file {self.path} fails its hash check: expected sha256 {sha256}, the "
                f"bytes read have {self._sha256} (was the file replaced?); fetch it again "
                f"(m360 models fetch {self.name})"
            )
        self.session = _session(
            self.path, data, self._sha256, self.requested_providers, self.threads
        )
        self.providers = tuple(self.session.get_providers())
        # Read from the graph (the bytes the session was made from), not a model card: the
        # same file is used both ways in the wild.
        self.normalization = onnx_file.input_normalization(
            self.path,
            None if mean is None else tuple(self.mean),
            None if std is None else tuple(self.std),
            expected=(tuple(self.mean), tuple(self.std)),
            data=data,
        )
        del data
        self.normalization_source = self.normalization.source
        self.mean, self.std = (np.asarray(v, dtype=np.float64) for v in self.normalization.feed())
        self._input = self._inspect_input()
        self._check_input_size()
        self._output_name = self.session.get_outputs()[0].name
        if self._input.batch is not None and self._input.batch != 1 and self.batch_size == 1:
            raise ModelError(
                f"{self.name}: input {self._input.name!r} has a fixed batch of "
                f"{self._input.batch}; m360 runs one tangent at a time and needs batch 1 "
                "(or a dynamic batch dimension)"
            )

    #: The estimator's role (:data:`m360.estimators.kinds.ESTIMATOR_KINDS`).
    kind = "tangent"
    #: The network (height, width) of a dynamic-size file when no ``input_size`` is given.
    default_input_size: tuple[int, int] = (384, 384)

    @staticmethod
    def _check_output_kind(output_kind: Any) -> str:
        return check_output_kind(output_kind)

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

    def _check_input_size(self) -> None:
        """Refuse an ``input_size`` the file's fixed input size cannot honour."""
        fixed = self._input.size
        if self.input_size is not None and fixed is not None and self.input_size != fixed:
            h, w = fixed
            raise InputError(
                f"input_size={self.input_size} but {self.path.name} takes a fixed {h}x{w} "
                f"input; omit input_size or pass ({h}, {w})"
            )

    @property
    def sha256(self) -> str:
        """sha256 of the model bytes that were loaded."""
        return self._sha256

    @property
    def resize_policy(self) -> str:
        """``resize`` by its user-facing name (``keep-aspect``, ``cover``, ``exact``)."""
        return next(k for k, v in RESIZE_POLICIES.items() if v == self.resize)

    @property
    def fixed_size(self) -> tuple[int, int] | None:
        """The (height, width) the file fixes, or None when its input size is dynamic."""
        return self._input.size

    @renamed(tile_shape="tangent_shape")
    def network_size(self, tangent_shape: tuple[int, int]) -> tuple[int, int]:
        """Network input (height, width) used for tangents of ``tangent_shape``."""
        if self._input.size is not None:
            return self._input.size
        target = self.input_size or self.default_input_size
        return network_size(tangent_shape, target, multiple_of=self.multiple_of, resize=self.resize)

    @renamed(tiles="tangents")
    def preprocess(self, tangents: np.ndarray) -> np.ndarray:
        """(B, h, w, 3) uint8/float RGB → network input (B, 3, H, W) or (B, H, W, 3) float32."""
        b, h, w = tangents.shape[:3]
        nh, nw = self.network_size((h, w))
        out = np.empty((b, nh, nw, 3), dtype=np.float32)
        for k in range(b):
            out[k] = _unit_rgb_at(tangents[k], (nh, nw))
        return self.network_input(out)

    def network_input(self, images: np.ndarray) -> np.ndarray:
        """(B, H, W, 3) float32 RGB in [0, 1] at the network size → the network's input tensor.

        Normalised as the model needs and in its layout; ``images`` is overwritten.
        """
        # Float input far outside [0, 1] may overflow float32 here: it becomes inf, the network's
        # output there is not finite, and predict() marks it NaN (no estimate).
        with np.errstate(over="ignore", invalid="ignore"):
            images -= self.mean.astype(np.float32)
            images /= self.std.astype(np.float32)
        if self._input.layout == "NCHW":
            images = images.transpose(0, 3, 1, 2)
        return np.ascontiguousarray(images)

    def run_network(self, batch: np.ndarray) -> np.ndarray:
        """Run the session on one input tensor; ONNX Runtime's own exceptions pass through."""
        import onnxruntime as ort

        quiet = ort.RunOptions()
        quiet.log_severity_level = 4  # a failure is raised (and reworded), not logged as well
        feed = {self._input.name: batch}
        return np.asarray(self.session.run([self._output_name], feed, quiet)[0])

    def runs_at(self, size: tuple[int, int]) -> str | None:
        """Run the network once on a grey image of ``size`` (H, W): None if it runs, else why."""
        grey = np.full((1, *size, 3), 0.5, dtype=np.float32)
        try:
            self.run_network(self.network_input(grey))
        except Exception as exc:  # ONNX Runtime raises its own types per failure
            return _short(exc)
        return None

    def size_rule(self, near: tuple[int, int]) -> int | None:
        """Find the multiple the dynamic input height and width must be, probing near ``near``.

        For each candidate m (:data:`SIZE_MULTIPLES`, then :data:`PATCH_MULTIPLES`) the network
        runs once at the odd multiples of m nearest ``near`` (a size that is a multiple of m and
        of no larger candidate); the rule is the smallest m that runs and whose next two
        candidates run too. None: no size tried runs (or the input size is fixed).
        """
        if self._input.size is not None:
            return None
        if near in self._size_rules:
            return self._size_rules[near]
        runs = {m: self.runs_at(probe_size(near, m)) is None for m in SIZE_MULTIPLES}
        ladder = list(SIZE_MULTIPLES)
        rule = next(
            (m for k, m in enumerate(ladder) if all(runs[n] for n in ladder[k : k + 3])), None
        )
        if rule is None and all(self.runs_at(probe_size(near, m)) is None for m in PATCH_MULTIPLES):
            rule = PATCH_MULTIPLES[0]
        self._size_rules[near] = rule
        return rule

    def _run(self, batch: np.ndarray) -> np.ndarray:
        try:
            pred = self.run_network(batch)
        except Exception as exc:  # ONNX Runtime's own exception types: say what to do instead
            raise ModelError(self._run_failure(batch, exc)) from exc
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

    @renamed(tiles="tangents")
    def predict(self, tangents: np.ndarray) -> np.ndarray:
        """Run the network on each tangent.

        Parameters
        ----------
        tangents : (N, h, w, 3) uint8 RGB (or float RGB in [0, 1])

        Returns
        -------
        (N, h, w) float32 in the model's ``output_kind``, NaN where the output is not finite
        (and, for the depth kinds ``metric_depth`` and ``distance``, where it is not > 0). An
        output at another size than the tangent is resized with :func:`resize_valid`, which
        masks those values first: a zero depth never leaks into its neighbours (it would become
        a disparity spike after 1/z).
        """
        array = as_array(tangents, "tangents")
        if array.ndim != 4 or array.shape[3] != 3 or min(array.shape[1:3]) < 1:
            raise InputError(
                f"tangents must have shape (N, h, w, 3) RGB with h, w > 0, got {array.shape}"
            )
        n, h, w = array.shape[:3]
        out = np.empty((n, h, w), dtype=np.float32)
        step = self.batch_size if self._input.batch is None else 1
        positive = self.output_kind in DEPTH_KINDS
        for start in range(0, n, step):
            pred = self._run(self.preprocess(array[start : start + step]))
            for k in range(pred.shape[0]):
                out[start + k] = resize_valid(pred[k], (h, w), positive=positive)
        return out

    def _run_failure(self, batch: np.ndarray, exc: Exception) -> str:
        """Say what to do when the network failed on ``batch`` (probing the sizes it takes)."""
        hw = batch.shape[2:4] if self._input.layout == "NCHW" else batch.shape[1:3]
        h, w = int(hw[0]), int(hw[1])
        head = f"{self.name}: ONNX Runtime failed on a {h}x{w} input ({_short(exc)})"
        check = f"`m360 models check {self.path}` diagnoses the file"
        if self._input.size is not None:
            return f"{head}; {check}"
        rule = self.size_rule((h, w))
        if rule is None:
            return f"{head}; it runs at none of the sizes tried near {h}x{w}; {check}"
        if rule > 1 and (h % rule or w % rule):
            how = (
                f"--prior-multiple-of {rule} (or prior_options={{'multiple_of': {rule}}})"
                if self.role == "prior"
                else f"--multiple-of {rule} (or multiple_of={rule})"
            )
            return f"{head}: this model needs input sizes that are multiples of {rule}: pass {how}"
        return f"{head}; other sizes near it run, so the size is not the cause; {check}"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.name!r}, output_kind={self.output_kind!r}, "
            f"providers={list(self.providers)}, threads={self.threads})"
        )


class PanoramicOnnxEstimator(OnnxEstimator):
    """A panoramic depth network in an ONNX file: the whole ERP in, one ERP map out.

    Takes the parameters of :class:`OnnxEstimator` (the same size rules, normalisation
    detection and checks); ``output_kind`` is one of
    :data:`m360.estimators.kinds.PANORAMIC_OUTPUT_KINDS` (``"metric_depth"`` is refused: an ERP
    map has no optical axis). A dynamic-size file runs at ``input_size`` (default 512 x 1024,
    the size panoramic networks are trained at) fitted to the ERP's 2:1 aspect by ``resize``
    and rounded to ``multiple_of``.

    :meth:`predict` runs the network once on an (H, W, 3) ERP and returns its output at the
    network's own resolution (callers upsample: :func:`m360.estimate` along the photo's edges).
    The input is the ERP as m360 lays it out (docs/conventions.md: column 0 at longitude −π,
    row 0 the zenith); networks trained on ERP images take that layout as it is.
    """

    kind = "panoramic"
    default_input_size = (512, 1024)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Per network size (h, w): whether the output of the input with the seam's context
        # wrapped on maps onto the panorama's columns; a network whose does not is run as it
        # is from then on, once per call instead of twice.
        self._wraps: dict[tuple[int, int], bool] = {}

    @staticmethod
    def _check_output_kind(output_kind: Any) -> str:
        return check_panoramic_output_kind(output_kind)

    def predict(self, erp: np.ndarray) -> np.ndarray:
        """Run the network once on one ERP panorama.

        Parameters
        ----------
        erp : (H, W, 3) uint8 RGB (or float RGB in [0, 1])
            The panorama; resized to :meth:`network_size` of its shape.

        Returns
        -------
        (h, w) float32
            The network's output of ``output_kind`` at its own resolution; NaN where it is not
            finite (and, for ``"distance"`` and ``"disparity"``, where it is not > 0).
        """
        array = as_array(erp, "erp")
        if array.ndim != 3 or array.shape[2] != 3 or min(array.shape[:2]) < 1:
            raise InputError(f"erp must have shape (H, W, 3) RGB with H, W > 0, got {array.shape}")
        out = np.array(self._run_across_the_seam(array), dtype=np.float32)
        with np.errstate(invalid="ignore"):
            invalid = ~np.isfinite(out)
            if self.output_kind in PANORAMIC_METRIC_KINDS:
                invalid |= ~(out > 0)
        out[invalid] = np.nan
        return out

    def _run_across_the_seam(self, erp: np.ndarray) -> np.ndarray:
        """Run the network on ``erp`` across the 0/360° seam: its (h, w) output.

        A network sees the ERP's left and right borders as image borders, and most panoramic
        networks are convolutional without circular padding: on the shared real photos a
        network's output jumped across 0/360° by ten times its ordinary column step, and as a
        prior that seam reached the stitch through the blend's vote. A dynamic-size network is
        therefore run on the ERP at its network size with :data:`SEAM_CONTEXT` of its columns
        wrapped onto each side (whole multiples of ``multiple_of``), and the output is cropped
        back to the panorama's own columns, cross-faded near the seam with the wrapped copies'
        (below). A fixed-size network runs on the ERP as it is (a wider input would squeeze
        the image), as does one whose output columns do not map onto the input's exactly
        (found on its first run at a size, then remembered).
        """
        if self.fixed_size is not None:
            return self._run_as_it_is(erp)
        nh, nw = self.network_size(erp.shape[:2])
        m = max(1, self.multiple_of)
        pad = max(m, round(nw * SEAM_CONTEXT / m) * m)
        if pad >= nw or not self._wraps.get((nh, nw), True):
            return self._run_as_it_is(erp)
        image = _unit_rgb_at(erp, (nh, nw))
        wrapped = np.concatenate([image[:, nw - pad :], image, image[:, :pad]], axis=1)
        pred: np.ndarray = self._run(self.network_input(wrapped[None]))[0]
        ow = pred.shape[-1]
        # The output's columns per input column (1 or a fraction for a strided network): the
        # panorama's own columns are an exact slice, or the context is not worth a resample.
        start, span = pad * ow / (nw + 2 * pad), nw * ow / (nw + 2 * pad)
        maps = start.is_integer() and span.is_integer() and 2 <= start <= span / 2
        self._wraps[(nh, nw)] = maps
        if not maps:
            return self._run_as_it_is(erp)
        lo, width = int(start), int(span)
        # Each column near the seam was seen twice: in the panorama and in a wrapped copy. The
        # copies' outputs differ a little (another position in the input), so they are
        # cross-faded from half and half at the seam, where the two sides then read columns
        # the network saw side by side, to the panorama's own over half the context.
        out = pred[..., lo : lo + width].copy()
        fade = np.minimum(1.0, (np.arange(lo) + 0.5) / (lo / 2)).astype(np.float32)
        own = 0.5 + 0.5 * fade  # the panorama's own output's weight, column c from the seam
        after = pred[..., lo + width : lo + width + lo]  # columns 0.. seen after the last
        before = pred[..., :lo]  # columns ..width - 1 seen before the first
        out[..., :lo] = own * out[..., :lo] + (1 - own) * after
        out[..., width - lo :] = own[::-1] * out[..., width - lo :] + (1 - own[::-1]) * before
        return np.asarray(out)

    def _run_as_it_is(self, erp: np.ndarray) -> np.ndarray:
        """Run the network on ``erp`` at its network size, nothing wrapped: its (h, w) output."""
        out: np.ndarray = self._run(self.preprocess(erp[None]))[0]
        return out


#: Share of a dynamic-size panoramic network's input width wrapped onto each side of the ERP
#: so that the network sees across the 0/360° seam (PanoramicOnnxEstimator.predict): an
#: eighth, for a quarter more compute.
SEAM_CONTEXT = 0.125


def _unit_rgb_at(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Give (h, w, 3) uint8 RGB (or float in [0, 1]) as float32 in [0, 1] at ``size`` (H, W).

    Area resampling when it shrinks both sides, bilinear otherwise.
    """
    h, w = image.shape[:2]
    nh, nw = size
    scale = 1.0 / 255.0 if image.dtype == np.uint8 else 1.0
    rgb: np.ndarray = image.astype(np.float32) * np.float32(scale)
    if (nh, nw) == (h, w):
        return rgb
    flag = cv2.INTER_AREA if nh <= h and nw <= w else cv2.INTER_LINEAR
    return np.asarray(cv2.resize(rgb, (nw, nh), interpolation=flag), dtype=np.float32)


def resize_valid(values: np.ndarray, shape: tuple[int, int], *, positive: bool) -> np.ndarray:
    """Resize one map to ``shape`` (h, w) bilinearly over its valid values only.

    Invalid values (not finite; with ``positive`` also not > 0) are masked before resampling:
    the resized map is ``resize(values·valid) / resize(valid)`` where at least half of the
    interpolation weight is valid, NaN elsewhere, so an invalid value (a zero depth) never mixes
    into its neighbours.

    Parameters
    ----------
    values : (H, W) float array
    shape : (int, int)
        Output (h, w).
    positive : bool
        Treat values ≤ 0 as invalid too (depth-like outputs).

    Returns
    -------
    (h, w) float32, NaN where invalid.
    """
    array = np.asarray(values, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(array) & (array > 0) if positive else np.isfinite(array)
    if array.shape == shape:
        return np.where(valid, array, np.float32(np.nan))
    h, w = shape
    weight = cv2.resize(valid.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    total = cv2.resize(
        np.where(valid, array, np.float32(0)), (w, h), interpolation=cv2.INTER_LINEAR
    )
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out = total / weight
    out[~(weight >= 0.5) | ~np.isfinite(out)] = np.nan
    return out.astype(np.float32, copy=False)


def is_file(path: Path) -> bool:
    """``path.is_file()``, False for names the OS refuses (too long, NUL bytes)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def probe_size(near: tuple[int, int], multiple: int) -> tuple[int, int]:
    """Give the size nearest ``near`` whose sides are odd multiples of ``multiple``.

    An odd multiple of m is a multiple of no larger power of two times m, so a network that
    needs 2m fails there.
    """

    def side(n: int) -> int:
        k = max(1, round(n / multiple))
        if k % 2 == 0:  # k - 1 >= 1: the nearer odd neighbour, the larger on a tie
            k = k - 1 if n - (k - 1) * multiple < (k + 1) * multiple - n else k + 1
        return k * multiple

    return side(near[0]), side(near[1])


def _short(exc: BaseException) -> str:
    """ONNX Runtime's message on one line without its source location, at most 200 chars."""
    text = " ".join(str(exc).split())
    node = re.search(r"while running (\w+) node", text)
    text = text.split("Status Message: ", 1)[-1]
    text = re.sub(r"^\[ONNXRuntimeError\] : \d+ : \w+ : ", "", text)
    # "/onnxruntime_src/.../element_wise_ops.h:583 void onnxruntime::...(...) " → the rest
    text = re.sub(r"^\S+\.(?:h|cc|cpp):\d+ (?:\w+ )?(?:[\w:]+\([^)]*\) )?", "", text)
    where = f"{node.group(1)} node: " if node else ""
    return (where + text)[:200] or type(exc).__name__


def check_triple(value: Sequence[float], name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be 3 numbers (R, G, B), got {value!r}") from exc
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise InputError(f"{name} must be 3 finite numbers (R, G, B), got {value!r}")
    return array
