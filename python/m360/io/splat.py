"""3D Gaussian splats of an ERP depth map (:func:`to_splats`) and their PLY file.

One flat Gaussian per pixel of the (strided) grid, in the layout of the 3D Gaussian Splatting
reference code (Kerbl et al. 2023) that its viewers and trainers read: binary little-endian
PLY, one ``vertex`` element of float32 properties

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

with ``f_dc`` the degree-0 spherical-harmonic colour ((c − 0.5) / C0, C0 = 0.28209479; no
``f_rest_*``: load with SH degree 0), ``opacity`` before the sigmoid (logit), ``scale_k`` the
log of the standard deviations along the rotation's axes, ``rot`` a unit quaternion
(w, x, y, z). The covariance is R diag(exp(scale))² Rᵀ. Coordinates are m360's frame (x right,
y down, z forward), which is also COLMAP's/OpenCV's, the frame 3DGS scenes are in.

The splat of a pixel lies in the surface's plane (:func:`m360.normals`: its third axis is the
normal, its third scale :data:`THICKNESS` of the second) and covers the pixel's footprint: the
two chords to its neighbours along longitude and latitude span the footprint on the surface, and
the in-plane covariance is :data:`FOOTPRINT_SIGMA`² times the sum of their outer products (a
frontal square pixel of side h gets σ = FOOTPRINT_SIGMA · h; a pixel seen at a grazing angle a
long one). The grid, its stride and vertex budget, and the depth-jump rule are the mesh's
(:func:`m360.to_mesh`): a pixel gets a splat when it has a depth and, along longitude and along
latitude, a neighbour within ``max_depth_ratio``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import number
from ..errors import InputError
from .mesh import (
    DEFAULT_MAX_DEPTH_RATIO,
    DEFAULT_MAX_VERTICES,
    _depth_source,
    _rgb_of,
    stride_for,
)
from .normals import _ratio, _SphereGrid

__all__ = [
    "DEFAULT_OPACITY",
    "FOOTPRINT_SIGMA",
    "FRAME",
    "SH_C0",
    "SPLAT_PROPERTIES",
    "THICKNESS",
    "Splats",
    "read_splats",
    "to_splats",
    "write_splat_ply",
    "write_splats",
]

#: The degree-0 spherical-harmonic constant: colour = 0.5 + SH_C0 · f_dc.
SH_C0 = 0.28209479177387814
#: Standard deviation of a splat in its plane, in units of its pixel's footprint (chosen so
#: that neighbouring splats overlap into a closed surface seen from the centre).
FOOTPRINT_SIGMA = 0.6
#: Standard deviation along the normal, as a share of the smaller in-plane one (flat discs).
THICKNESS = 0.1
#: Default opacity of every splat (after the sigmoid).
DEFAULT_OPACITY = 0.95
#: The PLY's vertex properties, in order (all float32).
SPLAT_PROPERTIES = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip
#: The frame of the file (recorded in the sidecar's ``frame``).
FRAME = (
    "m360 world frame: x right, y down, z forward (camera at the origin; COLMAP/OpenCV "
    "convention); 3D Gaussian Splatting PLY, SH degree 0, rot = (w, x, y, z), log scales, "
    "logit opacity"
)
_RECORD = np.dtype([(name, "<f4") for name in SPLAT_PROPERTIES])


@dataclass(frozen=True)
class Splats:
    """Gaussian splats of an ERP depth map (see :func:`to_splats`), as the PLY stores them.

    Attributes
    ----------
    xyz : (N, 3) float32
        Centres in the m360 world frame.
    normals : (N, 3) float32
        Unit normals facing the camera (the splats' thin axis).
    f_dc : (N, 3) float32
        Degree-0 SH colour: RGB in [0, 1] = 0.5 + SH_C0 · f_dc.
    opacity : (N,) float32
        Opacity before the sigmoid (logit).
    scales : (N, 3) float32
        Log standard deviations along the rotation's three axes (the third: the normal).
    rotations : (N, 4) float32
        Unit quaternions (w, x, y, z), w ≥ 0.
    pixels : (N,) int64
        Flat ERP index ``i * W + j`` of each splat's pixel.
    units : str
        Units of ``xyz`` (``"metres"`` or ``"relative"``).
    """

    xyz: np.ndarray
    normals: np.ndarray
    f_dc: np.ndarray
    opacity: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    pixels: np.ndarray
    units: str = "relative"

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) float32 covariances R diag(exp(scales))² Rᵀ."""
        return covariances(self.rotations, self.scales)

    def colours(self) -> np.ndarray:
        """(N, 3) float32 RGB in [0, 1] of the degree-0 colour."""
        return np.clip(0.5 + SH_C0 * self.f_dc, 0.0, 1.0)


def rotation_matrices(wxyz: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 4) quaternions (w, x, y, z), normalised first."""
    q = wxyz / np.linalg.norm(wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def covariances(wxyz: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """(N, 3, 3) covariances R diag(exp(log_scales))² Rᵀ (the 3DGS convention)."""
    axes = rotation_matrices(wxyz) * np.exp(log_scales)[:, None, :]
    return np.einsum("nik,njk->nij", axes, axes)  # type: ignore[no-any-return]


def _quaternions(rot: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z), w ≥ 0, of (N, 3, 3) rotation matrices.

    Shepperd's method: of w, x, y, z the largest is taken from the diagonal (never a square
    root of a value near 0), the others from off-diagonal sums, per row without a loop.
    """
    m = rot
    diag = np.stack([m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]])
    largest = np.argmax(np.stack([diag[0], diag[1], diag[2], diag[3]]), axis=0)
    sums = {
        "wx": m[:, 2, 1] - m[:, 1, 2],
        "wy": m[:, 0, 2] - m[:, 2, 0],
        "wz": m[:, 1, 0] - m[:, 0, 1],
        "xy": m[:, 0, 1] + m[:, 1, 0],
        "xz": m[:, 0, 2] + m[:, 2, 0],
        "yz": m[:, 1, 2] + m[:, 2, 1],
    }
    q = np.empty((rot.shape[0], 4), rot.dtype)
    # 4·q_k² = 1 + trace (k = w) or 1 + 2 m_kk − trace (k = x, y, z)
    fours = [1 + diag[0], 1 + 2 * diag[1] - diag[0], 1 + 2 * diag[2] - diag[0],
             1 + 2 * diag[3] - diag[0]]  # fmt: skip
    rows = (
        ("wx", "wy", "wz"),  # w largest: x, y, z from (w·x, w·y, w·z) sums
        ("wx", "xy", "xz"),  # x largest: w, y, z
        ("wy", "xy", "yz"),  # y largest: w, x, z
        ("wz", "xz", "yz"),  # z largest: w, x, y
    )
    for k in range(4):
        pick = largest == k
        if not pick.any():
            continue
        s = 2 * np.sqrt(np.maximum(fours[k][pick], 1e-12))  # 4 q_k
        others = [sums[name][pick] / s for name in rows[k]]
        parts = [*others[:k], s / 4, *others[k:]]
        q[pick] = np.stack(parts, axis=1)
    q *= np.where(q[:, :1] < 0, -1, 1).astype(q.dtype)
    return q / np.linalg.norm(q, axis=1, keepdims=True)  # type: ignore[no-any-return]


