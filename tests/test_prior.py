"""The global prior of m360.stitch (docs/method.md, "Global prior")."""

from __future__ import annotations

import re

import cv2
import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360.geometry import plan_for
from m360.geometry import sphere as sph

WIDTH = 512


@pytest.fixture(scope="module")
def room() -> tuple[m360.Layout, np.ndarray, np.ndarray, syn.Scene]:
    layout = m360.Layout.icosahedron(WIDTH, padding=0.3)
    scene = syn.room(3)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    tiles = syn.distort(exact, 7, scale=(0.5, 2.0), shift=0.3, field=0.0, noise=0.0)
    depth = scene.distance(sph.erp_directions(WIDTH // 2, WIDTH))
    return layout, tiles, depth, scene


def _distance(scene: syn.Scene, height: int) -> np.ndarray:
    return scene.distance(sph.erp_directions(height, 2 * height))


def test_without_a_prior_the_result_is_bit_identical(room: tuple) -> None:
    layout, tiles, _, _ = room
    plain = m360.stitch(tiles, layout)
    again = m360.stitch(tiles, layout, prior=None)
    assert np.array_equal(plain, again, equal_nan=True)


@pytest.mark.parametrize("kind", ["disparity", "distance"])
def test_an_absolute_prior_gives_its_units(room: tuple, kind: str) -> None:
    """A coarse exact prior (64 x 128) of a 512-wide stitch: the result is in 1/m."""
    layout, tiles, depth, scene = room
    distance = _distance(scene, 64)
    prior = 1.0 / distance if kind == "disparity" else distance
    res = m360.stitch(tiles, layout, prior=prior, prior_kind=kind, return_details=True)
    ratio = np.nanmedian(res.disparity * depth)
    assert abs(ratio - 1.0) < 0.01, ratio
    report = res.report["prior"]
    assert report is not None and report["kind"] == kind
    assert report["affine"] == pytest.approx((1.0, 0.0), abs=1e-9)
    assert report["samples"] > 1000


def test_a_relative_prior_reports_its_affine_map(room: tuple) -> None:
    """affine_disparity 3/d + 1: the reported map sends it onto the result."""
    layout, tiles, _, scene = room
    prior = 3.0 / _distance(scene, 64) + 1.0
    res = m360.stitch(tiles, layout, prior=prior, return_details=True)
    report = res.report["prior"]
    assert report is not None
    a, b = report["affine"]
    coarse = res.disparity[::4, ::4]
    fitted = a * prior + b
    rel = np.nanmedian(np.abs(coarse - fitted) / np.abs(coarse))
    assert rel < 0.02, rel
    # Disagreement with the prior is part of the confidence, never below the tangents' own.
    plain = m360.stitch(tiles, layout, return_details=True)
    assert np.all(res.confidence[np.isfinite(res.confidence)] >= 0)
    assert np.nanmean(res.confidence) >= np.nanmean(plain.confidence) * 0.5


def test_the_prior_fixes_what_the_tangents_cannot(room: tuple) -> None:
    """Content errors: the tangents alone leave an error a coarse exact prior removes."""
    layout, _, depth, scene = room
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    wrong = syn.content_errors(exact, 11, regions=(2, 3), amplitude=(0.2, 0.3))
    tiles = syn.distort(wrong, 7, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.0)
    prior = 1.0 / _distance(scene, 64)
    plain = m360.eval.depth_metrics(m360.stitch(tiles, layout), depth)["abs_rel"]
    with_prior = m360.stitch(tiles, layout, prior=prior, prior_kind="disparity")
    err = m360.eval.depth_metrics(with_prior, depth)["abs_rel"]
    assert err < plain, (err, plain)


def test_consistent_tangents_are_trusted_over_the_priors_smooth_error(room: tuple) -> None:
    """A deformation shared by all tangents is invisible to their overlaps, so a prior's own
    smooth error (here +-3 %) would pass into the result in full. Tangents that agree with each
    other (exact up to per-tangent affine maps: spread 1e-4) move the prior towards them in
    full: the result stays near the stitch without the prior, far from the prior's error.
    Tangents with content errors and +-10 % fields (spread 2 %) leave the prior as it is."""
    layout, tiles, depth, scene = room
    prior = np.asarray(syn.panoramic_prior(scene, 5, regions=(0, 0)))
    alone = cv2.resize(prior, (WIDTH, WIDTH // 2), interpolation=cv2.INTER_AREA)
    prior_err = m360.eval.depth_metrics(alone, depth)["abs_rel"]
    plain = m360.eval.depth_metrics(m360.stitch(tiles, layout), depth)["abs_rel"]
    res = m360.stitch(tiles, layout, prior=prior, return_details=True)
    err = m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
    report = res.report["prior"]
    assert report is not None
    assert report["tangent_share"] == 1.0, report
    assert report["tangent_spread"] is not None and report["tangent_spread"] < 0.004, report
    assert err < 0.4 * prior_err and err < plain + 0.001, (err, prior_err, plain)

    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    wrong = syn.content_errors(exact, 11, regions=(2, 3), amplitude=(0.2, 0.3))
    rough = syn.distort(wrong, 7, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.0)
    report = m360.stitch(rough, layout, prior=prior, return_details=True).report["prior"]
    assert report is not None and report["tangent_share"] == 0.0, report
    assert report["tangent_spread"] is not None and report["tangent_spread"] > 0.012, report
    # One level: nothing solved without the prior first, so nothing measured or fused.
    report = m360.stitch(tiles, layout, align=[(4, 3)], prior=prior, return_details=True).report[
        "prior"
    ]
    assert report is not None and report["tangent_spread"] is None, report
    assert report["tangent_share"] == 0.0, report


def test_a_prior_worse_than_the_tangents_hands_them_its_low_frequencies() -> None:
    """The fusion weighs the prior's quality, not only the tangents': the same tangents (a
    +-10 % field each, spread about 0.011, so the spread's rule alone gives a share near 0.1)
    hand a +-15 % prior most of their low frequencies (the gap to their consensus is far larger
    than its own uncertainty) and a +-3 % prior little. The bad prior then does less harm than
    unfused and than no prior at all. A regional error (30 % on a fifth of the sphere) is not
    such evidence: the judgement outvotes it, and it must not hand the tangents the whole
    prior's shape (a share of 0.96 here before the evidence skipped the region's samples and the
    fusion's line its weight). On the paper's layout (samples seen by 4 tangents or fewer) only
    the rule decides: the shares are the same (docs/method.md, "The prior's own quality")."""
    scene = syn.room(1)

    def shares_and_errors(layout: m360.Layout) -> tuple[list[float], list[float], float, float]:
        exact = syn.tangent_perspective_disparity(scene, layout.cameras)
        tiles = syn.distort(exact, 7, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01)
        depth = scene.distance(sph.erp_directions(WIDTH // 2, WIDTH))
        shares, errors = [], []
        wrong = {"regions": (1, 1), "region_share": (0.2, 0.2), "region_amplitude": (0.3, 0.3)}
        for kw in ({"field": 0.03}, {"field": 0.03, **wrong}, {"field": 0.15}):
            prior = np.asarray(syn.panoramic_prior(scene, 5, **{"regions": (0, 0), **kw}))
            res = m360.stitch(tiles, layout, prior=prior, return_details=True)
            assert res.report["prior"] is not None
            shares.append(res.report["prior"]["tangent_share"])
            errors.append(m360.eval.depth_metrics(res.disparity, depth)["abs_rel"])
        off = m360.stitch(tiles, layout, prior=prior, prior_fusion="off")
        plain = m360.stitch(tiles, layout)
        return (
            shares,
            errors,
            m360.eval.depth_metrics(off, depth)["abs_rel"],
            m360.eval.depth_metrics(plain, depth)["abs_rel"],
        )

    shares, (_, err_wrong, err_bad), err_off, err_plain = shares_and_errors(
        m360.Layout.icosahedron(WIDTH)
    )
    good, wrong_share, bad = shares
    assert good < 0.3 and bad > good + 0.4, shares
    assert err_bad < 0.95 * err_off and err_bad < err_plain, (err_bad, err_off, err_plain)
    assert wrong_share < bad - 0.3 and err_wrong < 0.9 * err_plain, (shares, err_wrong, err_plain)

    (good, _, bad), *_ = shares_and_errors(m360.Layout.icosahedron(WIDTH, padding=0.3))
    assert good == bad, (good, bad)


def test_fusion_off_keeps_the_priors_low_frequencies(room: tuple) -> None:
    """prior_fusion="off": the prior is not moved towards the tangents however well they agree.
    With the same +-3 % prior as above the result then follows the prior's smooth error (worse
    than fused); the report says nothing was measured or moved."""
    layout, tiles, depth, scene = room
    prior = np.asarray(syn.panoramic_prior(scene, 5, regions=(0, 0)))
    fused = m360.stitch(tiles, layout, prior=prior, return_details=True)
    kept = m360.stitch(tiles, layout, prior=prior, prior_fusion="off", return_details=True)
    assert kept.report["prior"] is not None and fused.report["prior"] is not None
    assert kept.report["prior"]["tangent_share"] == 0.0
    assert kept.report["prior"]["tangent_spread"] is None
    assert fused.report["prior"]["tangent_share"] == 1.0
    err_fused = m360.eval.depth_metrics(fused.disparity, depth)["abs_rel"]
    err_kept = m360.eval.depth_metrics(kept.disparity, depth)["abs_rel"]
    assert err_kept > 1.25 * err_fused, (err_kept, err_fused)  # 0.0039 against 0.0029


def test_a_prior_with_a_regional_error_is_outvoted(room: tuple) -> None:
    """A prior 30 % wrong on a fifth of the sphere: most of the wrong region's samples lose
    their pull, and the result stays as good as without a prior. The outvoted share is about
    the region's plus what the hard judgement costs right samples beyond 1.2 sigma: 0.36 with
    the prior as given, 0.43 fused with these exact tangents (the prior's residual scale
    shrinks, so more right samples fall beyond it; the error is the lower: 0.00271 vs 0.00277)."""
    layout, tiles, depth, scene = room
    h = 64
    prior = 1.0 / _distance(scene, h)
    dirs = sph.erp_directions(h, 2 * h)
    region = dirs[..., 0] > 0.6  # a cap of ~20 % of the sphere
    prior = np.where(region, prior * 1.3, prior)
    plain = m360.eval.depth_metrics(m360.stitch(tiles, layout), depth)["abs_rel"]
    res = m360.stitch(tiles, layout, prior=prior, return_details=True)
    err = m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
    assert err < plain + 0.002, (err, plain)
    report = res.report["prior"]
    assert report is not None and 0.1 < report["outvoted"] < 0.5, report


#: The regional error of the issue's wrong prior: 30 % on a fifth of the sphere.
WRONG_REGION = {"regions": (1, 1), "region_share": (0.2, 0.2), "region_amplitude": (0.3, 0.3)}


def _content_room(width: int) -> tuple[m360.Layout, np.ndarray, syn.Scene]:
    """Room 1 on the default layout at ``width``, its tangents with content errors."""
    layout = m360.Layout.icosahedron(width)
    scene = syn.room(1)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    tiles = syn.distort(syn.content_errors(exact, 201, blur=0.5), 101, field=0.1, noise=0.01)
    return layout, tiles, scene


def _stitch_with_1_and_2_threads(
    tiles: np.ndarray, layout: m360.Layout, prior: np.ndarray, rounds: int
) -> list[m360.StitchResult]:
    """``rounds`` pairs of stitches with the prior, on 1 then 2 threads (restored after)."""
    before = m360.get_num_threads()
    runs = []
    try:
        for n in (1, 2) * rounds:
            m360.set_num_threads(n)
            runs.append(m360.stitch(tiles, layout, prior=prior, return_details=True))
    finally:
        m360.set_num_threads(before)
    return runs


def test_the_consensus_outvotes_a_wrong_region_before_the_prior_pulls() -> None:
    """Under content errors (no fusion: the tangents disagree), a prior sample far outside the
    tangents' consensus (3 of its standard errors and 6 % of the disparity, on its own and
    low-passed) loses its pull before the prior joins: a cap 30 % wrong on 14 % of the sphere
    has 10 % of the samples outvoted (at 1K; its border and the parts the consensus does not
    contradict stay with the judgement), a prior without regional errors none, and the wrong
    one does better than with the prior as given (``prior_fusion="off"``, which outvotes
    nothing)."""
    width = 1024
    layout, tiles, scene = _content_room(width)
    depth = _distance(scene, width // 2)
    good = np.asarray(syn.panoramic_prior(scene, 301, regions=(0, 0)))
    report = m360.stitch(tiles, layout, prior=good, return_details=True).report["prior"]
    assert report is not None and report["consensus_outvoted"] == 0.0, report
    wrong, regions = syn.panoramic_prior(scene, 301, return_regions=True, **WRONG_REGION)
    res = m360.stitch(tiles, layout, prior=wrong, return_details=True)
    report = res.report["prior"]
    assert report is not None and 0.05 < report["consensus_outvoted"] < np.mean(regions != 0)
    off = m360.stitch(tiles, layout, prior=wrong, prior_fusion="off", return_details=True)
    assert off.report["prior"] is not None and off.report["prior"]["consensus_outvoted"] == 0.0
    err = m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
    assert err < m360.eval.depth_metrics(off.disparity, depth)["abs_rel"]


def test_the_consensus_corrects_the_prior_s_largest_scales() -> None:
    """Under content errors (no fusion: the tangents disagree), a prior with a ±10 % smooth
    error, as poor as a panoramic network worse than the simulated one, has its shape at the
    sphere's largest scales (spherical harmonics of degree ≤ 2) moved towards the tangents'
    consensus before it joins, and the result is clearly better than with the prior as given
    (``prior_fusion="off"``: 0.0217 against 0.0278 here, no prior 0.029). The bench's prior
    (±3 %) strays from the consensus there by less than the consensus's own error and is left as
    it is; so is a prior with a regional error the consensus outvoted in bulk (a cap 30 % wrong
    on a fifth of the sphere: its terms of degree 1 and 2 would pass for a bend), whose gap is
    then not measured."""
    width = 1024
    layout, tiles, scene = _content_room(width)
    depth = _distance(scene, width // 2)
    poor = np.asarray(syn.panoramic_prior(scene, 301, field=0.1))
    res = m360.stitch(tiles, layout, prior=poor, return_details=True)
    report = res.report["prior"]
    assert report is not None and report["low_order_share"] > 0.3, report
    assert report["low_order_gap"] > 0.01, report
    off = m360.stitch(tiles, layout, prior=poor, prior_fusion="off", return_details=True)
    assert off.report["prior"] is not None and off.report["prior"]["low_order_share"] == 0.0
    err = m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
    assert err < 0.9 * m360.eval.depth_metrics(off.disparity, depth)["abs_rel"]
    good = np.asarray(syn.panoramic_prior(scene, 301))
    report = m360.stitch(tiles, layout, prior=good, return_details=True).report["prior"]
    assert report is not None and report["low_order_share"] == 0.0, report
    assert 0.0 < report["low_order_gap"] < 0.008, report  # measured, below the consensus's error
    wrong = np.asarray(syn.panoramic_prior(scene, 301, **WRONG_REGION))
    report = m360.stitch(tiles, layout, prior=wrong, return_details=True).report["prior"]
    assert report is not None and report["consensus_outvoted"] > 0.03, report
    assert report["low_order_share"] == 0.0 and report["low_order_gap"] == 0.0, report


def test_a_prior_outvoted_on_both_sides_is_bent_back() -> None:
    """A prior tilted ±20 % between floor and ceiling strays from the consensus most where it is
    bent most, on both sides: room 3 at 2K (the bench's content errors) has 12 % of its samples
    outvoted, beyond the 3 % that a one-sided regional error may have, and still has its largest
    scales corrected (0.020 against 0.066 with ``prior_fusion="off"``, no prior 0.027). The lower
    third 30 % too far is outvoted on one side (24 %) and left as it is."""
    width = 2048
    layout = m360.Layout.icosahedron(width)
    scene = syn.room(3)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    wrong = syn.content_errors(exact, 203, blur=1.0)
    tiles = syn.distort(wrong, 103, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01)
    depth = _distance(scene, width // 2)
    good = np.asarray(syn.panoramic_prior(scene, 303))
    latitude = 90.0 - (np.arange(good.shape[0]) + 0.5) * 180.0 / good.shape[0]
    tilted = good * (1.0 + 0.2 * np.sin(np.radians(latitude)))[:, None]
    res = m360.stitch(tiles, layout, prior=tilted, return_details=True)
    report = res.report["prior"]
    assert report is not None and report["consensus_outvoted"] > 0.06, report
    assert report["low_order_share"] > 0.5, report
    off = m360.stitch(tiles, layout, prior=tilted, prior_fusion="off")
    err = m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
    assert err < 0.5 * m360.eval.depth_metrics(off, depth)["abs_rel"]
    far = good * np.where(latitude < -30.0, 0.7, 1.0)[:, None]
    report = m360.stitch(tiles, layout, prior=far, return_details=True).report["prior"]
    assert report is not None and report["consensus_outvoted"] > 0.1, report
    assert report["low_order_share"] == 0.0 and report["low_order_gap"] == 0.0, report


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("scale_deg", [3.0, 10.0])
def test_a_wrong_region_of_the_prior_does_no_harm(seed: int, scale_deg: float) -> None:
    """A prior 30 % wrong on a fifth of the sphere, three rooms at 1K (the default layout runs
    the prior-only level there): over the whole map the result is within 0.002 of the stitch
    without the prior, and at the default split also inside the wrong region within 40 % of it.

    Two faults are held here. Undamped, the prior-only level followed the region's edges in where
    its samples had lost their pull (room 0: 0.0304 at 3° and 0.0615 at 10°, no prior 0.0255).
    Judged softly (Cauchy weights, never 0), the region kept pulling the schedule's levels:
    inside it 1.55 and 1.92 times the error without the prior in rooms 1 and 2, and over the
    whole map 0.0365 against 0.0294 (room 1 at 10°) and 0.0255 against 0.0233 (room 2 at 3°)."""
    width = 1024
    layout = m360.Layout.icosahedron(width)
    scene = syn.room(seed)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    wrong = syn.content_errors(exact, seed + 200, blur=0.5)
    tiles = syn.distort(wrong, seed + 100, field=0.1, noise=0.01)
    prior, regions = syn.panoramic_prior(
        scene,
        seed + 300,
        regions=(1, 1),
        region_share=(0.2, 0.2),
        region_amplitude=(0.3, 0.3),
        return_regions=True,
    )
    depth = _distance(scene, width // 2)
    # The region map at the prior's size, nearest to each result pixel.
    rows = np.arange(width // 2) * regions.shape[0] // (width // 2)
    cols = np.arange(width) * regions.shape[1] // width
    inside = regions[rows[:, None], cols[None, :]] != 0

    def errors(disparity: np.ndarray) -> tuple[float, float]:
        whole = m360.eval.depth_metrics(disparity, depth)["abs_rel"]
        return whole, m360.eval.depth_metrics(disparity, depth, valid=inside)["abs_rel"]

    plain, plain_inside = errors(m360.stitch(tiles, layout))
    err, err_inside = errors(m360.stitch(tiles, layout, prior=prior, prior_scale_deg=scale_deg))
    assert err < plain + 0.002, (err, plain)
    if scale_deg == 3.0:
        assert err_inside < 1.4 * plain_inside, (err_inside, plain_inside)


@pytest.mark.parametrize(
    ("options", "kind"),
    [
        ({"energy": "paper"}, "affine_disparity"),
        ({"solver": "lbfgs"}, "affine_depth"),
        ({"loss": "squared", "blend": "poisson"}, "affine_disparity"),
        ({"blend": "frustum"}, "negated_affine_disparity"),
    ],
)
def test_every_energy_solver_and_kind_runs(room: tuple, options: dict, kind: str) -> None:
    layout, tiles, depth, scene = room
    distance = _distance(scene, 32)
    prior = {"affine_depth": distance, "negated_affine_disparity": -2.0 / distance + 5.0}.get(
        kind, 1.0 / distance
    )
    res = m360.stitch(tiles, layout, prior=prior, prior_kind=kind, return_details=True, **options)
    assert res.report["prior"] is not None
    # The prior's sign understood: its fitted slope onto the result's disparity is positive.
    assert res.report["prior"]["affine"][0] > 0
    assert m360.eval.depth_metrics(res.disparity, depth)["abs_rel"] < 0.05


def test_masks_unknown_prior_regions_and_confidence(room: tuple) -> None:
    """NaN in the prior and masked tangent pixels are left out; confidence 0 ignores."""
    layout, tiles, depth, scene = room
    prior = 1.0 / _distance(scene, 64)
    prior[:20] = np.nan
    confidence = np.ones_like(prior)
    confidence[:, :40] = 0.0
    mask = np.ones(tiles.shape, bool)
    mask[:, :10] = False
    res = m360.stitch(
        tiles, layout, mask=mask, prior=prior, prior_confidence=confidence, return_details=True
    )
    assert res.report["prior"] is not None
    assert m360.eval.depth_metrics(res.disparity, depth)["abs_rel"] < 0.05


def test_confidence_combines_the_prior_gap_where_the_prior_is_known(room: tuple) -> None:
    """Root sum of squares with |d − (a·P + b)|, P read bilinearly with longitude wrapping
    and rows clamped, against an independent float64 computation: the mean blend ignores the
    vote, so its confidence without a prior is the one combined. Unchanged where the prior is
    unknown (NaN confidence: the core's unit test, blend/tests.rs)."""
    from m360.geometry.layout import plan_for

    layout, tiles, _, _ = room
    plan = plan_for(layout)
    rng = np.random.default_rng(3)
    prior = rng.uniform(0.5, 2.0, (16, 32)).astype(np.float32)
    prior[8:10, 3:6] = np.nan
    mean = {"method": "mean"}
    disparity, confidence, _ = plan.blend(tiles, mean)
    got_d, got, _ = plan.blend(tiles, mean, prior=prior, prior_affine=(1.5, 0.25))
    assert confidence is not None and got is not None and got.dtype == np.float32
    assert np.array_equal(got_d, disparity, equal_nan=True)
    eh, ew = disparity.shape
    hp, wp = prior.shape
    cols = np.mod((np.arange(ew) + 0.5) * wp / ew - 0.5, wp)
    rows = np.clip((np.arange(eh) + 0.5) * hp / eh - 0.5, 0, hp - 1)
    c0 = np.floor(cols).astype(int)
    r0 = np.minimum(np.floor(rows).astype(int), hp - 2)
    fx, fy = (cols - c0)[None, :], (rows - r0)[:, None]
    p = prior.astype(np.float64)
    top = (1 - fx) * p[r0][:, c0] + fx * p[r0][:, (c0 + 1) % wp]
    bottom = (1 - fx) * p[r0 + 1][:, c0] + fx * p[r0 + 1][:, (c0 + 1) % wp]
    resized = (1 - fy) * top + fy * bottom
    gap = np.abs(disparity - (1.5 * resized + 0.25))
    expected = confidence.copy()
    known = np.isfinite(gap) & np.isfinite(confidence)
    expected[known] = np.hypot(confidence[known], gap[known])
    assert (~np.isfinite(gap) & np.isfinite(confidence)).any()  # the prior's NaN reached some
    assert known.mean() > 0.5
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got[known], expected[known], rtol=1e-5)
    assert np.array_equal(got[~known], confidence[~known], equal_nan=True)


def test_one_and_two_threads_give_the_same_bits_with_a_prior(room: tuple) -> None:
    """Every output of a stitch with a prior (its vote, its fit, the combined confidence) is the
    same bit for bit with 1 and 2 threads: the thread count is a speed setting."""
    layout, tiles, _, scene = room
    prior = (1.0 / _distance(scene, 32)).astype(np.float32)
    prior[:3] = np.nan
    runs = _stitch_with_1_and_2_threads(tiles, layout, prior, rounds=5)
    for res in runs[1:]:
        assert np.array_equal(res.disparity, runs[0].disparity)
        assert np.array_equal(res.confidence, runs[0].confidence, equal_nan=True)
        assert res.report["prior"] == runs[0].report["prior"]


def test_the_consensus_outvotes_the_same_samples_with_1_and_2_threads() -> None:
    """The consensus's outvote (the default layout's deep overlaps, content errors, a wrong
    region) reads per-cell variances summed over samples: the same bits with 1 and 2 threads."""
    layout, tiles, scene = _content_room(WIDTH)
    wrong = np.asarray(syn.panoramic_prior(scene, 301, **WRONG_REGION))
    runs = _stitch_with_1_and_2_threads(tiles, layout, wrong, rounds=3)
    report = runs[0].report["prior"]
    assert report is not None and report["consensus_outvoted"] > 0.05, report  # the path ran
    for res in runs[1:]:
        assert np.array_equal(res.disparity, runs[0].disparity)
        assert res.report["prior"] == report


def test_a_partial_panorama_aligns_to_its_prior(room: tuple) -> None:
    """A panorama missing a cap (masked): the prior, known everywhere, still aligns the rest."""
    layout, tiles, depth, scene = room
    mask = np.ones(tiles.shape, bool)
    h = tiles.shape[1]
    mask[:, : h // 2] = False  # the top half of every tangent: a partial panorama
    prior = 1.0 / _distance(scene, 64)
    res = m360.stitch(tiles, layout, mask=mask, prior=prior, prior_kind="disparity",
                      return_details=True)  # fmt: skip
    assert res.report["prior"] is not None
    assert np.isnan(res.disparity).any()
    assert m360.eval.depth_metrics(res.disparity, depth)["abs_rel"] < 0.05


@pytest.mark.parametrize(
    ("prior", "kwargs", "message"),
    [
        (np.ones((10, 10), np.float32), {}, "width = 2 x height"),
        (np.ones((4, 8, 1), np.float32), {}, "ERP map of shape (H, W)"),
        (np.ones((8, 16), bool), {}, "dtype"),
        (np.full((8, 16), np.nan, np.float32), {}, "no usable value"),
        (np.ones((8, 16), np.float32), {"prior_kind": "depth"}, "choose one of"),
        (
            np.ones((8, 16), np.float32),
            {"prior_confidence": np.full((8, 16), 2.0)},
            "[0, 1]",
        ),
        (np.ones((8, 16), np.float32), {"prior_confidence": np.ones((4, 8))}, "must match"),
        (np.ones((8, 16), np.float32), {"align": "none"}, "needs alignment"),
        (-np.ones((8, 16), np.float32), {"prior_kind": "distance"}, "no usable value"),
    ],
)
def test_bad_priors_are_input_errors(
    room: tuple, prior: np.ndarray, kwargs: dict, message: str
) -> None:
    layout, tiles, _, _ = room
    with pytest.raises(m360.InputError, match=re.escape(message)):
        m360.stitch(tiles, layout, prior=prior, **kwargs)


def test_prior_options_are_checked() -> None:
    with pytest.raises(m360.InputError, match="prior_weight"):
        m360.StitchOptions(prior_weight=-1.0)
    with pytest.raises(m360.InputError, match="prior_scale_deg"):
        m360.StitchOptions(prior_scale_deg=100.0)
    opts = m360.StitchOptions(prior_weight=2.0)
    assert opts.align is not None and opts.align["prior_weight"] == 2.0


@pytest.mark.parametrize("energy", ["normalized", "paper"])
def test_prior_energy_gradient_matches_finite_differences(room: tuple, energy: str) -> None:
    """Through the bindings: the energy with a prior term (confidence, reweighted) against
    central differences of itself, at a point away from the identity."""
    layout, tiles, _, scene = room
    prior = (2.0 / _distance(scene, 32) + 0.5).astype(np.float32)
    confidence = np.linspace(0.2, 1.0, prior.size, dtype=np.float32).reshape(prior.shape)
    plan = plan_for(layout)
    maps = plan.spherical_disparity(tiles)
    options = {"energy": energy, "prior_weight": 3.0}
    _, _, x0 = plan.alignment_energy(maps, (4, 3), options, None, prior, confidence)
    rng = np.random.default_rng(0)
    x = np.asarray(x0, np.float64) + rng.uniform(-0.2, 0.2, len(x0))
    # The IRLS weights are taken at x and held for every evaluation.
    energy0, grad, _ = plan.alignment_energy(maps, (4, 3), options, x, prior, confidence, x)
    assert np.isfinite(energy0)
    h = 1e-6
    for i in [*range(0, len(x), 11), len(x) - 2, len(x) - 1]:  # the last two: (alpha, beta)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fp = plan.alignment_energy(maps, (4, 3), options, xp, prior, confidence, x)[0]
        fm = plan.alignment_energy(maps, (4, 3), options, xm, prior, confidence, x)[0]
        fd = (fp - fm) / (2 * h)
        assert abs(fd - grad[i]) <= 1e-5 * max(abs(grad[i]), 1e-3), (i, fd, grad[i])


def test_panoramic_prior_simulates_a_coarse_affine_network() -> None:
    """Without its errors the simulator returns the scene's disparity; each error is what it
    says: the affine map is global, the regions multiply their caps, the result is seeded."""
    scene = syn.room(2)
    exact = 1.0 / _distance(scene, 32)
    clean = syn.panoramic_prior(
        scene, 0, height=32, blur=0, field=0, scale=(1, 1), shift=0, regions=(0, 0)
    )
    assert np.allclose(clean, exact, rtol=1e-5)
    affine = syn.panoramic_prior(scene, 0, height=32, blur=0, field=0, regions=(0, 0))
    a, b = np.polyfit(exact.ravel(), np.asarray(affine).ravel(), 1)
    assert np.allclose(affine, a * exact + b, rtol=1e-4, atol=1e-6)
    wrong, regions = syn.panoramic_prior(
        scene, 0, height=32, blur=0, field=0, scale=(1, 1), shift=0, regions=(1, 1),
        region_share=(0.2, 0.2), region_amplitude=(0.3, 0.3), return_regions=True,
    )  # fmt: skip
    assert np.allclose(wrong, exact * (1 + regions), rtol=1e-5)
    assert np.isclose(np.abs(regions).max(), 0.3)
    # The cap covers a fifth of the sphere (solid angle, not ERP pixels).
    lat = (0.5 - (np.arange(32) + 0.5) / 32) * np.pi
    area = np.cos(lat)[:, None] * (regions != 0)
    assert abs(area.sum() / (np.cos(lat).sum() * 64) - 0.2) < 0.03
    again = syn.panoramic_prior(scene, 5, height=32)
    assert np.array_equal(again, syn.panoramic_prior(scene, 5, height=32))
    with pytest.raises(m360.InputError, match="field"):
        syn.panoramic_prior(scene, 0, field=1.0)
    with pytest.raises(m360.InputError, match="truth"):
        syn.panoramic_prior(np.ones((4, 4)), 0)
