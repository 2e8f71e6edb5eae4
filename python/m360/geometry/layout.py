"""Tangent layouts, their compiled plans, and resampling between the ERP image and its tangents.

Conventions (docs/conventions.md): world frame x right, y down, z forward. ERP pixel (row i,
column j) of an H x 2H image looks at longitude 2π(j+0.5)/W − π and latitude π/2 − π(i+0.5)/H. A
tangent camera maps a world direction d to X = R d and, when X_z > 0, to pixel
x = fx X_x/X_z + cx, y = fy X_y/X_z + cy, pixel centres at integer coordinates.
"""

from __future__ import annotations

import hashlib
import sys
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .. import _core
from .._compat import renamed
from .._validate import (
    MAX_ERP_WIDTH,
    as_array,
    check_erp_shape,
    check_shape,
    float32_array,
    integer,
    number,
)
from ..errors import InputError

__all__ = [
    "DEFAULT_PADDING",
    "PAPER_PADDING",
    "Layout",
    "TangentCamera",
    "TangentSampling",
    "clear_plan_cache",
    "default_layout",
    "erp_to_tangents",
    "pixel_degrees",
    "tangents_to_erp",
]

#: How :func:`tangents_to_erp` reads the faces (the core's ``CHOICES["sampling"]``).
TangentSampling = Literal["bilinear", "depth_edges"]

#: Padding of the icosahedron layout when none is given, in gnomonic units: the layout
#: :func:`m360.estimate` runs on. Wider than the paper's 0.3, so that most pixels are seen by three
#: or more tangents and the consensus blend can outvote one tangent's content error
#: (docs/method.md, "More overlap").
DEFAULT_PADDING = 0.7
#: The paper's padding (``padding="paper"`` names it): the 20 tangents of 400x346 at W = 2048.
PAPER_PADDING = 0.3


