"""Input panoramas: reading and decoding image files into (H, W, 3) uint8 RGB.

JPEG, PNG, TIFF (what OpenCV decodes) and OpenEXR; every file is opened read-only. Outputs
(arrays, previews, sidecars) are :mod:`m360.io`'s.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from .._validate import check_erp_shape
from ..errors import AspectRatioError, ReadError

__all__ = [
    "IMAGE_SUFFIXES",
    "check_jpeg_complete",
    "decode_image",
    "fix_aspect_ratio",
    "load_image",
    "read_bytes",
    "read_exr",
    "read_image",
    "read_input_bytes",
    "to_rgb8",
    "tonemap",
]

#: Input images :func:`read_image` decodes (and batch folders collect): JPEG, PNG, TIFF, OpenEXR,
#: Radiance HDR, WebP, BMP.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr", ".hdr", ".webp", ".bmp")


def read_exr(path: Path) -> np.ndarray:
    """Read an EXR's channels as (H, W) or (H, W, C) float, colour channels in RGB order."""
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        channels = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    for name in ("Y", "Z", "RGB", "RGBA"):
        if name in channels:
            values = channels[name]
            return values[..., :3] if name == "RGBA" else values
    if {"R", "G", "B"} <= channels.keys():
        return np.stack([channels[c] for c in "RGB"], axis=-1)
    if len(channels) == 1:
        return next(iter(channels.values()))
    raise ReadError(f"{path}: EXR channels {sorted(channels)}; expected Y, Z or R, G, B")


def read_bytes(path: Path, what: str) -> bytes:
    """Read the bytes of a file, opened read-only.

    Raises :class:`m360.ReadError` naming it as ``what`` if it is missing, unreadable or empty.
    """
    if not path.is_file():
        raise ReadError(f"{what} {path} does not exist (or is not a file)")
    try:
        with open(path, "rb") as f:  # read-only: inputs are never modified
            data = f.read()
    except OSError as exc:
        raise ReadError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if not data:
        raise ReadError(f"{what} {path} is empty (0 bytes)")
    return data


def read_input_bytes(path: str | os.PathLike[str]) -> bytes:
    """Read the bytes of an input image, opened read-only.

    Raises :class:`m360.ReadError` if it is missing, unreadable or empty.
    """
    return read_bytes(Path(path), "input image")


def read_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB, whatever its aspect (opened read-only).

    JPEG, PNG, TIFF (what OpenCV decodes) and OpenEXR. 16-bit images are rounded to 8 bits,
    grey images get three channels, alpha is dropped; float images (EXR, float TIFF) are linear
    radiance: scaled so their 99th percentile is white, clipped and gamma-encoded (1/2.2). EXIF
    orientation is ignored: panorama pixels are taken as stored (a 360° camera's orientation flag
    would turn a 2:1 image into a 1:2 one). Raises :class:`m360.ReadError` for a missing, empty,
    truncated or undecodable file.
    """
    return decode_image(read_input_bytes(path), path)


def decode_image(data: bytes, path: str | os.PathLike[str]) -> np.ndarray:
    """:func:`read_image` of bytes already read from ``path`` (named in errors)."""
    p = Path(path)
    if data[:4] == b"\x76\x2f\x31\x01":  # OpenEXR magic
        try:
            image = read_exr(p)
        except ReadError:
            raise
        except Exception as exc:
            raise ReadError(f"cannot decode {p} as OpenEXR: {exc}") from exc
        return to_rgb8(image, p, order="RGB")
    if data[:2] == b"\xff\xd8":
        check_jpeg_complete(data, p)
    try:
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ReadError(f"cannot decode {p} as an image: {exc}") from exc
    if decoded is None:
        raise ReadError(f"cannot decode {p} as an image (truncated or not JPEG/PNG/TIFF/EXR?)")
    return to_rgb8(decoded, p, order="BGR")


def load_image(path: str | os.PathLike[str], *, fix_aspect: bool = False) -> np.ndarray:
    """Read an equirectangular panorama as (H, W, 3) uint8 RGB (see :func:`read_image`).

    A panorama must be W == 2H: otherwise :class:`m360.AspectRatioError` naming its size, or, with
    ``fix_aspect=True``, it is resized to W x W/2 (W rounded up to even).
    """
    return fix_aspect_ratio(read_image(path), path, fix=fix_aspect)


def fix_aspect_ratio(image: np.ndarray, path: str | os.PathLike[str], *, fix: bool) -> np.ndarray:
    """``image`` if it is W == 2H; else resized to W x W/2 if ``fix``, else AspectRatioError."""
    height, width = image.shape[:2]
    if width == 2 * height:
        return image
    if not fix:
        try:
            check_erp_shape(height, width, str(path))
        except AspectRatioError as exc:
            raise AspectRatioError(f"{exc}; resize it, or pass fix_aspect/--fix-aspect") from None
    width += width % 2
    interpolation = cv2.INTER_AREA if width // 2 < height else cv2.INTER_LINEAR
    return cv2.resize(image, (width, width // 2), interpolation=interpolation)


def to_rgb8(image: np.ndarray, path: Path, *, order: str) -> np.ndarray:
    """Convert a decoded image to (H, W, 3) uint8 RGB.

    16 bits are rounded, floats tone-mapped, grey repeated, alpha dropped; ``order`` is the
    image's colour order (``"RGB"`` or ``"BGR"``).
    """
    if image.dtype == np.uint16:
        image = ((image.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif image.dtype.kind == "f":
        image = tonemap(image)
    elif image.dtype != np.uint8:
        raise ReadError(f"{path} has pixel type {image.dtype}; use 8/16-bit or float images")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 2):  # grey (+ alpha)
        grey = image if image.ndim == 2 else image[:, :, 0]
        return np.ascontiguousarray(np.repeat(grey[:, :, None], 3, axis=2))
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ReadError(f"{path} has an unsupported channel layout {image.shape}")
    rgb = image[:, :, :3] if order == "RGB" else image[:, :, 2::-1]
    return np.ascontiguousarray(rgb)


def tonemap(image: np.ndarray) -> np.ndarray:
    """Linear float radiance as uint8: its 99th percentile white, clipped, gamma 1/2.2."""
    linear = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(linear, 0.0, out=linear)
    white = float(np.percentile(linear, 99.0)) or float(linear.max()) or 1.0
    encoded = np.clip(linear / white, 0.0, 1.0) ** (1.0 / 2.2)
    return np.rint(encoded * 255.0).astype(np.uint8)  # type: ignore[no-any-return]  # numpy stubs: Any


def check_jpeg_complete(data: bytes, path: Path) -> None:
    """Refuse a JPEG whose primary image has no end-of-image marker (a truncated download).

    Old OpenCV builds decode such files with a grey bottom and only a warning. Walks the marker
    segments to the first scan (so an EXIF thumbnail's own markers are skipped), then looks for
    EOI among the markers in the entropy-coded data (0xFF bytes there are stuffed, so every
    0xFF not followed by 0x00, a restart code or fill is a real marker). Bytes a camera appends
    after EOI are allowed.
    """
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            raise ReadError(f"{path} is not a valid JPEG (bad marker at byte {pos})")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0xDA:  # start of scan: entropy-coded data follows
            break
        pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    else:
        raise ReadError(f"{path} is a truncated JPEG (ends before its first scan)")
    scan = np.frombuffer(data, np.uint8)[pos + 2 :]
    ff = np.flatnonzero(scan[:-1] == 0xFF)
    if not (scan[ff + 1] == 0xD9).any():
        raise ReadError(f"{path} is a truncated JPEG (no end-of-image marker)")
