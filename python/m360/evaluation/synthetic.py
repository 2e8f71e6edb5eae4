"""Synthetic panoramas with exact depth, by analytic ray casting.

A :class:`Scene` is a box room that encloses the camera (at the world origin) plus a few
objects: oriented boxes (axis-aligned furniture, or thin tilted slabs) and spheres. Rays start at
the origin, so the radial distance to the first hit is the exact ground-truth depth of m360's
convention (docs/conventions.md: x right, y down, z forward; depth = |P|).

``room(seed)`` builds a random but deterministic scene; :func:`render` gives an ERP image and its
depth; :func:`tangent_distance` / :func:`tangent_perspective_disparity` give exact per-tangent
ground truth for any duck-typed pinhole cameras; :func:`distort` simulates the per-tangent affine
ambiguity of a monocular network and :func:`content_errors` the local, tangent-specific mistakes
(a region too near or too far, lost fine detail) that no affine map explains.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from m360._compat import renamed
from m360._validate import MAX_ERP_WIDTH, as_array, integer, number
from m360._validate import seed as check_seed
from m360.errors import InputError
from m360.geometry.sphere import (
    camera_pixel_directions,
    erp_latitudes,
    erp_longitudes,
    lonlat_to_directions,
)

__all__ = [
    "Box",
    "Hit",
    "Light",
    "Material",
    "Scene",
    "Sphere",
    "content_errors",
    "distort",
    "render",
    "room",
    "rotation_matrix",
    "tangent_distance",
    "tangent_perspective_disparity",
]

TEXTURES = ("plain", "checker", "stripes", "noise")
_CHUNK_RAYS = 1 << 18
_SHADOW_EPS = 1e-6
#: Largest coordinate, size or texture period (metres) of a scene: far enough for any room,
#: near enough that no intersection or texture computation overflows float64.
SCENE_LIMIT = 1e6
#: Most pixels :func:`tangent_distance` / :func:`tangent_perspective_disparity` ray cast in one
#: call (all cameras together): 2^28, a 1 GB float32 result.
MAX_RAYS = 1 << 28


def _vec3(name: str, value: Any) -> np.ndarray:
    v = as_array(value, name).astype(np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(np.abs(v) > SCENE_LIMIT):
        raise InputError(f"{name} must be 3 finite numbers of magnitude <= {SCENE_LIMIT:g}")
    return v


def _length(value: Any, name: str, low: float = 0.0) -> float:
    """Check a finite positive length (metres) up to SCENE_LIMIT."""
    result = number(value, name, low=low, high=SCENE_LIMIT)
    if result <= 0:
        raise InputError(f"{name}={value!r} must be > 0")
    return result


def rotation_matrix(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rotation matrix ``Rz(roll) · Rx(pitch) · Ry(yaw)`` (radians).

    Parameters
    ----------
    yaw, pitch, roll : float
        Angles about the y (down), x (right) and z (forward) axes, in radians.

    Returns
    -------
    np.ndarray
        (3, 3) float64 orthonormal matrix with determinant +1.
    """
    yaw, pitch, roll = (number(v, n) for v, n in ((yaw, "yaw"), (pitch, "pitch"), (roll, "roll")))
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return rz @ rx @ ry  # type: ignore[no-any-return]  # numpy stubs: Any


@dataclass(frozen=True)
class Material:
    """Surface appearance.

    Attributes
    ----------
    albedo : (3,) float64
        RGB reflectance in [0, 1].
    texture : str
        One of ``"plain"``, ``"checker"`` (3-D checker of cell size ``period``), ``"stripes"``
        (sinusoid along ``waves[0]``) or ``"noise"`` (sum of three sinusoids along ``waves``),
        evaluated at the world hit point.
    period : float
        Texture period in metres (> 0).
    waves : (3, 3) float64
        Unit wave directions (rows) used by stripes and noise.
    phase : (3,) float64
        Phases (radians) of the three waves.
    """

    albedo: np.ndarray = field(default_factory=lambda: np.array([0.7, 0.7, 0.7]))
    texture: str = "plain"
    period: float = 0.5
    waves: np.ndarray = field(default_factory=lambda: np.eye(3))
    phase: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        albedo = _vec3("albedo", self.albedo)
        if np.any(albedo < 0) or np.any(albedo > 1):
            raise InputError(f"albedo must lie in [0, 1], got {albedo.tolist()}")
        if not isinstance(self.texture, str) or self.texture not in TEXTURES:
            raise InputError(f"texture must be one of {TEXTURES}, got {self.texture!r}")
        # Below a micrometre the texture coordinates point/period could overflow.
        object.__setattr__(self, "period", _length(self.period, "period", low=1e-6))
        waves = as_array(self.waves, "waves").astype(np.float64)
        if waves.shape != (3, 3) or not np.all(np.isfinite(waves)):
            raise InputError(f"waves must be a finite (3, 3) array, got shape {waves.shape}")
        norms = np.linalg.norm(waves, axis=1, keepdims=True)
        if np.any(norms == 0):
            raise InputError("waves rows must be non-zero vectors")
        object.__setattr__(self, "albedo", albedo)
        object.__setattr__(self, "waves", waves / norms)
        object.__setattr__(self, "phase", _vec3("phase", self.phase))


@dataclass(frozen=True)
class Box:
    """Oriented box: points p with ``|R (p - center)| ≤ half_size`` componentwise.

    Attributes
    ----------
    center : (3,) float64
        Centre in world coordinates (metres).
    half_size : (3,) float64
        Half extents along the box's local axes (> 0). A slab is a box with one tiny half extent.
    rotation : (3, 3) float64
        R, world → box-local. Identity gives an axis-aligned box.
    material : Material
    """

    center: np.ndarray
    half_size: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    material: Material = field(default_factory=Material)

    def __post_init__(self) -> None:
        half = _vec3("half_size", self.half_size)
        if np.any(half <= 0):
            raise InputError(f"half_size must be > 0, got {half.tolist()}")
        rot = as_array(self.rotation, "rotation").astype(np.float64)
        if (
            rot.shape != (3, 3)
            or not np.all(np.isfinite(rot))
            or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9)
        ):
            raise InputError("rotation must be an orthonormal (3, 3) matrix")
        if not isinstance(self.material, Material):
            raise InputError(f"material must be a Material, got {type(self.material).__name__}")
        object.__setattr__(self, "center", _vec3("center", self.center))
        object.__setattr__(self, "half_size", half)
        object.__setattr__(self, "rotation", rot)

    @property
    def axis_aligned(self) -> bool:
        """True when ``rotation`` is the identity."""
        return bool(np.array_equal(self.rotation, np.eye(3)))

    def clearance(self, point: np.ndarray) -> float:
        """Euclidean distance from ``point`` (3,) to the box (0 inside)."""
        local = self.rotation @ (np.asarray(point, dtype=np.float64) - self.center)
        return float(np.linalg.norm(np.maximum(np.abs(local) - self.half_size, 0.0)))