def _band_fields(sphere: _SphereGrid, r0: int, r1: int) -> dict[str, np.ndarray]:
    """Compute the splats of grid rows r0…r1: :class:`Splats`' arrays (no opacity, units)."""
    band = sphere.band(r0, r1)
    keep = band.valid
    n_local, t_e, t_s = band.normal, band.east, band.south  # (3, b, cols) along (d, e, s)
    with np.errstate(invalid="ignore", divide="ignore"):
        # The footprint's in-plane frame: u1 along the longitude chord, u2 = n × u1 (both in
        # the plane: n = ±t_e × t_s). The (d, e, s) frame is right-handed: its cross is the
        # world's.
        a = np.sqrt(np.einsum("kij,kij->ij", t_e, t_e))
        u1 = t_e / np.where(a > 0, a, 1)
        u2 = np.cross(n_local, u1, axis=0)
        b = np.einsum("kij,kij->ij", t_s, u1)
        c = np.einsum("kij,kij->ij", t_s, u2)
        # In-plane second moment of the two chords, [[a² + b², bc], [bc, c²]]: its eigenvectors.
        m11, m12, m22 = a * a + b * b, b * c, c * c
        theta = 0.5 * np.arctan2(2 * m12, m11 - m22)
        mean, radius = (m11 + m22) / 2, np.sqrt(((m11 - m22) / 2) ** 2 + m12 * m12)
        major = np.sqrt(np.maximum(mean + radius, 0)) * np.float32(FOOTPRINT_SIGMA)
        minor = np.sqrt(np.maximum(mean - radius, 0)) * np.float32(FOOTPRINT_SIGMA)
        minor = np.maximum(minor, major * np.float32(1e-3))
        sigma = np.stack([major[keep], minor[keep], minor[keep] * np.float32(THICKNESS)], 1)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    v1 = u1 * cos_t + u2 * sin_t
    v2 = u2 * cos_t - u1 * sin_t  # n × v1
    # columns: the axes of scale_0, scale_1, scale_2 (the normal), in the world frame
    rotation = np.stack([sphere.to_world(v, r0, r1)[keep] for v in (v1, v2, n_local)], axis=2)
    colours = sphere.grid.rgb(r0, r1)
    if colours is None:
        f_dc = np.zeros((rotation.shape[0], 3), np.float32)
    else:
        f_dc = (colours[keep] / np.float32(255) - np.float32(0.5)) / np.float32(SH_C0)
    rows, cols = np.divmod(np.flatnonzero(keep), sphere.grid.cols)
    step, width = sphere.grid.step, sphere.grid.width
    return {
        "xyz": (sphere.grid.dirs(r0, r1) * band.depth[..., None])[keep],  # to_points' points
        "normals": rotation[:, :, 2],
        "f_dc": f_dc.astype(np.float32),
        "scales": np.log(sigma),
        "rotations": _quaternions(rotation),
        "pixels": (rows + r0) * step * width + cols * step,
    }


