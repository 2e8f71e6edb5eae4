"""Stereo 360° panoramas for VR headsets: :func:`stereo` and the top-bottom file.

Omnidirectional stereo (ODS): the eye ray of ERP pixel (λ, φ) leaves from the point of a
horizontal circle of diameter ``ipd`` (the viewing circle) where, seen from above, the ray is
tangent to the circle, on the left of the viewing direction for the left eye and on its right
for the right eye. Each eye's panorama is made from the centre panorama and its depth by forward
warping in the Rust core (``m360_core::stereo``; docs/vr.md): the panorama is a mesh on its pixel
grid, closed across the 0/360° seam; every grid triangle that lies on one surface (depths within
``max_depth_ratio``) is drawn into the eye's panorama with a z-buffer (nearest wins); pixels
without a depth are at infinity; the IPD fades to 0 towards the poles from ``pole_fade``
degrees of latitude; the pixels no triangle covers (disocclusions: what the eye sees and the
centre cannot) are filled along their row from the background side, never from the foreground.

ODS needs depth in metres, the IPD's unit. A result in metres (a metric model, or
``scale=m360.scale...``) is used as it is. A relative result is scaled so that its median
distance is ``median_distance`` metres (default :data:`DEFAULT_MEDIAN_DISTANCE`, a room's),
with a warning: the strength of the stereo effect then rests on that assumption. A plain
(H, W) array is taken as distances in metres.

The file (``formats=("stereo",)`` of :func:`m360.save`) stacks the eyes top-bottom, the left eye
on top, into ``STEM.stereo.jpg`` (``stereo-png``: ``STEM.stereo.png``) carrying Google's GPano
XMP with ``StereoMode="top-bottom"`` (:func:`m360.io.gpano.stereo_packet` lists every field).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypedDict

import cv2
import numpy as np

from .._keywords import Option, document, resolved
from .._validate import as_array, erp_map, number
from ..errors import InputError
from . import gpano
from .files import STEREO_FILES, atomic_path

__all__ = [
    "DEFAULT_IPD",
    "DEFAULT_MEDIAN_DISTANCE",
    "JPEG_QUALITY",
    "StereoKeywords",
    "StereoResult",
    "stereo",
    "write_stereo",
]

#: Default interpupillary distance, metres (the adult mean is about 63-64 mm).
DEFAULT_IPD = 0.064
#: Median distance (metres) a relative depth map is scaled to: a typical room's.
DEFAULT_MEDIAN_DISTANCE = 2.5
#: JPEG quality of ``STEM.stereo.jpg``.
JPEG_QUALITY = 95


def _core_defaults() -> dict[str, float]:
    from .._core import ods_defaults

    return dict(ods_defaults())


#: The core's defaults and limits of the warp (``m360_core::stereo``): written once, there.
_CORE = _core_defaults()


def _ipd(value: Any, name: str) -> float:
    return number(value, name, low=0.0, high=_CORE["max_ipd"])


def _pole_fade(value: Any, name: str) -> float:
    return number(value, name, low=0.0, high=90.0)


def _median_distance(value: Any, name: str) -> float:
    result = number(value, name, low=0.0, high=1e6)
    if not result > 0:
        raise InputError(f"{name} must be > 0 metres, got {value!r}")
    return result


@document
class StereoKeywords(TypedDict, total=False):
    """Options of the stereo outputs: :func:`m360.stereo`, formats ``stereo``, ``stereo-png``."""

    ipd: Annotated[
        float | None,
        Option(
            f"interpupillary distance of the stereo outputs in metres (default {DEFAULT_IPD})",
            check=_ipd,
            parse=float,
            metavar="M",
            default=DEFAULT_IPD,
        ),
    ]
    pole_fade: Annotated[
        float | None,
        Option(
            "latitude in degrees from which the stereo IPD fades to 0 at the poles (default "
            f"{_CORE['pole_fade']:g}; 90: no fade)",
            check=_pole_fade,
            parse=float,
            metavar="DEG",
            default=_CORE["pole_fade"],
        ),
    ]
    median_distance: Annotated[
        float | None,
        Option(
            "scale the depth so its median distance is this many metres before the stereo warp "
            f"(default: metric depth as it is, relative depth to {DEFAULT_MEDIAN_DISTANCE} m "
            "with a warning)",
            check=_median_distance,
            parse=float,
            metavar="M",
        ),
    ]


@dataclass(frozen=True)
class StereoResult:
    """An ODS pair (see :func:`stereo`).

    Attributes
    ----------
    left, right : (H, W, C) uint8
        The eyes' equirectangular panoramas.
    left_holes, right_holes : (H, W) bool
        Pixels filled (disocclusions) rather than seen from the centre panorama.
    ipd : float
        Interpupillary distance, metres.
    pole_fade : float
        Latitude (degrees) from which the IPD fades to 0 at the poles.
    depth_scale : float
        Factor the depth was multiplied by (1 for metric depth used as it is).
    assumption : str or None
        What was assumed about the depth's scale (None: metric depth used as it is).
    """

    left: np.ndarray
    right: np.ndarray
    left_holes: np.ndarray
    right_holes: np.ndarray
    ipd: float
    pole_fade: float
    depth_scale: float = 1.0
    assumption: str | None = None

    @property
    def holes(self) -> np.ndarray:
        """(H, W, 2) bool: ``[..., 0]`` the left eye's filled pixels, ``[..., 1]`` the right's."""
        return np.stack([self.left_holes, self.right_holes], axis=-1)

    @property
    def filled_fraction(self) -> float:
        """Share of the pixels of both eyes that were filled rather than seen."""
        return float((self.left_holes.mean() + self.right_holes.mean()) / 2)

    def top_bottom(self) -> np.ndarray:
        """(2H, W, C) uint8: the left eye on top of the right one (the file's layout)."""
        return np.concatenate([self.left, self.right], axis=0)

    def describe(self) -> dict[str, Any]:
        """JSON-ready description (the sidecar's ``stereo``)."""
        return {
            "model": "omnidirectional stereo (ODS), forward warped; docs/vr.md",
            "layout": "top-bottom, left eye on top",
            "ipd_m": self.ipd,
            "pole_fade_deg": self.pole_fade,
            "depth_scale": self.depth_scale,
            "assumption": self.assumption,
            "filled_fraction": {
                "left": float(self.left_holes.mean()),
                "right": float(self.right_holes.mean()),
            },
            "xmp": {"namespace": gpano.GPANO_NS, "StereoMode": gpano.STEREO_MODE},
        }


def _depth_of(source: Any) -> tuple[np.ndarray, str]:
    """Return the (H, W) float32 distance map of a result, a saved stem or an array, and units."""
    if isinstance(source, (str, os.PathLike)):
        from .reading import load

        source = load(source)
    if hasattr(source, "depth"):
        values, units, name = (
            source.depth,
            str(getattr(source, "units", "relative")),
            "result.depth",
        )
    else:
        values, units, name = source, "metres", "depth"
    array = erp_map(values, name)
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(array, dtype=np.float32), units


def _scale(
    depth: np.ndarray, units: str, median_distance: float | None
) -> tuple[float, str | None]:
    """Return the factor that puts ``depth`` in metres, and the assumption it rests on."""
    if median_distance is None and units != "relative":
        return 1.0, None
    target = DEFAULT_MEDIAN_DISTANCE if median_distance is None else median_distance
    with np.errstate(invalid="ignore"):
        usable = depth[np.isfinite(depth) & (depth > 0)]
    if not usable.size:
        return 1.0, "no valid depth: every pixel at infinity (the eyes equal the input)"
    factor = target / float(np.median(usable))
    assumption = f"depth scaled so that its median distance is {target:g} m"
    if median_distance is None:
        warnings.warn(
            f"stereo from relative depth: {assumption} (an assumption; give a metric scale, "
            "e.g. scale=m360.scale.camera_height(1.6), or median_distance=)",
            UserWarning,
            stacklevel=3,
        )
        assumption += " (assumed: the depth is relative)"
    return factor, assumption


def stereo(
    source: Any,
    rgb: Any,
    ipd: float = DEFAULT_IPD,
    *,
    pole_fade: float | None = None,
    median_distance: float | None = None,
    max_depth_ratio: float | None = None,
) -> StereoResult:
    """Make the left and right eye panoramas (omnidirectional stereo) of a panorama.

    Parameters
    ----------
    source : EstimateResult, saved stem or (H, W) array
        The depth: an :func:`m360.estimate` result (its ``depth`` and ``units``), a path given
        to :func:`m360.load`, or a plain (H, W) float array of radial distances in metres (NaN
        or ≤ 0: no depth, drawn at infinity).
    rgb : (H, W, C) uint8
        The panorama (float in [0, 1] accepted).
    ipd : float
        Interpupillary distance in metres (0: both eyes are the input).
    pole_fade : float, optional
        Latitude in degrees from which the IPD fades (half cosine) to 0 at the poles
        (default 60; 90: no fade).
    median_distance : float, optional
        Scale the depth so that its median distance is this many metres. Default: metric depth
        as it is; relative depth to :data:`DEFAULT_MEDIAN_DISTANCE`, with a ``UserWarning``.
    max_depth_ratio : float, optional
        Neighbouring pixels whose depths differ by more than this ratio are not one surface
        (an occlusion edge; default 1.1, as :func:`m360.to_mesh`).

    Returns
    -------
    StereoResult
        ``left``, ``right``, ``holes`` (what was filled), ``filled_fraction``.

    Raises
    ------
    InputError
        Shapes that do not match, or an option out of its range.
    """
    from .._core import ods_stereo
    from .mesh import _rgb_of

    options = resolved(
        {"ipd": ipd, "pole_fade": pole_fade, "median_distance": median_distance}, StereoKeywords
    )
    ratio = _CORE["max_depth_ratio"] if max_depth_ratio is None else max_depth_ratio
    ratio = number(ratio, "max_depth_ratio", low=1.0, high=1e6)
    depth, units = _depth_of(source)
    colours = _rgb_of(rgb, depth.shape) if as_array(rgb, "rgb").ndim == 3 else None
    if colours is None:
        raise InputError(f"rgb must be an (H, W, 3) panorama, got shape {np.shape(rgb)}")
    factor, assumption = _scale(depth, units, options["median_distance"])
    if factor != 1.0:
        depth = depth * np.float32(factor)
    left, right, left_holes, right_holes, _, _ = ods_stereo(
        np.ascontiguousarray(colours), depth, options["ipd"], options["pole_fade"], ratio
    )
    return StereoResult(
        left=left,
        right=right,
        left_holes=left_holes,
        right_holes=right_holes,
        ipd=options["ipd"],
        pole_fade=options["pole_fade"],
        depth_scale=factor,
        assumption=assumption,
    )


def write_stereo(path: str | os.PathLike[str], pair: StereoResult, fmt: str = "stereo") -> Path:
    """Write ``pair`` top-bottom (left eye on top) with GPano stereo XMP, atomically.

    ``fmt`` ``"stereo"``: JPEG (quality :data:`JPEG_QUALITY`), ``"stereo-png"``: PNG.
    """
    if fmt not in STEREO_FILES:
        raise InputError(f"stereo format {fmt!r} is not one of {tuple(STEREO_FILES)}")
    height, width = pair.left.shape[:2]
    image = pair.top_bottom()
    if image.ndim == 3 and image.shape[2] >= 3:  # OpenCV writes BGR
        image = cv2.cvtColor(
            image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4 else cv2.COLOR_RGB2BGR
        )
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if fmt == "stereo" else []
    ok, encoded = cv2.imencode(".jpg" if fmt == "stereo" else ".png", image, params)
    if not ok:
        raise InputError(f"cannot encode a {width}x{2 * height} stereo image")
    from .._core import __version__

    data = gpano.embed_xmp(
        encoded.tobytes(), gpano.stereo_packet(width, height, f"m360 {__version__}")
    )
    target = Path(path)
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return target
