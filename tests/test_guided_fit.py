"""The guided upsampling's working-resolution fit (``_core.guided_fit``, fused into
``_core.guided_upsample``) against an independent oracle: the whole-array numpy/OpenCV fit that
``m360.upsample`` used before the fit moved into the core, kept here verbatim apart from a
``dtype`` for its box filters and fit."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from m360 import _core
from m360.errors import InputError
from m360.upsample import guided_upsample

# --------------------------------------------------------------------------------------------
# The oracle: the former whole-array fit (benches/guided_reference.py).

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benches"))
from guided_reference import oracle_planes

# --------------------------------------------------------------------------------------------
# Test maps.


def _holed_map(h: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A disparity (h, 2h) with steps, scattered NaN, a NaN block across the seam and NaN in
    both pole rows; and a grey image at that size correlated with the steps."""
    rng = np.random.default_rng(seed)
    w = 2 * h
    cols = np.arange(w)
    step = ((cols // max(2, w // 6)) % 2).astype(np.float32)
    disp = 1.0 + step[None, :] + rng.uniform(-0.05, 0.05, (h, w))
    disp[rng.uniform(size=(h, w)) < 0.15] = np.nan
    disp[h // 3 : h // 3 + 2, -2:] = np.nan  # across the seam: columns w-2, w-1, 0
    disp[h // 3 : h // 3 + 2, :1] = np.nan
    disp[0, rng.integers(0, w, 3)] = np.nan
    disp[-1, rng.integers(0, w, 3)] = np.nan
    grey = np.clip(60 + 120 * step[None, :] + rng.normal(0, 20, (h, w)), 0, 255).astype(np.uint8)
    return disp.astype(np.float32), grey


CASES = [(h, r) for h in (4, 7, 16, 33) for r in (1, 2, 3) if r < h]

# --------------------------------------------------------------------------------------------
# Planes.


@pytest.mark.parametrize(("h", "radius"), CASES)
def test_fit_planes_match_the_oracle(h: int, radius: int) -> None:
    disp, grey = _holed_map(h, seed=h * 10 + radius)
    eps, low, high = 1e-3, 0.05, 0.15
    got = _core.guided_fit(disp, grey, radius, eps, low, high)
    assert got.shape == (h, 2 * h, 7) and got.dtype == np.float32
    want32 = oracle_planes(disp, grey, radius, eps, low, high)
    want64 = oracle_planes(disp, grey, radius, eps, low, high, dtype=np.float64)
    # p0, m, e, lo, hi: the same float32 arithmetic on the same values, so exactly equal.
    for k in (0, 1, 2, 5, 6):
        np.testing.assert_array_equal(got[..., k], want32[..., k], err_msg=f"plane {k}")
    if h >= 16:  # smaller maps have no 3 x 3 window without a NaN
        assert (got[..., 2] > 0).any() and (got[..., 2] == 0).any()
    # a, b: the core fits in f64; against the oracle run in float64 they agree to float32
    # rounding. The seam columns and pole rows are where wrap and reflect matter: check them on
    # their own as well as everywhere.
    for k in (3, 4):
        scale = np.abs(want64[..., k]).max()
        for where, name in [
            ((slice(None), slice(None)), "all"),
            ((slice(None), [0, 1, -2, -1]), "seam columns"),
            (([0, 1, -2, -1], slice(None)), "pole rows"),
        ]:
            np.testing.assert_allclose(
                got[..., k][where], want64[..., k][where], rtol=1e-5, atol=1e-6 * scale,
                err_msg=f"plane {k}, {name}",
            )  # fmt: skip
        # The oracle in float32 (the former code exactly) differs only by its float32
        # cancellation in cov(I, p) and var(I): absolute, of the order of 1e-7 / (var + eps).
        np.testing.assert_allclose(got[..., k], want32[..., k], rtol=1e-4, atol=2e-4 * scale)


def test_fit_of_a_pure_linear_model_is_exact() -> None:
    # A disparity that is exactly a·I + b everywhere: every window's fit recovers (almost: eps
    # shrinks a by var / (var + eps)) a and b, and so do their window means.
    rng = np.random.default_rng(5)
    grey = rng.integers(0, 256, (16, 32), dtype=np.uint8)
    disp = (0.5 * grey.astype(np.float32) / 255 + 2.0).astype(np.float32)
    planes = _core.guided_fit(disp, grey, 2, 1e-9, 0.05, 0.15)
    np.testing.assert_allclose(planes[..., 3], 0.5, rtol=1e-5)
    np.testing.assert_allclose(planes[..., 4], 2.0, rtol=1e-5)


# --------------------------------------------------------------------------------------------
# Outputs.


@pytest.mark.parametrize(("h", "radius"), [(7, 1), (16, 2), (33, 3), (33, 1)])
@pytest.mark.parametrize("factor", [1, 3])
def test_guided_upsample_matches_the_oracle(h: int, radius: int, factor: int) -> None:
    disp, _ = _holed_map(h, seed=100 + h + radius)
    rng = np.random.default_rng(h)
    height = factor * h
    # A photo with the map's steps and noise; its grey is what both paths shrink.
    rgb = rng.integers(0, 256, (height, 2 * height, 3), dtype=np.uint8)
    rgb[:, : 2 * height // 3] //= 3
    grey_full = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    grey = cv2.resize(grey_full, (2 * h, h), interpolation=cv2.INTER_AREA)
    planes = oracle_planes(disp, grey, radius, 1e-4, 0.05, 0.15, dtype=np.float64)
    want = _core.upsample_planes(planes, (height, 2 * height), grey_full)
    got = guided_upsample(disp, rgb, radius=radius)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=1e-5, atol=1e-6)
    # Against the former code exactly (float32 fit): within its float32 noise.
    want32 = _core.upsample_planes(oracle_planes(disp, grey, radius, 1e-4, 0.05, 0.15),
                                   (height, 2 * height), grey_full)  # fmt: skip
    np.testing.assert_allclose(got[ok], want32[ok], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("h", [4, 33])
def test_bilinear_upsample_equals_the_planes_pass(h: int) -> None:
    disp, _ = _holed_map(h, seed=7)
    guide = np.zeros((3 * h, 6 * h, 3), np.uint8)
    got = guided_upsample(disp, guide, method="bilinear")
    valid = np.isfinite(disp)
    planes = np.dstack([np.where(valid, disp, 0), valid]).astype(np.float32)
    want = _core.upsample_planes(planes, (3 * h, 6 * h))
    np.testing.assert_array_equal(got, want)


# --------------------------------------------------------------------------------------------
# Bad input.


def test_bad_fit_arguments_are_input_errors() -> None:
    disp, grey = _holed_map(8, seed=1)
    with pytest.raises(InputError, match="radius"):
        _core.guided_fit(disp, grey, 0, 1e-4, 0.05, 0.15)
    with pytest.raises(InputError, match="radius"):
        _core.guided_fit(disp, grey, 8, 1e-4, 0.05, 0.15)
    with pytest.raises(InputError, match="eps"):
        _core.guided_fit(disp, grey, 1, float("nan"), 0.05, 0.15)
    with pytest.raises(InputError, match="edge_low"):
        _core.guided_fit(disp, grey, 1, 1e-4, 0.2, 0.15)
    with pytest.raises(InputError, match="grey"):
        _core.guided_fit(disp, grey[:, :-1], 1, 1e-4, 0.05, 0.15)
    with pytest.raises(InputError, match="C-contiguous"):
        _core.guided_upsample(disp[:, ::2], grey[:, ::2], grey, 1, 1e-4, 0.05, 0.15)
    with pytest.raises(InputError, match="radius"):
        guided_upsample(disp, np.zeros((16, 32, 3), np.uint8), radius=8)


def test_result_does_not_depend_on_the_thread_count() -> None:
    disp, _ = _holed_map(40, seed=3)
    rgb = np.random.default_rng(3).integers(0, 256, (120, 240, 3), dtype=np.uint8)
    before = _core.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 3):
            _core.set_num_threads(threads)
            outs.append(guided_upsample(disp, rgb))
    finally:
        _core.set_num_threads(before)
    for out in outs[1:]:
        np.testing.assert_array_equal(out, outs[0])
