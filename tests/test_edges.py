"""m360.stitching.refine_edges: smeared depth edges made sharp along the photo's."""

from __future__ import annotations

import math

import cv2
import m360
import m360.synthetic as syn
import numpy as np
import onnx_graphs as g
import pytest
from m360.stitching.edges import AUTO_PHOTO_SHRINK, default_edge_radius, edges_for, refine_edges

BINS = 24  # rust/m360-core/src/edges.rs
FULL_TAPS = 3


def reference_refine(disparity, rgb, radius, colour_sigma=15.0, transition=0.05, jump=0.05):
    """The filter written plainly, pixel by pixel (the oracle for the core's)."""
    h, w = disparity.shape
    logd = np.where(disparity > 0, np.log(np.where(disparity > 0, disparity, 1)), np.nan)
    logd = logd.astype(np.float32)
    up = np.clip(np.arange(h) - 1, 0, h - 1)
    down = np.clip(np.arange(h) + 1, 0, h - 1)
    gx = (np.roll(logd, -1, axis=1) - np.roll(logd, 1, axis=1)) * 0.5
    gy = (logd[down] - logd[up]) / np.maximum(down - up, 1)[:, None]
    g2 = (gx * gx + gy * gy) * (radius / transition) ** 2
    flat = np.where(np.isfinite(g2), np.exp(-g2), 0.0)
    step = math.ceil(radius / FULL_TAPS)
    reach = radius // step
    cut = math.ceil(9 * colour_sigma**2)
    out = disparity.astype(np.float32).copy()
    rgb = rgb.astype(np.int64)
    for y in range(h):
        for x in range(w):
            if not np.isfinite(logd[y, x]):
                continue
            values, weights = [], []
            for ky in range(-reach, reach + 1):
                for kx in range(-reach, reach + 1):
                    yy, xx = y + ky * step, (x + kx * step) % w
                    if not 0 <= yy < h or not np.isfinite(logd[yy, xx]):
                        continue
                    d2 = int(((rgb[y, x] - rgb[yy, xx]) ** 2).sum())
                    space = math.exp(
                        -((ky * step) ** 2 + (kx * step) ** 2) / (2 * (radius / 2) ** 2)
                    )
                    colour = math.exp(-d2 / (2 * colour_sigma**2)) if d2 <= cut else 0.0
                    keep = flat[yy, xx] >= 1e-3
                    values.append(logd[yy, xx])
                    weights.append(space * colour * flat[yy, xx] if keep else 0.0)
            lo, hi = min(values), max(values)
            if not hi - lo > jump:
                continue
            v, wt = np.array(values, np.float64), np.array(weights)
            bins = np.minimum(((v - lo) * (BINS / (hi - lo))).astype(int), BINS - 1)
            per_bin = np.bincount(bins, wt, BINS)
            triple = np.array([per_bin[max(b - 1, 0) : b + 2].sum() for b in range(BINS)])
            best = int(np.argmax(triple))
            sel = (np.abs(bins - best) <= 1) & (wt > 0)
            if wt[sel].sum() > 0:
                mode = (v[sel] * wt[sel]).sum() / wt[sel].sum()
                keep = flat[y, x]  # a pixel outside any transition keeps its value
                out[y, x] = math.exp(keep * logd[y, x] + (1 - keep) * mode)
    return out


def blurred_scene(width, seed=0, blur=None):
    """A rendered room's photo and depth, and its disparity blurred as a network smears it."""
    rgb, depth = syn.render(syn.room(seed), width)
    disparity = (1 / depth).astype(np.float32)
    blur = width / 2048 if blur is None else blur
    return rgb, depth, cv2.GaussianBlur(disparity, (0, 0), blur, borderType=cv2.BORDER_REFLECT)


@pytest.mark.parametrize("radius", [3, 8])
def test_the_core_matches_the_filter_written_pixel_by_pixel(radius):
    rgb, _, blurred = blurred_scene(128, seed=1, blur=1.5)
    blurred[5, 7] = np.nan  # invalid pixels stay and are never samples
    blurred[40, 100] = -1.0
    got = refine_edges(blurred, rgb, radius=radius)
    want = reference_refine(blurred, rgb, radius)
    assert np.isnan(got[5, 7]) and got[40, 100] == -1.0
    changed = np.isfinite(want) & (want != blurred)
    assert changed.mean() > 0.02, "the filter must act on this scene"
    close = np.isclose(got, want, rtol=1e-4, equal_nan=True)
    # float32 sums in another order may tip a near tie between two bins: allow a few pixels.
    assert close.mean() > 0.999, np.argwhere(~close)[:5]


def test_smeared_edges_of_a_room_become_sharp_and_smooth_surfaces_stay():
    rgb, depth, blurred = blurred_scene(1024)
    band = m360.eval.edge_band(depth)
    refined = refine_edges(blurred, rgb)

    def band_error(d):
        return m360.eval.depth_metrics(d, depth, valid=band)["abs_rel"]

    assert band_error(refined) < 0.5 * band_error(blurred)
    # Windows without a jump are left bit for bit.
    log = np.log(blurred)
    k = np.ones((2 * default_edge_radius(1024) + 1,) * 2, np.uint8)
    flat = (cv2.dilate(log, k) - cv2.erode(log, k)) < 0.04
    assert flat.mean() > 0.5
    assert np.array_equal(refined[flat], blurred[flat])


