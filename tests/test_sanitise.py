"""Network outputs are checked before anything trusts them; the result before it is written.

Issue 23, items 1 and 2: NaN-aware resize of a network's output, per-tangent sanitising, the
``affine_depth`` and ``negated_affine_disparity`` kinds, metric results in metres, the result
check with its fallback, and the sidecar telling the truth. The last tests run the real
networks (tests/real_data.py; skipped when absent).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import m360
import m360.synthetic as syn
import numpy as np
import onnx_graphs as g
import pytest
import real_data
from conftest import scene
from m360.errors import ModelError
from m360.estimators import OnnxEstimator, kinds
from m360.estimators.onnx import resize_valid
from m360.pipeline import checks as checks_module
from m360.stitching.stitch import StitchResult

REAL = real_data.ROOT
needs_real = real_data.requires_real


# -- 1. NaN-aware resize ---------------------------------------------------------------------


def test_resize_valid_keeps_a_zero_out_of_its_neighbours() -> None:
    values = np.full((4, 4), 2.0, dtype=np.float32)
    values[1, 2] = 0.0  # a zero depth
    values[3, 0] = np.inf
    out = resize_valid(values, (8, 8), positive=True)
    finite = np.isfinite(out)
    # Oracle by hand: every valid input is 2, so every output made of valid inputs is exactly 2;
    # a plain bilinear resize gives values between 0 and 2 around the zero.
    np.testing.assert_allclose(out[finite], 2.0, rtol=1e-6)
    assert not finite[2:4, 4:6].any()  # the output pixels nearest the zero: NaN
    assert finite.mean() > 0.75
    # Not positive (an affine kind): the zero is a value like any other.
    kept = resize_valid(values, (8, 8), positive=False)
    assert np.isfinite(kept[2:4, 4:6]).all() and kept[2:4, 4:6].min() < 2.0


def test_resize_valid_same_shape_only_masks() -> None:
    values = np.array([[1.0, -1.0], [0.0, np.nan]], dtype=np.float32)
    out = resize_valid(values, (2, 2), positive=True)
    np.testing.assert_array_equal(np.isnan(out), [[False, True], [True, True]])
    assert out[0, 0] == 1.0


def test_onnx_predict_resizes_a_metric_output_without_zero_spikes(tmp_path: Path) -> None:
    # A fixed 8 x 8 network: output = mean of the RGB input, on 16 x 16 tangents, so the output
    # is resized 8 -> 16. A 2 x 2 block of black pixels is one zero depth at network size.
    path = g.affine_of_mean(tmp_path / "mean.onnx", input_shape=(1, 3, 8, 8))
    est = OnnxEstimator(path, output_kind="metric_depth", mean=(0, 0, 0), std=(1, 1, 1))
    tiles = np.full((2, 16, 16, 3), 128, dtype=np.uint8)
    tiles[0, 6:8, 8:10] = 0
    out = est.predict(tiles)
    depth = 128 / 255
    finite = np.isfinite(out)
    np.testing.assert_allclose(out[finite], depth, rtol=1e-5)  # no value mixed with the zero
    assert not finite[0, 6:8, 8:10].any() and finite[1].all()
    assert np.nanmax(1.0 / out) <= 1.0 / depth * (1 + 1e-5)  # no disparity spike


# -- 2. Per-tangent sanitising ---------------------------------------------------------------


def _stack(n: int = 6, h: int = 20, w: int = 20, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.5, 2.0, (n, h, w)).astype(np.float32)


def test_sanitise_masks_outliers_beyond_the_ratio_only() -> None:
    stack = _stack()
    median = float(np.median(stack[2]))
    stack[2, 0, 0] = median * (kinds.OUTLIER_RATIO * 1.5)  # a zero depth's spike
    stack[2, 0, 1] = median * (kinds.OUTLIER_RATIO * 0.5)  # large, but inside the bound
    stack[3, 5, 5] = np.inf
    out, checks = kinds.sanitise(stack.copy(), "metric_depth")
    assert np.isnan(out[2, 0, 0]) and np.isnan(out[3, 5, 5])
    assert out[2, 0, 1] == stack[2, 0, 1]
    assert checks["outlier_pixels"] == 1 and checks["dropped"] == []
    assert np.isfinite(out).sum() == stack.size - 2


def test_sanitise_drops_a_wrong_sign_tangent_and_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stack = _stack()
    stack[4] *= -1  # one tangent's affine disparity negated
    with caplog.at_level(logging.WARNING, logger="m360"):
        out, checks = kinds.sanitise(stack.copy(), "affine_disparity")
    assert [d["tangent"] for d in checks["dropped"]] == [4]
    assert "wrong sign" in checks["dropped"][0]["reason"]
    assert "tangent 4" in caplog.text and "negated_affine_disparity" in caplog.text
    assert np.isnan(out[4]).all()
    np.testing.assert_array_equal(out[[0, 1, 2, 3, 5]], stack[[0, 1, 2, 3, 5]])
    assert checks["valid_fraction"][4] == 0.0


def test_sanitise_drops_depths_of_the_wrong_sign_few_valid_and_constant() -> None:
    stack = _stack(n=8)
    raw = 1.0 / stack
    raw[1] = -raw[1]  # a depth that is negative: its disparity is NaN after the conversion
    perspective = np.where(raw > 0, 1.0 / raw, np.nan).astype(np.float32)
    perspective[2, :, 1:] = np.nan  # 1 column of 20: exactly MIN_VALID_FRACTION, kept
    perspective[3, :, :] = np.nan
    perspective[3, 0, :2] = 1.0  # 0.5 % valid
    perspective[5] = 0.7  # constant
    out, checks = kinds.sanitise(perspective, "metric_depth", raw=raw)
    reasons = {d["tangent"]: d["reason"] for d in checks["dropped"]}
    assert set(reasons) == {1, 3, 5}
    assert reasons[1].startswith("wrong sign") and "too few valid" in reasons[3]
    assert "no dynamic range" in reasons[5]
    assert np.isfinite(out[2]).sum() == 20  # exactly 5 %: kept


def test_sanitise_raises_when_too_few_tangents_are_left() -> None:
    stack = _stack(n=4)
    stack[1:] = 1.0
    with pytest.raises(ModelError, match=r"only 1 of 4 tangents .*no dynamic range"):
        kinds.sanitise(stack, "affine_disparity")


# -- 3. affine_depth and negated outputs -----------------------------------------------------


def test_affine_depth_recovers_disparity_up_to_scale_on_an_analytic_scene() -> None:
    lay = m360.Layout.icosahedron(128, padding="paper")
    z = 1.0 / syn.tangent_perspective_disparity(scene(0), lay.cameras).astype(np.float64)
    # Shift each tangent's true depth so its 1st percentile sits at AFFINE_DEPTH_FLOOR of its
    # 1st-99th percentile range: there the conversion's unknown shift is exactly right.
    flat = z.reshape(len(z), -1)
    p1, p99 = np.percentile(flat, [1, 99], axis=1)
    true = z - (p1 - kinds.AFFINE_DEPTH_FLOOR * (p99 - p1))[:, None, None]
    a = np.linspace(0.5, 3.0, len(z))[:, None, None]
    output = (a * true + 7.0).astype(np.float32)  # what an affine-depth network gives
    disparity = kinds.to_perspective_disparity(output, "affine_depth", lay)
    assert np.isfinite(disparity).all() and (disparity > 0).all()
    above = true >= kinds.AFFINE_DEPTH_FLOOR * (p99 - p1)[:, None, None] * (1 + 1e-3)
    expected = 1.0 / (a * true)
    np.testing.assert_allclose(disparity[above], expected[above], rtol=2e-3)
    # Below the 1st percentile the depth is clamped: never a spike beyond the floor's.
    assert (
        disparity * a <= (1.0 / (kinds.AFFINE_DEPTH_FLOOR * (p99 - p1)))[:, None, None] * 1.01
    ).all()


def test_negated_affine_disparity_is_the_negation() -> None:
    lay = m360.Layout.icosahedron(64, padding="paper")
    values = -_stack(len(lay), *lay.tangent_shape)
    out = kinds.to_perspective_disparity(values, "negated_affine_disparity", lay)
    np.testing.assert_array_equal(out, -values)
    assert {"affine_depth", "negated_affine_disparity"} <= set(m360.estimators.OUTPUT_KINDS)


# -- 4. metric results in metres -------------------------------------------------------------


class _MetricNetwork:
    """A metric z-depth network on a synthetic scene: exact depth times a per-tangent error."""

    output_kind = "metric_depth"
    name = "metric simulation"

    def __init__(self, lay: m360.Layout, seed: int = 0) -> None:
        self.layout = lay
        exact = syn.tangent_perspective_disparity(scene(0), lay.cameras)
        gain = np.random.default_rng(seed).uniform(0.9, 1.1, (len(lay), 1, 1))
        self.depth = (gain / exact).astype(np.float32)

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        return self.depth.copy()


def test_a_metric_network_gives_metres_after_alignment() -> None:
    width = 256
    lay = m360.geometry.default_layout(width)
    truth = syn.room(0).distance(m360.geometry.sphere.erp_directions(width // 2, width))
    erp = np.zeros((width // 2, width, 3), dtype=np.uint8)
    res = m360.estimate(erp, _MetricNetwork(lay), layout=lay)
    assert res.units == "metres" and res.scale is not None
    assert res.scale["method"] == "network" and res.scale["aligned"] is True
    ratio = float(np.nanmedian(res.depth / truth))
    print(f"median depth / truth {ratio:.4f}, fit {res.scale}")
    assert abs(ratio - 1.0) < 0.02  # per-tangent gains of ±10 %; measured 1.0005


# -- 5. the result check and its fallback ----------------------------------------------------


def test_a_diverged_stitch_falls_back_and_the_sidecar_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    width = 256
    lay = m360.geometry.default_layout(width)
    real_stitch = checks_module.stitch
    calls: list[Any] = []

    def diverging(*args: Any, **kw: Any) -> StitchResult:
        result = real_stitch(*args, **kw)
        calls.append(kw["options"])
        if len(calls) == 1:  # the asked alignment "diverges": no affine map undoes this
            result.disparity[::2] *= -1e3
        return result

    monkeypatch.setattr(checks_module, "stitch", diverging)
    erp = np.zeros((width // 2, width, 3), dtype=np.uint8)
    res = m360.estimate(erp, _MetricNetwork(lay), layout=lay, energy="paper", solver="lbfgs")
    assert len(calls) == 2 and calls[1].align["levels"] == [(4, 3)]
    assert calls[1].align["energy"] == "normalized"
    assert res.checks["fallback"] == "coarser alignment"
    first = res.checks["result"][0]
    assert first["negative_fraction"] > 0.4 and first["problems"]
    assert (res.disparity > 0).all() and res.checks["stitched_with"]["align"]["levels"] == [[4, 3]]
    m360.save(res, tmp_path / "pano")
    sidecar = json.loads((tmp_path / "pano.json").read_text())
    assert sidecar["fallback"] == "coarser alignment"
    assert sidecar["checks"]["result"][0]["problems"] == first["problems"]
    assert sidecar["units"] == "metres" and sidecar["scale"]["method"] == "network"


def test_no_alignment_is_the_last_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    width = 256
    lay = m360.geometry.default_layout(width)
    real_stitch = checks_module.stitch

    def diverging(*args: Any, **kw: Any) -> StitchResult:
        result = real_stitch(*args, **kw)
        if kw["options"].align is not None:
            result.disparity = -result.disparity
        return result

    monkeypatch.setattr(checks_module, "stitch", diverging)
    erp = np.zeros((width // 2, width, 3), dtype=np.uint8)
    res = m360.estimate(erp, _MetricNetwork(lay), layout=lay)
    assert res.checks["fallback"] == "no alignment"
    tried = [t["options"] for t in res.checks["result"]]
    assert tried == ["as asked", "coarser alignment", "no alignment"]
    assert res.checks["stitched_with"]["align"] is None and (res.disparity > 0).all()
    assert res.scale == {"method": "network", "aligned": False}


def test_sidecar_valid_fraction_is_finite_and_positive(tmp_path: Path) -> None:
    class Result:
        disparity = np.array([[1.0, -1.0, np.nan, 0.0], [2.0, 3.0, np.inf, 4.0]], np.float32)
        depth = disparity.copy()

    m360.save(Result(), tmp_path / "r", preview=False)
    sidecar = json.loads((tmp_path / "r.json").read_text())
    assert sidecar["valid_fraction"] == 4 / 8


def test_the_paper_energy_on_a_clean_stack_passes_its_checks() -> None:
    width = 256
    lay = m360.geometry.default_layout(width)
    erp = np.zeros((width // 2, width, 3), dtype=np.uint8)
    res = m360.estimate(erp, _MetricNetwork(lay), layout=lay, energy="paper", solver="lbfgs")
    assert res.checks["result"][0]["options"] == "as asked"
    assert res.checks["valid_fraction"] == pytest.approx(
        float((np.isfinite(res.disparity) & (res.disparity > 0)).mean())
    )


# -- real networks (tests/real_data.py) ------------------------------------------------------


def _real(
    name: str, pano: str, kind: str, multiple: int | None = None, **kw: Any
) -> m360.EstimateResult:
    rgb = m360.io.load_image(REAL / "panos" / pano)
    extra: dict[str, Any] = {"multiple_of": multiple} if multiple else {}
    return m360.estimate(
        rgb,
        REAL / "models" / name,
        output_kind=kind,
        mean=(0, 0, 0),
        std=(1, 1, 1),
        **extra,
        **kw,
    )


@needs_real
def test_real_street_12k_fastdepth_metric_is_sane(tmp_path: Path) -> None:
    """The issue's silent garbage: 12K photo, fastdepth_224, metric_depth, default width."""
    res = _real("fastdepth_224.onnx", "street_11968.jpg", "metric_depth")
    d = res.disparity
    truth = float((np.isfinite(d) & (d > 0)).mean())
    assert res.checks["valid_fraction"] == pytest.approx(truth)
    assert truth > 0.99
    finite = d[np.isfinite(d)]
    assert (finite > 0).all()
    # FastDepth reads 0.5 to 10 m (NYU-like): the disparity stays within 1/50 to 5 per metre.
    assert 1 / 50 < finite.min() and finite.max() < 5.0
    assert res.units == "metres" and res.scale is not None and res.scale["method"] == "network"
    m360.save(res, tmp_path / "street", preview=False)
    sidecar = json.loads((tmp_path / "street.json").read_text())
    assert sidecar["valid_fraction"] == pytest.approx(truth)
    assert sidecar["units"] == "metres" and sidecar["quantities"]["depth"]["units"] == "metres"


