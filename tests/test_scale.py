"""m360.scale: metric scale from the camera height, sparse points and a coarse metric map."""

from __future__ import annotations

import functools
import json

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360 import scale

WIDTH = 1024


@functools.cache
def rendered(seed: int, width: int = WIDTH) -> tuple[syn.Scene, np.ndarray, np.ndarray]:
    scene = syn.room(seed)
    rgb, depth = syn.render(scene, width)
    return scene, rgb, depth


@functools.cache
def aligned(seed: int) -> m360.EstimateResult:
    """The method on a room: exact tangent disparity, per-tangent affine distortion, aligned."""
    scene, rgb, _ = rendered(seed)
    # Per-tangent scales of 2 to 6: the aligned result (anchored to the tangents' own values,
    # docs/method.md) is then clearly not in metres before a scaler is applied.
    est = m360.estimators.SimulatedEstimator(
        scene, m360.geometry.default_layout(WIDTH), seed=seed, scale=(2.0, 6.0)
    )
    return m360.estimate(rgb, est)


def metric_error(depth: np.ndarray, truth: np.ndarray) -> float:
    return float(np.nanmedian(np.abs(depth / truth - 1)))


def camera_height_of(scene: syn.Scene) -> float:
    return float(scene.room_max[1])  # the floor is the room's +y face; the camera is at 0


