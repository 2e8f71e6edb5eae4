"""stitch(align="none", blend="mean"|"nn"): round trips against analytic ray casting."""

from __future__ import annotations

import m360
import numpy as np
import pytest
from conftest import (
    as_perspective,
    erp_depth,
    layout,
    smooth_field,
    tangent_directions,
    tangent_disparity,
)
from m360.errors import InputError
from m360.geometry import sphere as sph


def raw_abs_rel(disparity: np.ndarray, depth: np.ndarray) -> float:
    """AbsRel of 1/disparity against depth with no fitting at all (the round trip is exact)."""
    return float(np.mean(np.abs(1.0 / disparity - depth) / depth))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("blend", ["mean", "nn"])
def test_round_trip_2k(seed: int, blend: str) -> None:
    lay = layout(2048)
    disp = m360.stitch(tangent_disparity(seed, 2048), lay, align="none", blend=blend)
    assert isinstance(disp, np.ndarray)
    assert disp.shape == lay.erp_shape and disp.dtype == np.float32
    assert np.isfinite(disp).all()
    depth = erp_depth(seed, 2048)
    metrics = m360.eval.depth_metrics(disp, depth)
    print(f"seed {seed} {blend}: {m360.eval.format_metrics(metrics)}")
    assert metrics["abs_rel"] <= 0.002
    assert raw_abs_rel(disp, depth) <= 0.002


def test_round_trip_4k() -> None:
    lay = layout(4096)
    disp = m360.stitch(tangent_disparity(0, 4096), lay, align="none", blend="mean")
    assert disp.shape == (2048, 4096)
    depth = erp_depth(0, 4096)
    assert m360.eval.depth_metrics(disp, depth)["abs_rel"] <= 0.002
    assert raw_abs_rel(disp, depth) <= 0.002


def test_spherical_factor_is_per_pixel_and_per_face() -> None:
    """Reference pitfall B1 (docs/reference-pitfalls.md) used one face's factor for all faces: a
    constant perspective disparity of 1 must become exactly cos(angle to that face's own axis)
    on every face."""
    lay = layout(512)
    from m360.geometry import plan_for

    sph_disp = plan_for(lay).spherical_disparity(np.ones((20, *lay.tangent_shape), np.float32))
    dirs = tangent_directions(lay)
    for k, cam in enumerate(lay.cameras):
        np.testing.assert_allclose(sph_disp[k], dirs[k] @ cam.axis, rtol=1e-6)


