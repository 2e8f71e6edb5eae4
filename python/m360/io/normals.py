"""Surface normals of an ERP depth map (:func:`normals`) and their files.

A pixel's 3D point is its depth times its ray (docs/conventions.md). Its normal is the cross
product of two chords in 3D: one to a neighbour along longitude, one to a neighbour along
latitude. Of the two neighbours on each axis (east/west, north/south) the shorter chord is
used, and a chord whose depths differ by more than ``max_depth_ratio`` (the mesh's depth-jump
rule, :data:`m360.mesh.DEFAULT_MAX_DEPTH_RATIO`) is not used at all, so an occlusion edge never
bends the normal of the surface in front of it or behind it. Columns W − 1 and 0 are
neighbours (the 0/360° seam); the neighbour of the first (last) row across the pole is the same
row on the opposite meridian, as for bilinear taps.

The chords are computed in each pixel's own frame (ray, east, south) from per-row
coefficients in float64: differences of nearby float32 points near the poles (a few 1e-7 of
the depth apart at 8K) would lose most of their digits, the local form only keeps the depths'
own rounding. Next to the poles, where one column is too small an angle for float32 depths
to tell apart, the longitude chord spans several columns (:data:`MIN_CHORD_ANGLE`). For a
plane, any two chords from a pixel lie in the plane, so the normal is exact up to float
rounding.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import number
from ..errors import InputError
from .files import NORMALS_FILES
from .mesh import DEFAULT_MAX_DEPTH_RATIO, _depth_source, _Grid, _kept

__all__ = [
    "MIN_CHORD_ANGLE",
    "NORMALS_FILES",
    "NORMALS_FRAME",
    "encode_png",
    "normals",
    "write_normals",
]

#: The frame of :func:`normals` and of the normals files (recorded in the sidecar's ``frame``).
NORMALS_FRAME = (
    "m360 world frame: x right, y down, z forward; unit normals facing the camera "
    "(n . point < 0); png: code = round(255 (n + 1) / 2) per channel, x y z as R G B, "
    "0 0 0 = no normal"
)


def _ratio(max_depth_ratio: Any) -> float:
    if isinstance(max_depth_ratio, float) and max_depth_ratio == float("inf"):
        return float("inf")
    ratio = number(max_depth_ratio, "max_depth_ratio", low=1.0)
    if not ratio > 1.0:
        raise InputError(f"max_depth_ratio must be > 1, got {max_depth_ratio!r}")
    return ratio


#: Grid pixels per band (tens of MB of temporaries).
_BAND_PIXELS = 1 << 18
#: Shortest longitude chord, as an angle seen from the camera (radians). Near the poles one
#: column is a tiny angle (row 0 at 8K: 3e-7 rad), where the depth difference of neighbours is
#: below float32's resolution; there the chord reaches as many columns as this angle needs
#: (at most a quarter turn), which keeps the normal's error from the depths' rounding near
#: 0.02° (it was 3° median at 8K's first row with one column).
MIN_CHORD_ANGLE = 2.5e-4


@dataclass
class _Band:
    """One band of rows of the surface, in each pixel's frame (ray d, east e, south s).

    ``normal`` and the chosen chords ``east`` (t_e) and ``south`` (t_s) are (3, b, cols)
    float32 components along (d, e, s); ``valid`` is (b, cols) bool: a finite depth and a
    usable chord along both axes. Where not valid the values are meaningless.
    """

    depth: np.ndarray
    normal: np.ndarray
    east: np.ndarray
    south: np.ndarray
    valid: np.ndarray


class _SphereGrid:
    """A strided ERP depth map as a surface on the sphere, a band of rows at a time."""

    def __init__(
        self,
        array: np.ndarray,
        name: str,
        step: int,
        ratio: float,
        colours: np.ndarray | None = None,
    ) -> None:
        self.grid = _Grid(array, name, colours, step)
        # A band's temporaries are about 40 float32 arrays (normals) and 100 (splats).
        self.grid.band = max(1, _BAND_PIXELS // self.grid.cols)
        self.ratio = ratio
        height, width = array.shape
        rows = np.arange(0, height, step)
        cols = np.arange(0, width, step)
        self.lat = np.pi / 2 - np.pi * (rows + 0.5) / height
        self.lon = 2 * np.pi * (cols + 0.5) / width - np.pi
        # Columns the longitude chords reach per row (1 but near the poles, MIN_CHORD_ANGLE)
        # and the longitude step to the next grid column (the seam: column 0 plus 2π).
        column_angle = np.cos(self.lat) * (2 * np.pi * step / width)
        self.reach = np.clip(
            np.ceil(MIN_CHORD_ANGLE / np.maximum(column_angle, 1e-300)), 1, max(1, cols.size // 4)
        ).astype(np.int64)
        dlon = np.diff(self.lon, append=self.lon[0] + 2 * np.pi)
        # Latitude step to the next row south and north; across a pole it is twice the
        # distance to the pole, on the opposite meridian (``shift`` grid columns away: the
        # nearest grid column when the stride does not divide H, off by less than a column).
        lat = self.lat
        self.eps_south = np.append(np.diff(lat), -2 * (lat[-1] + np.pi / 2))
        self.eps_north = np.concatenate([[2 * (np.pi / 2 - lat[0])], -np.diff(lat)])
        self.shift = round(height / step) % cols.size
        # That column's longitude is λ + π + δ: the chords across a pole take δ into account
        # (cos²(δ/2) shortens them, sin δ turns them east); δ = 0 when the stride divides H.
        delta = self.lon[(np.arange(cols.size) + self.shift) % cols.size] - self.lon - np.pi
        delta = (delta + np.pi) % (2 * np.pi) - np.pi
        self.pole_cos2 = (np.cos(delta / 2) ** 2).astype(np.float32)
        self.pole_sin = np.sin(delta).astype(np.float32)
        self.one_minus_cos_east = (1 - np.cos(dlon)).astype(np.float32)
        self.sin_east = np.sin(dlon).astype(np.float32)
        self.one_minus_cos_west = np.roll(self.one_minus_cos_east, 1)
        self.sin_west = np.roll(self.sin_east, 1)

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.rows, self.grid.cols

    def bands(self) -> Iterator[tuple[int, int]]:
        return self.grid.bands()

    def halo(self, r0: int, r1: int) -> np.ndarray:
        """Depths of rows r0 − 1 … r1 (b + 2, cols); across a pole, the opposite meridian."""
        inner = self.grid.depth(r0, r1)
        north = self.grid.depth(r0 - 1, r0)[0] if r0 > 0 else np.roll(inner[0], -self.shift)
        south = (
            self.grid.depth(r1, r1 + 1)[0]
            if r1 < self.grid.rows
            else np.roll(inner[-1], -self.shift)
        )
        return np.concatenate([north[None], inner, south[None]])

    def valid(self, r0: int, r1: int) -> np.ndarray:
        """Which pixels of rows r0…r1 get a normal (cheap: depths and ratios only)."""
        return self._neighbours(self.halo(r0, r1), r0, r1)[-1]

    def _columns(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray] | None:
        """East and west neighbour columns (b, cols) of rows r0…r1; None: one column each."""
        reach = self.reach[r0:r1, None]
        if (reach == 1).all():
            return None
        cols = np.arange(self.grid.cols)
        return (cols + reach) % cols.size, (cols - reach) % cols.size

    def _neighbours(self, halo: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, ...]:
        r = halo[1:-1]
        columns = self._columns(r0, r1)
        if columns is None:
            r_e, r_w = np.roll(r, -1, axis=1), np.roll(r, 1, axis=1)
        else:
            r_e, r_w = (np.take_along_axis(r, c, axis=1) for c in columns)
        r_n, r_s = halo[:-2], halo[2:]
        ok = [_kept(self.ratio, r, other, r) for other in (r_e, r_w, r_s, r_n)]
        valid = (ok[0] | ok[1]) & (ok[2] | ok[3])
        return r, r_e, r_w, r_s, r_n, *ok, valid

    def _longitude_steps(self, r0: int, r1: int) -> tuple[np.ndarray, ...]:
        """1 − cos and sin of the longitude steps to the east and west neighbours."""
        columns = self._columns(r0, r1)
        if columns is None:
            return (self.one_minus_cos_east, self.sin_east, self.one_minus_cos_west,
                    self.sin_west)  # fmt: skip
        east = (self.lon[columns[0]] - self.lon) % (2 * np.pi)
        west = (self.lon - self.lon[columns[1]]) % (2 * np.pi)
        return tuple(
            f(angle).astype(np.float32)
            for angle in (east, west)
            for f in (lambda x: 1 - np.cos(x), np.sin)
        )

    def band(self, r0: int, r1: int) -> _Band:
        """Compute the normals and chords of rows r0…r1 in each pixel's frame (:class:`_Band`)."""
        r, r_e, r_w, r_s, r_n, ok_e, ok_w, ok_s, ok_n, valid = self._neighbours(
            self.halo(r0, r1), r0, r1
        )
        one_minus_cos_e, sin_e, one_minus_cos_w, sin_w = self._longitude_steps(r0, r1)
        lat = self.lat[r0:r1, None]
        cos_lat = np.cos(lat).astype(np.float32)
        cos2 = (np.cos(lat) ** 2).astype(np.float32)
        sin_cos = (np.sin(lat) * np.cos(lat)).astype(np.float32)
        with np.errstate(invalid="ignore", over="ignore"):
            # Chords along longitude, (d, e, s) components: P_e − P and P − P_w. The ray
            # component is (r_e − r) − r_e (1 − d_e·d): the depth difference first, exact.
            east = (
                (r_e - r) - r_e * (cos2 * one_minus_cos_e),
                r_e * (cos_lat * sin_e),
                -r_e * (sin_cos * one_minus_cos_e),
            )
            west = (
                (r - r_w) + r_w * (cos2 * one_minus_cos_w),
                r_w * (cos_lat * sin_w),
                r_w * (sin_cos * one_minus_cos_w),
            )
            # per grid column (the splats' footprint): a chord over k columns is k times one
            t_e = _shorter(east, west, ok_e, ok_w) / self.reach[r0:r1, None].astype(np.float32)
            # Chords along latitude: P_s − P and P − P_n (no east component on the same
            # meridian, nor across a pole on the opposite one: the same great circle).
            eps_s = self.eps_south[r0:r1, None]
            eps_n = self.eps_north[r0:r1, None]
            south_d = r_s * (1 - np.cos(eps_s)).astype(np.float32)
            south_s = -r_s * np.sin(eps_s).astype(np.float32)
            south_e = np.zeros_like(r)
            north_d = r_n * (1 - np.cos(eps_n)).astype(np.float32)
            north_s = r_n * np.sin(eps_n).astype(np.float32)
            north_e = np.zeros_like(r)
            if r0 == 0:  # across the north pole: the neighbour is at λ + π + δ
                north_d[0] *= self.pole_cos2
                north_s[0] *= self.pole_cos2
                north_e[0] = r_n[0] * np.float32(np.cos(self.lat[0])) * self.pole_sin
            if r1 == self.grid.rows:  # across the south pole
                south_d[-1] *= self.pole_cos2
                south_s[-1] *= self.pole_cos2
                south_e[-1] = -r_s[-1] * np.float32(np.cos(self.lat[-1])) * self.pole_sin
            south = ((r_s - r) - south_d, south_e, south_s)
            north = ((r - r_n) + north_d, north_e, north_s)
            t_s = _shorter(south, north, ok_s, ok_n)
            normal = _unit_facing_camera(np.cross(t_e, t_s, axis=0))
        return _Band(r, normal, t_e, t_s, valid)

    def to_world(self, local: np.ndarray, r0: int, r1: int) -> np.ndarray:
        """(b, cols, 3) float32 world vectors of (3, b, cols) components along (d, e, s)."""
        lat = self.lat[r0:r1, None]
        cos_lat, sin_lat = np.cos(lat).astype(np.float32), np.sin(lat).astype(np.float32)
        cos_lon = np.cos(self.lon).astype(np.float32)
        sin_lon = np.sin(self.lon).astype(np.float32)
        v_d, v_e, v_s = local
        # d = (cφ sλ, −sφ, cφ cλ), e = (cλ, 0, −sλ), s = (sφ sλ, cφ, sφ cλ)
        horizontal = v_d * cos_lat + v_s * sin_lat
        out = np.empty((*v_d.shape, 3), np.float32)
        out[..., 0] = horizontal * sin_lon + v_e * cos_lon
        out[..., 1] = v_s * cos_lat - v_d * sin_lat
        out[..., 2] = horizontal * cos_lon - v_e * sin_lon
        return out


