"""Tests of m360.eval: the paper's scale/shift-aligned depth metrics."""

from __future__ import annotations

import math

import m360.eval as ev
import numpy as np
import pytest
from m360.errors import InputError


def random_gt(h: int = 16, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.5, 10.0, size=(h, 2 * h))


def row_latitudes(h: int) -> np.ndarray:
    return np.pi / 2 - np.pi * (np.arange(h) + 0.5) / h


def two_level_example(h: int, error_row: int) -> tuple[np.ndarray, np.ndarray]:
    """pred in {1, 2}; gt disparity = 0.5·pred except two pixels of ``error_row`` at ±0.5.

    The two residuals (+0.5 and -0.5, both where pred = 2, in one row) are orthogonal to 1 and to
    pred under any row weighting, so the fit is exactly scale 0.5, shift 0 and the fitted depths are
    2 (pred 1) and 1 (pred 2). The erroneous pixels have GT depth 2/3 and 2 against a fitted 1.
    """
    w = 2 * h
    pred = np.where((np.arange(w) % 2) == 0, 1.0, 2.0)[None, :].repeat(h, axis=0)
    gt_disp = 0.5 * pred
    gt_disp[error_row, 1] += 0.5
    gt_disp[error_row, 3] -= 0.5
    return pred, 1.0 / gt_disp


