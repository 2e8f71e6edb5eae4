"""The m360 command: run, models, demo (in-process through m360.cli.main)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
from local_http import LocalServer
from m360 import models
from m360.cli import main


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    for var in ("M360_OFFLINE", "M360_MODEL_DIR", "M360_ALLOW_UNVERIFIED"):
        monkeypatch.delenv(var, raising=False)
    models._clear_verified()
    return tmp_path / "home" / "models"


@pytest.fixture(scope="module")
def panorama(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rgb, _ = m360.synthetic.render(m360.synthetic.room(3), 256)
    path = tmp_path_factory.mktemp("in") / "room.png"
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def test_run_writes_arrays_preview_and_sidecar(
    tmp_path: Path, panorama: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    out = tmp_path / "out"
    code = main(
        [
            "run", str(panorama), "-o", str(out), "--model", str(model),
            "--align", "none", "--blend", "mean", "--threads", "1", "--input-size", "64", "96",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "room.depth.npy",
        "room.disparity.npy",
        "room.json",
        "room.preview.png",
    ]  # fmt: skip  (no temporary files left)
    disparity = np.load(out / "room.disparity.npy")
    depth = np.load(out / "room.depth.npy")
    assert disparity.shape == depth.shape == (128, 256) and disparity.dtype == np.float32
    ok = disparity > 0
    np.testing.assert_allclose(depth[ok], 1.0 / disparity[ok], rtol=1e-6)
    preview = cv2.imread(str(out / "room.preview.png"))
    assert preview.shape == (128, 256, 3)
    meta = json.loads((out / "room.json").read_text())
    assert meta["m360_version"] == m360.__version__
    assert meta["model"]["sha256"] == hashlib.sha256(model.read_bytes()).hexdigest()
    assert meta["model"]["output_kind"] == "affine_disparity"
    # 43x50 tangents fit inside 64x96 keeping their aspect: scale 64/43 -> 64 x 74.4 -> 64 x 74.
    assert meta["model"]["threads"] == 1 and meta["model"]["network_size"] == [64, 74]
    # The angle of one network pixel at a tile's centre (its oracle: tests/test_layouts.py).
    layout = m360.geometry.default_layout(256)
    assert meta["model"]["degrees_per_pixel"] == round(layout.network_pixel_degrees(74), 4)
    assert meta["options"]["align"] is None and meta["options"]["blend"] == {"method": "mean"}
    assert meta["quantities"]["depth"]["units"] == "relative"
    assert meta["quantities"]["disparity"]["invalid"].startswith("NaN")
    assert "latitude" in meta["erp_convention"] and meta["input"]["path"] == str(panorama)
    assert {"project", "network", "align", "blend", "total"} <= set(meta["timings_s"])
    assert meta["files"]["disparity"] == {"npy": "room.disparity.npy"}


def test_run_goes_on_after_a_failed_image(
    tmp_path: Path, panorama: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A file a manifest lists that is missing fails alone (a path on the command line that is
    missing is a usage error: see the next test)."""
    model = g.affine_of_mean(tmp_path / "m.onnx")
    missing = tmp_path / "missing.jpg"
    manifest = tmp_path / "list.txt"
    manifest.write_text(f"{missing}\n{panorama}\n")
    out = tmp_path / "out"
    args = ["run", str(manifest), "-o", str(out), "--model", str(model)]
    code = main([*args, "--align", "none", "--blend", "mean"])
    err = capsys.readouterr().err
    assert code == 1
    assert f"{missing}: ReadError: input image {missing} does not exist" in err
    assert "1 done, 0 already done, 1 failed" in err
    assert (out / "room.json").is_file()


