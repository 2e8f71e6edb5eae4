"""Masks: ERP pixels that take no part in the estimate (tripod, camera operator, sky, no data).

A mask is an ERP boolean array, True = use. :func:`nadir` and :func:`zenith` are caps around the
poles that fit any resolution (they become arrays with :meth:`Cap.to_array`); user masks are
(H, W) bool arrays of the panorama's size. ``m360.estimate(rgb, mask=...)`` takes one of them or
a list (all must agree: a pixel is used when every mask uses it).

A masked ERP pixel leaves the method at both ends: :func:`tangent_mask` maps the ERP mask onto
the tangents (a tangent pixel is used only when all four ERP pixels its bilinear sample reads are
used), so the core sets those tangent pixels to NaN before alignment and blending and they
contribute to neither; the final ERP maps are NaN on the masked pixels.

``sky="nan"`` in :func:`m360.estimate` marks as sky every pixel whose final disparity is at or
below :data:`SKY_THRESHOLD` times the 90th percentile of the disparities (farther than 50× the
distance of the nearest tenth of the scene, or at/behind infinity) and makes it NaN instead of a
huge fake distance. A percentile of the near part, not the median: half of an outdoor panorama
may be sky.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validate import as_array, number
from ..errors import InputError

__all__ = [
    "SKY_MODES",
    "SKY_THRESHOLD",
    "Cap",
    "erp_mask",
    "nadir",
    "sky",
    "tangent_mask",
    "zenith",
]

#: ``sky=`` choices of :func:`m360.estimate`: keep every depth, or NaN for the sky.
SKY_MODES = ("keep", "nan")
#: Sky: disparity ≤ SKY_THRESHOLD · (90th percentile of the finite disparities).
SKY_THRESHOLD = 0.02
_SKY_PERCENTILE = 90.0


@dataclass(frozen=True)
class Cap:
    """A polar cap: every pixel within ``degrees`` of the nadir (bottom) or zenith (top) pole."""

    pole: str
    degrees: float

    def to_array(self, height: int, width: int) -> np.ndarray:
        """(H, W) bool mask, True = use (outside the cap): row centres beyond the cap's edge."""
        lat = np.pi / 2 - np.pi * (np.arange(height) + 0.5) / height
        edge = np.pi / 2 - np.radians(self.degrees)
        rows = lat > -edge if self.pole == "nadir" else lat < edge
        return np.repeat(rows[:, None], width, axis=1)


def _cap(pole: str, degrees: Any) -> Cap:
    return Cap(pole, number(degrees, f"{pole} cap (degrees)", low=0.0, high=180.0))


def nadir(degrees: float) -> Cap:
    """Mask out the cap within ``degrees`` of the bottom pole (tripod, the operator's feet).

    Parameters
    ----------
    degrees : float
        Angular radius of the cap, 0-180.

    Returns
    -------
    Cap
    """
    return _cap("nadir", degrees)


def zenith(degrees: float) -> Cap:
    """Mask out the cap within ``degrees`` of the top pole (a stitching seam, a ceiling lamp).

    Parameters
    ----------
    degrees : float
        Angular radius of the cap, 0-180.

    Returns
    -------
    Cap
    """
    return _cap("zenith", degrees)


def erp_mask(mask: Any, height: int, width: int) -> np.ndarray:
    """Combine masks (a Cap, an (H, W) bool array, or a list of them) into one (H, W) bool array.

    Raises
    ------
    InputError
        An array of another size or dtype, or an unknown kind of mask.
    """
    items: Sequence[Any] = mask if isinstance(mask, (list, tuple)) else [mask]
    out = np.ones((height, width), bool)
    for item in items:
        if isinstance(item, Cap):
            out &= item.to_array(height, width)
            continue
        array = as_array(item, "mask")
        if array.shape != (height, width):
            raise InputError(
                f"an ERP mask must have the panorama's shape {(height, width)}, got {array.shape}"
            )
        if array.dtype != np.bool_:
            raise InputError(f"a mask must be a bool array (True = use), got dtype {array.dtype}")
        out &= array
    return out


def tangent_mask(mask: np.ndarray, layout: Any) -> np.ndarray:
    """Map an ERP mask onto the tangents: (N, h, w) bool, True = use.

    A tangent pixel is used when its whole bilinear footprint in the ERP is used.
    """
    from ..geometry.layout import erp_to_tangents

    sampled = erp_to_tangents(mask.astype(np.float32), layout)
    return sampled >= 1.0 - 1e-6


def sky(disparity: np.ndarray, threshold: float = SKY_THRESHOLD) -> np.ndarray:
    """(H, W) bool: True where ``disparity`` ≤ ``threshold`` · 90th percentile of the finite ones.

    Parameters
    ----------
    disparity : (H, W) float
        Final spherical disparity (relative or metric).
    threshold : float
        Fraction of the 90th percentile of the disparities (0-1).

    Returns
    -------
    np.ndarray
        The sky (to be made NaN), False where the disparity is NaN.
    """
    limit = number(threshold, "sky threshold", low=0.0, high=1.0)
    values = np.asarray(disparity)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(values.shape, bool)
    near = float(np.percentile(values[finite], _SKY_PERCENTILE))
    with np.errstate(invalid="ignore"):
        return finite & (values <= limit * near)  # type: ignore[no-any-return]


@dataclass(frozen=True)
class PartialPanorama:
    """A cropped capture placed in its full ERP canvas (see :func:`partial_panorama`).

    Attributes
    ----------
    rgb : (H, W, 3) uint8
        The full canvas, black outside the capture.
    mask : (H, W) bool
        True on the captured pixels (pass it as ``mask=`` to :func:`m360.estimate`).
    crop : dict
        Full size, cropped size and offset (the sidecar's ``crop``).
    """

    rgb: np.ndarray
    mask: np.ndarray
    crop: dict[str, Any]


def partial_panorama(path: str | os.PathLike[str]) -> PartialPanorama | None:
    """Read an image with GPano XMP crop metadata and place it in its full ERP canvas.

    Only the GPano fields that place the crop are read (full panorama width/height, cropped
    area size and offset); columns wrap across the 0/360° seam.

    Parameters
    ----------
    path : path
        The image file.

    Returns
    -------
    PartialPanorama or None
        None when the file carries no GPano crop.

    Raises
    ------
    ReadError
        Unreadable file, or metadata that is incomplete, not equirectangular or contradicts the
        image's pixel size.
    """
    from ..io.decode import decode_image, read_input_bytes
    from ..io.gpano import place, read_gpano

    data = read_input_bytes(path)
    crop = read_gpano(data, str(path))
    if crop is None:
        return None
    canvas, mask = place(decode_image(data, path), crop, str(path))
    return PartialPanorama(canvas, mask, crop.as_dict())
