"""Panoramic estimators (ERP in, ERP out) and m360.estimate with one (issue 24).

Every expected value comes from an independent oracle: constant or block-wise images whose
network input is known in closed form, graphs whose output is the probe corridor's true ERP
distance, and a ray-cast room whose photo encodes its own distance (m360.evaluation.synthetic).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
from m360.errors import InputError, ModelError
from m360.estimators import (
    PANORAMIC_OUTPUT_KINDS,
    OnnxEstimator,
    PanoramicOnnxEstimator,
    _probe,
    load_estimator,
    to_spherical_disparity,
)
from m360.evaluation import synthetic

MEAN = np.array(m360.models.IMAGENET_MEAN)
STD = np.array(m360.models.IMAGENET_STD)


@pytest.fixture(scope="module")
def graphs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("pano_graphs")
    out = {
        "dynamic": g.affine_of_mean(folder / "dynamic.onnx", 2.0, 1.0),
        "fixed": g.affine_of_mean(folder / "fixed.onnx", 2.0, 1.0, input_shape=(1, 3, 32, 64)),
        "negative": g.affine_of_mean(folder / "negative.onnx", 1.0, -5.0),
        "nhwc": g.affine_of_mean(folder / "nhwc.onnx", 1.0, 0.0, input_shape=(1, "H", "W", 3)),
    }
    for kind in ("distance", "disparity", "scaled_distance", "scaled_disparity"):
        out[kind] = g.erp_oracle(folder / f"{kind}.onnx", kind)
    return out


# --------------------------------------------------------------------------------------------
# Output kinds.


def test_spherical_disparity_of_each_kind() -> None:
    d = np.array([[1.0, 2.0, 4.0, np.nan], [0.5, 8.0, -1.0, 0.0]], np.float32)
    d = np.tile(d, (1, 2))  # (2, 8)
    inv = to_spherical_disparity(d, "distance")
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = np.where(d > 0, 1.0 / d, np.nan)
    np.testing.assert_allclose(inv, expected, rtol=1e-6)
    disp = to_spherical_disparity(d, "disparity")  # metric: ≤ 0 is no estimate
    np.testing.assert_array_equal(np.isnan(disp), ~(np.nan_to_num(d, nan=-1) > 0))
    affine = to_spherical_disparity(d, "affine_disparity")  # passes through, sign and all
    np.testing.assert_array_equal(affine[np.isfinite(d)], d[np.isfinite(d)])
    negated = to_spherical_disparity(d, "negated_affine_disparity")  # sign flipped, no more
    np.testing.assert_array_equal(negated[np.isfinite(d)], -d[np.isfinite(d)])
    assert np.isnan(negated[~np.isfinite(d)]).all()
    # affine_depth: robust minimum (1st percentile) to 0.1 x the robust range, then 1/x.
    finite = d[np.isfinite(d)].astype(np.float64)
    lo, hi = np.percentile(finite, [1.0, 99.0])
    shifted = np.maximum(d.astype(np.float64) - lo, 0.0) + 0.1 * (hi - lo)
    np.testing.assert_allclose(
        to_spherical_disparity(d, "affine_depth"), 1.0 / shifted, rtol=1e-5, equal_nan=True
    )


def test_metric_depth_is_refused_for_erp_outputs(graphs: dict[str, Path]) -> None:
    with pytest.raises(InputError, match="no optical axis"):
        to_spherical_disparity(np.ones((4, 8)), "metric_depth")
    with pytest.raises(InputError, match=r"no optical axis.*'distance'"):
        load_estimator(graphs["dynamic"], kind="panoramic", output_kind="metric_depth")
    with pytest.raises(InputError, match="panoramic models"):
        load_estimator(graphs["dynamic"], output_kind="disparity")  # a tangent model
    with pytest.raises(InputError, match="estimator kind"):
        load_estimator(graphs["dynamic"], kind="spherical")
    assert set(PANORAMIC_OUTPUT_KINDS) == {
        "affine_disparity",
        "disparity",
        "affine_depth",
        "distance",
        "negated_affine_disparity",
    }


# --------------------------------------------------------------------------------------------
# PanoramicOnnxEstimator: sizes, values, kinds.


def test_fixed_size_runs_at_its_size_and_resizes_the_erp(graphs: dict[str, Path]) -> None:
    est = load_estimator(graphs["fixed"], kind="panoramic", output_kind="affine_disparity")
    assert isinstance(est, PanoramicOnnxEstimator) and est.kind == "panoramic"
    assert est.network_size((1024, 2048)) == (32, 64)
    # Rows brighten downwards in blocks of 4: an area resize by 4 keeps each block's value,
    # so the network sees exactly the block values (and the top stays at the top).
    rows = np.repeat(np.arange(32, dtype=np.uint8) * 8, 4)
    erp = np.repeat(np.repeat(rows[:, None], 256, axis=1)[..., None], 3, axis=2)
    out = est.predict(erp)
    assert out.shape == (32, 64) and out.dtype == np.float32
    level = (np.arange(32) * 8 / 255.0)[:, None]
    expected = 2.0 * ((level - MEAN) / STD).mean(axis=1) + 1.0  # a · mean of normalised + b
    np.testing.assert_allclose(out, np.repeat(expected[:, None], 64, axis=1), atol=1e-5)
    with pytest.raises(InputError, match="fixed 32x64"):
        load_estimator(graphs["fixed"], kind="panoramic", input_size=(64, 128))


@pytest.mark.parametrize(
    ("options", "size"),
    [
        ({}, (512, 1024)),  # the panoramic default, not the tangents' 384 x 384
        ({"input_size": (64, 128)}, (64, 128)),
        ({"input_size": (100, 200), "multiple_of": 32}, (96, 192)),
        ({"input_size": (100, 100), "resize": "cover", "multiple_of": 14}, (112, 210)),
        ({"input_size": (40, 60), "resize": "exact"}, (40, 60)),
    ],
)
def test_dynamic_size_rules(graphs: dict[str, Path], options: dict, size: tuple) -> None:
    est = load_estimator(graphs["dynamic"], kind="panoramic", normalize="unit", **options)
    assert est.network_size((256, 512)) == size
    erp = np.full((256, 512, 3), 51, np.uint8)  # 0.2 in [0, 1]
    out = est.predict(erp)
    assert out.shape == size  # its own resolution: the caller upsamples
    np.testing.assert_allclose(out, 2.0 * 0.2 + 1.0, atol=1e-5)


@pytest.mark.parametrize("multiple_of", [1, 4])
def test_a_dynamic_network_sees_across_the_seam(tmp_path: Path, multiple_of: int) -> None:
    """A convolution without circular padding (a box filter along rows, zero beyond the
    borders) gives at 0/360° what a circular one gives: the ERP is run with columns wrapped onto
    each side, cropped back and cross-faded near the seam. Oracle: the circular box filter of
    channel 0 in numpy."""
    radius = 1
    est = load_estimator(
        g.row_box(tmp_path / "box.onnx", radius),
        kind="panoramic",
        output_kind="affine_disparity",
        normalize="unit",
        input_size=(16, 32),
        multiple_of=multiple_of,
    )
    rng = np.random.default_rng(5)
    erp = rng.integers(0, 256, (16, 32, 3), dtype=np.uint8)
    assert est.network_size(erp.shape[:2]) == (16, 32)  # no resize: the oracle is exact
    red = erp[..., 0].astype(np.float64) / 255.0
    circular = sum(np.roll(red, s, axis=1) for s in range(-radius, radius + 1)) / (2 * radius + 1)
    out = est.predict(erp)
    assert out.shape == (16, 32)
    np.testing.assert_allclose(out, circular, rtol=1e-5, atol=1e-6)
    # Without the context the border columns differ: the test can fail.
    zero = est.run_network(est.network_input(erp[None].astype(np.float32) / 255.0))[0]
    assert np.abs(zero[:, 0] - circular[:, 0]).max() > 0.01


def test_a_network_whose_columns_do_not_map_runs_as_it_is_once_per_call(tmp_path: Path) -> None:
    """A strided network (3 input columns per output column): with the seam's context wrapped
    on (4 columns each side of 32) the panorama's columns are no whole slice of the output, so
    it runs on the ERP as it is; that is found on the first call and remembered."""
    est = load_estimator(
        g.column_stride(tmp_path / "stride.onnx", 3),
        kind="panoramic",
        output_kind="affine_disparity",
        normalize="unit",
        input_size=(16, 32),
    )
    runs: list[tuple[int, ...]] = []
    run = est._run

    def counted(x: np.ndarray) -> np.ndarray:
        runs.append(tuple(x.shape))
        return run(x)

    est._run = counted  # type: ignore[method-assign]
    erp = np.random.default_rng(2).integers(0, 256, (16, 32, 3), dtype=np.uint8)
    red = erp[..., 0].astype(np.float64) / 255.0
    oracle = red[:, :30].reshape(16, 10, 3).mean(axis=2)
    first = est.predict(erp)
    assert [r[-1] for r in runs] == [40, 32]  # wrapped, then as it is
    np.testing.assert_allclose(first, oracle, rtol=1e-5, atol=1e-6)
    runs.clear()
    np.testing.assert_array_equal(est.predict(erp), first)
    assert [r[-1] for r in runs] == [32]


def test_nhwc_and_detected_normalisation(graphs: dict[str, Path], tmp_path: Path) -> None:
    import norm_graphs

    nhwc = load_estimator(graphs["nhwc"], kind="panoramic", normalize="unit", input_size=(8, 16))
    np.testing.assert_allclose(nhwc.predict(np.full((16, 32, 3), 255, np.uint8)), 1.0, atol=1e-6)
    # A graph that normalises its own input (ImageNet): m360 feeds RGB in [0, 1] only, and the
    # network core sees (x - mean) / std of channel 0.
    path = norm_graphs.chain_then_channel(
        tmp_path / "normalising.onnx",
        0,
        [("Sub", MEAN.reshape(1, 3, 1, 1), "init"), ("Div", STD.reshape(1, 3, 1, 1), "init")],
        input_shape=(1, 3, 8, 16),
    )
    est = load_estimator(path, kind="panoramic")
    assert est.normalization.source == "graph"
    out = est.predict(np.full((64, 128, 3), 255, np.uint8))
    np.testing.assert_allclose(out, (1.0 - MEAN[0]) / STD[0], rtol=1e-5)


def test_metric_kinds_mark_non_positive_values(graphs: dict[str, Path]) -> None:
    erp = np.full((64, 128, 3), 128, np.uint8)  # output 128/255 - 5 < 0 everywhere
    for kind, invalid in (("distance", True), ("disparity", True), ("affine_depth", False)):
        est = load_estimator(
            graphs["negative"],
            kind="panoramic",
            output_kind=kind,
            normalize="unit",
            input_size=(16, 32),
        )
        out = est.predict(erp)
        assert np.isnan(out).all() == invalid
        if not invalid:
            np.testing.assert_allclose(out, 128 / 255 - 5.0, atol=1e-5)


def test_estimator_objects_and_kind_checks(graphs: dict[str, Path]) -> None:
    class Pano:
        kind = "panoramic"
        output_kind = "distance"

        def predict(self, erp: np.ndarray) -> np.ndarray:
            return np.ones((8, 16), np.float32)

    class Tiles:
        output_kind = "affine_disparity"

        def predict(self, tangents: np.ndarray) -> np.ndarray:
            return np.ones(tangents.shape[:3], np.float32)

    pano = Pano()
    assert load_estimator(pano) is pano and load_estimator(pano, kind="panoramic") is pano
    with pytest.raises(InputError, match="panoramic estimator"):
        load_estimator(pano, kind="tangent")
    with pytest.raises(InputError, match="tangent estimator"):
        load_estimator(Tiles(), kind="panoramic")
    bad = Pano()
    bad.output_kind = "metric_depth"  # type: ignore[misc]
    with pytest.raises(InputError, match="no optical axis"):
        load_estimator(bad)
    # A registry (tangent) model refuses kind="panoramic" before anything is fetched.
    with pytest.raises(InputError, match="tangent model"):
        load_estimator("midas-v21-small", kind="panoramic")
    assert isinstance(load_estimator(graphs["dynamic"]), OnnxEstimator)
    assert load_estimator(graphs["dynamic"]).kind == "tangent"


# --------------------------------------------------------------------------------------------
# m360 models check on panoramic models.


@pytest.mark.parametrize(
    ("graph", "kind"),
    [
        ("distance", "distance"),
        ("disparity", "disparity"),
        ("scaled_distance", "affine_depth"),
        ("scaled_disparity", "affine_disparity"),
    ],
)
def test_models_check_guesses_each_panoramic_kind(
    graphs: dict[str, Path], graph: str, kind: str
) -> None:
    info = m360.models.check(graphs[graph], kind="panoramic")
    assert info["kind"] == "panoramic" and info["usable"]
    assert info["tangent_shape"] == [1024, 2048]  # the whole ERP is the network's image
    assert info["network_size"] == [32, 64]  # the file's fixed size
    assert info["degrees_per_pixel"] == 5.625  # 360° over 64 pixels
    assert info["kind_guess"]["kind"] == kind
    assert info["flags"] == {"output_kind": kind}
    assert info["options"] == {"kind": "panoramic", "output_kind": kind}


def test_models_check_probes_a_dynamic_panoramic_size_rule(tmp_path: Path) -> None:
    import check_graphs

    info = m360.models.check(check_graphs.unet(tmp_path / "unet.onnx", 5), kind="panoramic")
    assert info["network_size"] == [512, 1024]
    assert info["size_rule"] == 32  # 2**5 downsamplings
    assert info["usable"]


def test_models_check_cli_prints_panoramic_use(graphs: dict[str, Path], capsys) -> None:
    from m360.cli import main

    code = main(["models", "check", str(graphs["distance"]), "--model-kind", "panoramic"])
    out = capsys.readouterr().out
    assert code == 0
    assert "--model-kind panoramic --output-kind distance" in out
    assert f"--prior {graphs['distance']} --prior-kind distance" in out
    # What feeds it, as the prior's own flags (m360 run --prior-normalize …).
    code = main(["models", "check", str(graphs["distance"]), "--model-kind", "panoramic",
                 "--normalize", "unit", "--threads", "1"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0
    line = next(ln for ln in out.splitlines() if ln.startswith("as a prior:"))
    assert line.endswith(
        f"--prior {graphs['distance']} --prior-kind distance --prior-normalize unit"
    ), line  # its threads are the main model's: not a prior flag


# --------------------------------------------------------------------------------------------
# m360.estimate with a panoramic model.


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray, float]:
    """A ray-cast room at 256 x 512 and a photo whose grey level is its distance / dmax."""
    _, distance = synthetic.render(synthetic.room(0), 512)
    dmax = float(np.nanmax(distance)) * 1.05
    grey = np.clip(np.round(distance / dmax * 255), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2), distance.astype(np.float64), dmax


def _encoder(path: Path, dmax: float, kind: str) -> Path:
    # The network reads the distance back from the grey level (RGB in [0, 1] · dmax).
    if kind == "distance":
        return g.affine_of_mean(path, dmax, 0.0)
    return g.affine_of_mean(path, 3.0 * dmax, 10.0)  # affine_depth: scale 3, shift 10


def test_estimate_runs_once_and_upsamples_to_the_photo(
    room: tuple[np.ndarray, np.ndarray, float], tmp_path: Path
) -> None:
    photo, distance, dmax = room
    model = _encoder(tmp_path / "encoder.onnx", dmax, "distance")
    res = m360.estimate(
        photo,
        model,
        kind="panoramic",
        output_kind="distance",
        normalize="unit",
        input_size=(64, 128),
    )
    assert res.disparity.shape == res.depth.shape == res.confidence.shape == (256, 512)
    assert res.units == "metres" and res.scale == {"method": "network"}
    assert res.layout is None and res.stitch is None and res.tangents is None
    assert res.model["kind"] == "panoramic" and res.model["output_shape"] == [64, 128]
    assert res.options["network_output_shape"] == [64, 128] and res.options["upsample"] == "guided"
    rel = np.abs(res.depth - distance) / distance
    # The network saw a 4x smaller photo: away from depth edges the distance comes back within
    # the grey level's quantisation (dmax / 255 / d, about 1 %).
    assert np.nanmedian(rel) < 0.01
    assert np.isfinite(res.depth).mean() > 0.99
    # Guided upsampling follows the photo's edges: better than bilinear near them.
    bilinear = m360.estimate(
        photo,
        model,
        kind="panoramic",
        output_kind="distance",
        normalize="unit",
        input_size=(64, 128),
        upsample="bilinear",
    )
    edges = _edge_band(distance)
    guided_err = np.nanmean(rel[edges])
    bilinear_err = np.nanmean((np.abs(bilinear.depth - distance) / distance)[edges])
    assert guided_err < bilinear_err


def _edge_band(distance: np.ndarray) -> np.ndarray:
    import cv2

    jump = np.zeros(distance.shape, bool)
    jump[:, 1:] |= np.abs(np.diff(distance, axis=1)) > 0.1 * distance[:, 1:]
    jump[1:] |= np.abs(np.diff(distance, axis=0)) > 0.1 * distance[1:]
    return cv2.dilate(jump.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def test_estimate_affine_kind_is_relative_and_right_up_to_affine(
    room: tuple[np.ndarray, np.ndarray, float], tmp_path: Path
) -> None:
    photo, distance, dmax = room
    model = _encoder(tmp_path / "affine.onnx", dmax, "affine_depth")
    res = m360.estimate(
        photo,
        model,
        kind="panoramic",
        output_kind="affine_depth",
        normalize="unit",
        input_size=(64, 128),
    )
    assert res.units == "relative" and res.scale is None
    # affine_depth: 1/(a d + b') for some a, b' (the robust shift): depth is affine in d.
    ok = np.isfinite(res.depth)
    a, b = np.polyfit(distance[ok], res.depth[ok], 1)
    fitted = (res.depth - b) / a
    assert a > 0 and np.nanmedian(np.abs(fitted - distance) / distance) < 0.01


def test_estimate_panoramic_masks_sky_scale_and_refusals(
    room: tuple[np.ndarray, np.ndarray, float], tmp_path: Path
) -> None:
    photo, distance, dmax = room
    model = load_estimator(
        _encoder(tmp_path / "m.onnx", dmax, "distance"),
        kind="panoramic",
        output_kind="distance",
        normalize="unit",
        input_size=(64, 128),
    )
    res = m360.estimate(photo, model, mask=m360.masks.nadir(30))
    lat = 90.0 - (np.arange(256) + 0.5) * 180.0 / 256  # row centres' latitude
    np.testing.assert_array_equal(np.isnan(res.disparity).all(axis=1), lat < -60.0)
    assert res.options["masked_fraction"] > 0
    assert res.model["network_size"] == [64, 128] and res.model["degrees_per_pixel"] == 2.8125
    half = m360.estimate(photo, model, scale=m360.scale.metric_map(distance / 2.0))
    ok = np.isfinite(half.depth) & np.isfinite(res.depth)
    np.testing.assert_allclose(np.median(half.depth[ok] / distance[ok]), 0.5, rtol=0.02)
    with pytest.raises(InputError, match="layout, padding and subdivisions do not apply"):
        m360.estimate(photo, model, layout=m360.geometry.default_layout(512))
    with pytest.raises(InputError, match="layout, padding and subdivisions do not apply"):
        m360.estimate(photo, model, subdivisions=1)
    cv2.imwrite(str(tmp_path / "pano.png"), np.ascontiguousarray(photo[:, :, ::-1]))
    with pytest.raises(InputError, match="padding and subdivisions do not apply"):
        m360.batch.run(tmp_path / "pano.png", tmp_path / "out", model=model, subdivisions=1)
    with pytest.raises(InputError, match="tangent mask"):
        m360.estimate(photo, model, mask=np.ones((20, 8, 8), bool))
    with pytest.raises(InputError, match="prior goes with a tangent model"):
        m360.estimate(photo, model, prior=np.ones((8, 16)), prior_kind="distance")


def test_estimate_panoramic_sidecar_round_trip(
    room: tuple[np.ndarray, np.ndarray, float], tmp_path: Path
) -> None:
    photo, _, dmax = room
    path = _encoder(tmp_path / "m.onnx", dmax, "distance")
    res = m360.estimate(
        photo,
        path,
        kind="panoramic",
        output_kind="distance",
        normalize="unit",
        input_size=(32, 64),
    )
    m360.save(res, tmp_path / "out" / "pano")
    back = m360.load(tmp_path / "out" / "pano")
    np.testing.assert_array_equal(back.depth, res.depth)
    assert back.metadata["model"]["kind"] == "panoramic"
    assert back.metadata["units"] == "metres" and back.metadata["layout"] is None


def test_a_broken_panoramic_model_is_a_model_error(
    room: tuple[np.ndarray, np.ndarray, float],
) -> None:
    photo = room[0]

    class Wrong:
        kind = "panoramic"
        output_kind = "distance"

        def predict(self, erp: np.ndarray) -> np.ndarray:
            return np.ones((3, 8, 16), np.float32)  # not one map

    class Raises(Wrong):
        def predict(self, erp: np.ndarray) -> np.ndarray:
            raise RuntimeError("boom")

    class Empty(Wrong):
        def predict(self, erp: np.ndarray) -> np.ndarray:
            return np.zeros((8, 16), np.float32)  # distance 0: no estimate anywhere

    with pytest.raises(ModelError, match="one float"):
        m360.estimate(photo, Wrong())
    with pytest.raises(ModelError, match="RuntimeError: boom"):
        m360.estimate(photo, Raises())
    with pytest.raises(ModelError, match="too few valid pixels"):
        m360.estimate(photo, Empty())
    assert _probe.erp_views((8, 16))[0][0].shape == (8, 16, 3)


@pytest.mark.parametrize("kind", [np.array(["a", "b"]), np.array(["metric_depth"] * 2), 3, None])
def test_an_output_kind_that_is_no_string_is_an_input_error(kind: object) -> None:
    # An array compared with == gives an array, whose truth value raised ValueError (found by
    # tests/test_fuzz.py): the kind checks must answer InputError for any object.
    from m360.estimators.kinds import check_output_kind, check_panoramic_output_kind

    with pytest.raises(InputError, match="output_kind"):
        check_output_kind(kind)
    with pytest.raises(InputError, match="output_kind"):
        check_panoramic_output_kind(kind)
