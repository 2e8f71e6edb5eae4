"""Result files one at a time, never half-written: atomic writes, the array formats, previews.

Every output file is written to a temporary name in its target folder and renamed onto its final
name (atomic on one file system); temporaries a killed writer left are removed by
:func:`remove_stale_temporaries`.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import io as _bytes_io
import json
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError, ReadError
from .decode import read_bytes, read_exr

#: Array formats :func:`save` writes (and :func:`load` reads back, in this order of preference).
SAVE_FORMATS = ("npy", "pfm", "exr", "png16")
#: 3D formats :func:`save` writes (optional extra ``m360[3d]``): ``ply`` the coloured point cloud
#: ``STEM.points.ply`` (m360 frame), ``glb`` the mesh ``STEM.mesh.glb`` (glTF frame, y up),
#: ``splat`` the 3D Gaussian splats ``STEM.splat.ply`` (m360 frame, :mod:`m360.io.splat`).
GEOMETRY_FORMATS = ("ply", "glb", "splat")
GEOMETRY_FILES = {
    "ply": ("points", ".points.ply"),
    "glb": ("mesh", ".mesh.glb"),
    "splat": ("splat", ".splat.ply"),
}
#: Surface normals (:func:`m360.normals`): ``normals`` writes ``STEM.normals.exr`` (float32,
#: channels R, G, B = x, y, z, NaN = none) and ``STEM.normals.png`` (8-bit, (n + 1) / 2).
NORMALS_FORMATS = ("normals",)
NORMALS_FILES = {"exr": ".normals.exr", "png": ".normals.png"}
#: Stereo formats :func:`save` writes (needs ``rgb``): the ODS pair of :func:`m360.stereo`,
#: top-bottom (left eye on top) with GPano stereo XMP, as ``STEM.stereo.jpg`` (``stereo``) or
#: ``STEM.stereo.png`` (``stereo-png``, lossless).
STEREO_FORMATS = ("stereo", "stereo-png")
STEREO_FILES = {"stereo": ("stereo", ".stereo.jpg"), "stereo-png": ("stereo", ".stereo.png")}
#: Every format name :func:`save` takes.
KNOWN_FORMATS = SAVE_FORMATS + GEOMETRY_FORMATS + NORMALS_FORMATS + STEREO_FORMATS
#: The quantities :func:`save` writes per format.
QUANTITIES = ("disparity", "depth")
#: File suffix of each array format: ``STEM.disparity.npy``, ``STEM.depth.png`` (16-bit) …
FORMAT_SUFFIXES = {"npy": ".npy", "pfm": ".pfm", "exr": ".exr", "png16": ".png"}
#: The longest file name (bytes) of most file systems (NAME_MAX): longer temporary names are hashed.
NAME_MAX = 255
#: PNG16 codes: 0 = invalid, 1..65535 = the finite range, linearly.
_PNG16_STEPS = 65534

#: The ERP convention written into every sidecar (docs/conventions.md).
ERP_CONVENTION = {
    "shape": "H x W with W == 2H",
    "longitude": "2*pi*(j + 0.5)/W - pi (column j; -pi at the left edge, increasing rightwards)",
    "latitude": "pi/2 - pi*(i + 0.5)/H (row i; +pi/2 at the top edge)",
    "direction": "(cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon)); x right, y down, z forward",
    "disparity": "spherical, 1/distance",
    "depth": "radial distance |P|",
    "invalid": "NaN in npy/pfm/exr; 0 in png16",
}


# --------------------------------------------------------------------------------------------
# Atomic writes.


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary file lives in the target folder so the final rename is atomic (same file
    system); on any exception (KeyboardInterrupt included) it is removed and ``path`` is left as
    it was. Temporary names are ``.NAME.XXXXXXXX.tmp`` (see :func:`temporary_prefix`).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    prefix = temporary_prefix(target.name)
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates 0600; give the result the permissions a plain open() would.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def temporary_prefix(name: str) -> str:
    """Give the prefix of the temporary files of ``name``: ``.NAME.``, or ``.HASH.`` when long.

    A temporary name is the prefix, 8 random characters and ``.tmp``. When ``.NAME.XXXXXXXX.tmp``
    would exceed :data:`NAME_MAX` bytes (a name of 242 bytes or more), HASH is the first
    16 hex digits of the name's sha1, so the temporary of any legal name is a legal name.
    """
    if len(os.fsencode(name)) + 14 <= NAME_MAX:  # 14: two dots, 8 random characters, ".tmp"
        return f".{name}."
    return f".{hashlib.sha1(os.fsencode(name)).hexdigest()[:16]}."


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    target = Path(path)
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return target


def save_npy(path: str | os.PathLike[str], array: np.ndarray) -> Path:
    """Write ``array`` as .npy atomically; returns the path (straight into the file: no copy)."""
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)
    return target


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write a uint8/uint16 image (H,W) or (H,W,3) BGR as PNG atomically; returns the path."""
    encoded = _encoded(".png", image)
    target = Path(path)
    with atomic_path(target) as tmp:
        encoded.tofile(tmp)  # the encoder's buffer itself, not a bytes copy of it
    return target


