"""``m360 models check FILE``: what m360 will do with a model, on tiny graphs (no real weights)."""

from __future__ import annotations

import dataclasses
import hashlib
import re
from pathlib import Path

import m360
import numpy as np
import onnx_graphs as g
import pytest
import real_data
from check_graphs import half_resolution, only_at, oracle, unet
from m360 import models
from m360.cli import main
from m360.estimators import _probe, network_size
from norm_graphs import NCHW, VARIANTS, chain_then_channel

WIDTH = 512  # a small ERP keeps the one-tangent run quick
REAL = real_data.MODELS


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
    # What the stitch can resolve (the angle's own oracle is tests/test_cli.py's).
    degrees = m360.Layout.icosahedron(WIDTH).network_pixel_degrees(8)
    where = "at a tile's centre, whatever the ERP width"
    assert field(out, "detail") == f"{degrees:.2f}° per network pixel {where}"
    # 8 px on the 400 px tangents of a 2K ERP: edges="auto" refines along the photo.
    tile = m360.Layout.icosahedron(WIDTH).tangent_shape[1]
    assert field(out, "edges") == (
        f"refined along the photo by default (the {tile}-px tangents are {tile / 8:.1f}x the "
        "network's 8-px input; --edges auto refines from 4x)"
    )
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
    assert field(out, "output") == f"{nh}x{nw} for a {nh}x{nw} input (the input's size)"
    assert field(out, "sizes") == f"runs at any size (probed near {nh}x{nw})"
    # As fine as its tangents: edges="auto" keeps the network's edges.
    assert field(out, "edges").startswith(
        f"as the network gives them by default (the {tangent[1]}-px tangents are "
        f"{tangent[1] / nw:.1f}x the network's {nw}-px input"
    )


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


# --------------------------------------------------------------------------------------------
# Probing: sizes, output shape, the output kind guess, and the flags printed.


def test_a_model_that_needs_multiples_of_32_gets_the_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = unet(tmp_path / "unet.onnx")
    tangent = m360.Layout.icosahedron(WIDTH).tangent_shape
    nh, nw = network_size(tangent, (384, 384))
    assert nh % 32 or nw % 32  # m360's default size is not a multiple of 32: it fails there
    code, out, err = run(capsys, str(path))
    assert code == 0 and err == ""
    assert field(out, "network size").endswith(")") and ": FAILS (Add node: " in out
    assert field(out, "sizes") == f"runs at sizes that are multiples of 32 (probed near {nh}x{nw})"
    h32, w32 = network_size(tangent, (384, 384), multiple_of=32)
    assert f"with --multiple-of 32: {h32}x{w32}" in out
    assert field(out, "output").startswith(f"{h32}x{w32} for a {h32}x{w32} input")
    assert field(out, "usable") == "yes, with the flags below"
    assert "--multiple-of 32" in field(out, "use")
    assert "multiple_of=32" in field(out, "python")
    # With the flag it prints, the file runs as is: nothing more to add.
    code, out, _ = run(capsys, str(path), "--multiple-of", "32", "--output-kind", "metric_depth")
    assert code == 0 and "FAILS" not in out and field(out, "usable") == "yes"


@pytest.mark.parametrize("levels", [3, 4, 6])
def test_the_size_rule_is_found_for_each_depth_of_unet(tmp_path: Path, levels: int) -> None:
    info = models.check(unet(tmp_path / "u.onnx", levels), erp_width=WIDTH)
    assert info["size_rule"] == 2**levels
    assert info["usable"]


def test_a_model_that_runs_at_no_size_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = only_at(tmp_path / "only.onnx", 101, 103)
    code, out, err = run(capsys, str(path))
    assert code == 2
    assert field(out, "sizes").startswith("runs at none of the sizes tried")
    assert field(out, "usable").startswith("no: ONNX Runtime fails at any size tried")
    assert err.startswith("m360: error: ") and "m360 cannot run it" in err


def test_a_half_resolution_output_is_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = run(capsys, str(half_resolution(tmp_path / "half.onnx")))
    assert code == 0
    tangent = m360.Layout.icosahedron(WIDTH).tangent_shape
    nh, nw = network_size(tangent, (384, 384))
    assert field(out, "output") == (
        f"{nh // 2}x{nw // 2} for a {nh}x{nw} input (1/2 of the input's size: m360 resizes it "
        "to the tangent)"
    )