@needs_real
@pytest.mark.parametrize("kind", ["affine_depth", "negated_affine_disparity"])
def test_real_pydnet_kinds_give_finite_positive_disparity(kind: str) -> None:
    res = _real("mobile_pydnet_dynamic.onnx", "st_fagans_interior_1k.tonemapped.png", kind, 64)
    d = res.disparity
    assert np.isfinite(d).all() and (d > 0).all()
    assert res.checks["tangents"]["dropped"] == [] and res.units == "relative"


@needs_real
def test_real_pydnet_as_affine_disparity_is_refused_naming_the_sign() -> None:
    with pytest.raises(ModelError, match="negated_affine_disparity"):
        _real(
            "mobile_pydnet_dynamic.onnx",
            "studio_small_03_1k.tonemapped.png",
            "affine_disparity",
            64,
        )


@needs_real
def test_real_paper_energy_never_returns_a_blow_up() -> None:
    res = _real(
        "fastdepth_dynamic.onnx",
        "potsdamer_platz_1k.tonemapped.png",
        "metric_depth",
        32,
        energy="paper",
        solver="lbfgs",
    )
    # Before: 5.5 % of the disparity <= 0 and 14x the tangents' range (a global offset blow-up).
    # The anchoring puts the global scale and offset back on the network's metres.
    d = res.disparity
    assert (d[np.isfinite(d)] > 0).all() and np.isfinite(d).mean() > 0.99
    tried = res.checks["result"]
    assert tried[-1]["problems"] == [] and tried[0]["anchor"]["scale"] < 1.0
    assert tried[-1]["negative_fraction"] == 0.0 and tried[-1]["dynamic_range"] < 1.0
    # Within the network's own range of metres (fastdepth_dynamic reads 0.6 to 7.5 m).
    assert 1 / 10 < np.nanmin(d) and np.nanmax(d) < 2.0