def save_json(path: str | os.PathLike[str], data: Mapping[str, Any]) -> Path:
    """Write ``data`` as indented UTF-8 JSON atomically; returns the path."""
    text = json.dumps(data, indent=2, sort_keys=False, default=_json_default, allow_nan=False)
    return _write_bytes(path, (text + "\n").encode("utf-8"))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _encode(extension: str, image: np.ndarray) -> bytes:
    return bytes(_encoded(extension, image))


def _encoded(extension: str, image: np.ndarray) -> np.ndarray:
    problem = (
        f"cannot encode an array of shape {image.shape} and dtype {image.dtype} as "
        f"{extension[1:].upper()}"
    )
    try:
        ok, encoded = cv2.imencode(extension, image)
    except cv2.error as exc:
        raise InputError(f"{problem}: {exc}") from exc
    if not ok:
        raise InputError(problem)
    return encoded


# --------------------------------------------------------------------------------------------
# Float maps in each format. Writers return the path; readers return (H, W) float32.


def write_array(path: str | os.PathLike[str], values: np.ndarray, fmt: str) -> dict[str, Any]:
    """Write one (H, W) float map in ``fmt`` (npy, pfm, exr, png16) atomically.

    npy, pfm and exr store float32 bit-exactly (NaN = invalid). png16 stores
    ``code = 1 + round((v - offset) / scale)`` with ``offset`` the minimum and
    ``scale = (max - min) / 65534`` of the finite values, 0 = invalid: reading it back is within
    ``scale / 2`` (plus float32 rounding). Returns what a reader needs besides the file
    (png16: ``offset``, ``scale``; others: nothing).
    """
    values = np.ascontiguousarray(values, dtype=np.float32)
    if fmt == "npy":
        save_npy(path, values)
    elif fmt == "pfm":
        _write_bytes(path, _encode(".pfm", values))
    elif fmt == "exr":
        _write_exr(path, values)
    elif fmt == "png16":
        codes, offset, scale = _png16_codes(values)
        save_png(path, codes)
        return {"offset": offset, "scale": scale, "invalid": 0}
    else:
        raise InputError(f"format {fmt!r} is not supported; choose from {SAVE_FORMATS}")
    return {}