def _records(fields: dict[str, np.ndarray], opacity: np.ndarray | float) -> np.ndarray:
    """Pack splat arrays (the keys of :class:`Splats`) into the PLY's records."""
    records = np.empty(fields["xyz"].shape[0], _RECORD)
    for key, names in (
        ("xyz", ("x", "y", "z")),
        ("normals", ("nx", "ny", "nz")),
        ("f_dc", ("f_dc_0", "f_dc_1", "f_dc_2")),
        ("scales", ("scale_0", "scale_1", "scale_2")),
        ("rotations", ("rot_0", "rot_1", "rot_2", "rot_3")),
    ):
        for k, name in enumerate(names):
            records[name] = fields[key][:, k]
    records["opacity"] = opacity
    return records


def _prepare(
    source: Any,
    rgb: Any,
    stride: int,
    max_depth_ratio: float,
    max_vertices: int | None,
    opacity: float,
    quantity: str | None,
) -> tuple[_SphereGrid, float, str]:
    array, name, units = _depth_source(source, quantity)
    height, width = array.shape
    colours = _rgb_of(rgb, (height, width))
    step = stride_for(height, width, stride, max_vertices)
    sphere = _SphereGrid(array, name, step, _ratio(max_depth_ratio), colours)
    if sphere.grid.rows < 2 or sphere.grid.cols < 3:
        raise InputError(f"stride {step} leaves a {sphere.grid.rows}x{sphere.grid.cols} grid; "
                         "splats need at least 2x3")  # fmt: skip
    alpha = number(opacity, "opacity", low=0.0, high=1.0)
    if not 0.0 < alpha < 1.0:
        raise InputError(f"opacity must be in (0, 1), got {opacity!r}")
    return sphere, float(np.log(alpha / (1 - alpha))), units


def _no_splats() -> InputError:
    return InputError(
        "no pixel gets a splat: no valid depth with a neighbour within max_depth_ratio along "
        "both longitude and latitude"
    )


def to_splats(
    source: Any,
    rgb: Any = None,
    *,
    stride: int = 1,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
    opacity: float = DEFAULT_OPACITY,
    quantity: str | None = None,
) -> Splats:
    """Turn an ERP depth map into flat 3D Gaussian splats, one per pixel of the grid.

    Parameters
    ----------
    source : EstimateResult, SavedResult, path or (H, W) float array
        As for :func:`m360.to_points`.
    rgb : (H, W, 3) uint8, optional
        The panorama: the splats' colours (mid grey without).
    stride : int
        A splat for every ``stride``-th row and column, covering that many pixels.
    max_depth_ratio : float
        The mesh's depth-jump rule (:func:`m360.to_mesh`): neighbours whose depths differ by
        more than this factor are on two surfaces.
    max_vertices : int or None
        At most this many splats: a larger grid takes a larger stride
        (:func:`m360.mesh.stride_for`; default :data:`m360.mesh.DEFAULT_MAX_VERTICES`).
    opacity : float
        Opacity of every splat, in (0, 1).
    quantity : {"depth", "disparity"}, optional
        What a plain array holds (default depth).

    Returns
    -------
    Splats
        Centres, normals, colours, opacities, scales and rotations (module docstring), in the
        m360 frame.

    Raises
    ------
    InputError
        Not an ERP map, shapes differ, bad options, or no pixel gets a splat.
    """
    sphere, log_opacity, units = _prepare(
        source, rgb, stride, max_depth_ratio, max_vertices, opacity, quantity
    )
    count = sum(int(sphere.valid(r0, r1).sum()) for r0, r1 in sphere.bands())
    if not count:
        raise _no_splats()
    widths = {"xyz": 3, "normals": 3, "f_dc": 3, "scales": 3, "rotations": 4}
    out: dict[str, Any] = {k: np.empty((count, w), np.float32) for k, w in widths.items()}
    out["pixels"] = np.empty(count, np.int64)
    start = 0
    for r0, r1 in sphere.bands():
        fields = _band_fields(sphere, r0, r1)
        stop = start + fields["pixels"].shape[0]
        for key, values in fields.items():
            out[key][start:stop] = values
        start = stop
    return Splats(**out, opacity=np.full(count, log_opacity, np.float32), units=units)