@dataclass(frozen=True, eq=False)
class TangentCamera:
    """A pinhole tangent camera.

    Attributes
    ----------
    rotation : (3, 3) float64
        World → camera rotation (rows: camera x, y, z axes in world coordinates).
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels (the principal point is where the tangent
        point falls; for the icosahedron it is off the image centre vertically).
    width, height : int
        Image size in pixels.
    face : (K, 2) float64 or None
        The polygon this camera is responsible for, in gnomonic coordinates (the un-padded
        icosahedron face triangle), or None.
    """

    rotation: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    face: np.ndarray | None = None

    @property
    def axis(self) -> np.ndarray:
        """(3,) world direction of the optical axis."""
        return self.rotation[2].copy()  # type: ignore[no-any-return]  # numpy stubs: Any

    def project(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel positions ``(x, y)`` of world directions (..., 3), and whether each is in front."""
        cam = np.asarray(directions, dtype=np.float64) @ self.rotation.T
        z = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = self.fx * cam[..., 0] / z + self.cx
            y = self.fy * cam[..., 1] / z + self.cy
        return x, y, z > 0


@dataclass(frozen=True, eq=False)
class Layout:
    """Tangent cameras covering the sphere, for one ERP size.

    Build the paper's layout with :meth:`icosahedron`, or any other with :meth:`from_cameras`.
    Layouts are immutable; two layouts with the same cameras and ERP size share one cached plan
    (the precomputed sampling maps).

    Attributes
    ----------
    erp_shape : (int, int)
        (H, W) of the ERP images this layout serves, W == 2H.
    cameras : tuple of TangentCamera
        All with the same image size.
    padding : float or None
        The icosahedron padding in gnomonic units, None for other layouts.
    subdivisions : int or None
        How many times the icosahedron's faces were split into 4 (0 = the paper's 20 faces),
        None for other layouts.
    """

    erp_shape: tuple[int, int]
    cameras: tuple[TangentCamera, ...]
    padding: float | None = None
    name: str = "custom"
    key: str = field(default="", repr=False)
    subdivisions: int | None = None

    @classmethod
    def icosahedron(
        cls,
        erp_width: int,
        padding: float | str | None = None,
        tangent_width: int | None = None,
        subdivisions: int = 0,
    ) -> Layout:
        """Make the paper's layout: 20 cameras, one per icosahedron face (or per sub-face).

        Each camera looks at its face centroid with no roll (image x = local east, y = local
        south); its image is the bounding box of the face triangle with every edge pushed out by
        ``padding`` gnomonic units (≈ 99.5° x 88° at 0.3), with square pixels.

        With ``subdivisions`` = n > 0 every face is split n times into 4 at its edge midpoints
        (pushed onto the sphere): 80 cameras at n = 1, 320 at n = 2, each looking at its
        sub-face's centroid. The sub-faces differ a little in shape, so all images take the
        largest padded bounding box; by default the pixels keep the angular size of the paper's
        layout at the same ``erp_width`` (209x189 at W = 2048, padding 0.15, n = 1). Sub-faces
        are about half as wide, so ``padding`` 0.15 at n = 1 overlaps them about as much, in
        relative terms, as 0.3 does the 20 faces. :func:`m360.stitch` and :func:`m360.estimate`
        align them with grids of half the nodes per side by default (2x2 → 4x4 at n = 1; the
        4x3 → 8x7 grids per smaller tile are twice as fine in angle and measured 2-5x slower
        for the same accuracy). Layouts that would let more than 16 tangents see one direction
        (n = 1 with padding above about 0.3) are refused.

        Parameters
        ----------
        erp_width : int
            Width W of the ERP images (height W/2); even, in
            [``LIMITS["min_erp_width"]``, ``LIMITS["max_erp_width"]``] of ``m360._core``.
        padding : float or "paper", optional
            Edge offset in gnomonic units. Default :data:`DEFAULT_PADDING` (0.7, the layout
            :func:`m360.estimate` uses); ``"paper"`` (or :data:`PAPER_PADDING`) is the paper's
            p = 0.3. Subdivided layouts default to 0.3: at 0.7 more than 16 of their smaller
            tangents would see one direction.
        tangent_width : int, optional
            Tangent width in pixels; default 400 at W = 2048, scaled linearly (800x693 at 4K);
            with subdivisions, the width that keeps the paper's angular pixel size.
        subdivisions : int
            Times each face is split into 4, in [0, ``LIMITS["max_subdivisions"]``]; 0 is the
            paper's layout.
        """
        # Types here (machine-sized integers); the core judges the values (_core.LIMITS).
        erp_width = integer(erp_width, "erp_width", low=0, high=sys.maxsize)
        subdivisions = integer(subdivisions, "subdivisions", low=0, high=sys.maxsize)
        padding = _padding(padding, subdivisions)
        if tangent_width is not None:
            tangent_width = integer(tangent_width, "tangent_width", low=0, high=sys.maxsize)
        rotations, intrinsics, (h, w), faces = _core.icosahedron_cameras(
            erp_width, float(padding), tangent_width, subdivisions
        )
        cameras = tuple(
            TangentCamera(
                rotation=_frozen(rotations[k]),
                fx=float(intrinsics[k, 0]),
                fy=float(intrinsics[k, 1]),
                cx=float(intrinsics[k, 2]),
                cy=float(intrinsics[k, 3]),
                width=w,
                height=h,
                face=_frozen(faces[k]),
            )
            for k in range(len(rotations))
        )
        return cls._make(
            (erp_width // 2, erp_width), cameras, float(padding), "icosahedron", subdivisions
        )

    @classmethod
    def from_cameras(cls, cameras: Sequence[TangentCamera], erp_shape: tuple[int, int]) -> Layout:
        """Make a layout of user-given cameras, all of one image size.

        For ERP images of ``erp_shape`` = (H, W).
        """
        if isinstance(cameras, (str, bytes)) or not isinstance(cameras, Sequence) or not cameras:
            raise InputError("a layout needs a non-empty sequence of TangentCamera")
        if not (isinstance(erp_shape, (tuple, list)) and len(erp_shape) == 2):
            raise InputError(f"erp_shape must be (H, W), got {erp_shape!r}")
        height, width = (_positive_int(v, "erp_shape") for v in erp_shape)
        check_erp_shape(height, width, "erp_shape")
        if width > MAX_ERP_WIDTH:
            raise InputError(f"erp_shape {erp_shape!r} is wider than {MAX_ERP_WIDTH} pixels")
        checked = []
        for k, cam in enumerate(cameras):
            if not isinstance(cam, TangentCamera):
                raise InputError(f"camera {k} is a {type(cam).__name__}, not a TangentCamera")
            checked.append(_checked_camera(cam, k))
        size = (checked[0].width, checked[0].height)
        for k, cam in enumerate(checked):
            if (cam.width, cam.height) != size:
                raise InputError(
                    f"camera {k} is {cam.width}x{cam.height} but camera 0 is {size[0]}x{size[1]}:"
                    " all tangent images of a layout must have one size"
                )
        return cls._make((height, width), tuple(checked), None, "custom")

    @classmethod
    def _make(
        cls,
        erp_shape: tuple[int, int],
        cameras: tuple[TangentCamera, ...],
        padding: float | None,
        name: str,
        subdivisions: int | None = None,
    ) -> Layout:
        digest = hashlib.sha1(repr(erp_shape).encode())
        for cam in cameras:
            digest.update(np.asarray(cam.rotation, dtype=np.float64).tobytes())
            digest.update(
                np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height]).tobytes()
            )
        return cls(erp_shape, cameras, padding, name, digest.hexdigest(), subdivisions)

    @property
    def tangent_shape(self) -> tuple[int, int]:
        """(h, w) of every tangent image."""
        return self.cameras[0].height, self.cameras[0].width

    def network_pixel_degrees(self, network_width: int) -> float:
        """Give the angle, in degrees, one pixel of a network spans at a tile's centre.

        A network that sees each tile (``tangent_shape[1]`` pixels wide) at ``network_width``
        pixels resolves no finer than this, whatever the ERP width (docs/method.md, "Where the
        detail comes from"). The first camera's: the icosahedron's tiles share their pixel
        size.
        """
        network_width = integer(network_width, "network_width", low=1, high=sys.maxsize)
        camera = self.cameras[0]
        step = camera.width / network_width  # tile pixels per network pixel
        return float(np.degrees(2.0 * np.arctan(step / (2.0 * camera.fx))))

    def prepare(self) -> Layout:
        """Build the plan of this layout now, instead of in the first call that needs it.

        Every map :func:`m360.estimate` needs with its default options is built: tangent and
        ERP taps, the frustum weights, the alignment samples.

        A later call on the layout then costs as much as a warm one. Plans live in a small
        in-process cache (:func:`plan_for`) and, unless turned off, on disk under
        ``$M360_HOME/plans`` (:mod:`m360.plan_cache`): maps found there are loaded instead of
        built, and maps built are written there, so a later process loads them too.

        Returns
        -------
        Layout
            ``self``, so ``layout = Layout.icosahedron(16384).prepare()`` works.
        """
        plan_for(self).prepare("estimate")
        return self

    def __len__(self) -> int:
        return len(self.cameras)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Layout) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)

    def __repr__(self) -> str:
        h, w = self.tangent_shape
        pad = "" if self.padding is None else f", padding={self.padding}"
        if self.subdivisions:
            pad += f", subdivisions={self.subdivisions}"
        return (
            f"Layout.{self.name}(erp_shape={self.erp_shape}, {len(self)} cameras of {w}x{h}{pad})"
        )


def default_layout(
    erp_width: int, padding: float | str | None = None, subdivisions: int | None = None
) -> Layout:
    """Return the layout :func:`m360.estimate` and the batch engines use when none is given.

    ``Layout.icosahedron(erp_width, padding, subdivisions=subdivisions)``: 20 tangents at
    :data:`DEFAULT_PADDING` (0.7) unless ``padding`` or ``subdivisions`` is given (the options
    of :func:`m360.estimate` and :func:`m360.batch.run`); ``padding="paper"`` is the paper's
    layout, ``subdivisions=1`` its 80 smaller tangents (padding 0.3 by default).
    """
    return Layout.icosahedron(erp_width, padding, subdivisions=subdivisions or 0)


def pixel_degrees(layout: Layout | None, width: int) -> float:
    """Give the angle, in degrees, one pixel of an image ``width`` pixels wide spans.

    A tangent network's input on ``layout``'s tiles (at a tile's centre,
    :meth:`Layout.network_pixel_degrees`), or with ``layout=None`` an ERP image (a panoramic
    network's input, a prior map) on its equator: 360° over its width.
    """
    if layout is not None:
        return layout.network_pixel_degrees(width)
    return 360.0 / integer(width, "width", low=1, high=sys.maxsize)


def _padding(padding: float | str | None, subdivisions: int) -> float:
    """Resolve ``padding`` for ``Layout.icosahedron``: a number, ``"paper"``, or the default."""
    if padding is None:
        return DEFAULT_PADDING if subdivisions == 0 else PAPER_PADDING
    if isinstance(padding, str):
        if padding == "paper":
            return PAPER_PADDING
        raise InputError(f"padding must be a number or 'paper' (the paper's 0.3), got {padding!r}")
    return number(padding, "padding")


# --------------------------------------------------------------------------------------------
# Plans: the compiled sampling maps, one per layout, reused across images.

_PLAN_CACHE_SIZE = 4
_plans: OrderedDict[str, _core.Plan] = OrderedDict()
_plans_lock = threading.Lock()


def plan_for(layout: Layout) -> _core.Plan:
    """Get the cached compiled plan of ``layout`` (maps are built lazily on first use).

    Safe to call from many threads at once (docs/architecture.md, plan cache): the lock guards
    only the cache's bookkeeping, never the core's work, so threads wanting other layouts do
    not wait for each other; two threads missing the same layout at once both build a plan
    and the first one stored wins.
    """
    from . import plan_cache

    with _plans_lock:
        plan = _plans.get(layout.key)
        if plan is not None:
            _plans.move_to_end(layout.key)
    if plan is not None:
        plan.set_cache_dir(plan_cache.current())
        return plan
    rotations = np.stack([np.asarray(c.rotation, dtype=np.float64) for c in layout.cameras])
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in layout.cameras], dtype=np.float64)
    built = _core.Plan(layout.erp_shape, rotations, intrinsics, layout.tangent_shape)
    evicted = []
    with _plans_lock:
        plan = _plans.setdefault(layout.key, built)
        _plans.move_to_end(layout.key)
        while len(_plans) > _PLAN_CACHE_SIZE:
            evicted.append(_plans.popitem(last=False))
    del evicted  # the evicted plans' maps are freed here, outside the lock
    # On disk under $M360_HOME/plans unless turned off (m360.plan_cache); the switch and the
    # folder are read on every call, so changing them applies to plans already in memory.
    folder = plan_cache.current()
    plan.set_cache_dir(folder)
    if folder is not None:
        plan_cache.trim()  # a new plan may write files: keep the folder under its limit
    return plan


def clear_plan_cache() -> None:
    """Drop every cached plan (frees their sampling maps)."""
    with _plans_lock:
        dropped = list(_plans.values())
        _plans.clear()
    del dropped  # freed outside the lock


# --------------------------------------------------------------------------------------------
# Resampling.


def erp_to_tangents(erp: np.ndarray, layout: Layout | None = None) -> np.ndarray:
    """Sample an ERP image into the tangent images of ``layout``.

    Bilinear, wrapping in longitude and across the poles.

    Parameters
    ----------
    erp : (H, W) or (H, W, C) uint8 or float32 array, W == 2H, C in 1..4
        float64 is converted to float32. NaN propagates to the samples that touch it.
    layout : Layout, optional
        Default: ``Layout.icosahedron(W)``. Its ``erp_shape`` must be (H, W).

    Returns
    -------
    (N, h, w) or (N, h, w, C) array of the input dtype.
    """
    array = as_array(erp, "erp")
    if array.ndim not in (2, 3):
        raise InputError(f"erp must be (H, W) or (H, W, C), got shape {array.shape}")
    if array.ndim == 3 and not 1 <= array.shape[2] <= 4:
        raise InputError(
            f"erp has {array.shape[2]} channels, expected 1 to 4 (shape {array.shape})"
        )
    height, width = array.shape[:2]
    check_erp_shape(height, width, "erp")
    layout = _layout_for(layout, height, width)
    if array.dtype == np.uint8:
        data = np.ascontiguousarray(array)
    elif array.dtype.kind == "f":
        data = float32_array(array, "erp")
    else:
        raise InputError(
            f"erp has dtype {array.dtype}; supported: uint8, float32 (float64 converted)"
        )
    planar = data.ndim == 2
    out = plan_for(layout).erp_to_tangents(data[..., None] if planar else data)
    return out[..., 0] if planar else out


@renamed(tiles="tangents")
def tangents_to_erp(
    tangents: np.ndarray,
    layout: Layout,
    *,
    sampling: TangentSampling = "bilinear",
) -> np.ndarray:
    """Map each tangent image onto the ERP grid.

    Every ERP pixel whose ray lands on a tangent image (in front of it) gets that image's value,
    sampled bilinearly at the exact projected position.

    Parameters
    ----------
    tangents : (N, h, w) float32 array
        One image per camera of ``layout``; NaN marks invalid pixels.
    layout : Layout
        The layout the tangents belong to.
    sampling : {"bilinear", "depth_edges"}
        ``"bilinear"`` (default) for any quantity. ``"depth_edges"`` reads disparity as the
        blends of :func:`m360.stitch` do (all but ``nn``): bilinear, but where the four
        neighbours span a jump of more than 5 % only the side with most of the weight, so no
        value lies between the two sides of a depth edge (docs/method.md, "Sampling across
        depth edges").

    Returns
    -------
    numpy.ndarray
        (N, H, W) float32, NaN where a face does not see the pixel or a bilinear neighbour is
        NaN.
    """
    data = check_tangents(tangents, layout, "tangents")
    return plan_for(layout).tangents_to_erp(data, sampling)


def check_tangents(tangents: np.ndarray, layout: Layout, name: str) -> np.ndarray:
    """Check ``tangents`` for ``layout``: (N, h, w) float32, C-contiguous."""
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    array = as_array(tangents, name)
    h, w = layout.tangent_shape
    check_shape(array, name, ("N", "h", "w"), N=len(layout), h=h, w=w)
    return float32_array(array, name)


def _layout_for(layout: Layout | None, height: int, width: int) -> Layout:
    if layout is None:
        return Layout.icosahedron(width)
    if not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    if layout.erp_shape != (height, width):
        raise InputError(
            f"erp is {height}x{width} but the layout was built for {layout.erp_shape[0]}x"
            f"{layout.erp_shape[1]}; use m360.Layout.icosahedron(erp_width={width})"
        )
    return layout


def _checked_camera(cam: TangentCamera, k: int) -> TangentCamera:
    """``cam`` with its fields checked and normalised (ints, floats, a float64 rotation)."""
    name = f"camera {k}"
    rotation = as_array(cam.rotation, f"{name} rotation").astype(np.float64)
    if (
        rotation.shape != (3, 3)
        or not np.all(np.isfinite(rotation))
        or not np.allclose(rotation @ rotation.T, np.eye(3))
    ):
        raise InputError(f"{name}: rotation must be a 3x3 rotation matrix")
    return TangentCamera(
        rotation=_frozen(rotation),
        fx=number(cam.fx, f"{name} fx"),
        fy=number(cam.fy, f"{name} fy"),
        cx=number(cam.cx, f"{name} cx"),
        cy=number(cam.cy, f"{name} cy"),
        width=integer(cam.width, f"{name} width", low=1, high=MAX_ERP_WIDTH),
        height=integer(cam.height, f"{name} height", low=1, high=MAX_ERP_WIDTH),
        face=cam.face,
    )


def _positive_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _frozen(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64)
    out.flags.writeable = False
    return out
