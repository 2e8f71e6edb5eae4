"""What an ONNX file is and what its network wants as input: sniffing, hashing, normalisation.

The registry (:mod:`m360.estimators.registry`) and the ONNX estimator
(:mod:`m360.estimators.onnx`) both read files through these: whether a file is an ONNX graph at
all, its sha256, and whether the graph normalises its input itself (:func:`input_normalization`).
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, ModelError
from . import _onnxgraph

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "NORMALIZE_PRESETS",
    "NO_NORMALISATION",
    "Normalization",
    "input_normalization",
    "sha256_of",
    "sniff_onnx",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NO_NORMALISATION = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
#: The named input normalisations (``normalize=``, ``--normalize``) as (mean, std) of RGB in
#: [0, 1]: ``imagenet`` the ImageNet statistics, ``unit`` RGB in [0, 1] as is, ``none`` the raw
#: 0-255 pixel values (no scaling at all: ``(rgb / 255 - 0) / (1 / 255)``).
NORMALIZE_PRESETS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "imagenet": (IMAGENET_MEAN, IMAGENET_STD),
    "unit": NO_NORMALISATION,
    "none": ((0.0, 0.0, 0.0), (1.0 / 255.0, 1.0 / 255.0, 1.0 / 255.0)),
}

#: Bytes an ONNX file (a protobuf ModelProto) may start with: field 1 (ir_version, varint) or,
#: for some exporters, field 8 (opset_import) / 2 (producer_name) / 7 (graph).
_ONNX_FIRST_BYTES = {0x08, 0x12, 0x1A, 0x22, 0x3A, 0x42}


def sha256_of(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks (ModelError if it cannot be read)."""
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(chunk), b""):
                digest.update(block)
    except (OSError, ValueError) as exc:  # missing, a folder, unreadable, a NUL in the name
        raise ModelError(f"cannot read {os.fspath(path)!r}: {exc}") from exc
    return digest.hexdigest()


def sniff_onnx(path: str | os.PathLike[str]) -> str | None:
    """Why the file at ``path`` is clearly not an ONNX model, or None if it may be one.

    Catches the usual accidents cheaply: an empty file, an HTML/JSON/text error page saved
    under the model's name, a Git LFS pointer instead of the file.
    """
    with open(path, "rb") as f:
        head = f.read(256)
    if not head:
        return "it is empty"
    text = head.lstrip().lower()
    if text.startswith((b"<!doctype html", b"<html", b"<?xml", b"<")):
        return "it is an HTML/XML page (an error or login page saved under the model's name?)"
    if text.startswith(b"version https://git-lfs"):
        return "it is a Git LFS pointer file, not the model itself"
    if text.startswith((b"{", b"[")):
        return "it is a JSON document (an error response saved under the model's name?)"
    if head[0] not in _ONNX_FIRST_BYTES:
        return f"it does not start like an ONNX protobuf (first bytes {head[:8].hex()})"
    return None


#: Input ranges a graph's own normalisation may expect: RGB in [0, 1] or in [0, 255].
_INPUT_RANGES = (1.0, 255.0)
#: Relative tolerance when matching a graph's constants to a known normalisation (exporters
#: round, or fold ``/ std`` into ``* (1 / std)``).
_MATCH_RTOL = 0.02


