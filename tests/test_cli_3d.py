"""m360 run --formats ply,glb --camera-height, and batch.run(scale=) end to end."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
from m360.cli import main

pytest.importorskip("trimesh")


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("M360_OFFLINE", "1")


@pytest.fixture(scope="module")
def room() -> tuple[m360.synthetic.Scene, np.ndarray, np.ndarray]:
    scene = m360.synthetic.room(3)
    rgb, depth = m360.synthetic.render(scene, 256)
    return scene, rgb, depth


def write_png(path: Path, rgb: np.ndarray) -> Path:
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def test_run_writes_ply_and_glb(tmp_path, room, capsys):
    _, rgb, _ = room
    panorama = write_png(tmp_path / "room.png", rgb)
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    out = tmp_path / "out"
    code = main(
        [
            "run", str(panorama), "-o", str(out), "--model", str(model), "--formats",
            "npy,ply,glb", "--align", "none", "--blend", "mean", "--input-size", "64", "96",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    meta = json.loads((out / "room.json").read_text())
    assert meta["files"]["points"] == {"ply": "room.points.ply"}
    assert meta["files"]["mesh"] == {"glb": "room.mesh.glb"}
    assert "y up" in meta["frame"]["room.mesh.glb"]
    xyz, faces = m360.mesh.read_geometry(out / "room.points.ply")
    assert faces is None
    saved = m360.load(out / "room")
    np.testing.assert_array_equal(xyz, m360.to_points(saved).xyz)
    # the point colours are the panorama's (read back through the viewer's loader)
    from m360.viewer import load_scene

    shown = load_scene(out / "room.points.ply")
    np.testing.assert_array_equal(shown.rgb, rgb.reshape(-1, 3)[m360.to_points(saved).pixels])


def test_camera_height_flag(tmp_path, room, capsys):
    _, rgb, _ = room
    panorama = write_png(tmp_path / "room.png", rgb)
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    base = ["run", str(panorama), "--model", str(model), "--input-size", "64", "96"]
    assert main([*base, "-o", str(tmp_path / "a"), "--camera-height", "-1"]) == 2
    assert "camera height must be > 0" in capsys.readouterr().err
    # A network that sees no floor (its disparity is the brightness, here of random noise): the
    # image fails with ScaleError and nothing is written as metres.
    noise = np.random.default_rng(0).integers(0, 256, (128, 256, 3), dtype=np.uint8)
    write_png(panorama, noise)
    code = main([*base, "-o", str(tmp_path / "b"), "--camera-height", "1.6", "--align", "none"])
    assert code == 1
    assert "ScaleError" in (tmp_path / "b" / "failures.jsonl").read_text()
    assert not (tmp_path / "b" / "room.json").exists()


def test_batch_scale_writes_metres(tmp_path, room):
    scene, rgb, depth = room
    panorama = write_png(tmp_path / "room.png", rgb)
    sim = m360.estimators.SimulatedEstimator(scene, m360.geometry.default_layout(256), seed=3)
    height = float(scene.room_max[1])
    report = m360.batch.run(
        [panorama], tmp_path / "out", model=sim, progress=False,
        scale=m360.scale.camera_height(height),
    )  # fmt: skip
    assert report.exit_code == 0
    saved = m360.load(tmp_path / "out" / "room")
    assert saved.units == "metres" and saved.metadata["scale"]["method"] == "camera_height"
    assert float(np.nanmedian(np.abs(saved.depth / depth - 1))) < 0.05
    assert saved.metadata["batch"]["fingerprint"]["scale"]["height"] == height
    # another height is another fingerprint: not skipped
    again = m360.batch.run(
        [panorama], tmp_path / "out", model=sim, progress=False,
        scale=m360.scale.camera_height(height * 2),
    )  # fmt: skip
    assert again.outcomes[0].status == "done"


def test_geometry_only_formats_are_resumed(tmp_path, room, capsys):
    """--formats ply,glb writes no arrays; a rerun still sees the image as done."""
    _, rgb, _ = room
    panorama = write_png(tmp_path / "room.png", rgb)
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    args = ["run", str(panorama), "-o", str(tmp_path / "out"), "--model", str(model)]
    args += ["--formats", "ply,glb", "--align", "none", "--input-size", "64", "96"]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args) == 0
    assert "0 done, 1 already done" in capsys.readouterr().err
    (tmp_path / "out" / "room.mesh.glb").unlink()  # a listed 3D file is missing: redo
    assert main(args) == 0
    assert "1 done, 0 already done" in capsys.readouterr().err


def test_nadir_zenith_and_sky_flags(tmp_path, room, capsys):
    _, rgb, _ = room
    panorama = write_png(tmp_path / "room.png", rgb)
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    base = ["run", str(panorama), "--model", str(model), "--input-size", "64", "96"]
    base += ["--formats", "npy", "--align", "none", "--blend", "mean"]
    assert main([*base, "-o", str(tmp_path / "plain")]) == 0
    assert main([*base, "-o", str(tmp_path / "caps"), "--nadir", "30", "--zenith", "20"]) == 0
    plain = m360.load(tmp_path / "plain" / "room").disparity
    capped = m360.load(tmp_path / "caps" / "room").disparity
    lat = 90 - 180 * (np.arange(plain.shape[0]) + 0.5) / plain.shape[0]
    assert np.isnan(capped[lat < -60]).all() and np.isnan(capped[lat > 70]).all()
    middle = (lat > -55) & (lat < 65)
    assert np.isfinite(capped[middle]).all()
    # the same estimate with the caps through the API: the CLI adds nothing else
    api = m360.estimate(
        rgb, str(model), align="none", blend="mean", input_size=(64, 96),
        mask=[m360.masks.nadir(30), m360.masks.zenith(20)],
    )  # fmt: skip
    np.testing.assert_array_equal(capped, api.disparity)
    # another mask is another result: the rerun into the same folder redoes the image
    capsys.readouterr()
    assert main([*base, "-o", str(tmp_path / "caps"), "--nadir", "25", "--zenith", "20"]) == 0
    assert "1 done, 0 already done" in capsys.readouterr().err
    assert main([*base, "-o", str(tmp_path / "caps"), "--nadir", "25", "--zenith", "20"]) == 0
    assert "0 done, 1 already done" in capsys.readouterr().err
    # sky=nan: the far pixels become NaN, recorded in the sidecar
    assert main([*base, "-o", str(tmp_path / "sky"), "--sky", "nan"]) == 0
    meta = json.loads((tmp_path / "sky" / "room.json").read_text())
    assert meta["options"]["sky"] == "nan"
    sky = m360.load(tmp_path / "sky" / "room").disparity
    expected = plain.copy()
    expected[m360.masks.sky(plain)] = np.nan
    np.testing.assert_array_equal(sky, expected)
    # bad values are usage errors
    assert main([*base, "-o", str(tmp_path / "bad"), "--nadir", "-5"]) == 2
    assert "nadir" in capsys.readouterr().err


def test_batch_mask_argument_is_checked(tmp_path, room):
    _, rgb, _ = room
    write_png(tmp_path / "room.png", rgb)
    with pytest.raises(m360.InputError, match="mask must be"):
        m360.batch.run(tmp_path / "room.png", tmp_path / "out", mask=np.ones((4, 8), np.uint8))
    with pytest.raises(m360.InputError, match="sky"):
        m360.batch.run(tmp_path / "room.png", tmp_path / "out", sky="blue")