def test_a_dropped_tangent_is_left_out_of_the_stitch_and_recorded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    width = 256
    lay = m360.geometry.default_layout(width)
    network = _MetricNetwork(lay)
    network.depth[7] *= -1  # one tangent of the wrong sign for a depth
    erp = np.zeros((width // 2, width, 3), dtype=np.uint8)
    with caplog.at_level(logging.WARNING, logger="m360"):
        res = m360.estimate(erp, network, layout=lay)
    assert [d["tangent"] for d in res.checks["tangents"]["dropped"]] == [7]
    assert "tangent 7 dropped: wrong sign" in caplog.text
    assert np.isnan(res.tangents[7]).all()
    # The other tangents cover the sphere (padding 0.7): the result is whole and in metres.
    truth = syn.room(0).distance(m360.geometry.sphere.erp_directions(width // 2, width))
    assert np.isfinite(res.depth).mean() > 0.99
    assert abs(float(np.nanmedian(res.depth / truth)) - 1.0) < 0.02
    m360.save(res, tmp_path / "drop", preview=False)
    sidecar = json.loads((tmp_path / "drop.json").read_text())
    assert sidecar["checks"]["tangents"]["dropped"][0]["tangent"] == 7


def test_a_network_that_ignores_its_input_is_refused_naming_the_normalisation(
    tmp_path: Path,
) -> None:
    """Raw 0-255 values into a network trained on [0, 1] saturate it: one map for every tile.
    That is refused with the normalisation that fits; fed right, the same network runs."""
    model = g.saturating(tmp_path / "saturating.onnx")
    rgb, _ = syn.render(scene(0), 256)
    options = {"output_kind": "affine_disparity", "multiple_of": 32}
    with pytest.raises(ModelError, match=r"same map for all 20 tangents.*normalize='unit'"):
        m360.estimate(rgb, model, normalize="none", **options)
    res = m360.estimate(rgb, model, normalize="unit", **options)
    assert np.isfinite(res.disparity).all()
    # A blank panorama is one photo in every tile: one map is the right answer there.
    blank = np.full_like(rgb, 128)
    assert np.isfinite(m360.estimate(blank, model, normalize="none", **options).disparity).any()


@needs_real
def test_real_fastdepth_fed_raw_pixels_is_refused() -> None:
    """The shared FastDepth takes RGB in [0, 1]; fed 0-255 it gave one map for every tile (what
    benches/bench_edges_real.py measured until stop 51)."""
    with pytest.raises(ModelError, match="same map for all"):
        m360.estimate(
            m360.io.load_image(REAL / "panos" / "studio_small_03_1k.tonemapped.png"),
            REAL / "models" / "fastdepth_dynamic.onnx",
            output_kind="affine_depth",
            normalize="none",
            multiple_of=32,
            input_size=224,
        )
