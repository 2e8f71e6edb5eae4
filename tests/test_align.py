"""stitch(align=...): the alignment against ray-cast truth, for both energies and solvers."""

from __future__ import annotations

import functools

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from conftest import erp_depth, layout, tangent_disparity
from m360.align import MULTISCALE
from m360.errors import InputError
from m360.geometry import sphere as sph

WIDTH = 1024
SEEDS = (0, 1, 2)


@functools.lru_cache(maxsize=4)
def distorted(seed: int) -> np.ndarray:
    """The issue's distortion: scale ×[0.5, 2], shift ±30 % of the median, smooth ±10 % field,
    1 % noise, independently per tangent (in perspective disparity, as a network errs)."""
    return syn.distort(
        tangent_disparity(seed, WIDTH),
        seed + 100,
        scale=(0.5, 2.0),
        shift=0.3,
        field=0.1,
        noise=0.01,
    )


def abs_rel(disparity: np.ndarray, seed: int, width: int = WIDTH) -> float:
    return m360.eval.depth_metrics(disparity, erp_depth(seed, width))["abs_rel"]


@pytest.mark.parametrize("seed", SEEDS)
def test_exact_tangents_stay_at_the_resampling_floor(seed: int) -> None:
    lay = layout(WIDTH)
    floor = abs_rel(m360.stitch(tangent_disparity(seed, WIDTH), lay, "none", "mean"), seed)
    aligned = abs_rel(m360.stitch(tangent_disparity(seed, WIDTH), lay, blend="mean"), seed)
    paper = abs_rel(
        m360.stitch(tangent_disparity(seed, WIDTH), lay, blend="mean", energy="paper"), seed
    )
    print(f"seed {seed}: floor {floor:.4f}, default {aligned:.4f}, paper solved {paper:.4f}")
    assert aligned <= 0.003
    assert aligned <= floor + 0.001
    # The paper's energy, solved to its optimum, moves exact tangents off the floor.
    assert paper > 2 * aligned


def test_constant_affine_distortion_is_undone_exactly() -> None:
    """Per-tangent scale and shift (of perspective disparity) on a room without objects, whose
    depth is continuous: the result is GT up to one global affine map."""
    scene = syn.Scene(room_min=(-3.0, -1.2, -2.5), room_max=(4.0, 1.6, 5.0))
    lay = layout(WIDTH)
    exact = syn.tangent_perspective_disparity(scene, lay.cameras)
    tangents = syn.distort(exact, 7, scale=(0.5, 2.0), shift=0.3)
    depth = scene.distance(sph.erp_directions(*lay.erp_shape))
    assert (
        m360.eval.depth_metrics(m360.stitch(tangents, lay, "none", "mean"), depth)["abs_rel"] > 0.05
    )
    for solver in ("newton", "lbfgs"):
        out = m360.stitch(tangents, lay, blend="mean", solver=solver, iterations=2000)
        assert m360.eval.depth_metrics(out, depth)["abs_rel"] < 1e-3, solver


def test_distorted_tangents_are_aligned() -> None:
    lay = layout(WIDTH)
    rows = []
    for seed in SEEDS:
        none = abs_rel(m360.stitch(distorted(seed), lay, "none", "mean"), seed)
        default = abs_rel(m360.stitch(distorted(seed), lay, blend="mean"), seed)
        paper = abs_rel(
            m360.stitch(distorted(seed), lay, blend="mean", energy="paper", solver="lbfgs"), seed
        )
        rows.append((seed, none, default, paper))
        print(f"seed {seed}: none {none:.4f}  default {default:.4f}  paper (L-BFGS 50) {paper:.4f}")
    for seed, none, default, paper in rows:
        assert default <= 0.03, seed
        assert none >= 5 * default, seed
        assert default < paper, seed
    assert np.median([r[2] for r in rows]) <= 0.02


