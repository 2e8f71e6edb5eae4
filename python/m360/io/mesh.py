"""Point clouds and meshes from ERP depth, and their PLY/GLB files.

Every 3D output is built in m360's world frame (docs/conventions.md: x right, y down, z forward,
camera at the origin): ERP pixel (i, j) with radial depth r becomes the point r·d(i, j). The mesh
lives on the ERP grid:

- columns W − 1 and 0 are neighbours, so the mesh is closed across the 0/360° seam;
- the first and last rows close with a fan of triangles to one vertex at each pole (its depth is
  the median of that row's depths);
- each grid quad is split along its shorter diagonal in 3D;
- a triangle is dropped when one of its depths is NaN (or ≤ 0) or when its largest depth exceeds
  its smallest by more than ``max_depth_ratio`` (an occlusion edge, not a surface).

Everything is vectorised numpy: index arrays over the whole grid, no Python list per vertex.
The writers (:func:`write_ply`, :func:`write_glb`) stream numpy arrays into the files (measured
faster and leaner than trimesh's exporters: benches/bench_3d.py); glTF is y-up, so
:func:`write_glb` rotates the frame at the writer (see :data:`FRAMES`). Reading back
(:func:`read_geometry`, the viewer) uses ``trimesh`` from the optional extra ``m360[3d]``.
"""

from __future__ import annotations

import io as _bytes_io
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import as_array, erp_map, flag, integer, number
from ..errors import InputError
from ..stitching.depth import depth_of

__all__ = [
    "DEFAULT_MAX_DEPTH_RATIO",
    "DEFAULT_MAX_VERTICES",
    "FRAMES",
    "Mesh",
    "PointCloud",
    "check_max_vertices",
    "erp_ray_grid",
    "stride_for",
    "to_mesh",
    "to_points",
    "write_glb",
    "write_mesh_glb",
    "write_ply",
    "write_points_ply",
]

#: Default cut of :func:`to_mesh`: a triangle whose depths differ by more than this ratio is
#: dropped. Measured on m360.synthetic rooms (benches/measure_depth_ratio.py, docs/method.md):
#: at 2K, 99.99 % of the grid triangles lying on one continuous surface have a ratio below
#: 1.06 (1.12 at 1K), while the triangles across an occlusion edge start at ~1.2.
DEFAULT_MAX_DEPTH_RATIO = 1.1

#: Default most vertices of a 3D output (:func:`to_points`, :func:`to_mesh`, the files
#: :func:`m360.save` writes): larger maps are strided to fit (4K stays whole, 8K takes every
#: 2nd pixel, the 12K street photo every 3rd). A 4K mesh is a 300 MB GLB that browsers still
#: open; the writers stream it in about 100 MB (docs/architecture.md, memory).
DEFAULT_MAX_VERTICES = 9_000_000

#: The frame each writer stores its coordinates in (also recorded in the sidecar's ``frame``).
FRAMES = {
    "ply": "m360 world frame: x right, y down, z forward (camera at the origin)",
    "glb": "glTF frame: x right, y up, z backward = (x, -y, -z) of the m360 frame",
}


@dataclass(frozen=True)
class PointCloud:
    """Points of an ERP depth map (see :func:`to_points`).

    Attributes
    ----------
    xyz : (N, 3) float32
        Positions in the m360 world frame (x right, y down, z forward), in the depth's units.
    rgb : (N, 3) uint8 or None
        Colours from the panorama.
    pixels : (N,) int64
        Flat ERP index ``i * W + j`` of each point's pixel (in the full-resolution map).
    units : str
        Units of ``xyz`` (``"metres"`` or ``"relative"``).
    """

    xyz: np.ndarray
    rgb: np.ndarray | None
    pixels: np.ndarray
    units: str = "relative"

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh on the ERP grid (see :func:`to_mesh`).

    Attributes
    ----------
    vertices : (V, 3) float32
        Positions in the m360 world frame; only vertices used by a face are kept.
    faces : (F, 3) int32 (int64 beyond 2**31 vertices)
        Vertex indices; counter-clockwise seen from the camera (normals face the origin).
    rgb : (V, 3) uint8 or None
        Vertex colours from the panorama (pole vertices: the mean colour of their row).
    units : str
        Units of ``vertices``.
    max_depth_ratio : float
        The cut used.
    """

    vertices: np.ndarray
    faces: np.ndarray
    rgb: np.ndarray | None
    units: str = "relative"
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO


# -------------------------------------------------------------------------------- inputs


def _depth_source(source: Any, quantity: str | None) -> tuple[np.ndarray, str, str]:
    """Return the checked (H, W) float map of a source, its name and its units."""
    if isinstance(source, (str, os.PathLike)):
        from .reading import load

        source = load(source)
    units = str(getattr(source, "units", "relative"))
    if hasattr(source, "depth") and hasattr(source, "disparity"):
        if quantity is not None:
            raise InputError("quantity applies to plain arrays only, not to a result")
        values = source.depth
        name = "result.depth"
    else:
        values = source
        name = "depth" if quantity in (None, "depth") else "disparity"
        if quantity not in (None, "depth", "disparity"):
            raise InputError(f"quantity must be 'depth' or 'disparity', got {quantity!r}")
    return erp_map(values, name), name, units


def _sanitised(array: np.ndarray, name: str) -> np.ndarray:
    """float32 radial depth of (part of) a checked map, NaN where invalid (a new array)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        depth = array.astype(np.float32)
        if name == "disparity":
            depth = depth_of(depth)
        depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return depth