@pytest.mark.parametrize("blend", ["mean", "nn"])
def test_no_seam_at_the_longitude_wrap_and_poles(blend: str) -> None:
    lay = layout(1024)
    tangents = as_perspective(smooth_field(tangent_directions(lay)), lay)
    out = m360.stitch(tangents, lay, align="none", blend=blend)
    grid = sph.erp_directions(*lay.erp_shape)
    want = smooth_field(grid)
    # Across the wrap: columns W-1 and 0 differ only as much as the field does there.
    jump = np.abs(out[:, 0] - out[:, -1])
    field_jump = np.abs(want[:, 0] - want[:, -1])
    assert np.abs(jump - field_jump).max() < 2e-3
    # Across each pole: row 0 at column j neighbours row 0 at column j + W/2.
    h, w = lay.erp_shape
    for row in (0, h - 1):
        across = np.abs(out[row] - np.roll(out[row], w // 2))
        field_across = np.abs(want[row] - np.roll(want[row], w // 2))
        assert np.abs(across - field_across).max() < 2e-3
    assert np.abs(out - want).max() < 3e-3


def test_nn_takes_the_face_whose_triangle_contains_the_pixel() -> None:
    lay = layout(512)
    face_id = np.broadcast_to(
        np.arange(20, dtype=np.float32)[:, None, None], (20, *lay.tangent_shape)
    )
    # Undo the spherical factor so the stitched value is exactly the face index.
    out = m360.stitch(as_perspective(face_id, lay), lay, align="none", blend="nn")
    # Oracle: the face whose (gnomonic) triangle contains the direction.
    grid = sph.erp_directions(*lay.erp_shape)
    owner = np.full(lay.erp_shape, -1)
    for k, cam in enumerate(lay.cameras):
        cam_xyz = grid @ cam.rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            g = cam_xyz[..., :2] / cam_xyz[..., 2:]
        inside = (cam_xyz[..., 2] > 0) & _in_triangle(g, cam.face)
        owner[inside] = k
    assert (owner >= 0).all()
    agree = np.abs(out - owner) < 1e-3
    # Pixels within rounding of an edge may go either way; nearly all must agree.
    assert agree.mean() > 0.999, agree.mean()


def _in_triangle(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    signs = []
    for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
        signs.append((b[0] - a[0]) * (p[..., 1] - a[1]) - (b[1] - a[1]) * (p[..., 0] - a[0]))
    s = np.stack(signs)
    return (s >= 0).all(axis=0) | (s <= 0).all(axis=0)


@pytest.mark.parametrize("blend", ["mean", "nn"])
def test_mask_excludes_pixels_even_through_bilinear_neighbours(blend: str) -> None:
    lay = layout(512)
    tangents = tangent_disparity(0, 512).copy()
    mask = np.ones(tangents.shape, bool)
    mask[3] = False  # a whole face without estimate
    mask[7, 40:60, 50:90] = False  # a tripod-like patch
    poisoned = tangents.copy()
    poisoned[~mask] = 1e6
    as_nan = tangents.copy()
    as_nan[~mask] = np.nan
    out = m360.stitch(poisoned, lay, align="none", blend=blend, mask=mask)
    ref = m360.stitch(as_nan, lay, align="none", blend=blend)
    np.testing.assert_array_equal(out, ref)
    assert np.nanmax(out) < 1e3
    # Where every covering face is masked the output is NaN.
    full = np.zeros(tangents.shape, bool)
    full[:10] = True
    partial = m360.stitch(tangents, lay, align="none", blend=blend, mask=full)
    assert np.isnan(partial).any() and np.isfinite(partial).any()


def test_same_result_with_one_and_two_threads() -> None:
    lay = layout(1024)
    tangents = tangent_disparity(1, 1024)
    outs = []
    before = m360.get_num_threads()
    try:
        for n in (1, 2):
            m360.set_num_threads(n)
            outs.append(m360.stitch(tangents, lay, align="none", blend="mean", return_details=True))
    finally:
        m360.set_num_threads(before)
    np.testing.assert_array_equal(outs[0].disparity, outs[1].disparity)
    np.testing.assert_array_equal(outs[0].confidence, outs[1].confidence)


def test_details() -> None:
    lay = layout(512)
    res = m360.stitch(
        tangent_disparity(0, 512), lay, align="none", blend="mean", return_details=True
    )
    assert isinstance(res, m360.StitchResult)
    assert res.disparity.shape == res.confidence.shape == res.coverage.shape == lay.erp_shape
    assert set(res.timings) == {"convert", "align", "blend"}
    assert (res.confidence[np.isfinite(res.confidence)] >= 0).all()
    # Exact tangents agree up to resampling: the disagreement is small relative to the values.
    assert np.nanmedian(res.confidence / res.disparity) < 1e-3


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"align": "bogus"}, "not supported"),
        ({"blend": "bogus"}, r"choose one of [\"']consensus"),
        ({"blend": "mean", "blend_options": {"fidelity": "nn"}}, "blend='poisson' only"),
        ({"blend": 3}, r"choose one of [\"']consensus"),
        ({"mask": np.ones((20, 2, 2), bool)}, "mask"),
        ({"mask": "yes"}, "mask"),
        ({"return_details": "yes"}, "return_details"),
    ],
)
def test_stitch_rejects_bad_options(kwargs: dict, match: str) -> None:
    lay = layout(512)
    args = {"align": "none", "blend": "mean", **kwargs}
    with pytest.raises(InputError, match=match):
        m360.stitch(np.ones((20, *lay.tangent_shape), np.float32), lay, **args)


def test_stitch_rejects_bad_tangents() -> None:
    lay = layout(512)
    h, w = lay.tangent_shape
    bad = np.ones((20, h, w), np.float32)
    bad[0, 0, 0] = np.inf
    with pytest.raises(InputError, match="infinite"):
        m360.stitch(bad, lay, align="none", blend="mean")
    with pytest.raises(InputError, match="expected"):
        m360.stitch(np.ones((20, w, h), np.float32), lay, align="none", blend="mean")
    mask = np.ones((20, h, w), np.uint8)
    with pytest.raises(InputError, match="bool"):
        m360.stitch(np.ones((20, h, w), np.float32), lay, align="none", blend="mean", mask=mask)