def _shorter(
    forward: tuple[np.ndarray, ...],
    backward: tuple[np.ndarray, ...],
    ok_forward: np.ndarray,
    ok_backward: np.ndarray,
) -> np.ndarray:
    """(3, b, cols): per pixel the shorter of two usable one-sided chords."""
    len_f = forward[0] ** 2 + forward[1] ** 2 + forward[2] ** 2
    len_b = backward[0] ** 2 + backward[1] ** 2 + backward[2] ** 2
    use_forward = ok_forward & (~ok_backward | (len_f <= len_b))
    return np.stack([np.where(use_forward, f, b) for f, b in zip(forward, backward, strict=True)])


def _unit_facing_camera(normal: np.ndarray) -> np.ndarray:
    """Scale (3, b, cols) vectors to unit length, ray component ≤ 0 (zero: facing the ray)."""
    length = np.sqrt(np.einsum("kij,kij->ij", normal, normal))
    sign = np.where(normal[0] > 0, -1.0, 1.0).astype(np.float32)
    degenerate = ~(length > 0)
    normal = normal * (sign / np.where(degenerate, 1.0, length))
    normal[:, degenerate] = np.array([-1.0, 0.0, 0.0], np.float32)[:, None]
    return normal


def normals(
    source: Any,
    *,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    quantity: str | None = None,
) -> np.ndarray:
    """Compute the unit surface normals of an ERP depth map (m360 frame, facing the camera).

    Per pixel, the cross product of two 3D chords to its neighbours (one along longitude, one
    along latitude; of the two sides the shorter one, never one across a depth jump),
    continuous across the 0/360° seam and over the poles (module docstring).

    Parameters
    ----------
    source : EstimateResult, SavedResult, path or (H, W) float array
        As for :func:`m360.to_points`: a result, an output stem, or a plain ERP map of radial
        depth (or disparity with ``quantity="disparity"``); NaN / ≤ 0 = invalid.
    max_depth_ratio : float
        A chord whose two depths differ by more than this factor crosses an occlusion edge
        and is not used (default: the mesh's, :data:`m360.mesh.DEFAULT_MAX_DEPTH_RATIO`;
        ``inf`` uses every finite neighbour).
    quantity : {"depth", "disparity"}, optional
        What a plain array holds (default depth).

    Returns
    -------
    (H, W, 3) float32
        Unit normals (x right, y down, z forward) with ``n · point < 0``. NaN where the depth
        is invalid, and where a pixel has no usable neighbour along longitude or along
        latitude (both sides NaN or across a depth jump: an isolated pixel or a one-pixel
        sliver).

    Raises
    ------
    InputError
        Not an ERP map, or a bad ``max_depth_ratio``.
    """
    array, name, _ = _depth_source(source, quantity)
    out = np.empty((*array.shape, 3), np.float32)
    for r0, r1, world in _world_bands(array, name, _ratio(max_depth_ratio)):
        out[r0:r1] = world
    return out