def _rgb_of(rgb: Any, shape: tuple[int, int]) -> np.ndarray | None:
    if rgb is None:
        return None
    array = as_array(rgb, "rgb")
    if array.shape != (*shape, 3):
        raise InputError(
            f"rgb must be the panorama of the depth map, shape {(*shape, 3)}, got {array.shape}"
        )
    if array.dtype == np.uint8:
        return array
    if array.dtype.kind == "f":
        if not np.all(np.isfinite(array)) or array.min() < 0 or array.max() > 1:
            raise InputError("a float rgb must be in [0, 1] without NaN (uint8 is usual)")
        return np.rint(array * 255).astype(np.uint8)  # type: ignore[no-any-return]
    raise InputError(f"rgb has dtype {array.dtype}; use uint8 (or float in [0, 1])")


def erp_ray_grid(height: int, width: int, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rows and unit directions of a strided ERP pixel grid, float32, without a per-pixel loop.

    Returns ``rows`` (h,) int64 and ``directions`` (h, w, 3) float32 for the pixel centres
    ``(i, j)`` with ``i, j`` multiples of ``stride`` (docs/conventions.md).
    """
    rows = np.arange(0, height, stride)
    return rows, _ray_rows(rows, height, width, stride)


def _ray_rows(rows: np.ndarray, height: int, width: int, stride: int) -> np.ndarray:
    """Directions (len(rows), w, 3) float32 of the strided grid's pixel centres in ``rows``."""
    cols = np.arange(0, width, stride)
    lat = (np.pi / 2 - np.pi * (rows + 0.5) / height).astype(np.float32)
    lon = (2 * np.pi * (cols + 0.5) / width - np.pi).astype(np.float32)
    cos_lat = np.cos(lat)[:, None]
    dirs = np.empty((rows.size, cols.size, 3), np.float32)
    dirs[..., 0] = cos_lat * np.sin(lon)[None, :]
    dirs[..., 1] = -np.sin(lat)[:, None]
    dirs[..., 2] = cos_lat * np.cos(lon)[None, :]
    return dirs


def _stride(stride: Any) -> int:
    return integer(stride, "stride", low=1, high=1 << 16)


def check_max_vertices(max_vertices: Any) -> int | None:
    """Check a ``max_vertices``: None (no limit) or an integer >= 64."""
    if max_vertices is None:
        return None
    return integer(max_vertices, "max_vertices", low=64)


def stride_for(
    height: int,
    width: int,
    stride: int = 1,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
    extra: int = 0,
) -> int:
    """Return the least stride (>= ``stride``) whose grid has at most ``max_vertices`` vertices.

    A ``stride``-strided grid of an (height, width) map has ceil(height / s) x ceil(width / s)
    vertices, plus ``extra`` (a mesh's two pole vertices). ``max_vertices=None``: no limit.
    """
    step = _stride(stride)
    budget = check_max_vertices(max_vertices)
    if budget is None:
        return step
    while -(-height // step) * -(-width // step) + extra > budget:
        step += 1
    return step


#: Grid vertices per band of the streaming writers: a few tens of MB of temporaries.
_BAND_VERTICES = 1 << 20


class _Grid:
    """A strided ERP depth map read a band of rows at a time (no full-size copy)."""

    def __init__(self, array: np.ndarray, name: str, colours: np.ndarray | None, step: int) -> None:
        self.array, self.name, self.colours, self.step = array, name, colours, step
        self.height, self.width = array.shape
        self.rows = -(-self.height // step)
        self.cols = -(-self.width // step)
        self.band = max(1, _BAND_VERTICES // self.cols)

    def bands(self, rows: int | None = None) -> Iterator[tuple[int, int]]:
        total = self.rows if rows is None else rows
        for start in range(0, total, self.band):
            yield start, min(start + self.band, total)

    def depth(self, r0: int, r1: int) -> np.ndarray:
        s = self.step
        return _sanitised(self.array[r0 * s : r1 * s : s, ::s], self.name)

    def dirs(self, r0: int, r1: int) -> np.ndarray:
        return _ray_rows(np.arange(r0 * self.step, r1 * self.step, self.step), self.height,
                         self.width, self.step)  # fmt: skip

    def rgb(self, r0: int, r1: int) -> np.ndarray | None:
        if self.colours is None:
            return None
        s = self.step
        return np.ascontiguousarray(self.colours[r0 * s : r1 * s : s, ::s])


# -------------------------------------------------------------------------------- points


def to_points(
    source: Any,
    *,
    rgb: Any = None,
    stride: int = 1,
    quantity: str | None = None,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
) -> PointCloud:
    """Turn an ERP depth map into a point cloud: each valid pixel's ray times its depth.

    Parameters
    ----------
    source : EstimateResult, SavedResult, path or (H, W) float array
        A result of :func:`m360.estimate`, one read by :func:`m360.load`, an output stem or file
        (read with :func:`m360.load`), or a plain ERP map (W == 2H, docs/conventions.md) of
        radial depth (or disparity with ``quantity="disparity"``); NaN / ≤ 0 = invalid.
    rgb : (H, W, 3) uint8, optional
        The panorama: colours of the points.
    stride : int
        Keep every ``stride``-th row and column (pixel centres ``i, j ≡ 0 mod stride``).
    quantity : {"depth", "disparity"}, optional
        What a plain array holds (default depth).
    max_vertices : int or None
        At most this many points: a larger grid takes a larger stride (:func:`stride_for`;
        default :data:`DEFAULT_MAX_VERTICES`, None = no limit).

    Returns
    -------
    PointCloud
        ``xyz`` (N, 3) float32 in the m360 frame (x right, y down, z forward), ``rgb`` (N, 3)
        uint8 or None, ``pixels`` (N,) flat ERP indices.

    Raises
    ------
    InputError
        Not an ERP map, shapes differ, or no valid depth at all.
    """
    array, name, units = _depth_source(source, quantity)
    height, width = array.shape
    colours = _rgb_of(rgb, (height, width))
    step = stride_for(height, width, stride, max_vertices)
    rows, dirs = erp_ray_grid(height, width, step)
    sub = _sanitised(array[::step, ::step], name)  # strided first: no full-size copy
    valid = np.isfinite(sub)
    if not valid.any():
        raise InputError("the depth map has no valid (finite, > 0) value: no points to make")
    flat_index = (rows[:, None] * width + np.arange(0, width, step)[None, :])[valid]
    xyz = dirs[valid] * sub[valid][:, None]
    colour = None if colours is None else colours[::step, ::step][valid]
    return PointCloud(xyz=xyz, rgb=colour, pixels=flat_index.astype(np.int64), units=units)


# -------------------------------------------------------------------------------- mesh


def to_mesh(
    source: Any,
    *,
    rgb: Any = None,
    stride: int = 1,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    poles: bool = True,
    quantity: str | None = None,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
) -> Mesh:
    """Triangulate an ERP depth map on its pixel grid (closed at the seam, fans at the poles).

    Parameters
    ----------
    source : EstimateResult, SavedResult, path or (H, W) float array
        As for :func:`to_points`.
    rgb : (H, W, 3) uint8, optional
        The panorama: vertex colours.
    stride : int
        Mesh every ``stride``-th row and column (column wrap and pole fans included).
    max_depth_ratio : float
        Drop a triangle whose largest depth exceeds its smallest by more than this factor
        (> 1; ``inf`` keeps every triangle with finite depths). Default
        :data:`DEFAULT_MAX_DEPTH_RATIO`, measured on synthetic rooms (docs/method.md).
    poles : bool
        Close the first and last grid rows with a fan to a pole vertex.
    quantity : {"depth", "disparity"}, optional
        What a plain array holds (default depth).
    max_vertices : int or None
        At most this many vertices (pole vertices included): a larger grid takes a larger
        stride (:func:`stride_for`; default :data:`DEFAULT_MAX_VERTICES`, None = no limit).

    Returns
    -------
    Mesh
        Vertices in the m360 frame, faces counter-clockwise seen from the camera.

    Raises
    ------
    InputError
        Not an ERP map, shapes differ, no valid depth, or no triangle survives the cut.
    """
    array, name, units = _depth_source(source, quantity)
    height, width = array.shape
    colours = _rgb_of(rgb, (height, width))
    ratio, closed, step = _mesh_cut(height, width, max_depth_ratio, poles, stride, max_vertices)
    _, dirs = erp_ray_grid(height, width, step)
    grid = _sanitised(array[::step, ::step], name)  # strided first: no full-size copy
    rows, cols = grid.shape
    if not np.isfinite(grid).any():
        raise InputError("the depth map has no valid (finite, > 0) value: no mesh to make")
    if rows < 2 or cols < 3:
        raise InputError(f"stride {step} leaves a {rows}x{cols} grid; a mesh needs at least 2x3")

    n_grid = rows * cols
    verts = dirs * grid[..., None]  # (rows, cols, 3)
    index_type = np.int32 if n_grid + 2 < np.iinfo(np.int32).max else np.int64
    keep1, keep2, use_ad = _quads(grid, verts, ratio)
    parts = [
        _triangles(keep, use_ad, k == 0, 0, cols, index_type)
        for k, keep in enumerate((keep1, keep2))
    ]
    del keep1, keep2, use_ad
    all_verts = verts.reshape(n_grid, 3)
    all_rgb = None if colours is None else colours[::step, ::step].reshape(n_grid, 3)
    if closed:
        ring_rgb = (None, None) if all_rgb is None else (all_rgb[:cols], all_rgb[-cols:])
        fans, pole_verts, pole_rgb = _pole_fans(
            grid[0], grid[-1], ring_rgb, rows, ratio, index_type
        )
        parts += fans
        all_verts = np.concatenate([all_verts, np.stack(pole_verts)])
        if all_rgb is not None:
            all_rgb = np.concatenate([all_rgb, np.stack(pole_rgb)])

    faces = np.concatenate(parts)
    if faces.shape[0] == 0:
        raise InputError(
            f"no triangle survives: every one touches NaN or spans a depth ratio above {ratio:g}"
        )
    used = np.zeros(all_verts.shape[0], bool)
    used[faces.ravel()] = True
    remap = (np.cumsum(used, dtype=np.int64) - 1).astype(index_type)
    return Mesh(
        vertices=np.ascontiguousarray(all_verts[used], np.float32),
        faces=remap[faces],
        rgb=None if all_rgb is None else all_rgb[used],
        units=units,
        max_depth_ratio=ratio,
    )


# -------------------------------------------------------------------------------- writers


def _mesh_cut(
    height: int,
    width: int,
    max_depth_ratio: float,
    poles: bool,
    stride: int,
    max_vertices: int | None,
) -> tuple[float, bool, int]:
    """Check a mesh's options: the depth-jump ratio, the pole fans and the stride to use."""
    ratio = (
        number(max_depth_ratio, "max_depth_ratio", low=1.0)
        if np.isfinite(max_depth_ratio)
        else float("inf")
    )
    if not ratio > 1.0:
        raise InputError(f"max_depth_ratio must be > 1, got {max_depth_ratio!r}")
    closed = flag(poles, "poles")
    return ratio, closed, stride_for(height, width, stride, max_vertices, 2 if closed else 0)


def _trimesh() -> Any:
    try:
        import trimesh
    except ImportError as exc:  # the optional extra
        raise InputError(
            "writing PLY/GLB needs the optional extra: pip install 'm360[3d]' (trimesh)"
        ) from exc
    return trimesh


def _geometry(item: Any) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    if isinstance(item, Mesh):
        return item.vertices, item.faces, item.rgb
    if isinstance(item, PointCloud):
        return item.xyz, None, item.rgb
    raise InputError(f"expected an m360 Mesh or PointCloud, got {type(item).__name__}")


def _ply_header(n_vertices: int, n_faces: int | None, colours: bool) -> bytes:
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment m360: x right, y down, z forward (camera at the origin)",
        f"element vertex {n_vertices}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if colours:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    if n_faces is not None:
        lines += [f"element face {n_faces}", "property list uchar int vertex_indices"]
    return ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")


#: Vertices per chunk of the in-memory writers (tens of MB of records at a time).
_CHUNK = 1 << 20


def _vertex_records(xyz: np.ndarray, rgb: np.ndarray | None) -> np.ndarray:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(xyz.shape[0], np.dtype(fields))
    for k, name in enumerate("xyz"):
        records[name] = xyz[:, k]
    if rgb is not None:
        for k, name in enumerate(("red", "green", "blue")):
            records[name] = rgb[:, k]
    return records


def _face_records(faces: np.ndarray) -> np.ndarray:
    records = np.empty(faces.shape[0], np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    records["n"] = 3
    records["v"] = faces
    return records


def write_ply(path: str | os.PathLike[str], item: Mesh | PointCloud) -> Path:
    """Write a mesh or point cloud as binary little-endian PLY (m360 frame), atomically.

    Vertices ``x, y, z`` float32 (and ``red, green, blue`` uchar when coloured), faces as
    ``vertex_indices`` lists of 3 int32. Written from numpy record arrays a chunk of about a
    million vertices (faces) at a time (no copy of the whole file in memory, no per-vertex
    Python). :func:`write_points_ply` writes a depth map's points without building them.
    """
    from .files import atomic_path

    vertices, faces, rgb = _geometry(item)
    n_faces = None if faces is None else faces.shape[0]
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(_ply_header(vertices.shape[0], n_faces, rgb is not None))
        for k in range(0, vertices.shape[0], _CHUNK):
            part = slice(k, k + _CHUNK)
            _vertex_records(vertices[part], None if rgb is None else rgb[part]).tofile(f)
        if faces is not None:
            for k in range(0, faces.shape[0], _CHUNK):
                _face_records(faces[k : k + _CHUNK]).tofile(f)
    return target


def _glb_start(
    n: int, n_indices: int | None, coloured: bool, low: list[float], high: list[float]
) -> tuple[bytes, int]:
    """Return the GLB's header, JSON chunk and binary chunk header, and the binary length.

    The binary chunk holds POSITION float32 (n, 3), COLOR_0 RGBA uint8 (n, 4) when coloured,
    and uint32 indices (triangles; points without), in that order.
    """
    import json

    views = [{"buffer": 0, "byteOffset": 0, "byteLength": 12 * n, "target": 34962}]
    accessors: list[dict[str, Any]] = [
        {
            "bufferView": 0,
            "componentType": 5126,
            "count": n,
            "type": "VEC3",
            "min": low if n else [0, 0, 0],
            "max": high if n else [0, 0, 0],
        }
    ]
    attributes = {"POSITION": 0}
    offset = 12 * n
    if coloured:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": 4 * n, "target": 34962})
        accessors.append(
            {"bufferView": 1, "componentType": 5121, "normalized": True, "count": n, "type": "VEC4"}
        )
        attributes["COLOR_0"] = 1
        offset += 4 * n
    primitive: dict[str, Any] = {"attributes": attributes, "mode": 0}
    if n_indices is not None:
        views.append(
            {"buffer": 0, "byteOffset": offset, "byteLength": 4 * n_indices, "target": 34963}
        )
        accessors.append(
            {
                "bufferView": len(views) - 1,
                "componentType": 5125,
                "count": n_indices,
                "type": "SCALAR",
            }
        )
        primitive.update(indices=len(accessors) - 1, mode=4)
        offset += 4 * n_indices
    gltf = {
        "asset": {"version": "2.0", "generator": "m360"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [primitive]}],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    # every part above is a multiple of 4 bytes: the binary chunk needs no padding
    total = 12 + 8 + len(text) + 8 + offset
    head = b"glTF" + np.array([2, total, len(text), 0x4E4F534A], "<u4").tobytes() + text
    return head + np.array([offset, 0x004E4942], "<u4").tobytes(), offset


#: glTF is y up, z backward: (x, -y, -z) of the m360 frame.
_TO_GLTF = np.array([1.0, -1.0, -1.0], np.float32)


def _rgba(rgb: np.ndarray) -> np.ndarray:
    rgba = np.empty((rgb.shape[0], 4), np.uint8)
    rgba[:, :3] = rgb
    rgba[:, 3] = 255
    return rgba


def write_glb(path: str | os.PathLike[str], item: Mesh | PointCloud) -> Path:
    """Write a mesh or point cloud as binary glTF 2.0 (GLB, y up: see :data:`FRAMES`), atomically.

    One mesh primitive: ``POSITION`` float32 (the m360 frame turned by π about x),
    ``COLOR_0`` normalised RGBA uint8 when coloured, uint32 ``indices`` (triangles; points
    without faces). Written from numpy arrays a chunk at a time; :func:`write_mesh_glb` writes
    a depth map's mesh without building it.
    """
    from .files import atomic_path

    vertices, faces, rgb = _geometry(item)
    n = vertices.shape[0]
    low = np.full(3, np.inf, np.float32)
    high = np.full(3, -np.inf, np.float32)
    for k in range(0, n, _CHUNK):
        part = vertices[k : k + _CHUNK] * _TO_GLTF
        low, high = np.minimum(low, part.min(axis=0)), np.maximum(high, part.max(axis=0))
    n_indices = None if faces is None else faces.size
    head, _ = _glb_start(n, n_indices, rgb is not None, low.tolist(), high.tolist())
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(head)
        for k in range(0, n, _CHUNK):
            (vertices[k : k + _CHUNK] * _TO_GLTF).tofile(f)
        if rgb is not None:
            for k in range(0, n, _CHUNK):
                _rgba(rgb[k : k + _CHUNK]).tofile(f)
        if faces is not None:
            for k in range(0, faces.shape[0], _CHUNK):
                np.ascontiguousarray(faces[k : k + _CHUNK], np.uint32).tofile(f)
    return target


# -------------------------------------------------------------------------------- streaming


def write_points_ply(
    path: str | os.PathLike[str],
    source: Any,
    *,
    rgb: Any = None,
    stride: int = 1,
    quantity: str | None = None,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
) -> dict[str, int]:
    """Write :func:`to_points`'s cloud as :func:`write_ply` does, a band of rows at a time.

    The same bytes as ``write_ply(path, to_points(source, ...))`` without the cloud's
    full-size arrays: memory stays a band's (about a million points) whatever the map's size.

    Returns
    -------
    dict
        ``stride`` (the one used, see :func:`stride_for`) and ``vertices`` (points written).
    """
    from .files import atomic_path

    array, name, _ = _depth_source(source, quantity)
    height, width = array.shape
    step = stride_for(height, width, stride, max_vertices)
    grid = _Grid(array, name, _rgb_of(rgb, (height, width)), step)
    count = sum(int(np.isfinite(grid.depth(r0, r1)).sum()) for r0, r1 in grid.bands())
    if not count:
        raise InputError("the depth map has no valid (finite, > 0) value: no points to make")
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(_ply_header(count, None, grid.colours is not None))
        for r0, r1 in grid.bands():
            depth = grid.depth(r0, r1)
            valid = np.isfinite(depth)
            xyz = grid.dirs(r0, r1)[valid] * depth[valid][:, None]
            colours = grid.rgb(r0, r1)
            _vertex_records(xyz, None if colours is None else colours[valid]).tofile(f)
    return {"stride": grid.step, "vertices": count}


def _kept(ratio: float, r0: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    # NaN anywhere makes both sides NaN and the comparison False: dropped.
    with np.errstate(invalid="ignore"):
        top = np.maximum(np.maximum(r0, r1), r2)
        low = np.minimum(np.minimum(r0, r1), r2)
        return top <= ratio * low  # type: ignore[no-any-return]


def _right(a: np.ndarray) -> np.ndarray:
    """Column j + 1 of every grid column j, wrapping W − 1 → 0."""
    return np.concatenate([a[:, 1:], a[:, :1]], axis=1)


def _quads(
    depth: np.ndarray, verts: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """keep1, keep2, use_ad of the quads between the grid rows of ``depth`` (r, c) and ``verts``.

    A quad's corners are a = (i, j), b = (i, j+1), c = (i+1, j), d = (i+1, j+1) (whole-array
    slices, no per-index gathers); it is split along its shorter 3D diagonal (a NaN diagonal
    counts as infinitely long), into tri1 = (a, c, d) or (a, c, b) and tri2 = (a, d, b) or
    (b, c, d), all counter-clockwise seen from the camera; a triangle is kept by :func:`_kept`.
    """
    r_a, r_c = depth[:-1], depth[1:]
    r_b, r_d = _right(depth)[:-1], _right(depth)[1:]
    v_right = _right(verts)
    diff_ad = verts[:-1] - v_right[1:]
    diff_bc = v_right[:-1] - verts[1:]
    len_ad = np.einsum("ijk,ijk->ij", diff_ad, diff_ad)
    len_bc = np.einsum("ijk,ijk->ij", diff_bc, diff_bc)
    del diff_ad, diff_bc, v_right
    use_ad = np.nan_to_num(len_ad, nan=np.inf) <= np.nan_to_num(len_bc, nan=np.inf)
    keep1 = _kept(ratio, r_a, r_c, np.where(use_ad, r_d, r_b))
    keep2 = np.where(use_ad, _kept(ratio, r_a, r_d, r_b), _kept(ratio, r_b, r_c, r_d))
    return keep1, keep2, use_ad


def _pole_fans(
    first: np.ndarray,
    last: np.ndarray,
    ring_rgb: tuple[np.ndarray | None, np.ndarray | None],
    rows: int,
    ratio: float,
    index_type: type,
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Close the first and last grid rows with a fan to a pole vertex each (see :func:`to_mesh`).

    Returns the fans' triangles, the two pole vertices (at the median depth of their ring, on
    the axis) and, with colours, the poles' colours (their ring's mean). The pole vertices are
    numbered after the ``rows`` x ``len(first)`` grid.
    """
    cols = len(first)
    n_grid = rows * cols
    fans, pole_verts, pole_rgb = [], [], []
    for k, (row_r, row, sign) in enumerate(((first, 0, -1.0), (last, rows - 1, 1.0))):
        finite = np.isfinite(row_r)
        pole_r = float(np.median(row_r[finite])) if finite.any() else np.nan
        pole_verts.append(np.array([0.0, sign * pole_r, 0.0], np.float32))
        colours = ring_rgb[k]
        if colours is not None:
            pole_rgb.append(np.rint(colours.mean(axis=0)).astype(np.uint8))
        ring: np.ndarray = np.arange(row * cols, (row + 1) * cols, dtype=index_type)
        nxt = np.roll(ring, -1)
        ok = _kept(ratio, row_r, np.roll(row_r, -1), np.full(cols, pole_r, np.float32))
        apex: np.ndarray = np.full(int(ok.sum()), n_grid + k, index_type)
        # top: (pole, ring[j], ring[j+1]); bottom: (ring[j], pole, ring[j+1]) — both CCW seen
        # from the camera, like the grid's triangles.
        fans.append(
            np.stack([apex, ring[ok], nxt[ok]], 1)
            if k == 0
            else np.stack([ring[ok], apex, nxt[ok]], 1)
        )
    return fans, pole_verts, pole_rgb


def _triangles(
    keep: np.ndarray, use_ad: np.ndarray, first: bool, q0: int, cols: int, index_type: type
) -> np.ndarray:
    """Return the triangles (t, 3) of a band of quads from grid row q0 (see :func:`to_mesh`)."""
    q: np.ndarray = np.flatnonzero(keep).astype(index_type)
    i, j = np.divmod(q, index_type(cols))
    i += index_type(q0)
    jn = j + 1
    jn[jn == cols] = 0
    a, b = i * cols + j, i * cols + jn
    c, d, ad = a + cols, b + cols, use_ad.ravel()[q]
    if first:  # (a, c, d) or (a, c, b)
        return np.stack([a, c, np.where(ad, d, b)], axis=1)
    return np.stack([np.where(ad, a, b), np.where(ad, d, c), np.where(ad, b, d)], axis=1)


def write_mesh_glb(
    path: str | os.PathLike[str],
    source: Any,
    *,
    rgb: Any = None,
    stride: int = 1,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    poles: bool = True,
    quantity: str | None = None,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
) -> dict[str, int]:
    """Write :func:`to_mesh`'s mesh as :func:`write_glb` does, a band of rows at a time.

    The same bytes as ``write_glb(path, to_mesh(source, ...))``; in memory only per-quad flags
    (3 bytes a quad) and the vertex renumbering (5 bytes a grid vertex) besides a band's
    temporaries. The grid is read three times: which triangles survive, the positions' bounds
    (the header comes first), and the data.

    Returns
    -------
    dict
        ``stride`` (the one used, see :func:`stride_for`), ``vertices`` and ``faces`` written.
    """
    from .files import atomic_path

    array, name, _ = _depth_source(source, quantity)
    height, width = array.shape
    colours = _rgb_of(rgb, (height, width))
    ratio, closed, step = _mesh_cut(height, width, max_depth_ratio, poles, stride, max_vertices)
    grid = _Grid(array, name, colours, step)
    rows, cols = grid.rows, grid.cols
    first, last = grid.depth(0, 1)[0], grid.depth(rows - 1, rows)[0]
    if not any(np.isfinite(grid.depth(r0, r1)).any() for r0, r1 in grid.bands()):
        raise InputError("the depth map has no valid (finite, > 0) value: no mesh to make")
    if rows < 2 or cols < 3:
        raise InputError(f"stride {step} leaves a {rows}x{cols} grid; a mesh needs at least 2x3")
    n_grid = rows * cols
    index_type = np.int32 if n_grid + 2 < np.iinfo(np.int32).max else np.int64

    # Pass 1: which triangles survive (per-quad flags) and which vertices they use.
    keep1 = np.empty((rows - 1, cols), bool)
    keep2 = np.empty((rows - 1, cols), bool)
    use_ad = np.empty((rows - 1, cols), bool)
    used = np.zeros(n_grid + 2, bool)
    n_faces = 0
    for q0, q1 in grid.bands(rows - 1):
        depth = grid.depth(q0, q1 + 1)
        verts = grid.dirs(q0, q1 + 1) * depth[..., None]
        keep1[q0:q1], keep2[q0:q1], use_ad[q0:q1] = _quads(depth, verts, ratio)
        for k, keep in enumerate((keep1, keep2)):
            tri = _triangles(keep[q0:q1], use_ad[q0:q1], k == 0, q0, cols, index_type)
            used[tri.ravel()] = True
            n_faces += tri.shape[0]
    fans: list[np.ndarray] = []
    pole_verts: list[np.ndarray] = []
    pole_rgb: list[np.ndarray] = []
    if closed:
        top, bottom = grid.rgb(0, 1), grid.rgb(rows - 1, rows)
        rings = (None if top is None else top[0], None if bottom is None else bottom[0])
        fans, pole_verts, pole_rgb = _pole_fans(first, last, rings, rows, ratio, index_type)
        for fan in fans:
            used[fan.ravel()] = True
            n_faces += fan.shape[0]
    if n_faces == 0:
        raise InputError(
            f"no triangle survives: every one touches NaN or spans a depth ratio above {ratio:g}"
        )
    remap = np.cumsum(used, dtype=index_type)
    remap -= 1
    n_verts = int(remap[-1]) + 1

    def positions(r0: int, r1: int) -> np.ndarray:
        verts = (grid.dirs(r0, r1) * grid.depth(r0, r1)[..., None]).reshape(-1, 3)
        return verts[used[r0 * cols : r1 * cols]] * _TO_GLTF  # type: ignore[no-any-return]

    poles_used = used[n_grid:]
    pole_positions = (
        np.stack(pole_verts)[poles_used] * _TO_GLTF if closed else np.empty((0, 3), np.float32)
    )
    # Pass 2: the bounds of the positions (the JSON header holds them).
    low = np.full(3, np.inf, np.float32)
    high = np.full(3, -np.inf, np.float32)
    for part in [*(positions(r0, r1) for r0, r1 in grid.bands()), pole_positions]:
        if part.shape[0]:
            low, high = np.minimum(low, part.min(axis=0)), np.maximum(high, part.max(axis=0))
    head, _ = _glb_start(n_verts, 3 * n_faces, colours is not None, low.tolist(), high.tolist())
    # Pass 3: the data, in the order of write_glb(to_mesh(...)).
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(head)
        for r0, r1 in grid.bands():
            positions(r0, r1).tofile(f)
        pole_positions.tofile(f)
        if colours is not None:
            for r0, r1 in grid.bands():
                band_rgb = grid.rgb(r0, r1)
                assert band_rgb is not None
                _rgba(band_rgb.reshape(-1, 3)[used[r0 * cols : r1 * cols]]).tofile(f)
            if closed:
                _rgba(np.stack(pole_rgb)[poles_used]).tofile(f)
        for k, keep in enumerate((keep1, keep2)):
            for q0, q1 in grid.bands(rows - 1):
                tri = _triangles(keep[q0:q1], use_ad[q0:q1], k == 0, q0, cols, index_type)
                remap[tri].astype(np.uint32).tofile(f)
        for fan in fans:
            remap[fan].astype(np.uint32).tofile(f)
    return {"stride": step, "vertices": n_verts, "faces": n_faces}


def read_geometry(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices (in the m360 frame) and faces (or None) of a PLY/GLB file written by m360."""
    trimesh = _trimesh()
    p = Path(path)
    from .decode import read_bytes

    data = read_bytes(p, "3D file")
    loaded = trimesh.load(_bytes_io.BytesIO(data), file_type=p.suffix[1:].lower(), process=False)
    if hasattr(loaded, "dump"):  # a glTF scene
        geoms = list(loaded.geometry.values())
        loaded = geoms[0] if len(geoms) == 1 else loaded.dump(concatenate=True)
    vertices = np.asarray(loaded.vertices, np.float32)
    if p.suffix.lower() == ".glb":
        vertices = vertices * np.array([1.0, -1.0, -1.0], np.float32)
    faces = getattr(loaded, "faces", None)
    return vertices, None if faces is None else np.asarray(faces)
