"""Writing results and reading them back, never leaving a half-written file.

Input panoramas are read by :mod:`m360.decode` (``m360.io.load_image`` and its kin are
re-exported here).

Every output file is written to a temporary name in its target folder and renamed onto its final
name (atomic on one file system). :func:`save` writes the sidecar ``STEM.json`` last, so a sidecar
means the whole set is there; :func:`load` refuses a stem without one.
"""

from __future__ import annotations

import contextlib
import datetime
import glob
import io as _bytes_io
import json
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ._validate import flag
from .decode import (
    IMAGE_SUFFIXES,
    decode_image,
    fix_aspect_ratio,
    load_image,
    read_bytes,
    read_exr,
    read_image,
    read_input_bytes,
)
from .errors import InputError, ReadError

__all__ = [
    "ERP_CONVENTION",
    "GEOMETRY_FORMATS",
    "IMAGE_SUFFIXES",
    "SAVE_FORMATS",
    "SavedResult",
    "atomic_path",
    "check_formats",
    "colorize",
    "decode_image",
    "fix_aspect_ratio",
    "listed_files",
    "load",
    "load_image",
    "output_stem",
    "read_array",
    "read_image",
    "read_input_bytes",
    "read_sidecar",
    "remove_stale_temporaries",
    "save",
    "save_json",
    "save_npy",
    "save_png",
    "write_array",
]

