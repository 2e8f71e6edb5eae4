"""m360.to_splats and STEM.splat.ply: read back with plyfile, checked against ray-cast rooms.

Oracles: the analytic walls of an empty room (centres on the walls, normals, and each splat's
in-plane covariance against the pixel's footprint on the wall, from the Jacobian of the
ray-plane intersection by central differences in float64), scipy's quaternion convention, and
counts from the grid and masks alone.
"""

from __future__ import annotations

import functools
import json
import os

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360.io import splat as splat_mod
from scipy.spatial.transform import Rotation

plyfile = pytest.importorskip("plyfile")

ROOM_MIN = np.array([-2.1, -1.3, -3.2])
ROOM_MAX = np.array([2.9, 1.55, 1.8])
PROPERTIES = (
    "x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3"
).split()


@functools.cache
def empty_room(width: int) -> tuple[np.ndarray, np.ndarray]:
    return syn.render(syn.Scene(room_min=ROOM_MIN, room_max=ROOM_MAX), width)


def ray(row: np.ndarray, col: np.ndarray, height: int) -> np.ndarray:
    """(…, 3) float64 unit rays at fractional ERP positions (docs/conventions.md)."""
    lat = np.pi / 2 - np.pi * (row + 0.5) / height
    lon = 2 * np.pi * (col + 0.5) / (2 * height) - np.pi
    return np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], -1)