@pytest.mark.parametrize(
    ("transform", "kind"),
    [
        ("depth", "metric_depth"),
        ("disparity", "affine_disparity"),
        ("negative_depth", "affine_depth"),
        ("negative_disparity", "affine_depth"),
        ("scaled_depth", "affine_depth"),
        ("flat", None),
    ],
)
def test_the_output_kind_is_guessed_from_the_probe_scene(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], transform: str, kind: str | None
) -> None:
    path = oracle(tmp_path / f"{transform}.onnx", transform)
    code, out, _ = run(capsys, str(path))
    assert code == 0
    assert field(out, "input") == "'x' (1, 3, 64, 80), NCHW, static size 64x80"
    guess = field(out, "kind guess")
    if kind is None:
        assert guess.startswith("cannot tell (the output does not follow the scene's depth")
        assert "--output-kind" not in out.split("usable:")[1]
    else:
        assert guess.startswith(f"{kind}, sure: ")
        assert f"--output-kind {kind}" in field(out, "use")
    # The image is ignored, so no normalisation does better than another: none is named.
    assert "no clear winner" in out and "--normalize" not in out.split("usable:")[1]
    if transform.startswith("negative"):
        lo, hi = re.search(r"values (\S+) … (\S+),", out).groups()  # type: ignore[union-attr]
        assert float(lo) < float(hi) < 0