def _world_bands(array: np.ndarray, name: str, ratio: float) -> Iterator[tuple[int, int, Any]]:
    """(r0, r1, (r1 − r0, W, 3) world normals, NaN where none) of a checked map, by bands."""
    sphere = _SphereGrid(array, name, 1, ratio)
    for r0, r1 in sphere.bands():
        band = sphere.band(r0, r1)
        world = sphere.to_world(band.normal, r0, r1)
        world[~band.valid] = np.nan
        yield r0, r1, world


def encode_png(normal_map: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR image of unit normals: round(255 (n + 1) / 2) per channel, NaN → 0.

    R, G, B hold x, y, z (OpenCV writes BGR, hence the reversed channels).
    """
    with np.errstate(invalid="ignore"):
        codes = np.rint((np.clip(normal_map[..., ::-1], -1, 1) + 1) * 127.5)
    codes[~np.isfinite(normal_map).all(axis=-1)] = 0
    return codes.astype(np.uint8)  # type: ignore[no-any-return]


def write_normals(
    stem: str | os.PathLike[str],
    source: Any,
    *,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
) -> dict[str, Path]:
    """Write ``STEM.normals.exr`` (float32 X, Y, Z) and ``STEM.normals.png`` (8-bit), atomically.

    The EXR holds the normals bit-exactly (channels R, G, B = x, y, z; NaN = no normal); the PNG
    the usual
    (n + 1) / 2 encoding (see :data:`NORMALS_FRAME`). Returns format → path.
    """
    from .files import save_png, write_exr_channels

    array, name, _ = _depth_source(source, None)
    # One plane per channel (the EXR's layout) and the PNG's codes, filled a band at a time:
    # 13 bytes a pixel besides the encoders' own buffers.
    planes = np.empty((3, *array.shape), np.float32)
    codes = np.empty((*array.shape, 3), np.uint8)
    for r0, r1, world in _world_bands(array, name, _ratio(max_depth_ratio)):
        planes[:, r0:r1] = np.moveaxis(world, -1, 0)
        codes[r0:r1] = encode_png(world)
    base = Path(stem)
    exr = base.with_name(base.name + NORMALS_FILES["exr"])
    png = base.with_name(base.name + NORMALS_FILES["png"])
    # R, G, B hold x, y, z: image tools show them, and m360's EXR reader gives (H, W, 3).
    write_exr_channels(exr, dict(zip("RGB", planes, strict=True)))
    del planes
    written = {"exr": exr}
    try:
        written["png"] = save_png(png, codes)
    except BaseException:
        exr.unlink(missing_ok=True)
        raise
    return written