def read_array(
    path: str | os.PathLike[str], *, png16: Mapping[str, float] | None = None
) -> np.ndarray:
    """Read an (H, W) float map written by :func:`write_array` (format from the suffix).

    A 16-bit PNG needs ``png16`` (``offset``, ``scale`` from the sidecar); without them the
    values are ``code − 1`` (0 → NaN). Raises :class:`m360.ReadError` for a missing,
    empty or corrupt file.
    """
    p = Path(path)
    data = read_bytes(p, "array file")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npy":
            values = np.load(_bytes_io.BytesIO(data), allow_pickle=False)
        elif suffix == ".exr":
            values = read_exr(p)
        elif suffix in (".pfm", ".png", ".tif", ".tiff"):
            values = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        else:
            raise ReadError(f"{p}: unknown array format {suffix!r} (npy, pfm, exr, png)")
    except ReadError:
        raise
    except Exception as exc:  # numpy/OpenCV/OpenEXR raise many kinds for corrupt files
        raise ReadError(f"cannot read {p}: {exc}") from exc
    if values is None or not isinstance(values, np.ndarray):
        raise ReadError(f"cannot decode {p} (corrupt or truncated?)")
    if values.ndim == 3 and values.shape[2] == 1:
        values = values[:, :, 0]
    if values.ndim != 2:
        raise ReadError(f"{p} holds an array of shape {values.shape}; expected one (H, W) map")
    if values.dtype == np.uint16 and suffix == ".png":
        return _png16_values(values, png16)
    if values.dtype.kind != "f":
        raise ReadError(
            f"{p} holds {values.dtype} values; expected a float map (.npy, .pfm, .exr, .tif) or "
            "a 16-bit PNG (an 8-bit image is too coarse for depth, and often a colour preview)"
        )
    return values.astype(np.float32, copy=False)  # type: ignore[no-any-return]  # numpy stubs: Any


def _png16_codes(values: np.ndarray) -> tuple[np.ndarray, float, float]:
    # In bands of rows: the float64 temporaries of the whole map were 24 bytes a pixel.
    codes = np.zeros(values.shape, np.uint16)
    low, top = np.inf, -np.inf
    for band in _bands(values):
        valid = band[np.isfinite(band)]
        if valid.size:
            low, top = min(low, float(valid.min())), max(top, float(valid.max()))
    if low > top:  # no finite value
        return codes, 0.0, 1.0
    offset = low
    scale = (top - offset) / _PNG16_STEPS if top > offset else 1.0
    for start, band in zip(range(0, values.shape[0], _BAND_ROWS), _bands(values), strict=True):
        finite = np.isfinite(band)
        valid = band[finite].astype(np.float64)
        codes[start : start + band.shape[0]][finite] = (
            np.rint((valid - offset) / scale).astype(np.uint16) + 1
        )
    return codes, offset, scale


#: Rows per band of the banded writers (a few MB of temporaries at 12K).
_BAND_ROWS = 256


def _bands(values: np.ndarray) -> Iterator[np.ndarray]:
    for start in range(0, values.shape[0], _BAND_ROWS):
        yield values[start : start + _BAND_ROWS]


def _png16_values(codes: np.ndarray, png16: Mapping[str, float] | None) -> np.ndarray:
    offset, scale = (0.0, 1.0) if png16 is None else (png16["offset"], png16["scale"])
    values = offset + (codes.astype(np.float64) - 1.0) * scale
    return np.where(codes == 0, np.nan, values).astype(np.float32)


def _write_exr(path: str | os.PathLike[str], values: np.ndarray) -> Path:
    return write_exr_channels(path, {"Y": values})


def write_exr_channels(path: str | os.PathLike[str], channels: Mapping[str, np.ndarray]) -> Path:
    """Write (H, W) float32 channels (name → map) as one ZIP-compressed EXR, atomically."""
    # OpenCV 5 wheels have no EXR codec; the OpenEXR package (ASWF) is the maintained one.
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(v, np.float32) for name, v in channels.items()}
    target = Path(path)
    with atomic_path(target) as tmp:
        OpenEXR.File(header, data).write(str(tmp))
    return target


# --------------------------------------------------------------------------------------------
# Results.