def noisy_points(seed: int, depth: np.ndarray, n: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """n points at random pixels: 5 % gaussian distance noise, 10 % gross outliers."""
    rng = np.random.default_rng(100 + seed)
    h, w = depth.shape
    i, j = rng.integers(0, h, n), rng.integers(0, w, n)
    dirs = m360.mesh.erp_ray_grid(h, w)[1][i, j].astype(np.float64)
    dist = depth[i, j] * (1 + 0.05 * rng.standard_normal(n))
    outliers = rng.permutation(n)[: n // 10]
    dist[outliers] *= rng.choice([0.3, 0.5, 2.0, 3.0], size=outliers.size)
    return dirs, dist


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_height_with_exact_depth(seed):
    scene, _, depth = rendered(seed)
    k = 3.7  # relative units: an unknown scale ...
    fit = scale.camera_height(camera_height_of(scene)).fit(1 / (k * depth))
    assert abs(fit.value * k - 1) < 0.02
    # ... and an unknown disparity shift too (affine)
    shifted = 0.5 / depth + 0.08
    fit = scale.camera_height(camera_height_of(scene)).fit(shifted, affine=True)
    metric = fit.disparity_scale * shifted + fit.disparity_shift
    assert metric_error(1 / metric, depth) < 0.02
    assert fit.residual < 0.01 and abs(fit.details["floor_tilt_deg"]) < 1


def test_camera_height_finds_a_tilted_floor():
    scene, _, depth = rendered(0)
    # Roll the camera by 10°: the same scene seen through a rotated ERP grid.
    rot = syn.rotation_matrix(roll=np.radians(10))
    dirs = m360.mesh.erp_ray_grid(*depth.shape)[1].astype(np.float64) @ rot.T
    tilted = scene.distance(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True))
    fit = scale.camera_height(camera_height_of(scene)).fit(2.0 / tilted)
    assert abs(fit.value / 2.0 - 1) < 0.02
    assert 9 < fit.details["floor_tilt_deg"] < 11


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_height_after_affine_distortion_and_alignment(seed):
    scene, _, depth = rendered(seed)
    result = aligned(seed)
    metric = m360.scale.apply(result, scale.camera_height(camera_height_of(scene)))
    assert metric.units == "metres" and metric.scale["method"] == "camera_height"
    assert metric_error(metric.depth, depth) < 0.05
    assert metric_error(result.depth, depth) > 0.3  # relative units before: the test can fail


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_points_with_noise_and_outliers(seed):
    _, _, depth = rendered(seed)
    dirs, dist = noisy_points(seed, depth)
    # scale only (a metric-up-to-scale map)
    fit = scale.points(dirs, dist, affine=False).fit(0.25 / depth)
    assert abs(fit.value / 0.25 - 1) < 0.02
    # scale and shift, on the aligned result of an affine network
    metric = m360.scale.apply(aligned(seed), scale.points(dirs, dist))
    assert metric.scale["affine"] is True
    assert metric_error(metric.depth, depth) < 0.02
    # given as 3D points instead of directions + distances
    fit3 = scale.points(dirs * dist[:, None], affine=False).fit(0.25 / depth)
    assert fit3.value == pytest.approx(fit.value)


def test_metric_map_low_resolution():
    _, _, depth = rendered(0)
    coarse = syn.render(syn.room(0), 64)[1]  # 64x32 metric map of the same room
    metric = m360.scale.apply(aligned(0), scale.metric_map(coarse))
    assert metric.scale["method"] == "metric_map"
    assert metric_error(metric.depth, depth) < 0.02


def test_estimate_with_scale_writes_metres(tmp_path):
    scene, rgb, depth = rendered(0, 256)
    est = m360.estimators.SimulatedEstimator(scene, m360.geometry.default_layout(256), seed=0)
    result = m360.estimate(rgb, est, scale=scale.camera_height(camera_height_of(scene)))
    assert result.units == "metres"
    assert metric_error(result.depth, depth) < 0.05
    m360.save(result, tmp_path / "pano")
    meta = json.loads((tmp_path / "pano.json").read_text())
    assert meta["quantities"]["depth"]["units"] == "metres"
    assert meta["scale"]["method"] == "camera_height"
    assert set(meta["scale"]) >= {"value", "residual", "disparity_scale", "disparity_shift"}
    assert m360.load(tmp_path / "pano").units == "metres"


def test_failed_fits_are_scale_errors():
    _, _, depth = rendered(0, 256)
    no_floor = 1 / depth
    no_floor[64:] = np.nan  # nothing below the horizon
    with pytest.raises(m360.ScaleError, match="no floor"):
        scale.camera_height(1.5).fit(no_floor)
    # depths scattered at random: no plane below the camera holds 5 % of the points
    scattered = np.random.default_rng(0).uniform(0.1, 1.0, (128, 256)).astype(np.float32)
    with pytest.raises(m360.ScaleError, match="no floor visible"):
        scale.camera_height(1.5).fit(scattered)
    dirs, dist = noisy_points(0, depth, n=2)
    with pytest.raises(m360.ScaleError, match="at least 3"):
        scale.points(dirs, dist).fit(1 / depth)
    dirs, dist = noisy_points(0, depth, n=20)
    wild = dist * np.repeat([0.2, 1.0, 5.0, 25.0], 5)  # four groups of 5 that disagree
    with pytest.raises(m360.ScaleError, match="disagree"):
        scale.points(dirs, wild, affine=False).fit(1 / depth)
    assert issubclass(m360.ScaleError, m360.M360Error)


def test_estimate_with_a_failing_scale_raises(tmp_path):
    scene, rgb, _ = rendered(0, 256)
    est = m360.estimators.SimulatedEstimator(scene, m360.geometry.default_layout(256), seed=0)
    with pytest.raises(m360.ScaleError):
        m360.estimate(rgb, est, scale=scale.points(np.eye(3), [1.0, 2.0, 3.0]))


def test_bad_scale_inputs_are_input_errors():
    for bad in (0, -1.6, float("nan"), "1.6", True):
        with pytest.raises(m360.InputError, match="camera height"):
            scale.camera_height(bad)
    with pytest.raises(m360.InputError, match="behind the camera"):
        scale.points(np.eye(3), [1.0, -2.0, 3.0])
    with pytest.raises(m360.InputError, match="shape"):
        scale.points(np.eye(3), [1.0, 2.0])
    with pytest.raises(m360.InputError, match="shape"):
        scale.points(np.ones((4, 2)), np.ones(4))
    with pytest.raises(m360.InputError, match="zero"):
        scale.points(np.zeros((3, 3)), np.ones(3))
    with pytest.raises(m360.InputError, match="<= 0"):
        scale.metric_map(np.zeros((8, 16)))
    with pytest.raises(m360.InputError, match="W == 2H"):
        scale.camera_height(1.6).fit(np.ones((8, 8)))
    with pytest.raises(m360.InputError, match="scaler"):
        m360.scale.apply(aligned(0), 1.6)  # type: ignore[arg-type]