def test_the_result_is_the_same_on_one_and_two_threads():
    rgb, _, blurred = blurred_scene(512)
    before = m360.get_num_threads()
    try:
        results = []
        for n in (1, 2):
            m360.set_num_threads(n)
            results.append(refine_edges(blurred, rgb, radius=9))
    finally:
        m360.set_num_threads(before)
    assert results[0].tobytes() == results[1].tobytes()


def test_the_seam_is_a_neighbour_like_any_other():
    rgb, _, blurred = blurred_scene(256)
    shift = 77
    rolled = refine_edges(np.roll(blurred, shift, axis=1), np.roll(rgb, shift, axis=1))
    assert np.array_equal(rolled, np.roll(refine_edges(blurred, rgb), shift, axis=1))
    # Edges are refined right at the rolled map's seam, so a window cut there would show.
    changed = rolled != np.roll(blurred, shift, axis=1)
    assert changed[:, :3].any() and changed[:, -3:].any()


def test_default_radius_scales_with_the_width():
    assert default_edge_radius(4096) == 10
    assert default_edge_radius(8192) == 20
    assert default_edge_radius(256) == 2


@pytest.mark.parametrize(
    ("disparity", "photo", "kwargs", "match"),
    [
        (np.ones((8, 8), np.float32), np.zeros((8, 8, 3), np.uint8), {}, "ERP map"),
        (np.ones((8, 16), np.int32), np.zeros((8, 16, 3), np.uint8), {}, "float"),
        (np.ones((8, 16), np.float32), np.zeros((8, 8, 3), np.uint8), {}, "photo must be RGB"),
        (np.ones((8, 16), np.float32), np.full((8, 16, 3), np.nan), {}, "NaN"),
        (np.ones((8, 16), np.float32), np.zeros((8, 16, 3), np.int16), {}, "uint8"),
        (np.ones((8, 16), np.float32), np.zeros((8, 16, 3), np.uint8), {"radius": 0}, "radius"),
        (np.ones((8, 16), np.float32), np.zeros((8, 16, 3), np.uint8), {"radius": 2.5}, "radius"),
        (np.ones((8, 16), np.float32), np.zeros((8, 16, 3), np.uint8), {"radius": 300}, "radius"),
        (
            np.ones((8, 16), np.float32),
            np.zeros((8, 16, 3), np.uint8),
            {"colour_sigma": 0},
            "colour_sigma",
        ),
        (np.ones((8, 16), np.float32), np.zeros((8, 16, 3), np.uint8), {"jump": -1}, "jump"),
    ],
)
def test_bad_input_is_an_input_error(disparity, photo, kwargs, match):
    with pytest.raises(m360.InputError, match=match):
        refine_edges(disparity, photo, **kwargs)


def test_estimate_with_photo_edges_is_the_refinement_of_its_result():
    width = 512
    scene = syn.room(2)
    rgb, _ = syn.render(scene, width)
    layout = m360.Layout.icosahedron(width)
    model = m360.estimators.SimulatedEstimator(scene, layout, seed=3)
    plain = m360.estimate(rgb, model=model, layout=layout)
    sharp = m360.estimate(rgb, model=model, layout=layout, edges="photo")
    assert sharp.options["edges"] == "photo" and "edges" not in plain.options
    expected = refine_edges(plain.disparity, rgb)
    assert np.array_equal(sharp.disparity, expected)
    assert (sharp.disparity != plain.disparity).any()
    with pytest.raises(m360.InputError, match="edges"):
        m360.estimate(rgb, model=model, layout=layout, edges="crisp")


def test_auto_edges_refine_along_the_photo_only_for_a_coarse_network(tmp_path):
    """``edges="auto"`` (the default) is ``"photo"`` for a network that sees its tile 4 or more
    times smaller, ``"network"`` otherwise and for a network of unknown size."""
    width = 512
    scene = syn.room(2)
    rgb, _ = syn.render(scene, width)
    model = g.channel(tmp_path / "green.onnx", 1)
    tile = m360.geometry.default_layout(width).tangent_shape[1]
    opts = {"normalize": "unit", "output_kind": "affine_disparity", "multiple_of": 4}
    for size, mode in ((4 * (tile // 20), "photo"), (4 * (tile // 12), "network")):
        assert (tile >= AUTO_PHOTO_SHRINK * size) == (mode == "photo")
        auto = m360.estimate(rgb, model, input_size=(size, size), **opts)
        chosen = m360.estimate(rgb, model, input_size=(size, size), edges=mode, **opts)
        assert np.array_equal(auto.disparity, chosen.disparity)
        assert auto.options.get("edges", "network") == mode
        other = "network" if mode == "photo" else "photo"
        unchosen = m360.estimate(rgb, model, input_size=(size, size), edges=other, **opts)
        assert not np.array_equal(auto.disparity, unchosen.disparity)
    assert edges_for("auto", tile, None) == "network"  # a simulated network: no input size
    assert edges_for("network", 800, 100) == "network" and edges_for("photo", 100, 100) == "photo"
