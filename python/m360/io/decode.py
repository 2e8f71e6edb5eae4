"""Input panoramas: reading and decoding image files into (H, W, 3) uint8 RGB.

JPEG, PNG, TIFF (what OpenCV decodes) and OpenEXR; every file is opened read-only. Outputs
(arrays, previews, sidecars) are :mod:`m360.io`'s.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from .._validate import check_erp_shape
from ..errors import AspectRatioError, ReadError

__all__ = [
    "IMAGE_SUFFIXES",
    "ImageHeader",
    "check_aspect_before_decoding",
    "check_jpeg_complete",
    "decode_image",
    "fix_aspect_ratio",
    "image_header",
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
#: Bytes :func:`image_header` reads of a file: enough for any ordinary EXR or JPEG header.
HEADER_BYTES = 65536
#: Pixels converted at once by :func:`to_rgb8` (16-bit and float images): the wide temporaries
#: stay a band of rows (about a million pixels, 16 MB), not the whole image.
_BAND_PIXELS = 1 << 20


@dataclass(frozen=True)
class ImageHeader:
    """What a file's header says about its image, read without decoding it.

    Attributes
    ----------
    width, height : int
        Size in pixels.
    channels : int
        Channels the decoder returns (grey 1, grey + alpha 2, RGB 3, RGBA 4).
    sample_bytes : int
        Bytes per channel the decoder returns before the conversion to 8 bits (1, 2 or 4).
    kind : str
        ``"png"``, ``"jpeg"``, ``"exr"``, ``"hdr"`` or ``"tiff"``.
    """

    width: int
    height: int
    channels: int
    sample_bytes: int
    kind: str

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoder's own array (before the 8-bit RGB copy)."""
        return self.width * self.height * self.channels * self.sample_bytes


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


