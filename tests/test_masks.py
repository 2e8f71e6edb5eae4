"""m360.masks: polar caps, user masks and sky="nan" in m360.estimate."""

from __future__ import annotations

import functools

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360 import masks

WIDTH = 256


@functools.cache
def scene_and_rgb() -> tuple[syn.Scene, np.ndarray, np.ndarray]:
    scene = syn.room(2)
    rgb, depth = syn.render(scene, WIDTH)
    return scene, rgb, depth


class Poisoned:
    """The simulated network, with garbage written into the masked tangent pixels."""

    output_kind = "affine_disparity"

    def __init__(self, inner: m360.estimators.SimulatedEstimator, used: np.ndarray) -> None:
        self.inner, self.used, self.name = inner, used, "poisoned"

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        out = self.inner.predict(tangents)
        out[~self.used] = np.float32(123.0)
        return out


def test_caps_follow_the_latitude():
    cap = masks.nadir(20).to_array(90, 180)
    lat = 90 - 180 * (np.arange(90) + 0.5) / 90  # degrees
    np.testing.assert_array_equal(cap[:, 0], lat > -70)
    assert cap.all(axis=1).sum() == (lat > -70).sum()  # whole rows
    top = masks.zenith(45).to_array(90, 180)
    np.testing.assert_array_equal(top[:, 7], lat < 45)
    both = masks.erp_mask([masks.nadir(20), masks.zenith(45)], 90, 180)
    np.testing.assert_array_equal(both, cap & top)


@pytest.mark.parametrize("align", ["multiscale", "none"])
def test_masked_pixels_take_no_part_in_alignment_or_blending(align):
    scene, rgb, _ = scene_and_rgb()
    layout = m360.geometry.default_layout(WIDTH)
    user = np.ones((WIDTH // 2, WIDTH), bool)
    user[40:70, 30:90] = False  # a box of "camera operator"
    mask = [masks.nadir(25), user]
    sim = m360.estimators.SimulatedEstimator(scene, layout, seed=1)
    clean = m360.estimate(rgb, sim, mask=mask, align=align)
    used = masks.tangent_mask(masks.erp_mask(mask, WIDTH // 2, WIDTH), layout)
    assert 0.05 < 1 - used.mean() < 0.5
    poisoned = m360.estimate(rgb, Poisoned(sim, used), mask=mask, align=align)
    # garbage in the masked tangent pixels changes nothing, bit for bit
    np.testing.assert_array_equal(poisoned.disparity, clean.disparity)
    # ... while without the mask it does (the test can fail)
    unmasked = m360.estimate(rgb, Poisoned(sim, used), align=align)
    assert not np.allclose(unmasked.disparity, clean.disparity, equal_nan=True)
    # masked ERP pixels are NaN in every output, the rest is estimated
    erp = masks.erp_mask(mask, WIDTH // 2, WIDTH)
    assert np.isnan(clean.disparity[~erp]).all() and np.isnan(clean.depth[~erp]).all()
    # (a border of about a pixel along the mask edge is lost to the bilinear footprints)
    assert np.isfinite(clean.disparity[erp]).mean() > 0.97
    assert clean.options["masked_fraction"] == pytest.approx(1 - erp.mean())


def test_sky_nan():
    # A floor 1.5 m below the camera; walls and ceiling 3 km away are the sky.
    scene = syn.Scene(room_min=np.full(3, -3000.0), room_max=np.array([3000.0, 1.5, 3000.0]))
    rgb, depth = syn.render(scene, WIDTH)
    sim = m360.estimators.SimulatedEstimator(scene, m360.geometry.default_layout(WIDTH), shift=0.0)
    keep = m360.estimate(rgb, sim, align="none", blend="mean")
    nan = m360.estimate(rgb, sim, align="none", blend="mean", sky="nan")
    far = depth > 1000
    assert far.mean() > 0.4
    assert np.isfinite(keep.depth[far]).mean() > 0.99  # today's behaviour: a fake distance
    assert np.isnan(nan.depth[far]).mean() > 0.99
    near = depth < 20
    np.testing.assert_array_equal(nan.depth[near], keep.depth[near])
    assert nan.options["sky"] == "nan"
    direct = masks.sky(keep.disparity)
    assert direct[far].mean() > 0.99 and not direct[near].any()


def test_bad_masks_are_input_errors():
    _, rgb, _ = scene_and_rgb()
    sim = m360.estimators.SimulatedEstimator(syn.room(2), m360.Layout.icosahedron(WIDTH))
    with pytest.raises(m360.InputError, match="panorama's shape"):
        m360.estimate(rgb, sim, mask=np.ones((10, 20), bool))
    with pytest.raises(m360.InputError, match="bool"):
        m360.estimate(rgb, sim, mask=np.ones((WIDTH // 2, WIDTH), np.uint8))
    with pytest.raises(m360.InputError, match="sky"):
        m360.estimate(rgb, sim, sky="blue")
    with pytest.raises(m360.InputError, match="nadir"):
        masks.nadir(-5)
