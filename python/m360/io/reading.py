"""Reading a saved result back: its sidecar, its files, :func:`load`."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, ReadError
from .files import (
    FORMAT_SUFFIXES,
    QUANTITIES,
    SAVE_FORMATS,
    output_stem,
    read_array,
)


@dataclass(frozen=True)
class SavedResult:
    """A result read back by :func:`load`.

    Attributes
    ----------
    disparity, depth : (H, W) float32
        NaN = invalid.
    metadata : dict
        The sidecar (model, options, timings, input …).
    stem : Path
    format : str
        The format the arrays were read from.
    """

    disparity: np.ndarray
    depth: np.ndarray
    metadata: dict[str, Any]
    stem: Path
    format: str

    @property
    def units(self) -> str:
        """``"relative"`` or ``"metres"`` (of depth)."""
        return str(self.metadata["quantities"]["depth"]["units"])


def read_sidecar(stem: str | os.PathLike[str]) -> dict[str, Any]:
    """Read the sidecar of an output set (:class:`m360.ReadError` if missing or corrupt)."""
    base = output_stem(stem)
    path = base.with_name(base.name + ".json")
    if not path.is_file():
        raise ReadError(
            f"{path} does not exist: {base} is not a complete m360 output (the sidecar is "
            "written last)"
        )
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReadError(f"cannot read the sidecar {path}: {exc}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("files"), dict):
        raise ReadError(f"{path} is not an m360 sidecar (no 'files')")
    return meta


def load(stem: str | os.PathLike[str], *, format: str | None = None) -> SavedResult:
    """Read back what :func:`save` wrote: the arrays and the sidecar metadata.

    ``stem`` is the stem given to :func:`save` (or any of its files). ``format`` picks the
    files to read; default: the first written of npy, pfm, exr, png16. Raises
    :class:`m360.ReadError` if the sidecar or a file is missing or corrupt.
    """
    base = output_stem(stem)
    meta = read_sidecar(base)
    files = listed_files(meta, base)
    available = [f for f in SAVE_FORMATS if all(f in files[q] for q in QUANTITIES)]
    if format is None:
        if not available:
            raise ReadError(f"{base}.json lists no array files")
        format = available[0]
    elif format not in available:
        raise InputError(f"{base} has no {format!r} files; it has {available}")
    arrays: dict[str, np.ndarray] = {}
    for quantity in QUANTITIES:
        params = _png16_params(meta, quantity, base) if format == "png16" else None
        values = read_array(base.with_name(files[quantity][format]), png16=params)
        if list(values.shape) != meta.get("shape"):
            raise ReadError(
                f"{files[quantity][format]} has shape {values.shape} but the sidecar {base}.json "
                f"says {meta.get('shape')}"
            )
        arrays[quantity] = values
    return SavedResult(arrays["disparity"], arrays["depth"], meta, base, format)


def read_map(path: str | os.PathLike[str]) -> np.ndarray:
    """Read one (H, W) float32 map from a file: an m360 output's, or any array file.

    A file of an output set (``STEM.depth.png``, ``STEM.disparity.exr`` … with its sidecar
    ``STEM.json`` beside it) is read as :func:`load` reads it, so a 16-bit PNG's codes are
    mapped back to values by the sidecar (only that file is read); any other file by
    :func:`m360.io.read_array` (a 16-bit PNG without an m360 sidecar: its codes minus one, 0 =
    unknown). Raises :class:`m360.ReadError` for a missing, empty or corrupt file.
    """
    p = Path(path)
    stem = output_stem(p)
    if stem != p and stem.with_name(stem.name + ".json").is_file() and p.suffix == ".png":
        for quantity in QUANTITIES:
            if p.name == f"{stem.name}.{quantity}{FORMAT_SUFFIXES['png16']}":
                return read_array(p, png16=_png16_params(read_sidecar(stem), quantity, stem))
    return read_array(p)


def listed_files(meta: Mapping[str, Any], stem: Path) -> dict[str, dict[str, str]]:
    """Quantity → format → file name from a sidecar, checked: plain names in the stem's folder.

    Raises :class:`m360.ReadError` for a malformed ``files`` entry.
    """
    files = meta.get("files")
    listed: dict[str, dict[str, str]] = {}
    for quantity in QUANTITIES:
        entry = files.get(quantity, {}) if isinstance(files, dict) else None
        if not isinstance(entry, dict):
            raise ReadError(f"{stem}.json: malformed 'files' entry for {quantity}: {entry!r}")
        names: dict[str, str] = {}
        for fmt, name in entry.items():
            if fmt not in SAVE_FORMATS:
                continue
            if not isinstance(name, str) or not name or Path(name).name != name:
                raise ReadError(f"{stem}.json: {quantity}.{fmt} names {name!r}, not a file name")
            names[fmt] = name
        listed[quantity] = names
    return listed


def _png16_params(meta: Mapping[str, Any], quantity: str, stem: Path) -> dict[str, float]:
    params = meta.get("png16")
    entry = params.get(quantity) if isinstance(params, dict) else None
    try:
        offset, scale = float(entry["offset"]), float(entry["scale"])  # type: ignore[index]
    except (TypeError, KeyError, ValueError) as exc:
        raise ReadError(f"{stem}.json: no usable png16 offset/scale for {quantity}") from exc
    if not (np.isfinite(offset) and np.isfinite(scale) and scale > 0):
        raise ReadError(f"{stem}.json: png16 offset/scale for {quantity} are {offset}, {scale}")
    return {"offset": offset, "scale": scale}
