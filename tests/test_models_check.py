"""``m360 models check FILE``: what m360 will do with a model, on tiny graphs (no real weights)."""

from __future__ import annotations

import dataclasses
import hashlib
import re
from pathlib import Path

import m360
import onnx_graphs as g
import pytest
from m360 import models
from m360.cli import main
from m360.estimators import network_size
from norm_graphs import NCHW, VARIANTS, chain_then_channel

WIDTH = 512  # a small ERP keeps the one-tangent run quick


@pytest.fixture(autouse=True)
def isolated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "m360home"))
    for var in ("M360_OFFLINE", "M360_MODEL_DIR", "M360_ALLOW_UNVERIFIED"):
        monkeypatch.delenv(var, raising=False)


def run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["models", "check", *args, "--width", str(WIDTH)])
    out, err = capsys.readouterr()
    return code, out, err


def field(out: str, name: str) -> str:
    match = re.search(rf"^{name}:\s+(.*)$", out, re.MULTILINE)
    assert match, f"no {name!r} line in:\n{out}"
    return match.group(1)


def test_static_normalising_registered_model(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = chain_then_channel(tmp_path / "in.onnx", 0, VARIANTS["sub_div"][0], NCHW)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    entry = dataclasses.replace(
        models.get(models.DEFAULT_MODEL), name="tiny-metric", sha256=digest, output_kind="distance"
    )
    monkeypatch.setitem(models.REGISTRY, "tiny-metric", entry)
    code, out, err = run(capsys, str(path))
    assert code == 0 and err == ""
    assert field(out, "registry") == "tiny-metric (matched by sha256)"
    assert field(out, "input") == "'x' (1, 3, 8, 8), NCHW, static size 8x8"
    assert field(out, "network size").startswith("8x8 for the default layout")
    norm = field(out, "normalisation")
    assert norm.startswith("graph (m360 feeds RGB in [0, 1]): mean (0.485, 0.456, 0.406)")
    assert "std (0.229, 0.224, 0.225)" in norm
    assert field(out, "output kind") == "distance (registry: tiny-metric)"
    assert field(out, "usable") == "yes"
    # The user's --output-kind wins over the registry's.
    code, out, _ = run(capsys, str(path), "--output-kind", "metric_depth")
    assert code == 0 and field(out, "output kind") == "metric_depth (--output-kind)"


def test_dynamic_model_without_normalisation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = g.affine_of_mean(tmp_path / "dyn.onnx", 2.0, 1.0)
    code, out, _ = run(capsys, str(path))
    assert code == 0
    assert field(out, "registry") == "not registered"
    assert field(out, "input") == "'x' (B, 3, H, W), NCHW, dynamic size"
    tangent = m360.Layout.icosahedron(WIDTH).tangent_shape
    nh, nw = network_size(tangent, (384, 384))
    assert field(out, "network size").startswith(f"{nh}x{nw} for the default layout")
    assert f"tangents {tangent[0]}x{tangent[1]}" in field(out, "network size")
    assert field(out, "normalisation").startswith("m360 feeds (rgb - mean) / std: mean (0.485")
    assert "no normalisation found" in out
    assert field(out, "output kind").startswith("unknown: pass --output-kind")
    assert field(out, "output") == f"shape (1, {nh}, {nw}) for one tangent"


def test_nhwc_graph_wanting_0_255(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    steps, shape, _, _ = VARIANTS["nhwc_255_after_transpose"]
    path = chain_then_channel(tmp_path / "nhwc.onnx", 1, steps, shape)
    code, out, _ = run(capsys, str(path), "--output-kind", "affine_disparity")
    assert code == 0
    assert field(out, "input") == "'x' (1, 8, 8, 3), NHWC, static size 8x8"
    assert field(out, "normalisation").startswith("graph (m360 feeds RGB in [0, 255])")
    assert "Transpose -> Sub -> Div" in out


@pytest.mark.parametrize(
    ("name", "data", "why"),
    [
        ("garbage.onnx", b"\x08\x07" + b"not a protobuf at all" * 20, "cannot load"),
        ("page.onnx", b"<!DOCTYPE html><html>Not found</html>", "HTML/XML page"),
        ("empty.onnx", b"", "it is empty"),
        ("lfs.onnx", b"version https://git-lfs.github.com/spec/v1\noid sha256:ab\n", "LFS"),
    ],
)
def test_a_corrupt_or_non_onnx_file_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, data: bytes, why: str
) -> None:
    path = tmp_path / name
    path.write_bytes(data)
    code, out, err = run(capsys, str(path))
    assert code == 2 and out == ""
    assert err.startswith("m360: error: ") and why in err and str(path) in err


def test_a_truncated_model_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    whole = g.conv_net(tmp_path / "net.onnx", size=32, width=8, layers=1).read_bytes()
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(whole[: len(whole) // 2])
    code, _, err = run(capsys, str(cut))
    assert code == 2 and "cannot load" in err


def test_an_onnx_model_m360_cannot_feed_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = g.identity(tmp_path / "rank3.onnx", [1, 8, 8])
    code, _, err = run(capsys, str(path))
    assert code == 2 and "rank 3" in err


def test_a_missing_file_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, str(tmp_path / "nowhere.onnx"))
    assert code == 2 and "does not exist" in err
