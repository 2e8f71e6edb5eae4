"""m360.estimate: kind conversion, ONNX pre/post-processing, errors, determinism, end to end.

Every ONNX model here is a tiny graph built in the test (tests/onnx_graphs.py); real weights are
only used by tests/test_models.py when M360_MODEL_DIR points at them.
"""

from __future__ import annotations

from pathlib import Path

import m360
import m360.synthetic as syn
import numpy as np
import onnx_graphs as g
import pytest
from conftest import erp_depth, layout, scene
from m360.errors import InputError, ModelError
from m360.estimators import (
    OnnxEstimator,
    SimulatedEstimator,
    load_estimator,
    network_size,
    ray_norms,
    to_perspective_disparity,
)
from m360.geometry import sphere as sph

NO_NORM = {"mean": (0.0, 0.0, 0.0), "std": (1.0, 1.0, 1.0)}


# ------------------------------------------------------------------ kind conversion


def test_ray_norms_match_the_numpy_oracle() -> None:
    """The core computes |q| in float32 (``Plan.ray_lengths``): equal to the float64 oracle
    within float32 rounding."""
    lay = layout(512)
    norms = ray_norms(lay)
    assert norms.shape == (20, *lay.tangent_shape) and not norms.flags.writeable
    assert norms.dtype == np.float32
    for k, cam in enumerate(lay.cameras):
        _, want = sph.camera_pixel_directions(
            cam.rotation, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
            return_ray_norm=True,
        )  # fmt: skip
        np.testing.assert_allclose(norms[k], want, rtol=2 * np.finfo(np.float32).eps)


def test_distance_becomes_the_ray_cast_perspective_disparity() -> None:
    lay = layout(512)
    distance = syn.tangent_distance(scene(0), lay.cameras)
    truth = syn.tangent_perspective_disparity(scene(0), lay.cameras)
    out = to_perspective_disparity(distance, "distance", lay)
    assert out.dtype == np.float32 and out.shape == truth.shape
    np.testing.assert_allclose(out, truth, rtol=2e-6)


def test_metric_z_depth_becomes_the_ray_cast_perspective_disparity() -> None:
    lay = layout(512)
    distance = syn.tangent_distance(scene(1), lay.cameras).astype(np.float64)
    # Independent z: the distance times the cosine between each pixel's ray and the axis.
    z = np.empty_like(distance)
    for k, cam in enumerate(lay.cameras):
        dirs = sph.camera_pixel_directions(
            cam.rotation, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height
        )
        z[k] = distance[k] * (dirs @ cam.axis)
    truth = syn.tangent_perspective_disparity(scene(1), lay.cameras)
    out = to_perspective_disparity(z, "metric_depth", lay)
    np.testing.assert_allclose(out, truth, rtol=2e-6)


def test_affine_disparity_passes_through_and_bad_depths_become_nan() -> None:
    lay = layout(256)
    values = np.random.default_rng(0).uniform(-1, 3, (20, *lay.tangent_shape))
    np.testing.assert_array_equal(
        to_perspective_disparity(values, "affine_disparity", lay), values.astype(np.float32)
    )
    for kind in ("metric_depth", "distance"):
        out = to_perspective_disparity(values, kind, lay)
        assert np.isnan(out[values <= 0]).all()
        assert np.isfinite(out[values > 0]).all()
    with pytest.raises(InputError, match="output_kind='disparity' is not supported"):
        to_perspective_disparity(values, "disparity", lay)
    with pytest.raises(InputError, match="expected"):
        to_perspective_disparity(values[:19], "distance", lay)


# ------------------------------------------------------------------ pre/post-processing


def test_network_sizes_follow_each_models_rule() -> None:
    # Hand-computed: 346x400 tile. Depth Anything: cover 518, ceil to 14 -> 518 x 602
    # (400 * 518/346 = 598.8 -> 43*14). MiDaS: fit in 256, floor to 32 -> 221.4 -> 192 x 256.
    assert network_size((346, 400), (518, 518), multiple_of=14, resize="lower_bound") == (518, 602)
    assert network_size((346, 400), (256, 256), multiple_of=32, resize="upper_bound") == (192, 256)
    assert network_size((346, 400), (384, 384), multiple_of=32, resize="exact") == (384, 384)