def wall_point(direction: np.ndarray, normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Where rays meet the planes normal · p = offset."""
    t = offset / (direction * normal).sum(-1)
    return direction * t[..., None]  # type: ignore[no-any-return]


class Result:
    def __init__(self, depth: np.ndarray) -> None:
        self.depth = depth
        self.disparity = (1 / depth).astype(np.float32)


def read_ply(path) -> np.ndarray:
    data = plyfile.PlyData.read(str(path))
    vertex = data["vertex"]
    assert [p.name for p in vertex.properties] == PROPERTIES
    assert all(p.val_dtype in ("f4", "float32") for p in vertex.properties)
    return vertex.data  # type: ignore[no-any-return]


def test_file_layout_count_and_colours(tmp_path):
    rgb, depth = empty_room(256)
    written = m360.save(Result(depth), tmp_path / "pano", formats=("splat",), rgb=rgb)
    records = read_ply(written["splat.splat"])
    assert len(records) == depth.size  # a closed room: every pixel gets a splat
    splats = m360.to_splats(depth, rgb)
    np.testing.assert_array_equal(records["x"], splats.xyz[:, 0])
    # colours: 0.5 + C0 · f_dc is the pixel's colour
    f_dc = np.stack([records[f"f_dc_{k}"] for k in range(3)], 1)
    colour = 0.5 + 0.28209479177387814 * f_dc
    np.testing.assert_allclose(colour * 255, rgb.reshape(-1, 3)[splats.pixels], atol=1e-3)
    # opacity is a logit, scales are logs, rotations unit quaternions with w >= 0
    np.testing.assert_allclose(1 / (1 + np.exp(-records["opacity"])), 0.95, rtol=1e-6)
    q = np.stack([records[f"rot_{k}"] for k in range(4)], 1)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-5)
    assert (q[:, 0] >= 0).all()
    meta = json.loads((tmp_path / "pano.json").read_text())
    assert meta["files"]["splat"] == {"splat": "pano.splat.ply"}
    assert "y down" in meta["frame"]["pano.splat.ply"]
    assert meta["geometry"]["pano.splat.ply"]["splats"] == depth.size
    # the in-memory writer gives the same bytes as the streamed one save uses
    splat_mod.write_splats(tmp_path / "again.ply", splats)
    assert (tmp_path / "again.ply").read_bytes() == written["splat.splat"].read_bytes()
    back = splat_mod.read_splats(tmp_path / "again.ply")
    np.testing.assert_array_equal(back.rotations, splats.rotations)


def test_splats_lie_on_the_walls_and_cover_each_pixels_footprint():
    width = 512
    height = width // 2
    _, depth = empty_room(width)
    splats = m360.to_splats(depth)
    rows, cols = np.divmod(splats.pixels, width)
    hit = syn.Scene(room_min=ROOM_MIN, room_max=ROOM_MAX).intersect(ray(rows, cols, height))
    np.testing.assert_allclose(splats.xyz, hit.point, atol=2e-5 * np.abs(hit.point).max())
    same_wall = np.ones(len(rows), bool)  # its neighbours on its wall: no crease in the chords
    ids = np.full((height, width), -1)
    ids[rows, cols] = hit.object_id
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        same_wall &= ids[np.clip(rows + dr, 0, height - 1), (cols + dc) % width] == hit.object_id
    assert same_wall.mean() > 0.97
    # the third axis is the wall's normal, in scipy's reading of the quaternion (x, y, z, w)
    axes = Rotation.from_quat(splats.rotations[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(axes[same_wall, :, 2], hit.normal[same_wall], atol=1e-3)
    np.testing.assert_allclose(splats.normals[same_wall], hit.normal[same_wall], atol=1e-3)
    # Footprint: away from the room's edges and the poles, the in-plane covariance is
    # FOOTPRINT_SIGMA² (J_c J_cᵀ + J_r J_rᵀ) with J the wall point's change per pixel column
    # and row (central differences of the exact ray-plane intersection).
    lat = np.pi / 2 - np.pi * (rows + 0.5) / height
    inner = np.abs(lat) < np.radians(60)
    offset = (hit.normal * hit.point).sum(-1)
    j_c = wall_point(ray(rows, cols + 0.5, height), hit.normal, offset) - wall_point(
        ray(rows, cols - 0.5, height), hit.normal, offset
    )
    j_r = wall_point(ray(rows + 0.5, cols, height), hit.normal, offset) - wall_point(
        ray(rows - 0.5, cols, height), hit.normal, offset
    )
    keep = inner & same_wall
    expected = splat_mod.FOOTPRINT_SIGMA**2 * (
        j_c[:, :, None] * j_c[:, None, :] + j_r[:, :, None] * j_r[:, None, :]
    )
    eigen = np.sqrt(np.clip(np.linalg.eigvalsh(expected[keep]), 0, None))  # ascending
    sigma = np.exp(splats.scales[keep].astype(np.float64))
    ratio_major = sigma[:, 0] / eigen[:, 2]
    ratio_minor = sigma[:, 1] / eigen[:, 1]
    assert np.median(np.abs(ratio_major - 1)) < 0.01 and np.quantile(ratio_major, 0.99) < 1.05
    assert np.median(np.abs(ratio_minor - 1)) < 0.01 and np.quantile(ratio_minor, 0.01) > 0.95
    # thin along the normal
    np.testing.assert_allclose(sigma[:, 2], splat_mod.THICKNESS * sigma[:, 1], rtol=1e-4)
    # the covariance's in-plane part itself (not only its eigenvalues), built as the 3DGS
    # reference code does (L = R S, Σ = L Lᵀ) with scipy's rotation of the quaternion
    scaled = axes[keep] * np.exp(splats.scales[keep].astype(np.float64))[:, None, :]
    cov = np.einsum("nik,njk->nij", scaled, scaled)
    np.testing.assert_allclose(splats.covariances()[keep], cov, rtol=1e-3, atol=1e-9)
    n = hit.normal[keep]
    thin = np.einsum("ni,nj->nij", n, n) * (sigma[:, 2] ** 2)[:, None, None]
    err = np.linalg.norm(cov - thin - expected[keep], axis=(1, 2)) / np.linalg.norm(
        expected[keep], axis=(1, 2)
    )
    assert np.median(err) < 0.02


def test_stride_budget_mask_and_depth_jumps(tmp_path):
    rgb, depth = empty_room(256)
    # stride and budget: the mesh's grid (every 3rd row and column; at 3 pixels of 1.4° a
    # grazing wall's steps exceed the depth-jump ratio, so that is lifted for the count)
    splats = m360.to_splats(depth, rgb, stride=3, max_depth_ratio=float("inf"))
    assert len(splats) == 43 * 86
    assert len(m360.to_splats(depth, rgb, stride=3)) < len(splats)
    rows, cols = np.divmod(splats.pixels, 256)
    assert (rows % 3 == 0).all() and (cols % 3 == 0).all()
    inf = float("inf")
    budget = m360.to_splats(depth, rgb, max_vertices=5000, max_depth_ratio=inf)
    step = m360.mesh.stride_for(128, 256, 1, 5000)
    assert len(budget) == -(-128 // step) * -(-256 // step) <= 5000
    info = splat_mod.write_splat_ply(
        tmp_path / "b.ply", depth, rgb=rgb, max_vertices=5000, max_depth_ratio=inf
    )
    assert info == {"stride": step, "splats": len(budget)}
    assert len(read_ply(tmp_path / "b.ply")) == len(budget)
    # masked pixels (NaN) get no splat; their neighbours keep theirs
    masked = depth.copy()
    masked[100:, :] = np.nan  # a nadir cap
    masked[40, 50] = np.nan
    cut = m360.to_splats(masked, rgb)
    assert len(cut) == np.isfinite(masked).sum()
    assert not np.isin(40 * 256 + 50, cut.pixels)
    # two posts in front of the wall, one pixel of wall between them: the splats at the
    # posts' edges do not stretch over the jump, and the sliver (both longitude neighbours
    # across a jump) gets none, as the mesh has no triangle there
    posts = depth.copy()
    posts[50:70, 60:64] *= 0.5
    posts[50:70, 65:69] *= 0.5
    footprint = posts.ravel() * (2 * np.pi / 256)  # a pixel's width at its depth
    kept = m360.to_splats(posts)
    stretch = np.exp(kept.scales[:, 0]) / footprint[kept.pixels]
    near = np.isin(kept.pixels // 256, np.arange(45, 75)) & np.isin(
        kept.pixels % 256, np.arange(55, 75)
    )
    assert stretch[near].max() < 1.5 * splat_mod.FOOTPRINT_SIGMA
    sliver = np.arange(50, 70) * 256 + 64
    assert not np.isin(sliver, kept.pixels).any()
    loose = m360.to_splats(posts, max_depth_ratio=float("inf"))
    at_sliver = np.isin(loose.pixels, sliver)
    assert at_sliver.sum() == 20
    assert (np.exp(loose.scales[at_sliver, 0]) / footprint[sliver] > 10).all()


def test_bad_input(tmp_path):
    rgb, depth = empty_room(64)
    with pytest.raises(m360.InputError):
        m360.to_splats(depth, rgb[:, :10])
    with pytest.raises(m360.InputError):
        m360.to_splats(depth, opacity=1.0)
    with pytest.raises(m360.InputError):
        m360.to_splats(np.full_like(depth, np.nan))
    with pytest.raises(m360.InputError):
        m360.to_splats(depth, max_depth_ratio=1.0)
    with pytest.raises(m360.InputError):
        splat_mod.write_splats(tmp_path / "x.ply", "not splats")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\n")
    with pytest.raises(m360.ReadError):
        splat_mod.read_splats(tmp_path / "bad.ply")
    with pytest.raises(m360.ReadError):
        splat_mod.read_splats(tmp_path / "missing.ply")
    assert not list(tmp_path.glob("*.tmp"))


# ------------------------------------------------------------------------- m360 run, batch


def run_room(tmp_path, engine: str):
    import cv2
    import onnx_graphs as g
    from m360.cli import main

    rgb, _ = m360.synthetic.render(m360.synthetic.room(3), 128)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(2):
        cv2.imwrite(str(photos / f"p{k}.png"), np.roll(rgb, 16 * k, axis=1)[:, :, ::-1])
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 3.0)
    out = tmp_path / "out"
    args = ["run", str(photos), "-o", str(out), "--model", str(model), "--formats",
            "npy,normals,splat", "--align", "none", "--blend", "mean", "--input-size", "64",
            "96", "--no-progress", "--engine", engine]  # fmt: skip
    return main(args), out, rgb


@pytest.fixture
def offline(tmp_path, monkeypatch):
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("M360_OFFLINE", "1")


def check_run(out, rgb) -> None:
    for k in range(2):
        saved = m360.load(out / f"p{k}")
        meta = saved.metadata
        assert meta["files"]["normals"] == {"exr": f"p{k}.normals.exr", "png": f"p{k}.normals.png"}
        assert meta["files"]["splat"] == {"splat": f"p{k}.splat.ply"}
        np.testing.assert_array_equal(
            m360.decode.read_exr(out / f"p{k}.normals.exr"), m360.normals(saved)
        )
        records = read_ply(out / f"p{k}.splat.ply")
        splats = m360.to_splats(saved, np.roll(rgb, 16 * k, axis=1))
        assert len(records) == len(splats)
        f_dc = np.stack([records[f"f_dc_{c}"] for c in range(3)], 1)
        np.testing.assert_array_equal(f_dc, splats.f_dc)  # the panorama's colours reached it


def test_cli_run_writes_normals_and_splats_and_resumes(tmp_path, offline, capsys):
    code, out, rgb = run_room(tmp_path, "local")
    assert code == 0, capsys.readouterr().err
    check_run(out, rgb)
    stamp = (out / "p0.splat.ply").stat().st_mtime_ns
    from m360.cli import main

    args = ["run", str(tmp_path / "photos"), "-o", str(out), "--model", str(tmp_path / "m.onnx"),
            "--formats", "npy,normals,splat", "--align", "none", "--blend", "mean",
            "--input-size", "64", "96", "--no-progress"]  # fmt: skip
    assert main(args) == 0
    assert "2 already done" in capsys.readouterr().err
    assert (out / "p0.splat.ply").stat().st_mtime_ns == stamp
    (out / "p1.normals.png").unlink()  # a missing file: that image is done again
    assert main(args) == 0
    assert (out / "p1.normals.png").is_file()


def test_ray_engine_writes_normals_and_splats(tmp_path, offline, monkeypatch, capsys):
    ray = pytest.importorskip("ray")
    from pathlib import Path

    here = str(Path(__file__).parent)
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")]))
    )
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        code, out, rgb = run_room(tmp_path, "ray")
    finally:
        ray.shutdown()
    assert code == 0, capsys.readouterr().err
    check_run(out, rgb)