@dataclass(frozen=True)
class Sphere:
    """Sphere of ``radius`` (> 0) metres around ``center`` (3,) float64."""

    center: np.ndarray
    radius: float
    material: Material = field(default_factory=Material)

    def __post_init__(self) -> None:
        if not isinstance(self.material, Material):
            raise InputError(f"material must be a Material, got {type(self.material).__name__}")
        object.__setattr__(self, "center", _vec3("center", self.center))
        object.__setattr__(self, "radius", _length(self.radius, "radius"))

    def clearance(self, point: np.ndarray) -> float:
        """Euclidean distance from ``point`` (3,) to the sphere (0 inside)."""
        d = np.linalg.norm(np.asarray(point, dtype=np.float64) - self.center) - self.radius
        return float(max(d, 0.0))


@dataclass(frozen=True)
class Light:
    """Point light at ``position`` (3,) with scalar ``intensity``; falloff ``1 / (1 + 0.1 r²)``."""

    position: np.ndarray
    intensity: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3("position", self.position))
        intensity = number(self.intensity, "intensity", low=0.0, high=SCENE_LIMIT)
        object.__setattr__(self, "intensity", intensity)


@dataclass(frozen=True)
class Hit:
    """First intersections of a bundle of rays from the origin.

    Attributes
    ----------
    distance : (...) float64
        Radial distance to the hit (the ray direction is unit), always finite.
    normal : (...,3) float64
        Unit surface normal at the hit, facing the camera (``normal · direction < 0``).
    point : (...,3) float64
        World hit point ``distance · direction``.
    object_id : (...) int64
        0-5: room faces (-x, +x, -y ceiling, +y floor, -z, +z), then boxes in order, then spheres.
    """

    distance: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    object_id: np.ndarray


def _items(values: Any, name: str, kind: type) -> tuple[Any, ...]:
    """``values`` as a tuple whose every item is a ``kind``."""
    if isinstance(values, (str, bytes)) or not isinstance(values, (Sequence, set, frozenset)):
        raise InputError(f"{name} must be a sequence of {kind.__name__}, got {values!r}")
    items = tuple(values)
    for item in items:
        if not isinstance(item, kind):
            raise InputError(f"{name} must hold {kind.__name__} objects, got {item!r}")
    return items


def _default_room_materials() -> tuple[Material, ...]:
    grey = np.array([0.75, 0.72, 0.68])
    return tuple(Material(albedo=grey) for _ in range(6))