def image_header(source: bytes | BinaryIO) -> ImageHeader | None:
    """Read an image's size and sample type from its header, without decoding it.

    PNG (IHDR), JPEG (the first SOF marker), OpenEXR (``dataWindow``, ``channels``), Radiance
    HDR (the resolution line) and TIFF (the first IFD). None for any other file or a header
    this reader does not understand: the caller then decodes the file to learn its size.
    OpenCV has no header-only API (and PIL is no dependency of m360), so the few fields are
    read here.

    Parameters
    ----------
    source : bytes or binary file
        The file's bytes, or the file open for reading: then only its first
        :data:`HEADER_BYTES` are read (and a TIFF's first IFD, wherever it lies).
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)

        def read_at(offset: int, size: int) -> bytes:
            return data[offset : offset + size]
    else:
        source.seek(0)
        data = source.read(HEADER_BYTES)

        def read_at(offset: int, size: int) -> bytes:
            source.seek(offset)
            return source.read(size)

    try:
        if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
            width, height, depth, colour = struct.unpack(">IIBB", data[16:26])
            channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour, 4)
            return ImageHeader(width, height, channels, 2 if depth == 16 else 1, "png")
        if data[:2] == b"\xff\xd8":
            return _jpeg_header(data)
        if data[:4] == b"\x76\x2f\x31\x01":
            return _exr_header(data)
        if data[:2] == b"#?":
            return _hdr_header(data)
        if data[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_header(data, read_at)
    except (struct.error, ValueError, IndexError, OSError):
        return None
    return None


def _jpeg_header(data: bytes) -> ImageHeader | None:
    pos = 2
    while pos + 9 < len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        # SOF0-15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame's size.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            precision, height, width, channels = struct.unpack(">BHHB", data[pos + 4 : pos + 10])
            return ImageHeader(width, height, channels, 2 if precision > 8 else 1, "jpeg")
        if marker == 0xDA:  # a scan before any frame header: not a JPEG we understand
            return None
        pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
    return None


def _exr_header(data: bytes) -> ImageHeader | None:
    pos = 8  # magic, version and flags
    window = None
    channels: list[int] = []
    while pos < len(data) and data[pos] != 0:
        name_end = data.index(b"\0", pos)
        type_end = data.index(b"\0", name_end + 1)
        name = data[pos:name_end]
        (size,) = struct.unpack("<i", data[type_end + 1 : type_end + 5])
        value = data[type_end + 5 : type_end + 5 + size]
        if name == b"dataWindow":
            x0, y0, x1, y1 = struct.unpack("<iiii", value[:16])
            window = (x1 - x0 + 1, y1 - y0 + 1)
        elif name == b"channels":  # name\0, pixel type int32 (0 uint, 1 half, 2 float), 12 more
            at = 0
            while at < len(value) and value[at] != 0:
                at = value.index(b"\0", at) + 1
                channels.append(struct.unpack("<i", value[at : at + 4])[0])
                at += 16
        pos = type_end + 5 + size
    if window is None or not channels:
        return None
    # read_exr returns the channels as stored (half 2 bytes, float and uint 4); to_rgb8 then
    # works in float32: count 4 bytes a sample.
    return ImageHeader(window[0], window[1], min(len(channels), 4), 4, "exr")


def _hdr_header(data: bytes) -> ImageHeader | None:
    end = data.find(b"\n\n", 0, 65536)
    if end < 0:
        return None
    line = data[end + 2 : data.find(b"\n", end + 2, end + 200)].split()
    if len(line) != 4 or line[0] not in (b"-Y", b"+Y") or line[2] not in (b"+X", b"-X"):
        return None  # a rotated layout (±X first): let the decoder say
    return ImageHeader(int(line[3]), int(line[1]), 3, 4, "hdr")


def _tiff_header(data: bytes, read_at: Callable[[int, int], bytes]) -> ImageHeader | None:
    order = "<" if data[:2] == b"II" else ">"
    (ifd,) = struct.unpack(order + "I", data[4:8])
    (count,) = struct.unpack(order + "H", read_at(ifd, 2))
    entries = read_at(ifd + 2, 12 * min(count, 512))
    tags: dict[int, int] = {}
    for k in range(len(entries) // 12):
        entry = entries[12 * k : 12 * k + 12]
        tag, kind, n = struct.unpack(order + "HHI", entry[:8])
        if kind == 3:  # SHORT: the first value sits at the start of the value field
            tags[tag] = struct.unpack(order + "H", entry[8:10])[0]
        elif kind == 4:  # LONG
            tags[tag] = struct.unpack(order + "I", entry[8:12])[0]
        if tag == 258 and n > 2 and kind == 3:  # BitsPerSample per channel: at an offset
            offset = struct.unpack(order + "I", entry[8:12])[0]
            tags[tag] = struct.unpack(order + "H", read_at(offset, 2))[0]
    if 256 not in tags or 257 not in tags:
        return None
    bits = tags.get(258, 8)
    channels = tags.get(277, 1)
    return ImageHeader(tags[256], tags[257], channels, max(1, bits // 8), "tiff")


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
    if decoded.dtype == np.uint8 and decoded.ndim == 3 and decoded.shape[2] == 3:
        # The decoder's own array turned to RGB in place: no second full-size copy.
        return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB, dst=decoded)
    return to_rgb8(decoded, p, order="BGR")


def load_image(path: str | os.PathLike[str], *, fix_aspect: bool = False) -> np.ndarray:
    """Read an equirectangular panorama as (H, W, 3) uint8 RGB (see :func:`read_image`).

    A panorama must be W == 2H: otherwise :class:`m360.AspectRatioError` naming its size, or, with
    ``fix_aspect=True``, it is resized to W x W/2 (W rounded up to even). The size is read from
    the file's header first where it can be (:func:`image_header`), so a wrong aspect is
    refused before the image is decoded.
    """
    data = read_input_bytes(path)
    check_aspect_before_decoding(data, path, fix=fix_aspect)
    return fix_aspect_ratio(decode_image(data, path), path, fix=fix_aspect)


def check_aspect_before_decoding(
    data: bytes, path: str | os.PathLike[str], *, fix: bool
) -> ImageHeader | None:
    """Read ``data``'s header (:func:`image_header`); refuse a wrong aspect before decoding.

    Returns the header (None when it cannot be read: the caller learns the size by decoding).
    Raises :class:`m360.AspectRatioError` as :func:`fix_aspect_ratio` does, unless ``fix``.
    """
    header = image_header(data)
    if header is not None and not fix and header.width != 2 * header.height:
        _refuse_aspect(header.height, header.width, path)
    return header


def _refuse_aspect(height: int, width: int, path: str | os.PathLike[str]) -> None:
    try:
        check_erp_shape(height, width, str(path))
    except AspectRatioError as exc:
        raise AspectRatioError(f"{exc}; resize it, or pass fix_aspect/--fix-aspect") from None


def fix_aspect_ratio(image: np.ndarray, path: str | os.PathLike[str], *, fix: bool) -> np.ndarray:
    """``image`` if it is W == 2H; else resized to W x W/2 if ``fix``, else AspectRatioError."""
    height, width = image.shape[:2]
    if width == 2 * height:
        return image
    if not fix:
        _refuse_aspect(height, width, path)
    width += width % 2
    interpolation = cv2.INTER_AREA if width // 2 < height else cv2.INTER_LINEAR
    return cv2.resize(image, (width, width // 2), interpolation=interpolation)


def to_rgb8(image: np.ndarray, path: Path, *, order: str) -> np.ndarray:
    """Convert a decoded image to (H, W, 3) uint8 RGB.

    16 bits are rounded, floats tone-mapped, grey repeated, alpha dropped; ``order`` is the
    image's colour order (``"RGB"`` or ``"BGR"``). Wide images are converted in bands of rows
    into the output, so the wider temporaries stay a band's (at 72 MP a whole-image uint32
    copy alone is 860 MB). Raises :class:`m360.ReadError` for a float image without one finite
    value (all NaN or infinite), as :func:`m360.estimate` refuses such an array.
    """
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if (image.ndim == 3 and image.shape[2] not in (2, 3, 4)) or image.ndim not in (2, 3):
        raise ReadError(f"{path} has an unsupported channel layout {image.shape}")
    if image.ndim == 3 and image.shape[2] == 2:  # grey + alpha
        image = image[:, :, 0]
    if image.dtype not in (np.uint8, np.uint16) and image.dtype.kind != "f":
        raise ReadError(f"{path} has pixel type {image.dtype}; use 8/16-bit or float images")
    white = _white_point(image, path) if image.dtype.kind == "f" else 0.0
    if image.ndim == 3:  # colour order and alpha as a view: no copy before the conversion
        image = image[:, :, :3] if order == "RGB" else image[:, :, 2::-1]
    height, width = image.shape[:2]
    out = np.empty((height, width, 3), np.uint8)
    rows = max(1, _BAND_PIXELS // width)
    for top in range(0, height, rows):
        band = image[top : top + rows]
        if band.dtype == np.uint16:
            wide = band.astype(np.uint32)
            wide += 128
            wide //= 257
            band = wide.astype(np.uint8)
        elif band.dtype.kind == "f":
            band = _encode(band, white)
        out[top : top + rows] = band[:, :, None] if band.ndim == 2 else band
    return out


def _linear(image: np.ndarray) -> np.ndarray:
    """Float radiance as float32 with NaN, ±inf and negative values 0."""
    linear = image.astype(np.float32)  # a copy, cleaned in place
    np.nan_to_num(linear, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(linear, 0.0, out=linear)
    return linear


def _white_point(image: np.ndarray, path: Path | None) -> float:
    """Return the 99th percentile of the linear radiance (its maximum, or 1, if 0)."""
    if path is not None and not np.isfinite(image).any():
        raise ReadError(
            f"{path} has no finite pixel value (every pixel is NaN or infinite): "
            "nothing to estimate"
        )
    linear = _linear(image)
    white = float(np.percentile(linear, 99.0, overwrite_input=True)) or float(linear.max())
    return white or 1.0


def _encode(image: np.ndarray, white: float) -> np.ndarray:
    encoded = np.clip(_linear(image) / white, 0.0, 1.0) ** (1.0 / 2.2)
    return np.rint(encoded * 255.0).astype(np.uint8)


def tonemap(image: np.ndarray) -> np.ndarray:
    """Linear float radiance as uint8: its 99th percentile white, clipped, gamma 1/2.2."""
    return _encode(image, _white_point(image, None))


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