def _fields(records: np.ndarray) -> dict[str, Any]:
    def columns(*names: str) -> np.ndarray:
        return np.stack([records[n] for n in names], axis=1)

    return {
        "xyz": columns("x", "y", "z"),
        "normals": columns("nx", "ny", "nz"),
        "f_dc": columns("f_dc_0", "f_dc_1", "f_dc_2"),
        "opacity": np.ascontiguousarray(records["opacity"]),
        "scales": columns("scale_0", "scale_1", "scale_2"),
        "rotations": columns("rot_0", "rot_1", "rot_2", "rot_3"),
    }


def _header(count: int) -> bytes:
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment m360 Gaussian splats: x right, y down, z forward (camera at the origin)",
        f"element vertex {count}",
        *(f"property float {name}" for name in SPLAT_PROPERTIES),
        "end_header",
    ]
    return ("\n".join(lines) + "\n").encode("ascii")


#: Splats per chunk of :func:`write_splats` (about 70 MB of records).
_CHUNK = 1 << 20


def write_splats(path: str | os.PathLike[str], splats: Splats) -> Path:
    """Write :class:`Splats` as a 3D Gaussian Splatting PLY (module docstring), atomically."""
    from .files import atomic_path

    if not isinstance(splats, Splats):
        raise InputError(f"expected m360 Splats, got {type(splats).__name__}")
    n = len(splats)
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(_header(n))
        for k in range(0, n, _CHUNK):
            part = slice(k, k + _CHUNK)
            fields = {
                "xyz": splats.xyz[part],
                "normals": splats.normals[part],
                "f_dc": splats.f_dc[part],
                "scales": splats.scales[part],
                "rotations": splats.rotations[part],
            }
            _records(fields, splats.opacity[part]).tofile(f)
    return target


def write_splat_ply(
    path: str | os.PathLike[str],
    source: Any,
    *,
    rgb: Any = None,
    stride: int = 1,
    max_depth_ratio: float = DEFAULT_MAX_DEPTH_RATIO,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
    opacity: float = DEFAULT_OPACITY,
    quantity: str | None = None,
) -> dict[str, int]:
    """Write :func:`to_splats`'s splats as :func:`write_splats` does, a band of rows at a time.

    The same bytes as ``write_splats(path, to_splats(source, ...))`` with a band's memory
    (about a million pixels) whatever the map's size: a first pass counts the splats (depths
    and ratios only), the second writes them.

    Returns
    -------
    dict
        ``stride`` (the one used, see :func:`m360.mesh.stride_for`) and ``splats`` written.
    """
    from .files import atomic_path

    sphere, log_opacity, _ = _prepare(
        source, rgb, stride, max_depth_ratio, max_vertices, opacity, quantity
    )
    count = sum(int(sphere.valid(r0, r1).sum()) for r0, r1 in sphere.bands())
    if not count:
        raise _no_splats()
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        f.write(_header(count))
        for r0, r1 in sphere.bands():
            _records(_band_fields(sphere, r0, r1), log_opacity).tofile(f)
    return {"stride": sphere.grid.step, "splats": count}


def read_splats(path: str | os.PathLike[str]) -> Splats:
    """Read a 3D Gaussian Splatting PLY (this module's, or another tool's float32 one).

    Needs ``plyfile`` (extra ``m360[3d]``). Extra properties (``f_rest_*``) are ignored.

    Raises
    ------
    ReadError
        A missing, corrupt or non-splat PLY.
    """
    from ..errors import ReadError
    from .decode import read_bytes

    try:
        import plyfile
    except ImportError as exc:  # the optional extra
        raise InputError("reading splats needs the optional extra: pip install 'm360[3d]'") from exc
    import io as _bytes_io

    p = Path(path)
    data = read_bytes(p, "splat file")
    try:
        vertex = plyfile.PlyData.read(_bytes_io.BytesIO(data))["vertex"].data
        missing = [n for n in SPLAT_PROPERTIES if n not in vertex.dtype.names and n[0] != "n"]
        if missing:
            raise ReadError(f"{p} is not a Gaussian-splat PLY: no {', '.join(missing)}")
        records = np.empty(vertex.shape[0], _RECORD)
        for name in SPLAT_PROPERTIES:
            records[name] = vertex[name] if name in vertex.dtype.names else 0.0
    except ReadError:
        raise
    except Exception as exc:  # plyfile raises many kinds for corrupt files
        raise ReadError(f"cannot read {p}: {exc}") from exc
    pixels = np.full(records.shape[0], -1, np.int64)
    return Splats(**_fields(records), pixels=pixels, units="unknown")
