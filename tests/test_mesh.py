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


# --------------------------------------------------------------------------------------------
# Streaming writers and the vertex budget (issue 23). The oracle is the writers as they were
# before they streamed (whole-array records), kept here verbatim in substance.


def _old_write_ply(path, item):
    vertices, faces, rgb = mesh_mod._geometry(item)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(vertices.shape[0], np.dtype(fields))
    for k, name in enumerate("xyz"):
        records[name] = vertices[:, k]
    if rgb is not None:
        for k, name in enumerate(("red", "green", "blue")):
            records[name] = rgb[:, k]
    with open(path, "wb") as f:
        n_faces = None if faces is None else faces.shape[0]
        f.write(mesh_mod._ply_header(vertices.shape[0], n_faces, rgb is not None))
        records.tofile(f)
        if faces is not None:
            face_records = np.empty(faces.shape[0], np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
            face_records["n"] = 3
            face_records["v"] = faces
            face_records.tofile(f)


def _old_write_glb(path, item):
    vertices, faces, rgb = mesh_mod._geometry(item)
    positions = np.ascontiguousarray(vertices * np.array([1.0, -1.0, -1.0], np.float32))
    n = positions.shape[0]
    chunks = [positions]
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": positions.nbytes, "target": 34962}]
    accessors = [
        {
            "bufferView": 0,
            "componentType": 5126,
            "count": n,
            "type": "VEC3",
            "min": positions.min(axis=0).tolist() if n else [0, 0, 0],
            "max": positions.max(axis=0).tolist() if n else [0, 0, 0],
        }
    ]
    attributes = {"POSITION": 0}
    offset = positions.nbytes
    if rgb is not None:
        rgba = np.empty((n, 4), np.uint8)
        rgba[:, :3] = rgb
        rgba[:, 3] = 255
        chunks.append(rgba)
        views.append(
            {"buffer": 0, "byteOffset": offset, "byteLength": rgba.nbytes, "target": 34962}
        )
        accessors.append(
            {"bufferView": 1, "componentType": 5121, "normalized": True, "count": n, "type": "VEC4"}
        )
        attributes["COLOR_0"] = 1
        offset += rgba.nbytes
    primitive = {"attributes": attributes, "mode": 0}
    if faces is not None:
        indices = np.ascontiguousarray(faces, np.uint32).reshape(-1)
        chunks.append(indices)
        views.append(
            {"buffer": 0, "byteOffset": offset, "byteLength": indices.nbytes, "target": 34963}
        )
        accessors.append(
            {
                "bufferView": len(views) - 1,
                "componentType": 5125,
                "count": indices.size,
                "type": "SCALAR",
            }
        )
        primitive.update(indices=len(accessors) - 1, mode=4)
        offset += indices.nbytes
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
    pad = -offset % 4
    total = 12 + 8 + len(text) + 8 + offset + pad
    with open(path, "wb") as f:
        f.write(b"glTF" + np.array([2, total, len(text), 0x4E4F534A], "<u4").tobytes())
        f.write(text)
        f.write(np.array([offset + pad, 0x004E4942], "<u4").tobytes())
        for chunk in chunks:
            chunk.tofile(f)
        f.write(b"\0" * pad)


def _holey(width: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    _, rgb, depth = furnished(1, width)
    depth = depth.astype(np.float32)
    rng = np.random.default_rng(seed)
    depth[rng.random(depth.shape) < 0.03] = np.nan
    depth[0, : width // 3] = np.nan  # part of the top ring missing
    return rgb, depth


@pytest.mark.parametrize("stride", [1, 3])
@pytest.mark.parametrize("coloured", [True, False])
def test_streaming_writers_write_the_bytes_of_the_whole_array_writers(
    tmp_path, monkeypatch, stride, coloured
):
    rgb, depth = _holey(128)
    colours = rgb if coloured else None
    # Small bands and chunks, so every writer goes through many of them (and uneven ends).
    monkeypatch.setattr(mesh_mod, "_BAND_VERTICES", 300)
    monkeypatch.setattr(mesh_mod, "_CHUNK", 257)
    for poles in (True, False):
        mesh = m360.to_mesh(depth, rgb=colours, stride=stride, poles=poles, max_vertices=None)
        _old_write_glb(tmp_path / "old.glb", mesh)
        info = mesh_mod.write_mesh_glb(
            tmp_path / "new.glb", depth, rgb=colours, stride=stride, poles=poles
        )
        assert (tmp_path / "new.glb").read_bytes() == (tmp_path / "old.glb").read_bytes()
        assert info == {"stride": stride, "vertices": len(mesh.vertices), "faces": len(mesh.faces)}
        mesh_mod.write_glb(tmp_path / "chunked.glb", mesh)
        assert (tmp_path / "chunked.glb").read_bytes() == (tmp_path / "old.glb").read_bytes()
        _old_write_ply(tmp_path / "old_m.ply", mesh)
        mesh_mod.write_ply(tmp_path / "new_m.ply", mesh)
        assert (tmp_path / "new_m.ply").read_bytes() == (tmp_path / "old_m.ply").read_bytes()
    points = m360.to_points(depth, rgb=colours, stride=stride)
    _old_write_ply(tmp_path / "old.ply", points)
    info = mesh_mod.write_points_ply(tmp_path / "new.ply", depth, rgb=colours, stride=stride)
    assert (tmp_path / "new.ply").read_bytes() == (tmp_path / "old.ply").read_bytes()
    assert info == {"stride": stride, "vertices": len(points)}
    _old_write_glb(tmp_path / "old_p.glb", points)
    mesh_mod.write_glb(tmp_path / "new_p.glb", points)
    assert (tmp_path / "new_p.glb").read_bytes() == (tmp_path / "old_p.glb").read_bytes()
    # A disparity map, converted a band at a time.
    with np.errstate(divide="ignore"):
        disparity = 1.0 / depth
    mesh = m360.to_mesh(disparity, rgb=colours, stride=stride, quantity="disparity")
    _old_write_glb(tmp_path / "old_d.glb", mesh)
    mesh_mod.write_mesh_glb(
        tmp_path / "d.glb", disparity, rgb=colours, stride=stride, quantity="disparity"
    )
    assert (tmp_path / "d.glb").read_bytes() == (tmp_path / "old_d.glb").read_bytes()


def test_stride_for_is_the_least_stride_within_the_budget():
    for height, width, stride, budget, extra in [
        (512, 1024, 1, 2**19, 2),
        (512, 1024, 1, 2**19 + 2, 2),
        (5984, 11968, 1, 2**23, 2),
        (4096, 8192, 1, 2**23, 0),
        (100, 200, 3, 64, 0),
        (2048, 4096, 1, None, 2),
    ]:
        step = mesh_mod.stride_for(height, width, stride, budget, extra)
        count = [-(-height // s) * -(-width // s) + extra for s in range(1, 1000)]
        want = (
            stride
            if budget is None
            else next(s for s in range(stride, 1000) if count[s - 1] <= budget)
        )
        assert step == want, (height, width, budget)
    # the defaults: 4K whole, 8K every 2nd pixel, the 12K street photo every 3rd
    assert mesh_mod.stride_for(2048, 4096) == 1
    assert mesh_mod.stride_for(4096, 8192, extra=0) == 2
    assert mesh_mod.stride_for(5984, 11968, extra=2) == 3
    with pytest.raises(m360.InputError, match="max_vertices"):
        mesh_mod.stride_for(64, 128, 1, 10)


def test_vertex_budget_strides_the_3d_files_and_the_sidecar_says_so(tmp_path):
    rgb, depth = _holey(256)
    budget = 4000  # 128x256 = 32768 grid vertices: stride 3 (43x86 = 3698 + 2 poles)
    mesh = m360.to_mesh(depth, rgb=rgb, max_vertices=budget)
    assert len(mesh.vertices) <= budget
    np.testing.assert_array_equal(mesh.vertices, m360.to_mesh(depth, rgb=rgb, stride=3).vertices)
    points = m360.to_points(depth, rgb=rgb, max_vertices=budget)
    assert len(points) <= budget
    np.testing.assert_array_equal(points.pixels, m360.to_points(depth, stride=3).pixels)

    result = type("R", (), {"disparity": 1.0 / depth, "depth": depth})()
    written = m360.save(
        result, tmp_path / "s", formats=["ply", "glb"], rgb=rgb, max_vertices=budget
    )
    sidecar = json.loads(written["sidecar"].read_text())
    glb = sidecar["geometry"]["s.mesh.glb"]
    ply = sidecar["geometry"]["s.points.ply"]
    assert glb["stride"] == ply["stride"] == 3
    assert glb["max_vertices"] == budget
    assert glb["vertices"] == len(mesh.vertices) and glb["faces"] == len(mesh.faces)
    assert ply["vertices"] == len(points)
    pos, faces, _ = read_glb(written["mesh.glb"])
    assert len(pos) == glb["vertices"] <= budget and len(faces) == glb["faces"]
    assert plyfile.PlyData.read(str(written["points.ply"]))["vertex"].count == ply["vertices"]
    # None: every pixel
    again = m360.save(result, tmp_path / "all", formats=["glb"], max_vertices=None)
    assert json.loads(again["sidecar"].read_text())["geometry"]["all.mesh.glb"]["stride"] == 1
    with pytest.raises(m360.InputError, match="max_vertices"):
        m360.save(result, tmp_path / "bad", formats=["glb"], max_vertices=0)


def test_cli_max_vertices_strides_the_files_and_a_new_budget_redoes_the_image(tmp_path, capsys):
    import cv2
    import onnx_graphs as g
    from m360.cli import main

    _, rgb, _ = furnished(2, 256)
    panorama = tmp_path / "room.png"
    cv2.imwrite(str(panorama), rgb[:, :, ::-1])
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    out = tmp_path / "out"
    args = ["run", str(panorama), "-o", str(out), "--model", str(model), "--align", "none"]
    args += ["--blend", "mean", "--input-size", "64", "96", "--formats", "glb", "--no-progress"]

    def geometry():
        return json.loads((out / "room.json").read_text())["geometry"]["room.mesh.glb"]

    assert main([*args, "--max-vertices", "5000"]) == 0, capsys.readouterr().err
    first = geometry()
    assert first["stride"] == 3 and first["max_vertices"] == 5000 and first["vertices"] <= 5000
    assert len(read_glb(out / "room.mesh.glb")[0]) == first["vertices"]
    assert main([*args, "--max-vertices", "5000"]) == 0
    assert "1 already done" in capsys.readouterr().err
    assert main([*args, "--max-vertices", "none"]) == 0
    assert "1 done" in capsys.readouterr().err and geometry()["stride"] == 1
    assert main([*args]) == 0  # the default (the whole 256 grid fits): redone, absent key
    assert "1 done" in capsys.readouterr().err and geometry()["stride"] == 1
    assert main([*args, "--max-vertices", "12"]) == 2
    assert "--max-vertices must be an integer >= 64" in capsys.readouterr().err