def test_normalisation_is_applied_per_channel(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    tangents = rng.integers(0, 256, (3, 12, 16, 3), dtype=np.uint8)
    mean, std = (0.4, 0.5, 0.6), (0.2, 0.25, 0.5)
    for c in range(3):
        path = g.channel(tmp_path / f"c{c}.onnx", c, input_shape=(1, 3, 12, 16))
        est = OnnxEstimator(path, mean=mean, std=std)
        want = (tangents[..., c] / 255.0 - mean[c]) / std[c]
        np.testing.assert_allclose(est.predict(tangents), want, rtol=1e-5, atol=1e-6)


def test_resize_to_the_network_and_back_keeps_a_ramp(tmp_path: Path) -> None:
    h, w = 30, 40
    ramp = 40.0 + 4.0 * np.arange(w)[None, :] + 2.0 * np.arange(h)[:, None]  # 40..274
    tangents = np.repeat(ramp[None, :, :, None], 3, axis=3).astype(np.uint8)
    path = g.channel(tmp_path / "c.onnx", 1, input_shape=(1, 3, "H", "W"))
    for size in ((60, 80), (15, 20), (45, 50)):
        est = OnnxEstimator(path, input_size=size, resize="exact", **NO_NORM)
        assert est.network_size((h, w)) == size
        out = est.predict(tangents)[0]
        # Linear interpolation reproduces a linear ramp away from the clamped borders.
        np.testing.assert_allclose(out[3:-3, 3:-3], ramp[3:-3, 3:-3] / 255.0, atol=2e-6)


def test_fixed_input_size_is_read_from_the_model(tmp_path: Path) -> None:
    path = g.affine_of_mean(tmp_path / "fixed.onnx", 2.0, 0.5, input_shape=(1, 3, 24, 24))
    for size in (None, (24, 24), 24):  # the file's own size, asked for or not, is fine
        est = OnnxEstimator(path, input_size=size, **NO_NORM)
        assert est.network_size((30, 40)) == (24, 24)
    tangents = np.full((2, 30, 40, 3), 102, np.uint8)
    np.testing.assert_allclose(est.predict(tangents), 2.0 * 0.4 + 0.5, rtol=1e-6)


@pytest.mark.parametrize("shape", [(1, 3, 24, 32), (1, 24, 32, 3)], ids=["nchw", "nhwc"])
def test_an_input_size_a_fixed_size_model_cannot_take_is_an_input_error(
    tmp_path: Path, shape: tuple[int, ...]
) -> None:
    """Asking for a size the file does not take is refused when the estimator is built (it was
    silently ignored): by OnnxEstimator, load_estimator and m360.estimate alike."""
    path = g.affine_of_mean(tmp_path / "fixed.onnx", input_shape=shape)
    expected = (
        r"input_size=\(24, 48\) but fixed.onnx takes a fixed 24x32 input; omit input_size or "
        r"pass \(24, 32\)"
    )
    with pytest.raises(InputError, match=expected):
        OnnxEstimator(path, input_size=(24, 48))
    with pytest.raises(InputError, match=expected):
        load_estimator(str(path), input_size=(24, 48))
    with pytest.raises(InputError, match="takes a fixed 24x32 input"):
        m360.estimate(np.zeros((64, 128, 3), np.uint8), path, input_size=(32, 24))
    assert load_estimator(str(path), input_size=(24, 32)).network_size((50, 50)) == (24, 32)


def test_a_dynamic_size_model_takes_any_input_size(tmp_path: Path) -> None:
    path = g.affine_of_mean(tmp_path / "dynamic.onnx", input_shape=(1, 3, "H", "W"))
    for size in [(24, 48), (64, 64), (7, 300)]:
        est = load_estimator(str(path), input_size=size)
        assert est.network_size(size) == size
        assert est.predict(np.zeros((1, *size, 3), np.uint8)).shape == (1, *size)


@pytest.mark.parametrize(
    "shape, output_4d",
    [((1, 3, "H", "W"), True), ((1, "H", "W", 3), False), (("B", 3, "H", "W"), False)],
    ids=["nchw-4d-output", "nhwc", "dynamic-batch"],
)
def test_layouts_and_output_ranks(tmp_path: Path, shape: tuple, output_4d: bool) -> None:
    path = g.affine_of_mean(tmp_path / "m.onnx", 3.0, -1.0, input_shape=shape, output_4d=output_4d)
    rng = np.random.default_rng(2)
    tangents = rng.integers(0, 256, (4, 10, 14, 3), dtype=np.uint8)
    est = OnnxEstimator(path, input_size=(10, 14), resize="exact", batch_size=3, **NO_NORM)
    want = 3.0 * tangents.mean(axis=3) / 255.0 - 1.0
    np.testing.assert_allclose(est.predict(tangents), want, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------ errors


def test_wrong_input_rank_is_a_model_error(tmp_path: Path) -> None:
    path = g.identity(tmp_path / "rank3.onnx", (1, 3, 64))
    with pytest.raises(ModelError, match=r"has rank 3 \(shape \[1, 3, 64\]\).*4-D image input"):
        OnnxEstimator(path)


def test_model_output_of_the_wrong_shape_is_a_model_error(tmp_path: Path) -> None:
    path = g.identity(tmp_path / "rgb_out.onnx", (1, 3, "H", "W"))
    est = OnnxEstimator(path, input_size=(8, 8), resize="exact")
    with pytest.raises(ModelError, match=r"output 'y' has shape \(1, 3, 8, 8\).*\(1, H, W\)"):
        est.predict(np.zeros((1, 8, 8, 3), np.uint8))


def test_html_page_saved_as_onnx_is_a_model_error(tmp_path: Path) -> None:
    path = tmp_path / "model.onnx"
    path.write_text("<!DOCTYPE html><html><body>404 Not Found</body></html>")
    with pytest.raises(
        ModelError, match=r"cannot load .*model.onnx as an ONNX model: it is an HTML"
    ):
        OnnxEstimator(path)


def test_missing_and_unknown_models_are_model_errors(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="does not exist"):
        OnnxEstimator(tmp_path / "nope.onnx")
    with pytest.raises(ModelError, match=r"unknown model 'midas-v9'.*midas-v21-small"):
        load_estimator("midas-v9")


def test_bad_options_are_input_errors(tmp_path: Path) -> None:
    path = g.affine_of_mean(tmp_path / "m.onnx")
    with pytest.raises(InputError, match="output_kind='depth' is not supported"):
        OnnxEstimator(path, output_kind="depth")
    with pytest.raises(InputError, match=r"none of providers=.*available: .*CPUExecutionProvider"):
        OnnxEstimator(path, providers=["NoSuchExecutionProvider"])
    with pytest.raises(InputError, match="threads must be a positive integer"):
        OnnxEstimator(path, threads=0)
    with pytest.raises(InputError, match="std must be > 0"):
        OnnxEstimator(path, std=(1, 0, 1))
    # An unavailable provider is skipped when another one is listed.
    est = OnnxEstimator(path, providers=["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert est.providers == ("CPUExecutionProvider",)


# ------------------------------------------------------------------ determinism


@pytest.mark.parametrize("threads", [1, 2])
def test_same_output_every_time_with_fixed_threads(tmp_path: Path, threads: int) -> None:
    path = g.conv_net(tmp_path / "net.onnx", size=None, width=8, layers=2)
    tangents = np.random.default_rng(3).integers(0, 256, (3, 86, 100, 3), dtype=np.uint8)
    first = OnnxEstimator(path, input_size=(64, 64), threads=threads).predict(tangents)
    again = OnnxEstimator(path, input_size=(64, 64), threads=threads).predict(tangents)
    np.testing.assert_array_equal(first, again)
    assert np.isfinite(first).all() and first.std() > 0


# ------------------------------------------------------------------ end to end


def distance_panorama(seed: int, width: int) -> tuple[np.ndarray, float]:
    """A float RGB panorama whose three channels are exact radial distance / scale."""
    depth = erp_depth(seed, width)
    scale = float(depth.max()) * 1.01
    return np.repeat((depth / scale)[..., None], 3, axis=2).astype(np.float32), scale


class PerTangentAffine:
    """Wraps an estimator: converts its output to perspective disparity, then distorts each
    tangent by its own random scale and shift (what an affine-invariant network gives)."""

    output_kind = "affine_disparity"

    def __init__(self, inner: OnnxEstimator, lay: m360.Layout, seed: int) -> None:
        self.inner, self.layout, self.seed = inner, lay, seed

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        exact = to_perspective_disparity(
            self.inner.predict(tangents), self.inner.output_kind, self.layout
        )
        return syn.distort(exact, self.seed, scale=(0.5, 2.0), shift=0.3)


def exact_estimator(tmp_path: Path, scale: float, lay: m360.Layout) -> OnnxEstimator:
    """An ONNX graph whose output on a distance panorama is the distance in metres."""
    path = g.affine_of_mean(tmp_path / "dist.onnx", scale, 0.0)
    return OnnxEstimator(
        path, output_kind="distance", input_size=lay.tangent_shape, resize="exact", **NO_NORM
    )


def test_end_to_end_recovers_metric_depth_without_alignment(tmp_path: Path) -> None:
    width = 1024
    lay = m360.geometry.default_layout(width)
    erp, scale = distance_panorama(0, width)
    est = exact_estimator(tmp_path, scale, lay)
    res = m360.estimate(erp, est, align="none", blend="mean")
    truth = erp_depth(0, width)
    h, w = lay.erp_shape
    assert res.disparity.shape == res.depth.shape == res.confidence.shape == (h, w)
    assert res.tangents.shape == (20, *lay.tangent_shape) and res.tangents.dtype == np.float32
    assert set(res.timings) >= {"project", "network", "align", "blend", "total"}
    assert res.units == "metres" and res.model["output_kind"] == "distance"
    assert len(res.model["sha256"]) == 64
    raw = np.abs(res.depth - truth) / truth  # no fitting: the depth is metric
    print(f"raw AbsRel {raw.mean():.5f}, median {np.median(raw):.2e}")
    assert np.isfinite(res.depth).all()
    assert raw.mean() <= 0.01
    assert m360.eval.depth_metrics(res.disparity, truth)["abs_rel"] <= 0.01


def test_end_to_end_per_tangent_distortion_is_what_alignment_must_fix(tmp_path: Path) -> None:
    """Without alignment the distorted tangents stitch badly: the default-settings test below
    (AbsRel ≤ 0.03) therefore measures the alignment, not an easy case."""
    width = 1024
    lay = m360.geometry.default_layout(width)
    erp, scale = distance_panorama(0, width)
    wrapped = PerTangentAffine(exact_estimator(tmp_path, scale, lay), lay, seed=5)
    res = m360.estimate(erp, wrapped, align="none", blend="mean")
    abs_rel = m360.eval.depth_metrics(res.disparity, erp_depth(0, width))["abs_rel"]
    print(f"distorted, align='none': AbsRel {abs_rel:.4f}")
    assert abs_rel > 0.05
    assert res.units == "relative"


def test_end_to_end_default_alignment_recovers_depth_up_to_one_affine_map(tmp_path: Path) -> None:
    """Projection → network → kind conversion → alignment → blending, with a per-tangent
    affine distortion that only the alignment can undo."""
    width = 1024
    lay = m360.geometry.default_layout(width)
    erp, scale = distance_panorama(0, width)
    wrapped = PerTangentAffine(exact_estimator(tmp_path, scale, lay), lay, seed=5)
    res = m360.estimate(erp, wrapped, blend="mean")
    metrics = m360.eval.depth_metrics(res.disparity, erp_depth(0, width))
    print(m360.eval.format_metrics(metrics))
    assert metrics["abs_rel"] <= 0.03


def test_end_to_end_default_settings_recover_depth_up_to_one_affine_map(tmp_path: Path) -> None:
    width = 1024
    lay = m360.geometry.default_layout(width)
    erp, scale = distance_panorama(0, width)
    wrapped = PerTangentAffine(exact_estimator(tmp_path, scale, lay), lay, seed=5)
    res = m360.estimate(erp, wrapped)
    metrics = m360.eval.depth_metrics(res.disparity, erp_depth(0, width))
    print(m360.eval.format_metrics(metrics))
    assert metrics["abs_rel"] <= 0.03


def test_simulated_estimator_runs_through_estimate_like_stitch(tmp_path: Path) -> None:
    lay = m360.geometry.default_layout(512)
    est = SimulatedEstimator(scene(2), lay, seed=4, noise=0.01)
    rgb, _ = syn.render(scene(2), 512)
    res = m360.estimate(rgb, est, align="none", blend="nn")
    want = m360.stitch(est.predict(np.zeros((20, *lay.tangent_shape, 3))), lay, "none", "nn")
    np.testing.assert_array_equal(res.disparity, want)
    assert res.model["name"].startswith("simulated")


def test_estimate_validates_its_inputs(tmp_path: Path) -> None:
    lay = m360.geometry.default_layout(256)
    est = SimulatedEstimator(scene(0), lay)
    with pytest.raises(InputError, match=r"\(H, W, 3\).*stack the channel"):
        m360.estimate(np.zeros((128, 256), np.uint8), est, align="none", blend="mean")
    with pytest.raises(InputError, match="W == 2H"):
        m360.estimate(np.zeros((128, 200, 3), np.uint8), est, align="none", blend="mean")
    with pytest.raises(InputError, match=r"float erp must be RGB in \[0, 1\]"):
        m360.estimate(np.full((128, 256, 3), 2.0), est, align="none", blend="mean")
    for dtype in (np.float32, np.uint8):  # found by test_fuzz: the float path reduced it
        with pytest.raises(InputError, match=r"0x0 \(HxW\): an empty image"):
            m360.estimate(np.zeros((0, 0, 3), dtype), est, align="none", blend="mean")
    with pytest.raises(InputError, match="model must be a registry name"):
        m360.estimate(np.zeros((128, 256, 3), np.uint8), 42, align="none", blend="mean")  # type: ignore[arg-type]

    with pytest.raises(InputError, match="threads, input_size apply to ONNX models"):
        m360.estimate(
            np.zeros((128, 256, 3), np.uint8), est, align="none", threads=2, input_size=(8, 8)
        )

    class Bad:
        output_kind = "affine_disparity"
        name = "bad"

        def predict(self, tangents: np.ndarray) -> np.ndarray:
            return np.zeros((20, 5, 5), np.float32)

    with pytest.raises(ModelError, match=r"estimator bad returned float32 of shape \(20, 5, 5\)"):
        m360.estimate(np.zeros((128, 256, 3), np.uint8), Bad(), align="none", blend="mean")


def test_a_model_with_external_weights_loads_from_its_verified_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The session is made from the bytes that were hashed, not the path: weights stored next
    to the file are still found (whatever the working directory)."""
    import onnx
    import onnxruntime as ort

    model = onnx.load(str(g.conv_net(tmp_path / "plain.onnx", size=None, width=8, layers=1)))
    path = tmp_path / "ext" / "net.onnx"
    path.parent.mkdir()
    onnx.save_model(model, str(path), save_as_external_data=True, location="net.data",
                    size_threshold=256)  # fmt: skip
    assert (tmp_path / "ext" / "net.data").stat().st_size > 1000
    monkeypatch.chdir(tmp_path)
    x = np.random.default_rng(0).random((1, 3, 16, 16), dtype=np.float32)
    expected = ort.InferenceSession(str(path)).run(None, {"x": x})[0]
    np.testing.assert_allclose(OnnxEstimator(path)._run(x), expected, rtol=1e-6)