#: Array formats :func:`save` writes (and :func:`load` reads back, in this order of preference).
SAVE_FORMATS = ("npy", "pfm", "exr", "png16")
#: 3D formats :func:`save` writes (optional extra ``m360[3d]``): ``ply`` the coloured point cloud
#: ``STEM.points.ply`` (m360 frame), ``glb`` the mesh ``STEM.mesh.glb`` (glTF frame, y up).
GEOMETRY_FORMATS = ("ply", "glb")
GEOMETRY_FILES = {"ply": ("points", ".points.ply"), "glb": ("mesh", ".mesh.glb")}
#: The quantities :func:`save` writes per format.
QUANTITIES = ("disparity", "depth")
#: File suffix of each array format: ``STEM.disparity.npy``, ``STEM.depth.png`` (16-bit) …
FORMAT_SUFFIXES = {"npy": ".npy", "pfm": ".pfm", "exr": ".exr", "png16": ".png"}
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
    it was. Temporary names are ``.NAME.XXXXXXXX.tmp``.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
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
    """Write ``array`` as .npy atomically; returns the path."""
    buffer = _bytes_io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return _write_bytes(path, buffer.getvalue())


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write a uint8/uint16 image (H,W) or (H,W,3) BGR as PNG atomically; returns the path."""
    return _write_bytes(path, _encode(".png", image))


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
    return bytes(encoded)


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
        raise ReadError(f"{p} holds {values.dtype} values; expected a float map")
    return values.astype(np.float32, copy=False)  # type: ignore[no-any-return]  # numpy stubs: Any


def _png16_codes(values: np.ndarray) -> tuple[np.ndarray, float, float]:
    finite = np.isfinite(values)
    codes = np.zeros(values.shape, np.uint16)
    if not finite.any():
        return codes, 0.0, 1.0
    valid = values[finite].astype(np.float64)
    offset, top = float(valid.min()), float(valid.max())
    scale = (top - offset) / _PNG16_STEPS if top > offset else 1.0
    codes[finite] = np.rint((valid - offset) / scale).astype(np.uint16) + 1
    return codes, offset, scale


def _png16_values(codes: np.ndarray, png16: Mapping[str, float] | None) -> np.ndarray:
    offset, scale = (0.0, 1.0) if png16 is None else (png16["offset"], png16["scale"])
    values = offset + (codes.astype(np.float64) - 1.0) * scale
    return np.where(codes == 0, np.nan, values).astype(np.float32)


def _write_exr(path: str | os.PathLike[str], values: np.ndarray) -> Path:
    # OpenCV 5 wheels have no EXR codec; the OpenEXR package (ASWF) is the maintained one.
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    target = Path(path)
    with atomic_path(target) as tmp:
        OpenEXR.File(header, {"Y": values}).write(str(tmp))
    return target


# --------------------------------------------------------------------------------------------
# Results.


def colorize(disparity: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """Colour a disparity map as a (H, W, 3) uint8 BGR preview: near warm, far cool, NaN black.

    Values are scaled between the given percentiles of the finite values (robust to outliers).
    """
    values = np.asarray(disparity, dtype=np.float32)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros((*values.shape, 3), np.uint8)
    lo, hi = np.percentile(values[finite], percentiles)
    scaled = np.clip((values - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0)
    grey = np.where(finite, scaled * 255.0 + 0.5, 0.0).astype(np.uint8)
    preview = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
    preview[~finite] = 0
    return preview


def output_stem(path: str | os.PathLike[str]) -> Path:
    """Find the stem of an output set given the stem itself or any of its files."""
    p = Path(path)
    name = p.name
    if name.endswith(".json") or name.endswith(".preview.png"):
        return p.with_name(name.removesuffix(".json").removesuffix(".preview.png"))
    for _, tail in GEOMETRY_FILES.values():
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
    known = SAVE_FORMATS + GEOMETRY_FORMATS
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


def save(
    result: Any,
    stem: str | os.PathLike[str],
    *,
    formats: Sequence[str] | str = ("npy",),
    preview: bool = True,
    extra: Mapping[str, Any] | None = None,
    rgb: np.ndarray | None = None,
    confidence: bool = False,
) -> dict[str, Path]:
    """Write an :class:`m360.EstimateResult` next to ``stem``, atomically, the sidecar last.

    Files: ``STEM.disparity.EXT`` and ``STEM.depth.EXT`` per format (``npy``, ``pfm``, ``exr``:
    float32, NaN = invalid; ``png16``: ``.png`` 16-bit, 0 = invalid, value = offset +
    (code − 1)·scale with offset/scale in the sidecar), ``STEM.preview.png`` (colour preview of
    the disparity) and last ``STEM.json``, the sidecar: quantities and units, ERP convention,
    model and its sha256, layout, options, timings, m360 version, the files (plus ``extra``,
    e.g. the input file and its sha256). Any earlier sidecar is removed first and the files of
    this call are removed again if it fails, so a sidecar always describes a complete set.

    Parameters
    ----------
    result : EstimateResult
        Or any object with ``disparity``/``depth`` (H, W) float arrays (``model``, ``units``,
        ``options``, ``timings``, ``layout`` are recorded when present).
    stem : path
        Output path without suffix, e.g. ``out/pano``; folders are created.
    formats : sequence of str
        Any of ``"npy"`` (default), ``"pfm"``, ``"exr"``, ``"png16"``, and the 3D formats
        (extra ``m360[3d]``) ``"ply"`` (``STEM.points.ply``: the point cloud, m360 frame) and
        ``"glb"`` (``STEM.mesh.glb``: the mesh of :func:`m360.to_mesh`, glTF frame, y up); the
        sidecar's ``frame`` says which frame each 3D file is in.
    preview : bool
        Also write the colour preview PNG.
    extra : mapping, optional
        More JSON-serialisable fields for the sidecar.
    rgb : (H, W, 3) uint8, optional
        The panorama: colours of the 3D files.
    confidence : bool
        Also write ``result.confidence`` (the overlap disagreement left, in disparity units,
        lower = more consistent; NaN = unseen) as ``STEM.confidence.EXT`` in every format, and
        describe it in the sidecar.

    Returns
    -------
    dict
        Role (``disparity.npy``, ``depth.pfm`` …, ``preview``, ``sidecar``) → path written.
    """
    from . import __version__

    chosen = check_formats(formats)
    with np.errstate(over="ignore"):  # float64 beyond float32's range is ±inf, as in m360's maps
        arrays = {
            q: np.ascontiguousarray(_check_map(getattr(result, q, None), q), dtype=np.float32)
            for q in QUANTITIES
        }
    flag(confidence, "confidence")
    if confidence:
        with np.errstate(over="ignore"):
            arrays["confidence"] = np.ascontiguousarray(
                _check_map(getattr(result, "confidence", None), "confidence"), dtype=np.float32
            )
        if arrays["confidence"].shape != arrays["disparity"].shape:
            raise InputError(
                f"result.confidence {arrays['confidence'].shape} and result.disparity "
                f"{arrays['disparity'].shape} differ in shape"
            )
    if arrays["disparity"].shape != arrays["depth"].shape:
        raise InputError(
            f"result.disparity {arrays['disparity'].shape} and result.depth "
            f"{arrays['depth'].shape} differ in shape"
        )
    base = Path(stem)
    sidecar_path = base.with_name(base.name + ".json")
    written: dict[str, Path] = {}
    files: dict[str, Any] = {q: {} for q in arrays}
    png16: dict[str, Any] = {}
    with contextlib.suppress(FileNotFoundError):
        sidecar_path.unlink()  # the old set is incomplete from here on
    try:
        for fmt in [f for f in chosen if f in SAVE_FORMATS]:
            for quantity, values in arrays.items():
                path = base.with_name(f"{base.name}.{quantity}{FORMAT_SUFFIXES[fmt]}")
                params = write_array(path, values, fmt)
                if params:
                    png16[quantity] = params
                written[f"{quantity}.{fmt}"] = path
                files[quantity][fmt] = path.name
        if preview:
            written["preview"] = save_png(
                base.with_name(base.name + ".preview.png"), colorize(arrays["disparity"])
            )
            files["preview"] = written["preview"].name
        frames = _save_geometry(result, base, chosen, rgb, written, files)
        sidecar = _sidecar(result, arrays["disparity"], files, png16, __version__)
        if frames:
            sidecar["frame"] = frames
        if extra:
            sidecar.update(extra)
        written["sidecar"] = save_json(sidecar_path, sidecar)
    except BaseException:
        for path in written.values():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        raise
    return written


def _save_geometry(
    result: Any,
    base: Path,
    chosen: Sequence[str],
    rgb: np.ndarray | None,
    written: dict[str, Path],
    files: dict[str, Any],
) -> dict[str, str]:
    """Write the 3D formats among ``chosen``; returns file name → frame for the sidecar."""
    from . import mesh

    frames: dict[str, str] = {}
    for fmt in [f for f in chosen if f in GEOMETRY_FORMATS]:
        kind, tail = GEOMETRY_FILES[fmt]
        path = base.with_name(base.name + tail)
        if fmt == "ply":
            geometry: Any = mesh.to_points(result, rgb=rgb)
            mesh.write_ply(path, geometry)
        else:
            geometry = mesh.to_mesh(result, rgb=rgb)
            mesh.write_glb(path, geometry)
        written[f"{kind}.{fmt}"] = path
        files[kind] = {fmt: path.name}
        frames[path.name] = mesh.FRAMES[fmt]
    return frames


def _sidecar(
    result: Any,
    disparity: np.ndarray,
    files: dict[str, Any],
    png16: dict[str, Any],
    version: str,
) -> dict[str, Any]:
    units = getattr(result, "units", "relative")
    layout = getattr(result, "layout", None)
    sidecar: dict[str, Any] = {
        "m360_version": version,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "files": files,
        "quantities": {
            "disparity": {
                "meaning": "spherical disparity 1/distance"
                + (" up to a global scale and shift" if units == "relative" else ""),
                "units": "relative" if units == "relative" else "1/metres",
                "dtype": "float32",
                "invalid": "NaN (png16: 0)",
            },
            "depth": {
                "meaning": "radial distance |P| = 1/disparity where disparity > 0",
                "units": units,
                "dtype": "float32",
                "invalid": "NaN (png16: 0)",
            },
        },
        "shape": list(disparity.shape),
        "erp_convention": ERP_CONVENTION,
        "model": getattr(result, "model", None),
        "layout": None
        if layout is None
        else {
            "name": layout.name,
            "erp_shape": list(layout.erp_shape),
            "cameras": len(layout),
            "tangent_shape": list(layout.tangent_shape),
            "padding": layout.padding,
            "key": layout.key,
        },
        "options": getattr(result, "options", {}),
        "timings_s": {k: round(float(v), 6) for k, v in getattr(result, "timings", {}).items()},
        "valid_fraction": float(np.isfinite(disparity).mean()),
    }
    if "confidence" in files:
        sidecar["quantities"]["confidence"] = {
            "meaning": "overlap disagreement left after blending (lower = more consistent)",
            "units": "disparity units",
            "dtype": "float32",
            "invalid": "NaN (png16: 0)",
        }
    report = getattr(getattr(result, "stitch", None), "report", None)
    if isinstance(report, Mapping) and "align_fallback" in report:
        sidecar["alignment"] = {"fallback": report["align_fallback"]}
    if png16:
        sidecar["png16"] = png16
    if getattr(result, "scale", None) is not None:
        sidecar["scale"] = result.scale
    return sidecar


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


def remove_stale_temporaries(stem: str | os.PathLike[str]) -> list[Path]:
    """Delete temporary files a killed writer left for the set ``stem``; returns them.

    Only the temporaries of this set's own file names (``.NAME.<8 random>.tmp`` for each name
    :func:`save` writes), so another set with a longer stem is never touched. Call this only
    while holding the set's claim (see :mod:`m360.batch`): a live writer's temporary file looks
    the same.
    """
    base = Path(stem)
    if not base.parent.is_dir():
        return []
    quantities = (*QUANTITIES, "confidence")
    names = [f"{base.name}.{q}{suffix}" for q in quantities for suffix in FORMAT_SUFFIXES.values()]
    names += [f"{base.name}.preview.png", f"{base.name}.json"]
    names += [base.name + tail for _, tail in GEOMETRY_FILES.values()]
    removed = []
    for name in names:
        for tmp in base.parent.glob(f".{glob.escape(name)}.{'?' * 8}.tmp"):
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    return removed