@dataclass(frozen=True)
class Scene:
    """A box room around the camera (world origin) with boxes, slabs and spheres inside.

    Attributes
    ----------
    room_min, room_max : (3,) float64
        Opposite corners of the room (metres); the origin must lie strictly inside.
    boxes : tuple[Box, ...]
    spheres : tuple[Sphere, ...]
    lights : tuple[Light, ...]
        Point lights; when empty, a single light at the camera is used for shading.
    room_materials : tuple[Material, ...]
        Six materials for the faces -x, +x, -y (ceiling), +y (floor), -z, +z.
    ambient : float
        Ambient light level added to the Lambert term.
    shadows : bool
        Cast shadow rays towards the lights in :meth:`shade`.
    """

    room_min: np.ndarray
    room_max: np.ndarray
    boxes: tuple[Box, ...] = ()
    spheres: tuple[Sphere, ...] = ()
    lights: tuple[Light, ...] = ()
    room_materials: tuple[Material, ...] = field(default_factory=_default_room_materials)
    ambient: float = 0.25
    shadows: bool = True

    def __post_init__(self) -> None:
        lo = _vec3("room_min", self.room_min)
        hi = _vec3("room_max", self.room_max)
        if not (np.all(lo < 0) and np.all(hi > 0)):
            raise InputError(
                f"the origin must lie strictly inside the room: expected room_min < 0 < room_max, "
                f"got room_min={lo.tolist()}, room_max={hi.tolist()}"
            )
        materials = _items(self.room_materials, "room_materials", Material)
        if len(materials) != 6:
            raise InputError(f"room_materials must hold 6 materials, got {len(materials)}")
        if not isinstance(self.shadows, bool):
            raise InputError(f"shadows must be True or False, got {self.shadows!r}")
        ambient = number(self.ambient, "ambient", low=0.0, high=SCENE_LIMIT)
        object.__setattr__(self, "room_min", lo)
        object.__setattr__(self, "room_max", hi)
        object.__setattr__(self, "boxes", _items(self.boxes, "boxes", Box))
        object.__setattr__(self, "spheres", _items(self.spheres, "spheres", Sphere))
        object.__setattr__(self, "lights", _items(self.lights, "lights", Light))
        object.__setattr__(self, "room_materials", materials)
        object.__setattr__(self, "ambient", ambient)

    @property
    def materials(self) -> tuple[Material, ...]:
        """Materials indexed by ``Hit.object_id``."""
        return (
            self.room_materials
            + tuple(b.material for b in self.boxes)
            + tuple(s.material for s in self.spheres)
        )

    def camera_clearance(self) -> float:
        """Smallest distance (metres) from the camera to a wall or an object."""
        walls = float(min(np.min(-self.room_min), np.min(self.room_max)))
        solids: tuple[Box | Sphere, ...] = (*self.boxes, *self.spheres)
        objs = [o.clearance(np.zeros(3)) for o in solids]
        return min([walls, *objs])

    # ---------------------------------------------------------------- ray casting

    def _cast_objects(
        self, origins: np.ndarray | None, dirs: np.ndarray, t_best: np.ndarray, first_id: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest object hit with 0 < t < t_best; returns (t, normal, id) where id = -1 if none."""
        n = dirs.shape[0]
        t_best = t_best.copy()
        normal = np.zeros((n, 3))
        obj = np.full(n, -1, dtype=np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_dirs = 1.0 / dirs if self.boxes else dirs
            for k, box in enumerate(self.boxes):
                rot = box.rotation
                o_l = -(rot @ box.center) if origins is None else (origins - box.center) @ rot.T
                if box.axis_aligned:
                    d_l, inv = dirs, inv_dirs
                else:
                    d_l = dirs @ rot.T
                    inv = 1.0 / d_l
                t1 = (-box.half_size - o_l) * inv
                t2 = (box.half_size - o_l) * inv
                tmin = np.minimum(t1, t2)
                tmax = np.maximum(t1, t2)
                tnear = np.maximum(np.maximum(tmin[:, 0], tmin[:, 1]), tmin[:, 2])
                tfar = np.minimum(np.minimum(tmax[:, 0], tmax[:, 1]), tmax[:, 2])
                hit = (tnear <= tfar) & (tnear > 0) & (tnear < t_best)
                if not np.any(hit):
                    continue
                idx = np.nonzero(hit)[0]
                axis = tmin[idx].argmax(axis=1)
                n_l = np.zeros((idx.size, 3))
                n_l[np.arange(idx.size), axis] = -np.sign(d_l[idx, axis])
                normal[idx] = n_l @ rot
                t_best[idx] = tnear[idx]
                obj[idx] = first_id + k
            first_sphere = first_id + len(self.boxes)
            for k, sph in enumerate(self.spheres):
                oc = sph.center if origins is None else sph.center - origins
                b = dirs @ oc if origins is None else np.einsum("ij,ij->i", dirs, oc)
                c = (oc * oc).sum(axis=-1) - sph.radius**2
                disc = b * b - c
                t = b - np.sqrt(np.maximum(disc, 0.0))
                hit = (disc >= 0) & (t > 0) & (t < t_best)
                if not np.any(hit):
                    continue
                idx = np.nonzero(hit)[0]
                p = t[idx, None] * dirs[idx]
                if origins is not None:
                    p = p + origins[idx]
                normal[idx] = (p - sph.center) / sph.radius
                t_best[idx] = t[idx]
                obj[idx] = first_sphere + k
        return t_best, normal, obj

    def _intersect_flat(
        self, dirs: np.ndarray, origins: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo = self.room_min if origins is None else self.room_min - origins
        hi = self.room_max if origins is None else self.room_max - origins
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axes = np.where(dirs > 0, hi / dirs, lo / dirs)
        t_axes = np.where(dirs == 0, np.inf, t_axes)
        axis = t_axes.argmin(axis=1)
        rows = np.arange(dirs.shape[0])
        t_room = t_axes[rows, axis]
        positive = dirs[rows, axis] > 0
        room_id = 2 * axis + positive
        t, normal, obj = self._cast_objects(origins, dirs, t_room, 6)
        room_hit = obj < 0
        obj[room_hit] = room_id[room_hit]
        nr = np.zeros((int(room_hit.sum()), 3))
        nr[np.arange(nr.shape[0]), axis[room_hit]] = np.where(positive[room_hit], -1.0, 1.0)
        normal[room_hit] = nr
        return t, normal, obj

    def _prepare(self, directions: np.ndarray) -> np.ndarray:
        d = as_array(directions, "directions").astype(np.float64)
        if d.ndim < 1 or d.shape[-1] != 3:
            raise InputError(f"directions must have shape (..., 3), got {d.shape}")
        norms = np.linalg.norm(d, axis=-1)
        if not np.all(np.isfinite(d)) or np.any(np.abs(norms - 1.0) > 1e-6):
            raise InputError("directions must be finite unit vectors (|d| = 1 within 1e-6)")
        return d

    def _origins(self, origins: Any, directions: np.ndarray) -> np.ndarray | None:
        """Check ray origins (..., 3) against the directions; None for the camera itself."""
        if origins is None:
            return None
        o = as_array(origins, "origins").astype(np.float64)
        if o.ndim < 1 or o.shape[-1] != 3 or not np.all(np.isfinite(o)):
            raise InputError(f"origins must be finite points of shape (..., 3), got {o.shape}")
        try:
            o = np.broadcast_to(o, directions.shape)
        except ValueError:
            raise InputError(
                f"origins {o.shape} do not broadcast to the directions {directions.shape}"
            ) from None
        if not (np.all(o > self.room_min) and np.all(o < self.room_max)):
            raise InputError("origins must lie strictly inside the room")
        return o.reshape(-1, 3)

    def intersect(self, directions: np.ndarray, origins: np.ndarray | None = None) -> Hit:
        """First hit of rays from the origin (or from ``origins``).

        Parameters
        ----------
        directions : array_like
            (..., 3) float64 unit directions in the world frame.
        origins : array_like, optional
            (..., 3) ray origins (broadcast to the directions), strictly inside the room; default
            the camera at the world origin. ODS eye rays, for instance, start on the viewing
            circle.

        Returns
        -------
        Hit
            Distances from each ray's origin (...), normals (..., 3), hit points (..., 3) and
            object ids (...).
        """
        d = self._prepare(directions)
        shape = d.shape[:-1]
        flat = d.reshape(-1, 3)
        starts = self._origins(origins, d)
        t = np.empty(flat.shape[0])
        normal = np.empty((flat.shape[0], 3))
        obj = np.empty(flat.shape[0], dtype=np.int64)
        for s in range(0, flat.shape[0], _CHUNK_RAYS):
            sl = slice(s, s + _CHUNK_RAYS)
            o = None if starts is None else starts[sl]
            t[sl], normal[sl], obj[sl] = self._intersect_flat(flat[sl], o)
        point = t[:, None] * flat
        if starts is not None:
            point = point + starts
        return Hit(
            distance=t.reshape(shape),
            normal=normal.reshape(*shape, 3),
            point=point.reshape(*shape, 3),
            object_id=obj.reshape(shape),
        )

    def distance(self, directions: np.ndarray, origins: np.ndarray | None = None) -> np.ndarray:
        """Radial distance from the origin to the first hit along each direction.

        Parameters
        ----------
        directions : array_like
            (..., 3) float64 unit world directions.
        origins : array_like, optional
            (..., 3) ray origins inside the room (see :meth:`intersect`); the distance is then
            from each origin.

        Returns
        -------
        np.ndarray
            (...) float64 distances in metres, always finite and > 0 (the room encloses the camera).
        """
        d = self._prepare(directions)
        flat = d.reshape(-1, 3)
        starts = self._origins(origins, d)
        out = np.empty(flat.shape[0])
        for s in range(0, flat.shape[0], _CHUNK_RAYS):
            o = None if starts is None else starts[s : s + _CHUNK_RAYS]
            out[s : s + _CHUNK_RAYS] = self._intersect_flat(flat[s : s + _CHUNK_RAYS], o)[0]
        return out.reshape(d.shape[:-1])

    # ---------------------------------------------------------------- shading

    def _texture(self, point: np.ndarray, obj: np.ndarray) -> np.ndarray:
        mats = self.materials
        kind = np.array([TEXTURES.index(m.texture) for m in mats])[obj]
        period = np.array([m.period for m in mats])[obj]
        waves = np.stack([m.waves for m in mats])[obj]
        phase = np.stack([m.phase for m in mats])[obj]
        tex = np.ones(point.shape[0])
        u = point / period[:, None]
        m = kind == 1
        if np.any(m):
            # The 0.37 offset keeps axis-aligned faces away from the cell boundaries.
            cells = np.floor(u[m] + 0.37).sum(axis=1)
            tex[m] = 0.65 + 0.35 * (cells % 2)
        proj = np.einsum("nkj,nj->nk", waves, u) * (2 * np.pi) + phase
        m = kind == 2
        tex[m] = 0.75 + 0.25 * np.sin(proj[m, 0])
        m = kind == 3
        scales = np.array([1.0, 2.3, 4.1])
        tex[m] = 0.75 + 0.25 * (np.sin(proj[m] * scales) * [0.5, 0.3, 0.2]).sum(axis=1)
        return tex

    def _shade_flat(
        self,
        dirs: np.ndarray,
        hit: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        origins: np.ndarray | None = None,
    ) -> np.ndarray:
        t, normal, obj = self._intersect_flat(dirs, origins) if hit is None else hit
        point = t[:, None] * dirs if origins is None else origins + t[:, None] * dirs
        albedo = np.stack([m.albedo for m in self.materials])[obj]
        light = np.full(t.shape[0], self.ambient)
        lights = self.lights or (Light(position=np.zeros(3)),)
        for lt in lights:
            to_l = lt.position - point
            r = np.linalg.norm(to_l, axis=1)
            ldir = to_l / np.maximum(r, 1e-12)[:, None]
            lam = np.maximum((normal * ldir).sum(axis=1), 0.0)
            if self.shadows and self.lights:
                lit = np.nonzero(lam > 0)[0]
                origins = point[lit] + _SHADOW_EPS * normal[lit]
                _, _, occ = self._cast_objects(origins, ldir[lit], r[lit], 6)
                lam[lit[occ >= 0]] = 0.0
            light += lt.intensity * lam / (1.0 + 0.1 * r * r)
        rgb = albedo * (self._texture(point, obj) * light)[:, None]
        rgb = np.clip(rgb, 0.0, 1.0) ** (1 / 2.2)
        return np.round(rgb * 255).astype(np.uint8)  # type: ignore[no-any-return]  # numpy stubs: Any

    def shade(self, directions: np.ndarray, origins: np.ndarray | None = None) -> np.ndarray:
        """Colour seen along each direction: textured albedo, Lambert point lights, ambient.

        Parameters
        ----------
        directions : array_like
            (..., 3) float64 unit world directions.
        origins : array_like, optional
            (..., 3) ray origins inside the room (see :meth:`intersect`); default the camera.
            Shading depends on the hit point only, so a point looks the same from any origin.

        Returns
        -------
        np.ndarray
            (..., 3) uint8 RGB (gamma 2.2 encoded).
        """
        d = self._prepare(directions)
        flat = d.reshape(-1, 3)
        starts = self._origins(origins, d)
        out = np.empty((flat.shape[0], 3), dtype=np.uint8)
        for s in range(0, flat.shape[0], _CHUNK_RAYS):
            o = None if starts is None else starts[s : s + _CHUNK_RAYS]
            out[s : s + _CHUNK_RAYS] = self._shade_flat(flat[s : s + _CHUNK_RAYS], None, o)
        return out.reshape(*d.shape[:-1], 3)


# -------------------------------------------------------------------- scene generator


def _random_material(rng: np.random.Generator, texture: str | None = None) -> Material:
    waves = rng.normal(size=(3, 3))
    return Material(
        albedo=rng.uniform(0.25, 0.95, size=3),
        texture=texture if texture is not None else str(rng.choice(TEXTURES[1:])),
        period=float(rng.uniform(0.15, 0.6)),
        waves=waves,
        phase=rng.uniform(0, 2 * np.pi, size=3),
    )


def room(seed: int = 0) -> Scene:
    """Make a random furnished room around the camera, deterministic for a seed.

    The room is 3-9 m wide (x) and deep (z), 2.4-4 m high; the camera (origin) is off-centre
    horizontally and 1-1.8 m above the floor. Inside are 2-4 axis-aligned boxes standing on the
    floor, 1-3 spheres and 1-3 thin slabs (table tops or tilted planks), each with its own
    material, plus 1-2 point lights below the ceiling. Every wall and object is at least 0.3 m
    from the camera.

    Parameters
    ----------
    seed : int
        Seed of ``np.random.default_rng``.

    Returns
    -------
    Scene
    """
    rng = np.random.default_rng(check_seed(seed))
    clearance = 0.3
    size_x, size_z = rng.uniform(3.0, 9.0, size=2)
    height = float(rng.uniform(2.4, 4.0))
    frac_x, frac_z = 0.5 + rng.choice([-1.0, 1.0], size=2) * rng.uniform(0.08, 0.3, size=2)
    cam_h = float(rng.uniform(1.0, min(1.8, height - 0.6)))
    lo = np.array([-frac_x * size_x, cam_h - height, -frac_z * size_z])
    hi = np.array([(1 - frac_x) * size_x, cam_h, (1 - frac_z) * size_z])
    floor_y = hi[1]
    origin = np.zeros(3)

    def inside_xz(half: np.ndarray) -> np.ndarray:
        return np.array(
            [
                rng.uniform(lo[0] + half[0], hi[0] - half[0]),
                0.0,
                rng.uniform(lo[2] + half[2], hi[2] - half[2]),
            ]
        )

    boxes: list[Box] = []
    for _ in range(int(rng.integers(2, 5))):
        for _try in range(100):
            half = np.array(
                [rng.uniform(0.15, 0.75), rng.uniform(0.15, 0.9), rng.uniform(0.15, 0.75)]
            )
            center = inside_xz(half)
            center[1] = floor_y - half[1]
            box = Box(center=center, half_size=half, material=_random_material(rng))
            if box.clearance(origin) >= clearance:
                boxes.append(box)
                break

    for _ in range(int(rng.integers(1, 4))):
        for _try in range(100):
            half = np.array(
                [rng.uniform(0.2, 0.6), rng.uniform(0.01, 0.025), rng.uniform(0.2, 0.6)]
            )
            if rng.random() < 0.5:
                rot = rotation_matrix(yaw=rng.uniform(0, np.pi))
                center = inside_xz(half)
                center[1] = floor_y - rng.uniform(0.4, 1.1)
            else:
                rot = rotation_matrix(*rng.uniform([0, -1.2, -1.2], [np.pi, 1.2, 1.2]))
                reach = np.full(3, np.linalg.norm(half))
                center = inside_xz(reach)
                center[1] = rng.uniform(lo[1] + reach[1], floor_y - reach[1])
            slab = Box(center=center, half_size=half, rotation=rot, material=_random_material(rng))
            if slab.clearance(origin) >= clearance:
                boxes.append(slab)
                break

    spheres: list[Sphere] = []
    for _ in range(int(rng.integers(1, 4))):
        for _try in range(100):
            radius = float(rng.uniform(0.15, 0.6))
            center = inside_xz(np.full(3, radius))
            center[1] = rng.uniform(lo[1] + radius, floor_y - radius)
            sph = Sphere(center=center, radius=radius, material=_random_material(rng))
            if sph.clearance(origin) >= clearance:
                spheres.append(sph)
                break

    lights: list[Light] = []
    for _ in range(int(rng.integers(1, 3))):
        for _try in range(100):
            pos = rng.uniform(lo + 0.3, hi - 0.3)
            pos[1] = lo[1] + 0.2
            solids: list[Box | Sphere] = [*boxes, *spheres]
            if all(o.clearance(pos) > 0.1 for o in solids):
                lights.append(Light(position=pos, intensity=float(rng.uniform(2.0, 4.0))))
                break

    wall_textures = ["stripes", "stripes", "plain", "checker", "noise", "noise"]
    room_materials = tuple(_random_material(rng, texture=t) for t in wall_textures)
    return Scene(
        room_min=lo,
        room_max=hi,
        boxes=tuple(boxes),
        spheres=tuple(spheres),
        lights=tuple(lights),
        room_materials=room_materials,
        ambient=float(rng.uniform(0.15, 0.3)),
    )


# -------------------------------------------------------------------- rendering


def render(scene: Scene, erp_width: int) -> tuple[np.ndarray, np.ndarray]:
    """Render an ERP panorama and its exact radial depth.

    Parameters
    ----------
    scene : Scene
    erp_width : int
        ERP width W (even, ≥ 8); the height is H = W // 2.

    Returns
    -------
    rgb : np.ndarray
        (H, W, 3) uint8.
    depth : np.ndarray
        (H, W) float32 radial distance |P| in metres (docs/conventions.md pixel-centre convention).
    """
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be an m360.synthetic.Scene, got {type(scene).__name__}")
    if (
        isinstance(erp_width, bool)
        or not isinstance(erp_width, (int, np.integer))
        or not 8 <= erp_width <= MAX_ERP_WIDTH
        or erp_width % 2
    ):
        raise InputError(
            f"erp_width must be an even integer >= 8 (at most {MAX_ERP_WIDTH}), got {erp_width!r}"
        )
    w = int(erp_width)
    h = w // 2
    rgb = np.empty((h, w, 3), dtype=np.uint8)
    depth = np.empty((h, w), dtype=np.float32)
    rows = max(1, _CHUNK_RAYS // w)
    lon = erp_longitudes(w)[None, :]
    lat = erp_latitudes(h)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        flat = lonlat_to_directions(lon, lat[r0:r1, None]).reshape(-1, 3)
        hit = scene._intersect_flat(flat)
        depth[r0:r1] = hit[0].reshape(r1 - r0, w)
        rgb[r0:r1] = scene._shade_flat(flat, hit).reshape(r1 - r0, w, 3)
    return rgb, depth


_CAMERA_FIELDS = ("rotation", "fx", "fy", "cx", "cy", "width", "height")


def _camera_rays(cam: Any) -> tuple[np.ndarray, np.ndarray]:
    rotation = as_array(cam.rotation, "camera rotation").astype(np.float64)
    if rotation.shape != (3, 3) or not np.all(np.isfinite(rotation)):
        raise InputError(f"camera rotation must be a finite (3, 3) array, got {rotation.shape}")
    return camera_pixel_directions(
        rotation,
        number(cam.fx, "camera fx"),
        number(cam.fy, "camera fy"),
        number(cam.cx, "camera cx"),
        number(cam.cy, "camera cy"),
        int(cam.width),
        int(cam.height),
        return_ray_norm=True,
    )


def _check_cameras(cameras: Sequence[Any]) -> list[Any]:
    if isinstance(cameras, (str, bytes)) or not isinstance(cameras, Sequence):
        raise InputError(f"cameras must be a sequence of cameras, got {type(cameras).__name__}")
    cams = list(cameras)
    if not cams:
        raise InputError("cameras must be a non-empty sequence, got 0 cameras")
    for cam in cams:
        if not all(hasattr(cam, f) for f in _CAMERA_FIELDS):
            raise InputError(f"each camera needs attributes {', '.join(_CAMERA_FIELDS)}")
    sizes = {
        (
            integer(c.height, "camera height", low=1, high=MAX_ERP_WIDTH),
            integer(c.width, "camera width", low=1, high=MAX_ERP_WIDTH),
        )
        for c in cams
    }
    if len(sizes) != 1:
        raise InputError(f"all cameras must share one (height, width), got {sorted(sizes)}")
    (h, w), n = sizes.pop(), len(cams)
    if n * h * w > MAX_RAYS:
        raise InputError(f"{n} cameras of {w}x{h} pixels exceed the {MAX_RAYS} rays of one call")
    return cams


def tangent_distance(scene: Scene, cameras: Sequence[Any]) -> np.ndarray:
    """Exact radial distance seen by each pixel centre of each pinhole camera.

    Parameters
    ----------
    scene : Scene
    cameras : sequence
        N objects with ``rotation`` (3, 3) world → camera, ``fx, fy, cx, cy`` and ``width, height``
        (all equal across cameras); pixel (r, c) has its centre at (x = c, y = r).

    Returns
    -------
    np.ndarray
        (N, h, w) float32 distances |P| in metres.
    """
    _check_scene(scene)
    cams = _check_cameras(cameras)
    out = [scene.distance(_camera_rays(c)[0]).astype(np.float32) for c in cams]
    return np.stack(out)


def tangent_perspective_disparity(scene: Scene, cameras: Sequence[Any]) -> np.ndarray:
    """Exact perspective disparity 1/z of each pixel centre of each pinhole camera.

    z is the camera-frame depth of the hit point, so ``1/z = |q| / distance`` with the pixel ray
    ``q = ((c - cx)/fx, (r - cy)/fy, 1)``.

    Parameters
    ----------
    scene : Scene
    cameras : sequence
        As in :func:`tangent_distance`.

    Returns
    -------
    np.ndarray
        (N, h, w) float32 perspective disparity in 1/metres (> 0).
    """
    _check_scene(scene)
    cams = _check_cameras(cameras)
    out = []
    for c in cams:
        dirs, ray_norm = _camera_rays(c)
        out.append((ray_norm / scene.distance(dirs)).astype(np.float32))
    return np.stack(out)


def _check_scene(scene: Any) -> None:
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be an m360.synthetic.Scene, got {type(scene).__name__}")


# -------------------------------------------------------------------- distortion


def _smooth_field(rng: np.random.Generator, h: int, w: int, n_waves: int = 4) -> np.ndarray:
    """Low-frequency random field on an (h, w) tangent with max |f| ≤ 1."""
    y = (np.arange(h, dtype=np.float64) + 0.5) / h
    x = (np.arange(w, dtype=np.float64) + 0.5) / w
    amp = rng.uniform(0.2, 1.0, size=n_waves)
    amp /= amp.sum()
    freq = rng.uniform(-1.5, 1.5, size=(n_waves, 2))
    phase = rng.uniform(0, 2 * np.pi, size=n_waves)
    f = np.zeros((h, w))
    for a, (fx, fy), p in zip(amp, freq, phase, strict=True):
        f += a * np.cos(2 * np.pi * (fx * x[None, :] + fy * y[:, None]) + p)
    return f


@renamed(tiles="tangents")
def distort(
    tangents: np.ndarray,
    seed: int,
    *,
    scale: tuple[float, float] = (0.5, 2.0),
    shift: float = 0.3,
    field: float = 0.0,
    noise: float = 0.0,
) -> np.ndarray:
    """Simulate a network's per-tangent affine ambiguity, plus an optional smooth warp and noise.

    For each tangent independently: ``d' = s·d + o`` with ``s`` log-uniform in ``scale`` and ``o``
    uniform in ``±shift·|median(d)|``; then, if ``field > 0``, ``d' *= 1 + field·f(x, y)`` with
    ``f`` a sum of four random low-frequency cosines (≤ 1.5 cycles per tangent, |f| ≤ 1); then, if
    ``noise > 0``, gaussian noise of std ``noise·|median(d)|`` is added. Medians ignore NaN; NaN
    stays NaN. The random draws per tangent do not depend on ``field``/``noise`` being zero, so the
    affine part for a given seed is the same whichever extras are enabled.

    Parameters
    ----------
    tangents : np.ndarray
        (N, h, w) floating array (typically perspective disparity).
    seed : int
        Seed of ``np.random.default_rng``.
    scale : (float, float)
        Range (lo ≤ hi, both > 0, at most 1e6) of the log-uniform scale.
    shift : float
        Relative shift amplitude (≥ 0, at most 1e6).
    field : float
        Amplitude of the multiplicative smooth field, in [0, 1).
    noise : float
        Relative noise std (≥ 0, at most 1e6).

    Returns
    -------
    np.ndarray
        (N, h, w) float32 (values beyond the float32 range become ±inf).
    """
    t = as_array(tangents, "tangents")
    if t.ndim != 3:
        raise InputError(f"tangents must have shape (N, h, w), got {t.shape}")
    if not np.issubdtype(t.dtype, np.floating):
        raise InputError(f"tangents must be a float array (float32 expected), got dtype {t.dtype}")
    with np.errstate(invalid="ignore"):
        too_large = np.abs(t[np.isfinite(t)]) > np.finfo(np.float32).max
    if too_large.any():
        raise InputError(f"tangents has {int(too_large.sum())} values beyond the float32 range")
    if not (isinstance(scale, (tuple, list)) and len(scale) == 2):
        raise InputError(f"scale must be a pair (lo, hi), got {scale!r}")
    # Bounded so that s·d + o and the noise stay far inside float64 for any float32 tangent.
    lo, hi = (number(v, "scale", low=0.0, high=SCENE_LIMIT) for v in scale)
    if not 0 < lo <= hi:
        raise InputError(f"scale must satisfy 0 < lo <= hi, got {scale!r}")
    shift = number(shift, "shift", low=0.0, high=SCENE_LIMIT)
    field = number(field, "field", low=0.0, high=1.0)
    if field == 1:
        raise InputError("field must be in [0, 1), got 1")
    noise = number(noise, "noise", low=0.0, high=SCENE_LIMIT)
    rng = np.random.default_rng(check_seed(seed))
    n, h, w = t.shape
    out = np.empty((n, h, w), dtype=np.float32)
    for k in range(n):
        d = t[k].astype(np.float64)
        finite = np.isfinite(d)
        med = float(np.abs(np.median(d[finite]))) if finite.any() else 0.0
        s = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        o = float(rng.uniform(-shift * med, shift * med))
        f = _smooth_field(rng, h, w)
        eps = rng.standard_normal((h, w))
        d = s * d + o
        if field > 0:
            d = d * (1.0 + field * f)
        if noise > 0:
            d = d + noise * med * eps
        with np.errstate(over="ignore"):  # beyond float32: ±inf, as documented
            out[k] = d
    return out


# -------------------------------------------------------------------- content errors


def _blur(d: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of std ``sigma`` pixels that ignores NaN (normalised convolution)."""
    import cv2  # opencv is a core dependency; imported here to keep `import m360` light

    valid = np.isfinite(d)
    filled = np.where(valid, d, 0.0)
    num = cv2.GaussianBlur(filled, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(valid.astype(np.float64), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    return np.where(valid, out, np.nan)


def content_errors(
    tangents: np.ndarray,
    seed: int,
    *,
    regions: tuple[int, int] = (1, 3),
    size: tuple[float, float] = (0.03, 1 / 6),
    amplitude: tuple[float, float] = (0.1, 0.3),
    blur: float = 0.0,
    return_regions: bool = False,
    reference_area: float | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Simulate a network's content errors: local regions of a tangent too near or too far.

    Each tangent independently gets between ``regions[0]`` and ``regions[1]`` (inclusive)
    elliptic regions at random positions (centres anywhere in the tile), each covering a
    fraction of the tile's area drawn uniformly from ``size``, with a random aspect ratio in
    [1/2, 2] and orientation; inside, the disparity is multiplied by ``1 ± a`` with ``a``
    uniform in ``amplitude`` and a random sign, fading to 1 over the outer fifth of the
    ellipse's radius (a flat-topped bump). The overlapping tangents do not share the error:
    every tangent's draws are its own. Then, if ``blur > 0``, every tangent is blurred with a
    gaussian of std ``blur`` pixels (lost fine detail of a low-resolution network input; NaN are
    ignored and stay NaN). Apply it to exact tangents before :func:`distort` to get both kinds of
    network error.

    Parameters
    ----------
    tangents : np.ndarray
        (N, h, w) floating array (typically perspective disparity).
    seed : int
        Seed of ``np.random.default_rng``.
    regions : (int, int)
        Range (0 ≤ lo ≤ hi ≤ 64) of the number of regions per tangent.
    size : (float, float)
        Range (0 < lo ≤ hi ≤ 1) of each region's area as a fraction of the tile's.
    amplitude : (float, float)
        Range (0 ≤ lo ≤ hi < 1) of the relative error a.
    blur : float
        Gaussian std in pixels (≥ 0, at most 1000); 0 = none.
    return_regions : bool
        Also return the (N, h, w) float32 map of the relative error factor minus 1 (0 outside
        every region), the ground truth of where the tangents are wrong.
    reference_area : float, optional
        Area in pixels (> 0) that ``size`` and ``regions`` refer to instead of the tile's own
        ``h * w``: region areas are fractions of it, and the number of regions drawn from
        ``regions`` is scaled by ``h * w / reference_area`` (rounded at random, seeded). Pass
        the paper's tile area at the same angular pixel size to give layouts with other tile
        sizes errors of the same angular size and the same density per solid angle. Default:
        the tile's area (the draws are then exactly those without it).

    Returns
    -------
    np.ndarray or (np.ndarray, np.ndarray)
        (N, h, w) float32 tangents with content errors, and the error map if asked.
    """
    t = as_array(tangents, "tangents")
    if t.ndim != 3:
        raise InputError(f"tangents must have shape (N, h, w), got {t.shape}")
    if not np.issubdtype(t.dtype, np.floating):
        raise InputError(f"tangents must be a float array (float32 expected), got dtype {t.dtype}")
    pairs = {"regions": regions, "size": size, "amplitude": amplitude}
    for name, pair in pairs.items():
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
            raise InputError(f"{name} must be a pair (lo, hi), got {pair!r}")
    r_lo, r_hi = (integer(v, "regions", low=0, high=64) for v in regions)
    s_lo, s_hi = (number(v, "size", low=0.0, high=1.0) for v in size)
    a_lo, a_hi = (number(v, "amplitude", low=0.0, high=1.0) for v in amplitude)
    if not r_lo <= r_hi:
        raise InputError(f"regions must satisfy lo <= hi, got {regions!r}")
    if not 0 < s_lo <= s_hi:
        raise InputError(f"size must satisfy 0 < lo <= hi <= 1, got {size!r}")
    if not a_lo <= a_hi < 1:
        raise InputError(f"amplitude must satisfy 0 <= lo <= hi < 1, got {amplitude!r}")
    blur = number(blur, "blur", low=0.0, high=1000.0)
    rng = np.random.default_rng(check_seed(seed))
    n, h, w = t.shape
    area_ref = float(h * w)
    if reference_area is not None:
        area_ref = number(reference_area, "reference_area", low=0.0)
        if not area_ref > 0:
            raise InputError(f"reference_area must be > 0, got {reference_area!r}")
    y = np.arange(h, dtype=np.float64)[:, None]
    x = np.arange(w, dtype=np.float64)[None, :]
    out = np.empty((n, h, w), dtype=np.float32)
    errors = np.zeros((n, h, w), dtype=np.float32)
    for k in range(n):
        factor = np.ones((h, w))
        count = int(rng.integers(r_lo, r_hi + 1))
        if reference_area is not None:  # same density per pixel area: scale, round at random
            expected = count * h * w / area_ref
            count = int(expected) + int(rng.random() < expected - int(expected))
        for _ in range(count):
            area = rng.uniform(s_lo, s_hi) * area_ref
            aspect = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
            ra = np.sqrt(area * aspect / np.pi)  # semi-axes with π·ra·rb = area
            rb = area / (np.pi * ra)
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            angle = rng.uniform(0, np.pi)
            a = rng.uniform(a_lo, a_hi) * rng.choice([-1.0, 1.0])
            u = (x - cx) * np.cos(angle) + (y - cy) * np.sin(angle)
            v = -(x - cx) * np.sin(angle) + (y - cy) * np.cos(angle)
            radius = np.sqrt((u / ra) ** 2 + (v / rb) ** 2)
            bump = np.clip((1.0 - radius) / 0.2, 0.0, 1.0)
            factor *= 1.0 + a * bump
        d = t[k].astype(np.float64) * factor
        if blur > 0:
            d = _blur(d, blur)
        out[k] = d
        errors[k] = factor - 1.0
    return (out, errors) if return_regions else out


# -------------------------------------------------------------------- panoramic prior


def _cap_share_radius(share: float) -> float:
    """Angular radius (radians) of a spherical cap covering ``share`` of the sphere."""
    return float(np.arccos(1.0 - 2.0 * share))


def panoramic_prior(
    truth: Any,
    seed: int,
    *,
    height: int = 512,
    blur: float = 1.5,
    field: float = 0.03,
    scale: tuple[float, float] = (0.5, 2.0),
    shift: float = 0.3,
    regions: tuple[int, int] = (0, 2),
    region_share: tuple[float, float] = (0.01, 0.05),
    region_amplitude: tuple[float, float] = (0.1, 0.3),
    return_regions: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Simulate a panoramic depth network's output: coarse, blurred, smoothly biased, affine.

    Panoramic networks (trained on whole ERP images) are globally consistent but run at about
    0.5 MP and blur above it, bend the geometry at low frequencies, and occasionally get a whole
    region wrong (windows, mirrors, sky). From the true distance this builds, as spherical
    disparity at ``height`` × 2·``height``:

    1. the true disparity 1/distance, area-averaged to that size (ray cast there for a scene);
    2. a gaussian blur of std ``blur`` pixels (wrapping in longitude): blurred edges;
    3. a smooth multiplicative error ``1 + field·f`` with ``f`` a sum of four random
       low-frequency waves over the sphere (≤ 2 cycles around it, |f| ≤ 1);
    4. between ``regions[0]`` and ``regions[1]`` regional errors: spherical caps at random
       centres, each covering a share of the sphere uniform in ``region_share``, whose
       disparity is multiplied by ``1 ± a`` (``a`` uniform in ``region_amplitude``, random
       sign), fading over the outer tenth of the cap's radius;
    5. the network's own affine ambiguity in disparity: ``s·d + o``, ``s`` log-uniform in
       ``scale``, ``o`` uniform in ``±shift·median(d)``.

    Parameters
    ----------
    truth : Scene or (H, 2H) array
        A scene (ray cast at the prior's size) or its true radial distance as an ERP map of
        any size (area-averaged in disparity to the prior's size); NaN = unknown.
    seed : int
        Seed of ``np.random.default_rng``.
    height : int
        Rows of the prior (columns: 2·height); default 512 (a 512 x 1024 network).
    blur : float
        Gaussian std in pixels (≥ 0, at most 100).
    field : float
        Amplitude of the smooth error, in [0, 1).
    scale : (float, float)
        Range (0 < lo ≤ hi) of the log-uniform scale.
    shift : float
        Relative shift amplitude (≥ 0).
    regions : (int, int)
        Range (0 ≤ lo ≤ hi ≤ 64) of the number of regional errors.
    region_share : (float, float)
        Range (0 < lo ≤ hi ≤ 1) of each region's share of the sphere.
    region_amplitude : (float, float)
        Range (0 ≤ lo ≤ hi < 1) of each region's relative error.
    return_regions : bool
        Also return the (height, 2·height) float32 map of the regional error factor minus 1.

    Returns
    -------
    np.ndarray or (np.ndarray, np.ndarray)
        (height, 2·height) float32 affine spherical disparity, and the region map if asked.
    """
    import cv2  # opencv is a core dependency; imported here to keep `import m360` light

    h = integer(height, "height", low=2, high=MAX_ERP_WIDTH // 2)
    blur = number(blur, "blur", low=0.0, high=100.0)
    field = number(field, "field", low=0.0, high=1.0)
    if field == 1:
        raise InputError("field must be in [0, 1), got 1")
    pairs = {
        "scale": (scale, 1e-6, SCENE_LIMIT),
        "region_share": (region_share, 0.0, 1.0),
        "region_amplitude": (region_amplitude, 0.0, 1.0),
    }
    checked: dict[str, tuple[float, float]] = {}
    for name, (pair, low, high) in pairs.items():
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
            raise InputError(f"{name} must be a pair (lo, hi), got {pair!r}")
        lo, hi = (number(v, name, low=low, high=high) for v in pair)
        if lo > hi:
            raise InputError(f"{name} must satisfy lo <= hi, got {pair!r}")
        checked[name] = (lo, hi)
    if checked["region_amplitude"][1] >= 1:
        raise InputError(f"region_amplitude must be < 1, got {region_amplitude!r}")
    if checked["region_share"][0] <= 0:
        raise InputError(f"region_share must be > 0, got {region_share!r}")
    if not (isinstance(regions, (tuple, list)) and len(regions) == 2):
        raise InputError(f"regions must be a pair (lo, hi), got {regions!r}")
    r_lo, r_hi = (integer(v, "regions", low=0, high=64) for v in regions)
    if r_lo > r_hi:
        raise InputError(f"regions must satisfy lo <= hi, got {regions!r}")
    shift = number(shift, "shift", low=0.0, high=SCENE_LIMIT)
    rng = np.random.default_rng(check_seed(seed))
    w = 2 * h
    lat = erp_latitudes(h)
    lon = erp_longitudes(w)
    dirs = lonlat_to_directions(lon[None, :], lat[:, None])
    if isinstance(truth, Scene):
        with np.errstate(divide="ignore"):
            disparity = 1.0 / truth.distance(dirs)
    else:
        distance = as_array(truth, "truth")
        if distance.ndim != 2 or distance.shape[1] != 2 * distance.shape[0]:
            raise InputError(
                f"truth must be a Scene or an (H, 2H) distance map, got shape {distance.shape}"
            )
        with np.errstate(divide="ignore", invalid="ignore"):
            full = np.where(distance > 0, 1.0 / distance.astype(np.float64), np.nan)
        valid = np.isfinite(full)
        num = cv2.resize(np.where(valid, full, 0.0), (w, h), interpolation=cv2.INTER_AREA)
        den = cv2.resize(valid.astype(np.float64), (w, h), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            disparity = np.where(den > 0, num / den, np.nan)
    d = np.asarray(disparity, np.float64)
    if blur > 0:
        # Wrap in longitude: pad by 4σ each side, blur, cut.
        pad = min(int(np.ceil(4 * blur)) + 1, w)
        padded = np.concatenate([d[:, -pad:], d, d[:, :pad]], axis=1)
        d = _blur(padded, blur)[:, pad : pad + w]
    # Smooth error over the sphere: waves in the direction coordinates.
    amp = rng.uniform(0.2, 1.0, size=4)
    amp /= amp.sum()
    axes = rng.standard_normal((4, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    freq = rng.uniform(0.5, 2.0, size=4)
    phase = rng.uniform(0, 2 * np.pi, size=4)
    smooth = np.zeros((h, w))
    for a, axis, f, p in zip(amp, axes, freq, phase, strict=True):
        smooth += a * np.cos(f * np.pi * (dirs @ axis) + p)
    d = d * (1.0 + field * smooth)
    factor = np.ones((h, w))
    for _ in range(int(rng.integers(r_lo, r_hi + 1))):
        share = rng.uniform(*checked["region_share"])
        centre = rng.standard_normal(3)
        centre /= np.linalg.norm(centre)
        radius = _cap_share_radius(share)
        angle = np.arccos(np.clip(dirs @ centre, -1.0, 1.0))
        a = rng.uniform(*checked["region_amplitude"]) * rng.choice([-1.0, 1.0])
        bump = np.clip((radius - angle) / (0.1 * radius), 0.0, 1.0)
        factor *= 1.0 + a * bump
    d = d * factor
    finite = np.isfinite(d)
    med = float(np.abs(np.median(d[finite]))) if finite.any() else 0.0
    lo, hi = checked["scale"]
    s = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    o = float(rng.uniform(-shift * med, shift * med))
    out = (s * d + o).astype(np.float32)
    regions_map = (factor - 1.0).astype(np.float32)
    return (out, regions_map) if return_regions else out


__all__ += ["panoramic_prior"]
