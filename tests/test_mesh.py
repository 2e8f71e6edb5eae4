"""m360.to_points / m360.to_mesh and the PLY/GLB writers against analytic rooms."""

from __future__ import annotations

import functools
import json
import struct

import m360
import m360.mesh as mesh_mod
import m360.synthetic as syn
import numpy as np
import pytest

plyfile = pytest.importorskip("plyfile")
pytest.importorskip("trimesh")

ROOM_MIN = np.array([-2.1, -1.3, -3.2])
ROOM_MAX = np.array([2.9, 1.55, 1.8])


@functools.cache
def empty_room(width: int) -> tuple[np.ndarray, np.ndarray]:
    return syn.render(syn.Scene(room_min=ROOM_MIN, room_max=ROOM_MAX), width)


@functools.cache
def furnished(seed: int, width: int) -> tuple[syn.Scene, np.ndarray, np.ndarray]:
    scene = syn.room(seed)
    rgb, depth = syn.render(scene, width)
    return scene, rgb, depth


def plane_distance(xyz: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest of the six analytic walls of the empty room."""
    p = xyz.astype(np.float64)
    return np.min(np.concatenate([np.abs(p - ROOM_MIN), np.abs(p - ROOM_MAX)], axis=1), axis=1)


def edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges and how often each appears; directed edges for the winding check."""
    f = faces.astype(np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    return counts, directed[:, 0] * n + directed[:, 1]


def test_points_lie_on_the_analytic_walls_at_2k():
    rgb, depth = empty_room(2048)
    pc = m360.to_points(depth, rgb=rgb)
    assert pc.xyz.dtype == np.float32 and pc.xyz.shape == (depth.size, 3)
    assert pc.rgb is not None and pc.rgb.dtype == np.uint8
    dist = plane_distance(pc.xyz)
    assert np.median(dist) < 1e-3
    assert np.quantile(dist, 0.999) < 1e-3
    # colours and pixels follow the points: pixel index → ERP position
    k = np.array([0, 12345, depth.size - 1])
    np.testing.assert_array_equal(pc.rgb[k], rgb.reshape(-1, 3)[pc.pixels[k]])


def test_points_frame_directions():
    # Four walls at known places: +z ahead (image centre), +x right, −y up (top row), +y down.
    _, depth = empty_room(256)
    pc = m360.to_points(depth)
    by_pixel = pc.xyz.reshape(128, 256, 3)
    np.testing.assert_allclose(by_pixel[64, 128, 2], ROOM_MAX[2], rtol=1e-3)  # centre: forward
    np.testing.assert_allclose(by_pixel[64, 192, 0], ROOM_MAX[0], rtol=1e-3)  # lon +90°: right
    np.testing.assert_allclose(by_pixel[0, 0, 1], ROOM_MIN[1], rtol=1e-3)  # top row: ceiling
    np.testing.assert_allclose(by_pixel[127, 0, 1], ROOM_MAX[1], rtol=1e-3)  # bottom row: floor


def test_points_stride_and_nan_and_disparity():
    _, depth = empty_room(256)
    holes = depth.copy()
    holes[10:20, 30:60] = np.nan
    pc = m360.to_points(holes, stride=2)
    assert len(pc) == np.isfinite(holes[::2, ::2]).sum()
    rows, cols = np.divmod(pc.pixels, 256)
    assert (rows % 2 == 0).all() and (cols % 2 == 0).all()
    assert np.isfinite(pc.xyz).all()
    disp = m360.to_points(1.0 / depth, quantity="disparity")
    np.testing.assert_allclose(disp.xyz, m360.to_points(depth).xyz, rtol=1e-5)


@pytest.mark.parametrize("stride", [1, 2])
def test_mesh_of_a_closed_room_is_watertight(stride):
    _, depth = empty_room(1024)
    mesh = m360.to_mesh(depth, stride=stride)
    counts, directed = edge_counts(mesh.faces)
    assert (counts == 2).all()  # seam joined, poles fanned, no hole
    # consistently wound: each directed edge appears once (the neighbour runs it backwards)
    assert np.unique(directed).shape[0] == directed.shape[0]
    # normals face the camera, and the enclosed volume is the room's
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert ((normals * tri.mean(axis=1)).sum(axis=1) < 0).all()
    volume = -np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    np.testing.assert_allclose(volume, np.prod(ROOM_MAX - ROOM_MIN), rtol=0.01)


def test_mesh_without_cut_is_closed_for_a_furnished_room():
    _, _, depth = furnished(1, 512)
    mesh = m360.to_mesh(depth, max_depth_ratio=np.inf)
    counts, _ = edge_counts(mesh.faces)
    assert (counts == 2).all()
    assert mesh.vertices.shape[0] == depth.size + 2  # every pixel plus two pole vertices


def spans_jump(scene: syn.Scene, tri_dirs: np.ndarray, jump: float) -> np.ndarray:
    """Oracle: ray cast 8 steps along each triangle edge; True where a step jumps by > jump."""
    t = np.linspace(0.0, 1.0, 9)[None, :, None]
    out = np.zeros(tri_dirs.shape[0], bool)
    for k in range(3):
        p, q = tri_dirs[:, k], tri_dirs[:, (k + 1) % 3]
        rays = p[:, None] * (1 - t) + q[:, None] * t
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        dist = scene.distance(rays)
        step = dist[:, 1:] / dist[:, :-1]
        out |= (np.maximum(step, 1 / step) > jump).any(axis=1)
    return out


def test_no_triangle_spans_a_depth_discontinuity():
    scene, _, depth = furnished(0, 1024)
    ratio = m360.mesh.DEFAULT_MAX_DEPTH_RATIO
    cut = m360.to_mesh(depth, poles=False)
    full = m360.to_mesh(depth, max_depth_ratio=np.inf, poles=False)

    def jumps(mesh: m360.Mesh) -> int:
        tri = mesh.vertices[mesh.faces].astype(np.float64)
        r = np.linalg.norm(tri, axis=-1)
        # A triangle whose corners agree within 1 % cannot show a jump its pixels would see.
        suspect = r.max(axis=1) > 1.01 * r.min(axis=1)
        return int(spans_jump(scene, tri[suspect] / r[suspect][..., None], ratio).sum())

    in_scene = jumps(full)
    assert in_scene > 1000  # the oracle sees the scene's occlusion edges ...
    # ... and the cut mesh spans none of them, but for features thinner than a pixel (a slab
    # seen edge-on between two pixels of the wall behind it: 2 triangles of 1024x512 here).
    assert jumps(cut) <= in_scene // 1000
    # boundaries only where triangles were cut: the kept ones are 99 % of the grid's
    assert cut.faces.shape[0] > 0.99 * full.faces.shape[0]


def test_mesh_never_touches_nan():
    _, depth = empty_room(256)
    holes = depth.copy()
    holes[40:50, :] = np.nan  # a full ring of NaN, across the seam
    holes[0, 5] = np.nan
    mesh = m360.to_mesh(holes, max_depth_ratio=np.inf)
    assert np.isfinite(mesh.vertices).all()
    r = np.linalg.norm(mesh.vertices, axis=1)
    pc = m360.to_points(holes)
    assert mesh.vertices.shape[0] == len(pc) + 2  # NaN pixels have no vertex
    assert np.all(r > 0)


def test_mesh_colours_and_result_inputs(tmp_path):
    rgb, _ = empty_room(256)
    result = m360.estimate(
        rgb,
        m360.estimators.SimulatedEstimator(
            syn.Scene(room_min=ROOM_MIN, room_max=ROOM_MAX),
            m360.geometry.default_layout(256),
            shift=0,
        ),
        align="none",
        blend="mean",
    )
    pc = m360.to_points(result, rgb=rgb)
    mesh = m360.to_mesh(result, rgb=rgb)
    assert mesh.rgb is not None and mesh.rgb.shape == mesh.vertices.shape
    m360.save(result, tmp_path / "pano")
    again = m360.to_points(tmp_path / "pano", rgb=rgb)
    np.testing.assert_array_equal(again.xyz, pc.xyz)


def read_glb(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Independent GLB reader (glTF 2.0: JSON chunk + BIN chunk): positions, faces, colours."""
    data = path.read_bytes()
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2
    json_len, _ = struct.unpack_from("<II", data, 12)
    gltf = json.loads(data[20 : 20 + json_len])
    bin_start = 20 + json_len + 8
    types = {5126: np.float32, 5125: np.uint32, 5121: np.uint8, 5123: np.uint16}
    sizes = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def accessor(k: int) -> np.ndarray:
        acc = gltf["accessors"][k]
        view = gltf["bufferViews"][acc["bufferView"]]
        start = bin_start + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        dtype = np.dtype(types[acc["componentType"]])
        n = acc["count"] * sizes[acc["type"]]
        return np.frombuffer(data, dtype, n, start).reshape(acc["count"], -1)

    prim = gltf["meshes"][0]["primitives"][0]
    pos = accessor(prim["attributes"]["POSITION"])
    faces = accessor(prim["indices"]).reshape(-1, 3)
    colours = accessor(prim["attributes"]["COLOR_0"])
    return pos, faces, colours


def test_ply_and_glb_reread_with_independent_readers(tmp_path):
    rgb, depth = empty_room(256)
    mesh = m360.to_mesh(depth, rgb=rgb)
    mesh_mod.write_ply(tmp_path / "m.ply", mesh)
    ply = plyfile.PlyData.read(str(tmp_path / "m.ply"))
    v = ply["vertex"]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
    np.testing.assert_array_equal(xyz, mesh.vertices)  # PLY: the m360 frame, bit-exact
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), mesh.rgb)
    faces = np.stack(ply["face"]["vertex_indices"])
    np.testing.assert_array_equal(faces, mesh.faces)

    mesh_mod.write_glb(tmp_path / "m.glb", mesh)
    pos, gfaces, colours = read_glb(tmp_path / "m.glb")
    # glTF is y up: (x, -y, -z) of the m360 frame, a rotation (winding kept)
    np.testing.assert_array_equal(pos * np.array([1, -1, -1], np.float32), mesh.vertices)
    np.testing.assert_array_equal(gfaces, mesh.faces)
    np.testing.assert_array_equal(colours[:, :3], mesh.rgb)

    # trimesh reads both back as well (the viewer's reader)
    for name in ("m.ply", "m.glb"):
        vertices, faces = mesh_mod.read_geometry(tmp_path / name)
        np.testing.assert_array_equal(vertices, mesh.vertices)
        np.testing.assert_array_equal(faces, mesh.faces)

    pc = m360.to_points(depth, rgb=rgb, stride=4)
    mesh_mod.write_ply(tmp_path / "p.ply", pc)
    mesh_mod.write_glb(tmp_path / "p.glb", pc)
    np.testing.assert_array_equal(mesh_mod.read_geometry(tmp_path / "p.glb")[0], pc.xyz)
    v = plyfile.PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), pc.xyz)


def test_bad_inputs_are_input_errors():
    _, depth = empty_room(64)
    with pytest.raises(m360.InputError, match="no valid"):
        m360.to_mesh(np.full((32, 64), np.nan, np.float32))
    with pytest.raises(m360.InputError, match="no valid"):
        m360.to_points(np.zeros((32, 64), np.float32))
    with pytest.raises(m360.InputError, match="rgb must be the panorama"):
        m360.to_points(depth, rgb=np.zeros((16, 32, 3), np.uint8))
    with pytest.raises(m360.InputError, match="W == 2H"):
        m360.to_mesh(np.ones((32, 32), np.float32))
    with pytest.raises(m360.InputError, match="max_depth_ratio"):
        m360.to_mesh(depth, max_depth_ratio=1.0)
    with pytest.raises(m360.InputError, match="stride"):
        m360.to_mesh(depth, stride=0)
    with pytest.raises(m360.InputError, match="float"):
        m360.to_points(np.ones((32, 64), np.int32))
    with pytest.raises(m360.InputError, match="Mesh or PointCloud"):
        mesh_mod.write_ply("/nonexistent/x.ply", depth)