@dataclass(frozen=True)
class Normalization:
    """How a model's input is normalised, and by whom.

    Attributes
    ----------
    source : str
        ``"graph"`` (the ONNX graph normalises its input itself: m360 only scales RGB to
        ``input_range``) or ``"m360"`` (m360 feeds ``(rgb - mean) / std``).
    mean, std : (float, float, float)
        The normalisation of RGB in [0, 1]: the one found in the graph (``source="graph"``) or
        the one m360 applies.
    input_range : float
        The graph is fed RGB in [0, input_range]: 1, or 255 when its own constants are in
        0-255 units (``source="graph"`` only; 1 otherwise).
    explicit : bool
        ``mean``/``std`` were given by the user: they win over what the graph holds.
    found : dict or None
        The per-channel affine map found at the graph's input, as mean/std in the input's own
        units with the operations followed, whether it matched a known normalisation; None
        when the graph starts with no such map (or could not be read: see ``detail``).
    detail : str
        One line for reports.
    """

    source: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    input_range: float
    explicit: bool
    found: dict[str, Any] | None
    detail: str

    def feed(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Return the ``(mean, std)`` m360 applies to RGB in [0, 1] before the network."""
        if self.source == "graph":
            return (0.0, 0.0, 0.0), (1.0 / self.input_range,) * 3
        return self.mean, self.std

    def as_dict(self) -> dict[str, Any]:
        """JSON-able record (sidecars, ``m360 models check``)."""
        return {
            "source": self.source,
            "mean": list(self.mean),
            "std": list(self.std),
            "input_range": self.input_range,
            "explicit": self.explicit,
            "found_in_graph": self.found,
            "detail": self.detail,
        }


def _triple(values: Any) -> tuple[float, float, float]:
    a, b, c = (float(v) for v in values)
    return (a, b, c)


def _match(
    mean: np.ndarray, std: np.ndarray, candidates: list[tuple[tuple[float, ...], tuple[float, ...]]]
) -> tuple[tuple[float, ...], tuple[float, ...], float] | None:
    for cand_mean, cand_std in candidates:
        for k in _INPUT_RANGES:
            m, s = np.asarray(cand_mean) * k, np.asarray(cand_std) * k
            if np.allclose(mean, m, rtol=_MATCH_RTOL, atol=1e-3 * k) and np.allclose(
                std, s, rtol=_MATCH_RTOL, atol=0.0
            ):
                return cand_mean, cand_std, k
    return None


def _rounded(values: np.ndarray) -> tuple[float, float, float]:
    # float32 constants: more digits than 7 are noise
    return _triple(round(float(v), 7) for v in values)


@functools.lru_cache(maxsize=16)
def _graph_summary(path: str, size: int, mtime_ns: int) -> _onnxgraph.Summary | str:
    try:
        return _onnxgraph.inspect_file(path)
    except ModelError as exc:
        return str(exc)


def input_normalization(
    path: str | os.PathLike[str],
    mean: tuple[float, float, float] | None = None,
    std: tuple[float, float, float] | None = None,
    *,
    expected: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        IMAGENET_MEAN,
        IMAGENET_STD,
    ),
    data: bytes | None = None,
) -> Normalization:
    """Find whether the ONNX graph at ``path`` normalises its input, and decide who does.

    The graph's first operations on its input are read (after any Transpose/Cast/Resize): if
    they are a per-channel affine map (Sub/Div/Mul/Add by constants, in any order) equal, within
    2 %, to ``(x - mean·k) / (std·k)`` for the ImageNet constants or ``expected``, with
    k = 1 or 255, the graph normalises itself and m360 only scales RGB to [0, k]. Otherwise m360
    applies ``expected``. An explicit ``mean``/``std`` wins over both (the other one then
    defaults to ``expected``'s). Read once per (file, size, mtime) and process.

    Parameters
    ----------
    path : str or PathLike
        The .onnx file.
    mean, std : 3 floats, optional
        The user's explicit normalisation.
    expected : (mean, std)
        The normalisation the network was trained with (a registry entry's; default ImageNet).
    data : bytes, optional
        The file's bytes when already in memory (e.g. the verified bytes a session is loaded
        from): read instead of the file, so both come from the same bytes.

    Returns
    -------
    Normalization
    """
    summary: _onnxgraph.Summary | str
    if data is not None:
        try:
            summary = _onnxgraph.inspect(data)
        except ModelError as exc:
            summary = str(exc)
    else:
        p = Path(path)
        try:
            stat = p.stat()
        except (OSError, ValueError) as exc:
            raise ModelError(f"cannot read {os.fspath(path)!r}: {exc}") from exc
        summary = _graph_summary(str(p.resolve()), stat.st_size, stat.st_mtime_ns)
    found: dict[str, Any] | None = None
    matched = None
    g_mean = g_std = np.zeros(3)
    if isinstance(summary, str):
        note = f"graph not readable by m360 ({summary}): assumed not to normalise"
    elif summary.affine is None:
        note = "the graph's input goes straight into the network (no normalisation found)"
    else:
        scale, offset = np.asarray(summary.affine.scale), np.asarray(summary.affine.offset)
        if np.any(scale == 0):
            note = "the graph zeroes its input (scale 0)"
        else:
            g_mean, g_std = -offset / scale, 1.0 / scale
            candidates = [(IMAGENET_MEAN, IMAGENET_STD), (expected[0], expected[1])]
            matched = _match(g_mean, g_std, candidates)  # type: ignore[arg-type]
            found = {
                "ops": list(summary.affine.ops),
                "mean": [round(float(v), 6) for v in g_mean],
                "std": [round(float(v), 6) for v in g_std],
                "matched": matched is not None,
            }
            note = (
                f"the graph normalises its input ({' -> '.join(summary.affine.ops)})"
                if matched
                else f"the graph starts with a per-channel map ({' -> '.join(summary.affine.ops)})"
                " that is no known normalisation: m360 normalises"
            )
    if mean is not None or std is not None:
        chosen = (
            _triple(expected[0] if mean is None else mean),
            _triple(expected[1] if std is None else std),
        )
        return Normalization("m360", *chosen, 1.0, True, found, f"given explicitly (wins); {note}")
    if matched is not None and found is not None:
        k = matched[2]
        return Normalization(
            "graph", _rounded(g_mean / k), _rounded(g_std / k), k, False, found, note
        )
    return Normalization(
        "m360", _triple(expected[0]), _triple(expected[1]), 1.0, False, found, note
    )