def test_a_declared_kind_that_the_output_contradicts_is_warned_about(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = oracle(tmp_path / "disp.onnx", "disparity")
    code, out, _ = run(capsys, str(path), "--output-kind", "metric_depth")
    assert code == 0 and field(out, "output kind") == "metric_depth (--output-kind)"
    assert "warning: declared metric_depth, the output looks like affine_disparity" in out


def test_the_guess_against_an_independent_oracle() -> None:
    # guess_kind on arrays: z from the probe views, outputs made from it here.
    z = [v[1] for v in _probe.views((60, 70))]
    assert _probe.guess_kind([1 / d for d in z], z).kind == "affine_disparity"
    assert _probe.guess_kind([d.copy() for d in z], z).kind == "metric_depth"
    assert _probe.guess_kind([d * 10 for d in z], z).kind == "affine_depth"
    assert _probe.guess_kind([-d for d in z], z).kind == "affine_disparity"  # falls with depth
    assert _probe.guess_kind([np.full_like(d, np.nan) for d in z], z).kind is None
    assert _probe.guess_kind([np.full_like(d, 2.0) for d in z], z).kind is None  # ties
    rng = np.random.default_rng(0)
    noise = [rng.standard_normal(d.shape).astype(np.float32) for d in z]
    assert _probe.guess_kind(noise, z).kind is None
    # Spearman's rank correlation against scipy's.
    scipy_stats = pytest.importorskip("scipy.stats")
    a, b = rng.standard_normal(500), rng.standard_normal(500)
    b += a
    assert _probe.rank_correlation(a, b) == pytest.approx(scipy_stats.spearmanr(a, b)[0])
    a, b = np.round(a), np.round(b)  # many ties: scipy's mean ranks
    assert _probe.rank_correlation(a, b) == pytest.approx(scipy_stats.spearmanr(a, b)[0])


def test_the_normalisation_hint_follows_the_declared_kind() -> None:
    # The rule on scores given here (the oracle): a declared kind's sign must hold; the winner
    # must follow depth (0.3) and lead the next by 0.12.
    fastdepth_as_pano = {"imagenet": 0.18, "unit": 0.27, "none": -0.77}  # measured, stop 39
    assert _probe.best_normalisation(fastdepth_as_pano) == "none"  # no kind: either sign
    assert _probe.best_normalisation(fastdepth_as_pano, +1) is None  # a depth must grow
    assert _probe.best_normalisation(fastdepth_as_pano, -1) == "none"  # a disparity falls
    fastdepth_tangent = {"imagenet": 0.52, "unit": 0.82, "none": -0.46}
    for direction in (0, +1):
        assert _probe.best_normalisation(fastdepth_tangent, direction) == "unit"
    assert _probe.best_normalisation({"unit": 0.5, "imagenet": 0.45}) is None  # no clear lead
    assert _probe.best_normalisation({"unit": -0.9, "imagenet": 0.5}, +1) == "imagenet"
    assert _probe.best_normalisation({"unit": 0.9}) is None  # nothing to compare with
    assert _probe.DEPTH_DIRECTION.keys() == set(m360.estimators.kinds.ALL_OUTPUT_KINDS)


def test_a_real_panoramic_depth_is_not_told_to_take_raw_input() -> None:
    # The shared FastDepth run on the probe corridor as one panorama: on raw 0-255 input its
    # output falls with distance (-0.77), which once made check name --normalize none for a
    # model declared as a depth; the depth it declares must grow with distance.
    path = REAL / "fastdepth_dynamic.onnx"
    if not path.is_file():
        pytest.skip(f"real networks not available ({REAL} is absent)")
    info = models.check(path, kind="panoramic", output_kind="affine_depth")
    assert info["usable"]
    assert info["normalize_scores"]["none"] < -0.3  # the trap is there
    assert info["normalize_guess"] != "none" and info["flags"].get("normalize") != "none"


def test_probe_size_gives_odd_multiples_nearest() -> None:
    from m360.estimators.onnx import probe_size

    assert probe_size((332, 384), 32) == (352, 416)  # 11·32, 13·32
    assert probe_size((332, 384), 64) == (320, 448)  # 5·64, 7·64
    assert probe_size((332, 384), 1) == (333, 385)
    assert probe_size((10, 10), 16) == (16, 16)


def test_a_json_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    code = main(["models", "check", str(unet(tmp_path / "u.onnx")), "--width", "512", "--json"])
    info = json.loads(capsys.readouterr().out)
    assert code == 0 and info["size_rule"] == 32 and info["flags"]["multiple_of"] == 32


def test_check_options_as_in_m360_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = g.affine_of_mean(tmp_path / "dyn.onnx", 2.0, 1.0)
    code, out, _ = run(
        capsys, str(path), "--normalize", "unit", "--input-size", "224", "224", "--resize", "exact"
    )
    assert code == 0
    assert field(out, "network size").startswith("224x224 for the default layout")
    assert field(out, "normalisation").startswith("m360 feeds (rgb - mean) / std: mean (0.0, 0.0")
    code, _, err = run(capsys, str(path), "--normalize", "unit", "--mean", "0", "0", "0")
    assert code == 2 and "not both" in err


# --------------------------------------------------------------------------------------------
# The real networks (tests/real_data.py; skipped when absent).


@pytest.mark.parametrize(
    ("name", "rule", "kind", "scale"),
    [
        ("fastdepth_224.onnx", None, "metric_depth", 1.0),
        ("fastdepth_dynamic.onnx", 32, "metric_depth", 1.0),
        ("mobile_pydnet_dynamic.onnx", 64, "affine_depth", 0.5),
    ],
)
def test_the_shared_real_networks(
    name: str, rule: int | None, kind: str, scale: float, capsys: pytest.CaptureFixture[str]
) -> None:
    path = REAL / name
    if not path.is_file():
        pytest.skip(f"real networks not available ({REAL} is absent)")
    info = models.check(path)
    assert info["usable"] and info["size_rule"] == rule
    assert info["input"]["static"] == (rule is None)
    if rule is not None:  # m360's default 332x384 is no multiple of 32: it fails there
        assert info["network_size_runs"] is not None
        assert info["flags"]["multiple_of"] == rule
    assert info["normalization"]["source"] == "m360"  # the graphs hold no normalisation
    assert info["normalize_guess"] == "unit" and info["flags"]["normalize"] == "unit"
    assert info["kind_guess"]["kind"] == kind and info["flags"]["output_kind"] == kind
    assert info["output_scale"] == [scale, scale]
    if kind == "affine_depth":  # PyDNet: negative, growing with depth
        assert info["output_range"][2] < 0 and info["kind_guess"]["correlation_with_depth"] > 0
    # The flags it prints make the file run at m360's size for the default layout.
    options = dict(info["options"])
    if options["output_kind"] not in m360.estimators.OUTPUT_KINDS:  # affine_depth: #23 too
        del options["output_kind"]
    est = m360.estimators.load_estimator(path, **options)
    tangent = m360.Layout.icosahedron(models.CHECK_ERP_WIDTH).tangent_shape
    grey = np.full((1, *tangent, 3), 128, np.uint8)
    assert np.isfinite(est.predict(grey)).all()
    code = main(["models", "check", str(path)])
    out = capsys.readouterr().out
    assert code == 0 and field(out, "usable") == "yes, with the flags below"


def test_a_registered_model_keeps_its_own_normalisation(monkeypatch: pytest.MonkeyPatch) -> None:
    path = REAL / "fastdepth_224.onnx"
    if not path.is_file():
        pytest.skip(f"real networks not available ({REAL} is absent)")
    entry = dataclasses.replace(
        models.get(models.DEFAULT_MODEL),
        name="fastdepth-imagenet",
        sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
        output_kind="metric_depth",
    )
    monkeypatch.setitem(models.REGISTRY, entry.name, entry)
    info = models.check(path, erp_width=WIDTH)
    assert info["registry"] == entry.name and info["normalize_guess"] == "unit"  # the hint
    assert info["flags"] == {} and info["usable"]  # but the registry's word stands