@pytest.mark.parametrize("model", [None, "midas-v21-small", "model.onnx"])
def test_run_on_a_missing_path_is_a_usage_error_before_any_model_work(
    model: str | None,
    tmp_path: Path,
    panorama: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Offline with an empty M360_HOME any model access fails (exit 1): a missing input must
    be found first, as a usage error naming it."""
    monkeypatch.setenv("M360_OFFLINE", "1")
    monkeypatch.chdir(tmp_path)
    args = ["run", "missing.jpg", str(panorama), "-o", "out"]
    code = main([*args, *(["--model", model] if model else [])])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "input missing.jpg does not exist" in err
    assert "model" not in err.lower() and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_run_with_the_default_model_offline_says_where_to_put_it(
    panorama: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("M360_OFFLINE", "1")
    code = main(["run", str(panorama), "-o", str(tmp_path / "out"), "--align", "none"])
    err = capsys.readouterr().err
    assert code == 1
    entry = models.get(models.DEFAULT_MODEL)
    assert "M360_OFFLINE=1 forbids downloading" in err and entry.sha256 in err  # type: ignore[operator]
    assert str(models.cache_dir() / entry.filename) in err


def test_models_lists_and_fetches(
    server: LocalServer,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    isolated_cache: Path,
) -> None:
    data = g.affine_of_mean(tmp_path / "tiny.onnx").read_bytes()
    server.routes["/tiny.onnx"] = (200, data, "ok")
    entry = dataclasses.replace(
        models.get("midas-v21-small"),
        name="tiny",
        filename="tiny.onnx",
        urls=(server.url("/tiny.onnx"),),
        sha256=hashlib.sha256(data).hexdigest(),
        size_bytes=len(data),
    )
    monkeypatch.setitem(models.REGISTRY, "tiny", entry)
    assert main(["models"]) == 0
    listing = capsys.readouterr().out
    for name in models.names():
        assert name in listing
    assert "midas-v21-small-isl" in listing and "UNKNOWN" in listing  # unconfirmed hash shown
    tiny_line = next(line for line in listing.splitlines() if line.startswith("tiny "))
    assert " no " in tiny_line
    assert main(["models", "fetch", "tiny"]) == 0
    assert "sha256 verified" in capsys.readouterr().out
    assert (isolated_cache / "tiny.onnx").read_bytes() == data
    assert main(["models"]) == 0
    tiny_line = next(
        line for line in capsys.readouterr().out.splitlines() if line.startswith("tiny ")
    )
    assert " yes " in tiny_line
    assert main(["models", "path", "tiny"]) == 0
    assert capsys.readouterr().out.strip() == str(isolated_cache / "tiny.onnx")


def test_demo_runs_estimate_with_a_labelled_simulated_network(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--width", "256"]) == 0
    text = capsys.readouterr().out
    assert "SIMULATED" in text and "AbsRel" in text
    meta = json.loads((out / "demo.json").read_text())
    assert meta["model"]["name"].startswith("simulated")
    for name in ("demo.disparity.npy", "demo.depth.npy", "demo.preview.png", "demo_rgb.png"):
        assert (out / name).is_file()


def test_run_passes_every_stitching_flag(
    tmp_path: Path, panorama: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    out = tmp_path / "out"
    code = main(
        [
            "run", str(panorama), "-o", str(out), "--model", str(model), "--threads", "1",
            "--input-size", "64", "96", "--align", "4x3,6x5", "--energy", "paper",
            "--solver", "lbfgs", "--iterations", "9", "--tolerance", "1e-5",
            "--sample-fraction", "0.02", "--pole-cap-deg", "2", "--smoothness", "3",
            "--scale-weight", "0.05", "--offsets", "perspective", "--loss", "huber",
            "--prior-weight", "0.5", "--prior-scale-deg", "2", "--prior-fusion", "off",
            "--blend", "poisson",
            "--fidelity", "nn", "--poisson-lam", "0.2", "--poisson-tolerance", "1e-5",
            "--poisson-iterations", "800", "--poisson-solver", "fused",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    options = json.loads((out / "room.json").read_text())["options"]
    assert options["align"] == {
        "levels": [[4, 3], [6, 5]],
        "energy": "paper",
        "solver": "lbfgs",
        "iterations": 9,
        "tolerance": 1e-5,
        "sample_fraction": 0.02,
        "pole_cap_deg": 2.0,
        "smoothness": 3.0,
        "scale_weight": 0.05,
        "offsets": "perspective",
        "loss": "huber",
        "prior_weight": 0.5,
        "prior_scale_deg": 2.0,
        "prior_fusion": "off",
    }
    assert options["blend"] == {
        "method": "poisson",
        "fidelity": "nn",
        "lam": 0.2,
        "tolerance": 1e-5,
        "iterations": 800,
        "solver": "fused",
    }


def test_run_with_an_input_size_the_model_cannot_take_is_a_usage_error(
    tmp_path: Path, panorama: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Like an unavailable provider, an impossible --input-size is refused (exit 2) when the
    model is loaded, before any image; the model's own size runs."""
    model = g.affine_of_mean(tmp_path / "fixed.onnx", input_shape=(1, 3, 32, 32))
    args = ["run", str(panorama), "-o", str(tmp_path / "out"), "--model", str(model),
            "--align", "none", "--blend", "mean", "--no-progress"]  # fmt: skip
    assert main([*args, "--input-size", "32", "48"]) == 2
    err = capsys.readouterr().err
    assert "m360: error: input_size=(32, 48) but fixed.onnx takes a fixed 32x32 input" in err
    assert "omit input_size or pass (32, 32)" in err
    assert not (tmp_path / "out").exists()
    assert main([*args, "--input-size", "32", "32"]) == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "out" / "room.json").read_text())["model"]["network_size"] == [
        32,
        32,
    ]