def test_details_report_and_grids() -> None:
    lay = layout(512)
    res = m360.stitch(tangent_disparity(0, 512), lay, blend="mean", return_details=True)
    assert isinstance(res, m360.StitchResult)
    levels = res.report["align"]
    assert [lvl["grid"] for lvl in levels] == [(4, 3), (8, 7)]
    assert [g.shape for g in res.grids] == [(20, 3, 4, 2), (20, 7, 8, 2)]
    paper = m360.stitch(
        tangent_disparity(0, 512), lay, blend="mean", energy="paper", return_details=True
    )
    assert isinstance(paper, m360.StitchResult)
    assert [g.shape for g in paper.grids] == [(20, 3, 4, 2), (20, 7, 8, 2), (20, 14, 16, 2)]
    three = m360.stitch(tangent_disparity(0, 512), lay, MULTISCALE, "mean")
    assert isinstance(three, np.ndarray)
    for lvl in levels:
        assert lvl["converged"]
        assert lvl["gradient_norm"] <= 1e-6 * max(1.0, abs(lvl["energy"]))
        assert lvl["energy"] <= lvl["initial_energy"]
        assert lvl["samples"] > 100
    assert all((g[..., 0] > 0).all() for g in res.grids)


def test_converged_only_when_the_gradient_criterion_holds() -> None:
    lay = layout(512)
    tangents = syn.distort(tangent_disparity(1, 512), 3, field=0.1)
    # Least squares: one solve per level (a robust loss solves each level again per reweighting).
    stopped = m360.stitch(
        tangents, lay, (8, 7), "mean", iterations=1, loss="squared", return_details=True
    )
    assert isinstance(stopped, m360.StitchResult)
    level = stopped.report["align"][0]
    assert level["iterations"] == 1
    assert level["converged"] == (level["gradient_norm"] <= 1e-6 * max(1.0, abs(level["energy"])))
    assert not level["converged"]


def test_lbfgs_and_newton_reach_the_same_energy() -> None:
    lay = layout(512)
    tangents = syn.distort(tangent_disparity(2, 512), 4, field=0.1)
    # Least squares: the robust loss's weights come from each solver's own first answer.
    newton = m360.stitch(
        tangents, lay, (4, 3), "mean", solver="newton", loss="squared", return_details=True
    )
    lbfgs = m360.stitch(
        tangents,
        lay,
        (4, 3),
        "mean",
        solver="lbfgs",
        loss="squared",
        iterations=20000,
        tolerance=1e-8,
        return_details=True,
    )
    assert isinstance(newton, m360.StitchResult) and isinstance(lbfgs, m360.StitchResult)
    en, el = newton.report["align"][0], lbfgs.report["align"][0]
    assert en["converged"] and el["converged"]
    assert el["energy"] == pytest.approx(en["energy"], rel=1e-6)
    assert en["iterations"] < el["iterations"]


def test_same_result_with_one_and_two_threads() -> None:
    lay = layout(512)
    tangents = syn.distort(tangent_disparity(0, 512), 5, field=0.1, noise=0.01)
    outs = []
    before = m360.get_num_threads()
    try:
        for n in (1, 2):
            m360.set_num_threads(n)
            for solver in ("newton", "lbfgs"):
                outs.append(m360.stitch(tangents, lay, blend="mean", solver=solver))
    finally:
        m360.set_num_threads(before)
    np.testing.assert_array_equal(outs[0], outs[2])
    np.testing.assert_array_equal(outs[1], outs[3])


def test_masked_pixels_do_not_affect_the_alignment() -> None:
    lay = layout(512)
    tangents = distorted_small = syn.distort(tangent_disparity(0, 512), 9, field=0.05)
    mask = np.ones(tangents.shape, bool)
    mask[4, 20:60, 30:80] = False
    poisoned = distorted_small.copy()
    poisoned[~mask] = 1e4
    nan = distorted_small.copy()
    nan[~mask] = np.nan
    np.testing.assert_array_equal(
        m360.stitch(poisoned, lay, blend="mean", mask=mask), m360.stitch(nan, lay, blend="mean")
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"align": (500, 3)}, "more nodes than the tangent"),
        ({"align": (1, 3)}, "at least 2"),
        ({"align": [(4, 3), (0, 2)]}, "at least 2"),
        ({"align": [(4, 3), (-8, 7)]}, "at least 2"),
        ({"align": []}, "not supported"),
        ({"align": (4.0, 3.0)}, "not supported"),
        ({"energy": "huber"}, "energy"),
        ({"solver": "adam"}, "solver"),
        ({"iterations": -1}, "iterations"),
        ({"sample_fraction": 2.0}, "sample_fraction"),
        ({"pole_cap_deg": 95.0}, "pole_cap_deg"),
        ({"scale_weight": 0.0}, "scale_weight"),
        ({"offsets": "radial"}, "offsets"),
        ({"mask": np.ones((20, 3, 3), bool)}, "mask"),
    ],
)
def test_bad_alignment_options(kwargs: dict, match: str) -> None:
    lay = layout(512)
    args = {"blend": "mean", **kwargs}
    with pytest.raises(InputError, match=match):
        m360.stitch(tangent_disparity(0, 512), lay, **args)


