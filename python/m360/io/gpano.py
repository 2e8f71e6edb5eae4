r"""Partial panoramas: the few GPano XMP fields that place a cropped capture in its full ERP canvas.

Google's Photo Sphere XMP (namespace ``http://ns.google.com/photos/1.0/panorama/``) says where a
cropped equirectangular image sits in the full panorama: ``FullPanoWidthPixels``,
``FullPanoHeightPixels``, ``CroppedAreaImageWidthPixels``, ``CroppedAreaImageHeightPixels``,
``CroppedAreaLeftPixels``, ``CroppedAreaTopPixels`` and ``ProjectionType``. Only these are read,
from the XMP packet (``<x:xmpmeta>`` … ``</x:xmpmeta>``) found in the file's bytes (JPEG APP1,
PNG iTXt, or any container that stores the packet as plain text), with the standard library's
XML parser; the fields may be attributes of ``rdf:Description`` or child elements. A file whose
``StereoMode`` says it holds two eyes (a stereo panorama such as m360's own ``STEM.stereo.jpg``)
is refused with a clear :class:`~m360.errors.ReadError`: m360 reads monoscopic panoramas.

The writer side (:func:`stereo_packet`, :func:`embed_xmp`) puts the packet VR players read into
m360's top-bottom stereo files: ``GPano:ProjectionType="equirectangular"``,
``GPano:UsePanoramaViewer="True"``, ``GPano:StereoMode="top-bottom"`` (the spelling of Google's
spherical metadata, as OmniCapture and other ODS renderers write it), the full panorama and the
cropped area both one eye's size (W × H, left 0, top 0), and ``GPano:StitchingSoftware``. JPEG:
an APP1 segment ``http://ns.adobe.com/xap/1.0/\0`` + packet after the JFIF header; PNG: an
``iTXt`` chunk with keyword ``XML:com.adobe.xmp`` after ``IHDR``.
"""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
import zlib
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
    stereo = values.get("StereoMode", "mono").strip().lower()
    if stereo not in ("", "mono"):
        raise ReadError(
            f"{name}: GPano StereoMode is {values['StereoMode']!r}: a stereo panorama (two eyes "
            "in one image); m360 estimates depth from one monoscopic panorama, e.g. one eye's"
        )
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


# --------------------------------------------------------------------------------------------
# Writing: the stereo files' packet.

#: ``GPano:StereoMode`` of m360's stereo files: left eye on top, right eye below.
STEREO_MODE = "top-bottom"
_XMP_JPEG_HEADER = b"http://ns.adobe.com/xap/1.0/\x00"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Largest XMP packet one JPEG APP1 segment holds (65535 − 2 length bytes − the header).
_MAX_JPEG_PACKET = 65535 - 2 - len(_XMP_JPEG_HEADER)


def stereo_packet(width: int, height: int, software: str = "m360") -> bytes:
    """Return the XMP packet of a top-bottom stereo ERP image of two ``width`` × ``height`` eyes.

    The fields are listed in the module docstring; the file is ``width`` × ``2 * height``.
    """
    fields = {
        "UsePanoramaViewer": "True",
        "ProjectionType": "equirectangular",
        "StereoMode": STEREO_MODE,
        "FullPanoWidthPixels": str(int(width)),
        "FullPanoHeightPixels": str(int(height)),
        "CroppedAreaImageWidthPixels": str(int(width)),
        "CroppedAreaImageHeightPixels": str(int(height)),
        "CroppedAreaLeftPixels": "0",
        "CroppedAreaTopPixels": "0",
        "StitchingSoftware": software,
    }
    attributes = "".join(f'\n    GPano:{key}="{_escape(value)}"' for key, value in fields.items())
    text = (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about=""\n'
        f'    xmlns:GPano="{GPANO_NS}"{attributes}/>\n'
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        '<?xpacket end="w"?>'
    )
    return text.encode("utf-8")


def _escape(value: str) -> str:
    return (
        value.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")
    )


def embed_xmp(data: bytes, packet: bytes) -> bytes:
    """Return the encoded JPEG or PNG ``data`` with the XMP ``packet`` added (see module doc).

    Raises
    ------
    InputError
        ``data`` is neither a JPEG nor a PNG, or the packet does not fit a JPEG segment.
    """
    from ..errors import InputError

    if data.startswith(b"\xff\xd8"):
        if len(packet) > _MAX_JPEG_PACKET:
            raise InputError(f"an XMP packet of {len(packet)} bytes does not fit a JPEG APP1")
        segment = _XMP_JPEG_HEADER + packet
        app1 = b"\xff\xe1" + struct.pack(">H", len(segment) + 2) + segment
        at = 2
        if data[2:4] == b"\xff\xe0":  # JFIF's APP0 stays first
            at = 4 + struct.unpack(">H", data[4:6])[0]
        return data[:at] + app1 + data[at:]
    if data.startswith(_PNG_SIGNATURE):
        body = b"XML:com.adobe.xmp\x00\x00\x00\x00\x00" + packet  # no compression, no language
        chunk = b"iTXt" + body
        itxt = struct.pack(">I", len(body)) + chunk + struct.pack(">I", zlib.crc32(chunk))
        ihdr_end = len(_PNG_SIGNATURE) + 8 + struct.unpack(">I", data[8:12])[0] + 4
        return data[:ihdr_end] + itxt + data[ihdr_end:]
    raise InputError("embed_xmp takes an encoded JPEG or PNG")