def colorize(disparity: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """Colour a disparity map as a (H, W, 3) uint8 BGR preview: near warm, far cool, NaN black.

    Values are scaled between the given percentiles of the finite values (robust to outliers).
    Coloured in bands of rows: the float temporaries stay a band's.
    """
    values = np.asarray(disparity, dtype=np.float32)
    finite_values = values[np.isfinite(values)]
    if not finite_values.size:
        return np.zeros((*values.shape, 3), np.uint8)
    lo, hi = np.percentile(finite_values, percentiles, overwrite_input=True)
    del finite_values
    preview = np.empty((*values.shape, 3), np.uint8)
    for start, band in zip(range(0, values.shape[0], _BAND_ROWS), _bands(values), strict=True):
        finite = np.isfinite(band)
        scaled = np.clip((band - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0)
        grey = np.where(finite, scaled * 255.0 + 0.5, 0.0).astype(np.uint8)
        out = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
        out[~finite] = 0
        preview[start : start + band.shape[0]] = out
    return preview


def output_stem(path: str | os.PathLike[str]) -> Path:
    """Find the stem of an output set given the stem itself or any of its files."""
    p = Path(path)
    name = p.name
    if name.endswith(".json") or name.endswith(".preview.png"):
        return p.with_name(name.removesuffix(".json").removesuffix(".preview.png"))
    for tail in [
        *(tail for _, tail in GEOMETRY_FILES.values()),
        *NORMALS_FILES.values(),
        *(tail for _, tail in STEREO_FILES.values()),
    ]:
        if name.endswith(tail):
            return p.with_name(name.removesuffix(tail))
    for quantity in QUANTITIES:
        for suffix in set(FORMAT_SUFFIXES.values()):
            tail = f".{quantity}{suffix}"
            if name.endswith(tail):
                return p.with_name(name.removesuffix(tail))
    return p


def check_formats(formats: Sequence[str] | str) -> tuple[str, ...]:
    """Check the formats ``formats`` names (one name or a list; array or 3D); drop repeats."""
    if isinstance(formats, str):
        chosen: tuple[Any, ...] = (formats,)
    elif isinstance(formats, (list, tuple)):
        chosen = tuple(formats)
    else:
        raise InputError(f"formats must be a format name or a list of them, got {formats!r}")
    known = KNOWN_FORMATS
    for fmt in chosen:
        if not isinstance(fmt, str) or fmt not in known:
            raise InputError(f"format {fmt!r} is not supported; choose from {known}")
    if not chosen:
        raise InputError(f"formats is empty; choose at least one of {known}")
    return tuple(dict.fromkeys(chosen))


def _check_map(values: Any, name: str) -> np.ndarray:
    array = values if isinstance(values, np.ndarray) else None
    if array is None or array.ndim != 2 or array.dtype.kind != "f" or array.size == 0:
        got = type(values).__name__ if array is None else f"{array.dtype} {array.shape}"
        raise InputError(f"result.{name} must be a non-empty (H, W) float array, got {got}")
    return array


def remove_stale_temporaries(stem: str | os.PathLike[str]) -> list[Path]:
    """Delete temporary files a killed writer left for the set ``stem``; returns them.

    Only the temporaries of this set's own file names (``.NAME.<8 random>.tmp`` for each name
    :func:`save` writes, hashed when long: :func:`temporary_prefix`), so another set with a
    longer stem is never touched. Call this only while holding the set's claim (see
    :mod:`m360.batch`): a live writer's temporary file looks the same.
    """
    base = Path(stem)
    if not base.parent.is_dir():
        return []
    quantities = (*QUANTITIES, "confidence")
    names = [f"{base.name}.{q}{suffix}" for q in quantities for suffix in FORMAT_SUFFIXES.values()]
    names += [f"{base.name}.preview.png", f"{base.name}.json"]
    names += [base.name + tail for _, tail in GEOMETRY_FILES.values()]
    names += [base.name + tail for tail in NORMALS_FILES.values()]
    names += [base.name + tail for _, tail in STEREO_FILES.values()]
    removed = []
    for name in names:
        for tmp in base.parent.glob(f"{glob.escape(temporary_prefix(name))}{'?' * 8}.tmp"):
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    return removed