def test_an_all_invalid_tangent_is_an_input_error() -> None:
    lay = layout(512)
    tangents = tangent_disparity(0, 512).copy()
    tangents[6] = np.nan
    with pytest.raises(InputError, match="tangent 6 has no valid pixel"):
        m360.stitch(tangents, lay, blend="mean")
    mask = np.ones(tangents.shape, bool)
    mask[2] = False
    with pytest.raises(InputError, match="tangent 2"):
        m360.stitch(tangent_disparity(0, 512), lay, blend="mean", mask=mask)


def test_energy_matches_an_independent_scipy_assembly() -> None:
    """m360's reported energies equal the energy assembled from the exported terms with
    scipy.sparse, at the identity and at the solved fields (paper energy: fields not rescaled)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benches"))
    import align_scipy
    from m360.geometry import plan_for

    lay = layout(512)
    tangents = syn.distort(tangent_disparity(1, 512), 8, field=0.1)
    plan = plan_for(lay)
    spherical = plan.spherical_disparity(tangents)
    for energy, offsets in (("paper", "spherical"), ("normalized", "perspective")):
        weights = {"smoothness": 40.0, "scale_weight": 0.007, "sample_fraction": 0.01}
        problem = plan.alignment_problem(
            spherical, (4, 3), {"energy": energy, "offsets": offsets, **weights}
        )
        f = align_scipy.energy_function(problem)
        res = m360.stitch(
            tangents, lay, (4, 3), "mean", energy=energy, offsets=offsets, smoothness=40.0,
            scale_weight=0.007, return_details=True,
        )  # fmt: skip
        assert isinstance(res, m360.StitchResult)
        level = res.report["align"][0]
        assert level["samples"] == len(problem["nodes"])
        e0, _ = f(align_scipy.identity(problem))
        assert level["initial_energy"] == pytest.approx(e0, rel=1e-9)
        if energy == "paper":
            e1, g1 = f(res.grids[0].reshape(-1))
            assert level["energy"] == pytest.approx(e1, rel=1e-9)
            assert np.abs(g1).max() == pytest.approx(level["gradient_norm"], rel=1e-4, abs=1e-10)


def test_aligning_in_place_gives_the_same_maps_and_refuses_read_only_ones() -> None:
    from m360.geometry import plan_for

    lay = layout(512)
    plan = plan_for(lay)
    spherical = plan.spherical_disparity(syn.distort(tangent_disparity(2, 512), 9, field=0.1))
    options = {"energy": "normalized"}
    copy, _, grids, _ = plan.align(spherical, options)
    before = spherical.copy()
    same, _, grids_in_place, _ = plan.align(spherical, options, in_place=True)
    assert same is spherical
    np.testing.assert_array_equal(spherical, copy)
    assert not np.array_equal(before, copy, equal_nan=True)  # the alignment moved the maps
    for g, h in zip(grids, grids_in_place, strict=True):
        np.testing.assert_array_equal(g, h)
    before.flags.writeable = False
    with pytest.raises(InputError, match="in place"):
        plan.align(before, options, in_place=True)
    with pytest.raises(InputError, match="C-contiguous"):
        plan.align(np.asfortranarray(before.copy()), options, in_place=True)


def test_the_core_refuses_fortran_ordered_arrays_instead_of_misreading_them() -> None:
    from m360.geometry import plan_for

    lay = layout(256)
    plan = plan_for(lay)
    maps = np.random.default_rng(0).random((20, *lay.tangent_shape), dtype=np.float32)
    fortran = np.asfortranarray(maps)  # contiguous, but not in C order
    for call in (
        lambda: plan.spherical_disparity(fortran),
        lambda: plan.align(fortran, {}),
        lambda: plan.blend(fortran, {}),
    ):
        with pytest.raises(InputError, match="C-contiguous"):
            call()