@pytest.mark.parametrize("weighting", ["uniform", "solid_angle"])
@pytest.mark.parametrize("seed", range(4))
def test_affine_of_gt_disparity_is_perfect(weighting: str, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    gt = random_gt(seed=seed)
    a = float(rng.uniform(0.01, 100.0))
    b = float(rng.uniform(-5.0, 5.0))
    pred = a / gt + b
    m = ev.depth_metrics(pred.astype(np.float32), gt, weighting=weighting)
    assert m["abs_rel"] < 1e-6
    assert m["rmse"] < 1e-5 and m["mae"] < 1e-5 and m["rmse_log10"] < 1e-6
    assert m["delta1"] == m["delta2"] == m["delta3"] == 1.0
    assert m["scale"] == pytest.approx(1 / a, rel=1e-5)
    assert m["shift"] == pytest.approx(-b / a, rel=1e-4, abs=1e-5)
    assert m["n_valid"] == gt.size and m["coverage"] == 1.0


def test_hand_computed_example() -> None:
    pred, gt = two_level_example(4, error_row=2)
    m = ev.depth_metrics(pred, gt)
    n = 32
    assert m["scale"] == pytest.approx(0.5, abs=1e-14)
    assert m["shift"] == pytest.approx(0.0, abs=1e-14)
    # Errors: fitted 1 vs GT 2/3 (rel 1/2, abs 1/3) and fitted 1 vs GT 2 (rel 1/2, abs 1).
    assert m["abs_rel"] == pytest.approx(1.0 / n, rel=1e-12)
    assert m["mae"] == pytest.approx((1 / 3 + 1) / n, rel=1e-12)
    assert m["rmse"] == pytest.approx(math.sqrt((1 / 9 + 1) / n), rel=1e-12)
    log_err = math.log10(1.5) ** 2 + math.log10(2.0) ** 2
    assert m["rmse_log10"] == pytest.approx(math.sqrt(log_err / n), rel=1e-12)
    # Ratios 1.5 and 2: both fail δ<1.25; 1.5 passes δ<1.5625 and δ<1.953; 2 fails all.
    assert m["delta1"] == pytest.approx(30 / n, abs=1e-15)
    assert m["delta2"] == pytest.approx(31 / n, abs=1e-15)
    assert m["delta3"] == pytest.approx(31 / n, abs=1e-15)
    assert m["n_valid"] == n


def test_rmse_log_is_base_10() -> None:
    pred, gt = two_level_example(4, error_row=2)
    m = ev.depth_metrics(pred, gt)
    ln_value = math.sqrt((math.log(1.5) ** 2 + math.log(2.0) ** 2) / 32)
    assert m["rmse_log10"] == pytest.approx(ln_value / math.log(10), rel=1e-12)


@pytest.mark.parametrize(("cap", "excluded_each"), [(0.0, 0), (10.0, 10), (25.0, 25), (89.0, 89)])
def test_pole_cap_excludes_expected_rows(cap: float, excluded_each: int) -> None:
    h = 180  # one row per degree: row centres at ±0.5°, ±1.5°, …
    gt = random_gt(h)
    pred = 1 / gt
    m = ev.depth_metrics(pred, gt, pole_cap_deg=cap)
    assert m["n_valid"] == (h - 2 * excluded_each) * 2 * h
    # Errors placed only inside the caps do not matter.
    if excluded_each:
        noisy = pred.copy()
        noisy[:excluded_each] *= 3.0
        noisy[h - excluded_each :] = np.nan
        m2 = ev.depth_metrics(noisy, gt, pole_cap_deg=cap)
        assert m2["abs_rel"] < 1e-9 and m2["coverage"] == 1.0


def test_solid_angle_weighting_near_poles() -> None:
    h = 8
    lat = row_latitudes(h)
    for row in (0, 3):
        pred, gt = two_level_example(h, error_row=row)
        uni = ev.depth_metrics(pred, gt, weighting="uniform")
        sa = ev.depth_metrics(pred, gt, weighting="solid_angle")
        n = 2 * h * h
        assert uni["abs_rel"] == pytest.approx(1.0 / n, rel=1e-12)
        # Two pixels of relative error 1/2 with weight cos(lat_row), over Σ cos over all pixels.
        expected = np.cos(lat[row]) / (2 * h * np.cos(lat).sum())
        assert sa["abs_rel"] == pytest.approx(expected, rel=1e-12)
    # Near the pole the weighted error is much smaller than the uniform one.
    pred, gt = two_level_example(h, error_row=0)
    sa_pole = ev.depth_metrics(pred, gt, weighting="solid_angle")["abs_rel"]
    assert sa_pole < 0.5 * ev.depth_metrics(pred, gt)["abs_rel"]


def test_solid_angle_weighting_no_effect_when_error_uniform_over_rows() -> None:
    rng = np.random.default_rng(3)
    h = 12
    gt_row = rng.uniform(1.0, 5.0, size=2 * h)
    noise_row = rng.normal(0.0, 0.05, size=2 * h)
    gt = np.tile(gt_row, (h, 1))
    pred = np.tile(2.0 / gt_row + 0.1 + noise_row, (h, 1))
    uni = ev.depth_metrics(pred, gt, weighting="uniform")
    sa = ev.depth_metrics(pred, gt, weighting="solid_angle")
    assert uni["abs_rel"] > 1e-3
    for key in ("abs_rel", "mae", "rmse", "rmse_log10", "delta1", "scale", "shift"):
        assert sa[key] == pytest.approx(uni[key], rel=1e-9, abs=1e-12)


def test_nan_predictions_excluded_and_coverage() -> None:
    gt = random_gt(10)
    pred = 3.0 / gt + 0.2
    pred[2, :7] = np.nan
    pred[5, 4] = np.inf
    gt[7, 3] = np.nan  # invalid GT counts for neither n_valid nor coverage
    gt[8, 8] = 0.0
    m = ev.depth_metrics(pred, gt)
    n_gt = gt.size - 2
    assert m["n_valid"] == n_gt - 8
    assert m["coverage"] == pytest.approx((n_gt - 8) / n_gt, rel=1e-15)
    assert m["abs_rel"] < 1e-9


def test_valid_mask() -> None:
    pred, gt = two_level_example(4, error_row=2)
    mask = np.ones_like(gt, dtype=bool)
    mask[2, 1] = mask[2, 3] = False
    m = ev.depth_metrics(pred, gt, valid=mask)
    assert m["n_valid"] == 30 and m["abs_rel"] < 1e-12 and m["delta1"] == 1.0


def test_negative_fit_is_clamped_to_floor() -> None:
    gt = np.ones((4, 8))
    gt[:, :4] = 2.0
    pred = -1.0 / gt  # anti-correlated: fitted disparity ≥ floor keeps depths finite
    pred[0, 0] = 5.0
    m = ev.depth_metrics(pred, gt)
    assert all(np.isfinite(v) for v in m.values())


def test_fit_scale_shift_weighted() -> None:
    x = np.array([0.0, 1.0, 2.0, 3.0])
    y = np.array([1.0, 3.0, 5.0, 100.0])
    assert ev.fit_scale_shift(x, 2 * x + 1) == pytest.approx((2.0, 1.0), rel=1e-14)
    s, o = ev.fit_scale_shift(x, y, weights=np.array([1.0, 1.0, 1.0, 0.0]))
    assert (s, o) == pytest.approx((2.0, 1.0), rel=1e-14)
    # By hand: mean x 1.5, mean y 27.25, Σ(x-x̄)² = 5, Σ(x-x̄)(y-ȳ) = 149.5.
    s, o = ev.fit_scale_shift(x, y)
    assert s == pytest.approx(29.9, rel=1e-14)
    assert o == pytest.approx(27.25 - 29.9 * 1.5, rel=1e-14)
    assert ev.fit_scale_shift(np.ones(3), np.array([1.0, 2.0, 6.0])) == (0.0, 3.0)


def test_fit_scale_shift_rejects_bad_input() -> None:
    with pytest.raises(InputError, match="same shape"):
        ev.fit_scale_shift(np.ones(3), np.ones(4))
    with pytest.raises(InputError, match="finite"):
        ev.fit_scale_shift(np.array([1.0, np.nan]), np.ones(2))
    with pytest.raises(InputError, match=">= 0"):
        ev.fit_scale_shift(np.ones(2), np.ones(2), weights=np.array([1.0, -1.0]))
    with pytest.raises(InputError, match="positive sum"):
        ev.fit_scale_shift(np.ones(2), np.ones(2), weights=np.zeros(2))


@pytest.mark.parametrize(
    ("pred_shape", "gt_shape", "kwargs", "match"),
    [
        ((4, 8), (4, 6), {}, "shape mismatch"),
        ((4, 8, 1), (4, 8, 1), {}, "2-D"),
        ((4, 6), (4, 6), {}, "W == 2H"),
        ((4, 8), (4, 8), {"weighting": "cosine"}, "weighting"),
        ((4, 8), (4, 8), {"pole_cap_deg": -1.0}, r"\[0, 90\)"),
        ((4, 8), (4, 8), {"pole_cap_deg": 90.0}, r"\[0, 90\)"),
        ((4, 8), (4, 8), {"valid": np.ones((4, 7), bool)}, "valid must have shape"),
        ((4, 8), (4, 8), {"valid": np.ones((4, 8))}, "bool"),
    ],
)
def test_depth_metrics_rejects_bad_input(
    pred_shape: tuple[int, ...], gt_shape: tuple[int, ...], kwargs: dict[str, object], match: str
) -> None:
    with pytest.raises(InputError, match=match):
        ev.depth_metrics(np.ones(pred_shape), np.ones(gt_shape), **kwargs)  # type: ignore[arg-type]


def test_depth_metrics_no_valid_pixel() -> None:
    with pytest.raises(InputError, match="no valid ground-truth"):
        ev.depth_metrics(np.ones((4, 8)), np.full((4, 8), np.nan))
    with pytest.raises(InputError, match="no valid pixel"):
        ev.depth_metrics(np.full((4, 8), np.nan), np.ones((4, 8)))
    # H = 4 has row centres at ±67.5° and ±22.5°: a 60° cap keeps the middle rows, 80° none.
    assert ev.depth_metrics(np.ones((4, 8)), np.ones((4, 8)), pole_cap_deg=60.0)["n_valid"] == 16
    with pytest.raises(InputError, match="no valid ground-truth"):
        ev.depth_metrics(np.ones((4, 8)), np.ones((4, 8)), pole_cap_deg=80.0)


def test_format_metrics() -> None:
    pred, gt = two_level_example(4, error_row=2)
    text = ev.format_metrics(ev.depth_metrics(pred, gt))
    assert "\n" not in text
    assert "AbsRel 0.0312" in text and "d1 0.9375" in text and "n 32" in text
    assert "cov 100.00%" in text
    assert ev.format_metrics({"abs_rel": 0.5}) == "AbsRel 0.5000"


def test_edge_band_is_the_pixels_within_band_of_a_depth_jump_across_the_seam() -> None:
    depth = np.full((16, 32), 2.0, np.float32)
    depth[:, 10:20] = 1.0  # two vertical edges, at columns 9|10 and 19|20
    depth[:, 31] = 1.5  # and one across the seam (31|0) and at 30|31
    band = ev.edge_band(depth, band=2)
    # An edge marks its left pixel (the jump to its right neighbour, column 31's is column 0),
    # then dilated by 2, wrapping in longitude (the seam's edge reaches columns 0 and 1).
    expected_cols = {0, 1, 7, 8, 9, 10, 11, 17, 18, 19, 20, 21, 28, 29, 30, 31}
    assert {int(c) for c in np.nonzero(band.all(axis=0))[0]} == expected_cols
    assert not band[:, [c for c in range(32) if c not in expected_cols]].any()
    assert not ev.edge_band(depth, jump=1.5).any()  # the jumps are 33 % to 100 %
    # Rows stop at the poles: an edge in the top row does not reach the bottom one.
    rows = np.full((16, 32), 2.0, np.float32)
    rows[0] = 1.0
    assert ev.edge_band(rows, band=2)[:3].all() and not ev.edge_band(rows, band=2)[3:].any()
    with pytest.raises(InputError, match="2-D float"):
        ev.edge_band(np.ones((4, 8), np.int32))
