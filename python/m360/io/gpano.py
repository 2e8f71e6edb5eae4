"""Partial panoramas: the few GPano XMP fields that place a cropped capture in its full ERP canvas.

Google's Photo Sphere XMP (namespace ``http://ns.google.com/photos/1.0/panorama/``) says where a
cropped equirectangular image sits in the full panorama: ``FullPanoWidthPixels``,
``FullPanoHeightPixels``, ``CroppedAreaImageWidthPixels``, ``CroppedAreaImageHeightPixels``,
``CroppedAreaLeftPixels``, ``CroppedAreaTopPixels`` and ``ProjectionType``. Only these are read,
from the XMP packet (``<x:xmpmeta>`` … ``</x:xmpmeta>``) found in the file's bytes (JPEG APP1,
PNG iTXt, or any container that stores the packet as plain text), with the standard library's
XML parser; the fields may be attributes of ``rdf:Description`` or child elements.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ReadError

GPANO_NS = "http://ns.google.com/photos/1.0/panorama/"
_FIELDS = {
    "full_width": "FullPanoWidthPixels",
    "full_height": "FullPanoHeightPixels",
    "crop_width": "CroppedAreaImageWidthPixels",
    "crop_height": "CroppedAreaImageHeightPixels",
    "left": "CroppedAreaLeftPixels",
    "top": "CroppedAreaTopPixels",
}
_PACKET = re.compile(rb"<x:xmpmeta[\s>].*?</x:xmpmeta>", re.DOTALL)
#: Largest full panorama accepted (the core's ERP width limit is checked again by estimate).
_MAX_SIDE = 1 << 16


@dataclass(frozen=True)
class GPanoCrop:
    """Where a cropped image sits in its full ERP canvas (pixels)."""

    full_width: int
    full_height: int
    crop_width: int
    crop_height: int
    left: int
    top: int

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (the sidecar's ``crop``)."""
        return {**self.__dict__, "source": "GPano XMP"}


def _values(packet: bytes) -> dict[str, str]:
    try:
        root = ET.fromstring(packet)
    except ET.ParseError as exc:
        raise ReadError(f"the XMP packet is not valid XML: {exc}") from exc
    found: dict[str, str] = {}
    for element in root.iter():
        for key, value in element.attrib.items():
            if key.startswith("{" + GPANO_NS + "}"):
                found[key.split("}", 1)[1]] = value.strip()
        if element.tag.startswith("{" + GPANO_NS + "}") and element.text:
            found[element.tag.split("}", 1)[1]] = element.text.strip()
    return found


def read_gpano(data: bytes, name: str = "image") -> GPanoCrop | None:
    """Read the crop of a partial panorama from its file bytes; None when it has no GPano crop.

    Raises
    ------
    ReadError
        A GPano packet that is malformed, incomplete, not equirectangular or self-contradictory.
    """
    match = _PACKET.search(data)
    if match is None or GPANO_NS.encode() not in match.group(0):
        return None
    values = _values(match.group(0))
    if not any(v in values for v in _FIELDS.values()):
        return None
    projection = values.get("ProjectionType", "equirectangular")
    if projection.lower() != "equirectangular":
        raise ReadError(f"{name}: GPano ProjectionType is {projection!r}, not equirectangular")
    missing = [v for v in _FIELDS.values() if v not in values]
    if missing:
        raise ReadError(f"{name}: GPano metadata lacks {', '.join(missing)}")
    numbers: dict[str, int] = {}
    for key, field_name in _FIELDS.items():
        text = values[field_name]
        if not re.fullmatch(r"[+-]?\d+", text):
            raise ReadError(f"{name}: GPano {field_name} is {text!r}, not an integer")
        numbers[key] = int(text)
    crop = GPanoCrop(**numbers)
    if not (0 < crop.full_height <= _MAX_SIDE and crop.full_width == 2 * crop.full_height):
        raise ReadError(
            f"{name}: GPano full panorama {crop.full_width}x{crop.full_height} is not an ERP "
            "canvas (width == 2 * height)"
        )
    if not (0 < crop.crop_width <= crop.full_width and 0 < crop.crop_height):
        raise ReadError(
            f"{name}: GPano cropped area {crop.crop_width}x{crop.crop_height} does not fit the "
            f"full panorama {crop.full_width}x{crop.full_height}"
        )
    if crop.top < 0 or crop.top + crop.crop_height > crop.full_height:
        raise ReadError(
            f"{name}: GPano rows {crop.top}..{crop.top + crop.crop_height} lie outside the full "
            f"panorama's {crop.full_height} rows"
        )
    if not 0 <= crop.left < crop.full_width:
        raise ReadError(
            f"{name}: GPano CroppedAreaLeftPixels {crop.left} is outside 0..{crop.full_width - 1}"
        )
    return crop


def place(rgb: np.ndarray, crop: GPanoCrop, name: str = "image") -> tuple[np.ndarray, np.ndarray]:
    """Put a cropped image into its full ERP canvas: (canvas (H, W, 3), mask (H, W) True = data).

    Columns wrap (a crop may cross the 0/360° seam).

    Raises
    ------
    ReadError
        The image's pixel size is not the cropped area's.
    """
    if rgb.shape[:2] != (crop.crop_height, crop.crop_width):
        raise ReadError(
            f"{name}: the image is {rgb.shape[1]}x{rgb.shape[0]} pixels but its GPano metadata "
            f"says the cropped area is {crop.crop_width}x{crop.crop_height}"
        )
    canvas = np.zeros((crop.full_height, crop.full_width, *rgb.shape[2:]), rgb.dtype)
    mask = np.zeros((crop.full_height, crop.full_width), bool)
    cols = (crop.left + np.arange(crop.crop_width)) % crop.full_width
    rows = slice(crop.top, crop.top + crop.crop_height)
    canvas[rows, cols] = rgb
    mask[rows, cols] = True
    return canvas, mask
