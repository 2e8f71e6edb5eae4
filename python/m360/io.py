"""Reading panoramas and writing results without ever leaving a half-written file behind."""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import InputError

__all__ = [
    "ERP_CONVENTION",
    "SAVE_FORMATS",
    "atomic_path",
    "colorize",
    "load_image",
    "save",
    "save_json",
    "save_npy",
    "save_png",
]

#: Formats :func:`save` writes in this version (PNG16/PFM/EXR come with the batch module).
SAVE_FORMATS = ("npy",)
_PLANNED_FORMATS = ("png16", "pfm", "exr")

#: The ERP convention written into every sidecar (DESIGN.md §1).
ERP_CONVENTION = {
    "shape": "H x W with W == 2H",
    "longitude": "2*pi*(j + 0.5)/W - pi (column j; -pi at the left edge, increasing rightwards)",
    "latitude": "pi/2 - pi*(i + 0.5)/H (row i; +pi/2 at the top edge)",
    "direction": "(cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon)); x right, y down, z forward",
    "disparity": "spherical, 1/distance",
    "depth": "radial distance |P|",
    "invalid": "NaN in .npy",
}


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary file lives in the target folder so the final rename is atomic (same file
    system); on any exception it is removed and ``path`` is left as it was.
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


def save_npy(path: str | os.PathLike[str], array: np.ndarray) -> Path:
    """Write ``array`` as .npy atomically; returns the path."""
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
    return target


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write a uint8/uint16 image (H,W) or (H,W,3) BGR as PNG atomically; returns the path."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise InputError(
            f"cannot encode an image of shape {image.shape} and dtype {image.dtype} as PNG"
        )
    target = Path(path)
    with atomic_path(target) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return target


def colorize(disparity: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """A colour preview (H, W, 3) uint8 BGR of a disparity map: near warm, far cool, NaN black.

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


def save_json(path: str | os.PathLike[str], data: Mapping[str, Any]) -> Path:
    """Write ``data`` as indented UTF-8 JSON atomically; returns the path."""
    target = Path(path)
    text = json.dumps(data, indent=2, sort_keys=False, default=_json_default, allow_nan=False)
    with atomic_path(target) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")
    return target


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an equirectangular panorama as (H, W, 3) uint8 RGB (file opened read-only).

    16-bit images are reduced to 8 bits, grey images get three channels and alpha is dropped.
    Raises InputError if the file is missing, not an image OpenCV can decode, or not W == 2H.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"input image {p} does not exist (or is not a file)")
    data = np.fromfile(p, dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"cannot decode {p} as an image (supported: what OpenCV reads)")
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise InputError(f"{p} has pixel type {image.dtype}; use 8- or 16-bit images")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    height, width = image.shape[:2]
    if width != 2 * height:
        raise InputError(
            f"{p} is {width}x{height} (WxH) but an equirectangular panorama must have "
            f"W == 2H (expected width {2 * height})"
        )
    return image


def save(
    result: Any,
    stem: str | os.PathLike[str],
    *,
    formats: Sequence[str] = ("npy",),
    preview: bool = True,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Path]:
    """Write an :class:`m360.EstimateResult` next to ``stem``; every file atomically.

    Files: ``STEM.disparity.npy`` and ``STEM.depth.npy`` (float32, NaN = invalid),
    ``STEM.preview.png`` (colour preview of the disparity) and last ``STEM.json``, the sidecar:
    quantities and units, ERP convention, model and its sha256, options, timings, m360 version
    (plus ``extra``). The sidecar is written last, so its presence means the set is complete.

    Parameters
    ----------
    result : EstimateResult
    stem : path
        Output path without suffix, e.g. ``out/pano``; folders are created.
    formats : sequence of str
        ``"npy"`` in this version.
    preview : bool
        Also write the colour preview PNG.
    extra : mapping, optional
        More JSON-serialisable fields for the sidecar (e.g. the input path).

    Returns
    -------
    dict
        Role (``disparity``, ``depth``, ``preview``, ``sidecar``) → path written.
    """
    from . import __version__

    for fmt in formats:
        if fmt in _PLANNED_FORMATS:
            raise InputError(f"format {fmt!r} is not available in this version yet; use 'npy'")
        if fmt not in SAVE_FORMATS:
            raise InputError(f"format {fmt!r} is not supported; choose from {SAVE_FORMATS}")
    base = Path(stem)
    written: dict[str, Path] = {}
    if "npy" in formats:
        written["disparity"] = save_npy(
            base.with_name(base.name + ".disparity.npy"), result.disparity
        )
        written["depth"] = save_npy(base.with_name(base.name + ".depth.npy"), result.depth)
    if preview:
        written["preview"] = save_png(
            base.with_name(base.name + ".preview.png"), colorize(result.disparity)
        )
    units = result.units
    height, width = result.disparity.shape
    sidecar: dict[str, Any] = {
        "m360_version": __version__,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "files": {role: path.name for role, path in written.items()},
        "quantities": {
            "disparity": {
                "meaning": "spherical disparity 1/distance"
                + (" up to a global scale and shift" if units == "relative" else ""),
                "units": "relative" if units == "relative" else "1/metres",
                "dtype": "float32",
                "invalid": "NaN",
            },
            "depth": {
                "meaning": "radial distance |P| = 1/disparity where disparity > 0",
                "units": units,
                "dtype": "float32",
                "invalid": "NaN",
            },
        },
        "shape": [height, width],
        "erp_convention": ERP_CONVENTION,
        "model": result.model,
        "options": result.options,
        "timings_s": {k: round(float(v), 6) for k, v in result.timings.items()},
        "valid_fraction": float(np.isfinite(result.disparity).mean()),
    }
    if extra:
        sidecar.update(extra)
    written["sidecar"] = save_json(base.with_name(base.name + ".json"), sidecar)
    return written
