"""The global prior's plumbing: m360.estimate, m360.batch.run (both engines) and m360 run (#24).

What reaches :func:`m360.stitch` is recorded by wrapping the stitch the pipeline calls
(``m360.pipeline.checks.stitch``): the prior map, its kind and its trust, checked against
independent oracles (block means, the probe corridor's true ERP distance, the masks' latitude
bands). Where the installed stitch takes no prior yet, the wrapper drops it before calling it.
"""

from __future__ import annotations

import hashlib
import inspect
import json
from pathlib import Path
from typing import Any

import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
import ray_helpers
import real_data
from check_graphs import unet
from m360.cli import main
from m360.errors import InputError, ModelError
from m360.estimators import SimulatedEstimator, _probe, load_estimator
from m360.evaluation import synthetic
from m360.pipeline import checks, memory

WIDTH = 512
#: One coarse alignment level and a row blend: quick (a prior acts through the alignment).
FAST = {"align": (4, 3), "blend": "frustum"}
#: Whether the installed m360.stitch takes a prior (the alignment's prior term).
STITCH_TAKES_PRIOR = "prior" in inspect.signature(m360.stitch).parameters


@pytest.fixture
def stitched(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Record the prior keywords of every stitch the pipeline runs (in this process)."""
    calls: list[dict[str, Any]] = []
    real = checks.stitch

    def recording(*args: Any, **keywords: Any) -> Any:
        calls.append({k: v for k, v in keywords.items() if k.startswith("prior")})
        if not STITCH_TAKES_PRIOR:
            keywords = {k: v for k, v in keywords.items() if not k.startswith("prior")}
        return real(*args, **keywords)

    monkeypatch.setattr(checks, "stitch", recording)
    return calls


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray, Any]:
    scene = synthetic.room(0)
    rgb, distance = synthetic.render(scene, WIDTH)
    return rgb, distance, scene


@pytest.fixture(scope="module")
def network(room: tuple[np.ndarray, np.ndarray, Any]) -> SimulatedEstimator:
    return SimulatedEstimator(room[2], m360.geometry.default_layout(WIDTH), seed=0)


@pytest.fixture(scope="module")
def priors(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("priors")
    return {
        "distance": g.erp_oracle(folder / "distance.onnx", "distance"),
        "scaled": g.erp_oracle(folder / "scaled.onnx", "scaled_distance"),
        "broken": _write(folder / "broken.onnx", b"<html>not found</html>"),
    }


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _sha(values: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(values, dtype=np.float32).tobytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# m360.estimate.


def test_an_array_prior_reaches_every_stitch_as_given(
    room: tuple, network: SimulatedEstimator, stitched: list
) -> None:
    rgb, distance, _ = room
    prior = np.ascontiguousarray(distance[::4, ::4], dtype=np.float32)  # (64, 128)
    prior[10:20, 30:60] = np.nan  # unknown there
    trust = np.linspace(0, 1, prior.size, dtype=np.float32).reshape(prior.shape)
    res = m360.estimate(
        rgb, network, prior=prior, prior_kind="distance", prior_confidence=trust, **FAST
    )
    assert len(stitched) >= 1
    for call in stitched:
        assert call["prior_kind"] == "distance"
        np.testing.assert_array_equal(call["prior"], prior)  # NaN where unknown, as given
        np.testing.assert_array_equal(call["prior_confidence"], trust)
    record = res.options["prior"]
    assert record == {
        "kind": "distance",
        "source": "array",
        "shape": [64, 128],
        "sha256": _sha(prior),
        "confidence_sha256": _sha(trust),
        "used_shape": [64, 128],
    }
    # A prior in metres gives the result its metres: no anchoring on the tangents.
    assert res.units == "metres" and res.scale == {"method": "prior", "prior_kind": "distance"}
    assert res.checks["anchor"] is None
    assert "prior" in res.timings


def test_a_relative_prior_keeps_the_tangents_anchoring(
    room: tuple, network: SimulatedEstimator, stitched: list
) -> None:
    rgb, distance, _ = room
    prior = (3.0 / distance[::2, ::2] + 1.0).astype(np.float32)
    res = m360.estimate(rgb, network, prior=prior, prior_kind="affine_disparity")
    assert stitched[0]["prior_kind"] == "affine_disparity" and "prior_confidence" not in stitched[0]
    assert res.units == "relative" and res.scale is None
    assert res.checks["anchor"] is not None


@pytest.mark.skipif(not STITCH_TAKES_PRIOR, reason="the installed m360.stitch takes no prior yet")
def test_a_metric_prior_gives_the_result_its_metres_end_to_end(
    room: tuple, network: SimulatedEstimator
) -> None:
    rgb, distance, _ = room
    # The prior says the room is twice as large as it is (the simulated network's own scale is
    # about 1: without a prior its depth is within 10 % of the truth's median).
    coarse = 2.0 * cv2.resize(distance, (128, 64), interpolation=cv2.INTER_AREA)
    res = m360.estimate(rgb, network, prior=coarse, prior_kind="distance")
    assert res.units == "metres"
    ok = np.isfinite(res.depth)
    # No scale or shift fitted here: the metres come from the prior through the stitch.
    ratio = res.depth[ok] / distance[ok]
    assert abs(float(np.median(ratio)) - 2.0) < 0.1
    abs_rel = float(np.mean(np.abs(res.depth[ok] / 2.0 - distance[ok]) / distance[ok]))
    assert abs_rel < 0.05, abs_rel


def test_a_large_prior_is_shrunk_to_the_working_erp(
    room: tuple, stitched: list, tmp_path: Path
) -> None:
    rgb, distance, scene = room
    layout = m360.geometry.default_layout(128)
    network = SimulatedEstimator(scene, layout, seed=0)
    prior = distance.astype(np.float32)  # (256, 512): four times the working ERP's size
    res = m360.estimate(rgb, network, prior=prior, prior_kind="distance", working_width=128, **FAST)
    given = stitched[0]["prior"]
    assert given.shape == (64, 128) == layout.erp_shape
    block_means = prior.reshape(64, 4, 128, 4).mean(axis=(1, 3))  # INTER_AREA by 4
    np.testing.assert_allclose(given, block_means, rtol=1e-5)
    assert res.options["prior"]["shape"] == [256, 512]
    assert res.options["prior"]["used_shape"] == [64, 128]


def test_the_prior_is_masked_with_the_image(
    room: tuple, network: SimulatedEstimator, stitched: list
) -> None:
    rgb = room[0]
    prior = np.ones((64, 128), np.float32)
    m360.estimate(
        rgb, network, prior=prior, prior_kind="distance", mask=m360.masks.nadir(30), **FAST
    )
    given = stitched[0]["prior"]
    # Prior row r covers output rows 4r … 4r + 3; it is unknown when any of them is masked
    # (latitude of the row centre below -60°), known elsewhere.
    out_lat = 90.0 - (np.arange(256) + 0.5) * 180.0 / 256
    masked_rows = (out_lat < -60.0).reshape(64, 4).any(axis=1)
    np.testing.assert_array_equal(np.isnan(given).all(axis=1), masked_rows)
    np.testing.assert_array_equal(np.isnan(given).any(axis=1), masked_rows)


def test_a_prior_model_runs_on_the_photo(
    room: tuple, network: SimulatedEstimator, stitched: list, priors: dict[str, Path]
) -> None:
    rgb = room[0]
    res = m360.estimate(rgb, network, prior=str(priors["distance"]), prior_kind="distance", **FAST)
    truth = _probe.erp_views((32, 64))[0][1]  # what the oracle graph outputs
    np.testing.assert_allclose(stitched[0]["prior"], truth, rtol=1e-6)
    record = res.options["prior"]
    assert record["source"] == "model" and record["kind"] == "distance"
    assert record["name"] == "distance.onnx"
    assert record["sha256"] == hashlib.sha256(priors["distance"].read_bytes()).hexdigest()
    assert res.timings["prior"] > 0
    # The same model as an estimator object: its own output kind; a contradicting one refused.
    pano = load_estimator(priors["scaled"], kind="panoramic", output_kind="affine_depth")
    stitched.clear()
    res = m360.estimate(rgb, network, prior=pano, **FAST)
    assert stitched[0]["prior_kind"] == "affine_depth"
    np.testing.assert_allclose(stitched[0]["prior"], 40.0 * truth + 100.0, rtol=1e-5)
    with pytest.raises(InputError, match="outputs 'affine_depth'"):
        m360.estimate(rgb, network, prior=pano, prior_kind="distance", **FAST)


def test_a_prior_model_output_that_is_not_2_to_1_becomes_an_erp_grid(
    room: tuple, network: SimulatedEstimator, stitched: list
) -> None:
    class Square:
        kind = "panoramic"
        output_kind = "affine_disparity"

        def predict(self, erp: np.ndarray) -> np.ndarray:
            return np.full((40, 60), 2.0, np.float32)

    m360.estimate(room[0], network, prior=Square(), **FAST)
    given = stitched[0]["prior"]
    assert given.shape == (35, 70)  # h = mean of 40 and 60 / 2
    np.testing.assert_allclose(given, 2.0)

    class Blind(Square):
        def predict(self, erp: np.ndarray) -> np.ndarray:
            return np.full((8, 16), np.nan, np.float32)

    with pytest.raises(ModelError, match="no finite value"):
        m360.estimate(room[0], network, prior=Blind(), **FAST)


def test_prior_options_are_checked_before_the_network_runs(
    room: tuple, network: SimulatedEstimator, priors: dict[str, Path]
) -> None:
    rgb = room[0]
    good = np.ones((8, 16), np.float32)
    cases = [
        ({"prior": good}, InputError, "prior_kind= one of"),
        ({"prior": good, "prior_kind": "metric_depth"}, InputError, "not supported"),
        ({"prior": np.ones((8, 8))}, InputError, r"\(Hp, 2 Hp\)"),
        ({"prior": good * np.inf, "prior_kind": "distance"}, InputError, "infinite"),
        ({"prior_kind": "distance"}, InputError, "need a prior"),
        (
            {"prior": good, "prior_kind": "distance", "prior_confidence": np.ones((4, 8))},
            InputError,
            "prior_confidence has shape",
        ),
        (
            {"prior": good, "prior_kind": "distance", "prior_confidence": good * 2},
            InputError,
            r"in \[0, 1\]",
        ),
        (
            {"prior": str(priors["distance"]), "prior_confidence": good},
            InputError,
            "goes with a prior map",
        ),
        ({"prior": network}, InputError, "tangent estimator"),
        ({"prior": 3}, InputError, "must be an ERP map"),
        ({"prior": good, "prior_kind": "distance", "align": "none"}, InputError, "alignment"),
        ({"prior": str(priors["broken"])}, ModelError, "the prior model cannot be used"),
        ({"prior_options": {"normalize": "unit"}}, InputError, "need a prior"),
        (
            {"prior": good, "prior_kind": "distance", "prior_options": {"normalize": "unit"}},
            InputError,
            "go with a prior model given by path",
        ),
        (
            {
                "prior": load_estimator(str(priors["distance"]), kind="panoramic"),
                "prior_options": m360.ModelOptions(normalize="unit"),
            },
            InputError,
            "loaded with its own options",
        ),
        (
            {"prior": str(priors["distance"]), "prior_options": {"threads": 2}},
            InputError,
            "main model's threads",
        ),
        (
            {"prior": str(priors["distance"]), "prior_options": {"output_kind": "distance"}},
            InputError,
            "give prior_kind",
        ),
        (
            {"prior": str(priors["distance"]), "prior_options": {"gamma": 2}},
            InputError,
            "no option 'gamma'",
        ),
        (
            {"prior": str(priors["distance"]), "prior_options": {"normalize": "sometimes"}},
            InputError,
            "normalize",
        ),
        ({"prior": str(priors["distance"]), "prior_options": 3}, InputError, "m360.ModelOptions"),
        ({"prior": "nowhere/pano.onnx"}, ModelError, "the prior model cannot be used"),
    ]
    for keywords, error, message in cases:
        with pytest.raises(error, match=message):
            m360.estimate(rgb, network, **keywords)


@pytest.mark.parametrize("given", ["dict", "ModelOptions"])
def test_a_prior_model_is_fed_as_prior_options_say(
    room: tuple, network: SimulatedEstimator, stitched: list, tmp_path: Path, given: str
) -> None:
    # The prior network outputs the mean over RGB of what it is fed, so the map the stitch gets
    # shows the normalisation: raw 0-255 values are 255 × the unit ones, and (x − ½)/½ is
    # 2·unit − 1, exactly (every step in between is linear); its size is the input size asked.
    model = str(g.affine_of_mean(tmp_path / "mean.onnx", 1.0, 0.0))

    def prior_map(**feed: Any) -> np.ndarray:
        options = feed if given == "dict" else m360.ModelOptions(**feed)
        m360.estimate(room[0], network, prior=model, prior_options=options, **FAST)
        return np.asarray(stitched[-1]["prior"], np.float64)

    unit = prior_map(input_size=(32, 64), normalize="unit")
    assert unit.shape == (32, 64) and 0.05 < np.nanmean(unit) < 0.95
    raw = prior_map(input_size=(32, 64), normalize="none")
    np.testing.assert_allclose(raw, 255 * unit, rtol=1e-5)
    centred = prior_map(input_size=(32, 64), mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5))
    np.testing.assert_allclose(centred, 2 * unit - 1, rtol=1e-5, atol=1e-5)
    assert prior_map(input_size=(64, 128), normalize="unit").shape == (64, 128)


def test_a_prior_model_that_needs_other_sizes_names_the_prior_flags(
    room: tuple, network: SimulatedEstimator, stitched: list, tmp_path: Path
) -> None:
    # A U-Net that runs only at multiples of 8: as the prior, at 36 x 72 (wrapped at the seam
    # to a width of 90) it fails, and the hint names the prior's own option, not the model's.
    model = str(unet(tmp_path / "unet.onnx", levels=3))
    with pytest.raises(ModelError, match=r"^prior model: unet.onnx: ONNX Runtime failed") as e:
        m360.estimate(room[0], network, prior=model, prior_options={"input_size": (36, 72)})
    assert "pass --prior-multiple-of 8 (or prior_options={'multiple_of': 8})" in str(e.value)
    # As the hint says, it runs.
    feed = {"input_size": (36, 72), "multiple_of": 8}
    m360.estimate(room[0], network, prior=model, prior_options=feed, **FAST)
    given = np.asarray(stitched[-1]["prior"])
    assert given.shape[1] == 2 * given.shape[0] and np.isfinite(given).all()


def test_the_fallback_without_alignment_stitches_without_the_prior(
    room: tuple, network: SimulatedEstimator, stitched: list, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every try fails its checks: the asked options, a coarser alignment, then none.
    real = checks._result_problems

    def failing(*args: Any, **keywords: Any) -> Any:
        measured, _ = real(*args, **keywords)
        return measured, ["forced by the test"]

    monkeypatch.setattr(checks, "_result_problems", failing)
    prior = np.ones((16, 32), np.float32)
    res = m360.estimate(room[0], network, prior=prior, prior_kind="distance", align=(8, 7))
    assert [("prior" in call) for call in stitched] == [True, True, False]
    tries = res.checks["result"]
    assert [t.get("prior") for t in tries] == [None, None, "dropped"]
    assert res.checks["fallback"] == "no alignment"


def test_a_prior_map_file(
    room: tuple, network: SimulatedEstimator, stitched: list, tmp_path: Path
) -> None:
    prior = np.random.default_rng(0).uniform(1, 2, (16, 32)).astype(np.float32)
    np.save(tmp_path / "lidar.npy", prior)
    res = m360.estimate(
        room[0], network, prior=str(tmp_path / "lidar.npy"), prior_kind="distance", **FAST
    )
    np.testing.assert_array_equal(stitched[0]["prior"], prior)
    assert res.options["prior"]["source"] == "array"


def test_a_prior_map_as_a_16_bit_png(
    room: tuple, network: SimulatedEstimator, stitched: list, tmp_path: Path
) -> None:
    # What other tools and LiDAR exports write most: a 16-bit PNG (here millimetres, 0 = no
    # return). It was taken for an ONNX model ("does not start like an ONNX protobuf").
    codes = np.random.default_rng(1).integers(1000, 5000, (16, 32)).astype(np.uint16)
    codes[0, :4] = 0
    assert cv2.imwrite(str(tmp_path / "lidar_mm.png"), codes)
    res = m360.estimate(
        room[0], network, prior=str(tmp_path / "lidar_mm.png"), prior_kind="affine_depth", **FAST
    )
    want = np.where(codes == 0, np.nan, codes.astype(np.float32) - 1)
    np.testing.assert_array_equal(stitched[-1]["prior"], want)
    assert res.options["prior"]["source"] == "array"
    # An earlier run's 16-bit PNG output: read with its sidecar, as m360.load reads it.
    m360.save(res, tmp_path / "earlier", formats=("png16",))
    m360.estimate(
        room[0], network, prior=str(tmp_path / "earlier.depth.png"), prior_kind="affine_depth",
        **FAST,
    )  # fmt: skip
    earlier = m360.load(tmp_path / "earlier").depth
    np.testing.assert_array_equal(stitched[-1]["prior"], earlier)


def test_the_memory_estimate_counts_the_prior() -> None:
    layout = m360.geometry.default_layout(2048)
    without = memory.estimate_memory(4096, 2048, "consensus", layout)
    with_prior = memory.estimate_memory(4096, 2048, "consensus", layout, prior_pixels=512 * 1024)
    # The measured peaks: +51 MB at 2K and +118 MB at 4K for a 512 x 1024 prior (within 10 %).
    assert with_prior - without == pytest.approx(51 * 2**20 + 16 * 512 * 1024, rel=0.1)
    at_4k = memory.estimate_memory(4096, 4096, "consensus", m360.geometry.default_layout(4096))
    at_4k_prior = memory.estimate_memory(
        4096, 4096, "consensus", m360.geometry.default_layout(4096), prior_pixels=512 * 1024
    )
    assert at_4k_prior - at_4k == pytest.approx(118 * 2**20 + 16 * 512 * 1024, rel=0.1)


# --------------------------------------------------------------------------------------------
# m360.batch.run and m360 run.


@pytest.fixture(scope="module")
def photo_folder(tmp_path_factory: pytest.TempPathFactory, room: tuple) -> Path:
    folder = tmp_path_factory.mktemp("photos")
    assert cv2.imwrite(str(folder / "room.png"), room[0][:, :, ::-1])
    return folder


def _sidecar(out: Path) -> dict[str, Any]:
    return json.loads((out / "room.json").read_text())


def test_batch_resume_redoes_an_image_when_the_prior_changes(
    photo_folder: Path,
    network: SimulatedEstimator,
    priors: dict[str, Path],
    stitched: list,
    tmp_path: Path,
) -> None:
    out = tmp_path / "out"

    def run(**prior: Any) -> m360.batch.BatchReport:
        return m360.batch.run([photo_folder], out, model=network, progress=False, **FAST, **prior)

    first = run(prior=str(priors["distance"]), prior_kind="distance")
    assert len(first.done) == 1 and first.exit_code == 0
    assert stitched[0]["prior_kind"] == "distance"
    record = _sidecar(out)["options"]["prior"]
    assert record["sha256"] == hashlib.sha256(priors["distance"].read_bytes()).hexdigest()
    assert _sidecar(out)["batch"]["fingerprint"]["prior"]["kind"] == "distance"
    assert len(run(prior=str(priors["distance"]), prior_kind="distance").skipped) == 1
    # Another prior model (other bytes): redone.
    assert len(run(prior=str(priors["scaled"]), prior_kind="affine_depth").done) == 1
    # The same model declared as another kind: redone.
    assert len(run(prior=str(priors["scaled"]), prior_kind="distance").done) == 1
    # A prior map instead, then another map: redone each time; the same map: skipped.
    a = np.ones((16, 32), np.float32)
    assert len(run(prior=a, prior_kind="distance").done) == 1
    assert len(run(prior=a.copy(), prior_kind="distance").skipped) == 1
    assert len(run(prior=a * 2, prior_kind="distance").done) == 1
    # A map file: its values are what counts (the same values: skipped; rewritten: redone).
    np.save(tmp_path / "map.npy", a * 2)
    assert len(run(prior=str(tmp_path / "map.npy"), prior_kind="distance").skipped) == 1
    np.save(tmp_path / "map.npy", a * 3)
    assert len(run(prior=str(tmp_path / "map.npy"), prior_kind="distance").done) == 1
    # The prior's own stitching options count with a prior: another weight redoes.
    weighted = run(prior=str(tmp_path / "map.npy"), prior_kind="distance", prior_weight=2.0)
    assert len(weighted.done) == 1
    assert _sidecar(out)["batch"]["fingerprint"]["prior_options"]["prior_weight"] == 2.0
    kept = run(
        prior=str(tmp_path / "map.npy"), prior_kind="distance", prior_weight=2.0, prior_fusion="off"
    )
    assert len(kept.done) == 1
    assert _sidecar(out)["batch"]["fingerprint"]["prior_options"]["prior_fusion"] == "off"
    # No prior at all: redone, and its fingerprint has no prior and none of the prior's options
    # (as before the prior existed, so earlier runs' outputs stay valid).
    assert len(run().done) == 1
    fingerprint = _sidecar(out)["batch"]["fingerprint"]
    assert "prior" not in fingerprint and "prior_options" not in fingerprint
    assert not {"prior_weight", "prior_scale_deg", "prior_fusion"} & set(
        fingerprint["stitch"]["align"]
    )
    # Without a prior its weight changes no byte: skipped.
    assert len(run(prior_weight=3.0).skipped) == 1


@pytest.mark.skipif(not STITCH_TAKES_PRIOR, reason="the installed m360.stitch takes no prior yet")
def test_batch_workers_load_the_prior_themselves(
    room: tuple, priors: dict[str, Path], tmp_path: Path
) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    for k in range(2):
        assert cv2.imwrite(str(folder / f"p{k}.png"), np.roll(room[0], 40 * k, axis=1)[:, :, ::-1])
    tangent = str(g.affine_of_mean(tmp_path / "tiny.onnx", 1.0, 3.0))
    common = {
        "model": tangent, "input_size": (64, 64), "threads": 1, "progress": False,
        "prior": str(priors["distance"]), "prior_kind": "distance", **FAST,
    }  # fmt: skip
    one = m360.batch.run([folder], tmp_path / "one", workers=1, **common)
    two = m360.batch.run([folder], tmp_path / "two", workers=2, **common)
    assert one.exit_code == two.exit_code == 0 and len(two.done) == 2
    for name in ("p0.depth.npy", "p1.depth.npy"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def test_batch_refuses_a_broken_prior_model_before_any_image(
    photo_folder: Path, network: SimulatedEstimator, priors: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    with pytest.raises(ModelError, match=r"the prior model cannot be used.*HTML"):
        m360.batch.run([photo_folder], out, model=network, prior=str(priors["broken"]))
    assert not out.exists()  # nothing made, nothing claimed


def test_cli_run_with_a_prior_model(
    photo_folder: Path,
    priors: dict[str, Path],
    stitched: list,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    model = g.affine_of_mean(tmp_path / "tiny.onnx", 1.0, 3.0)
    base = [
        "run", str(photo_folder), "-o", str(tmp_path / "out"), "--model", str(model),
        "--input-size", "64", "64", "--align", "4x3", "--blend", "frustum", "--no-progress",
    ]  # fmt: skip
    code = main([*base, "--prior", str(priors["distance"]), "--prior-kind", "distance"])
    assert code == 0, capsys.readouterr().err
    assert stitched[0]["prior_kind"] == "distance"
    assert _sidecar(tmp_path / "out")["options"]["prior"]["name"] == "distance.onnx"
    # The prior model's own feed: --prior-* flags, recorded, and a change redoes the image.
    mean = g.affine_of_mean(tmp_path / "mean.onnx", 1.0, 1.0)
    fed = [*base, "--prior", str(mean), "--prior-input-size", "32", "64"]
    assert main([*fed, "--prior-normalize", "unit"]) == 0, capsys.readouterr().err
    record = _sidecar(tmp_path / "out")["options"]["prior"]
    assert (record["mean"], record["std"], record["input_size"]) == ([0, 0, 0], [1, 1, 1], [32, 64])
    assert np.asarray(stitched[-1]["prior"]).shape == (32, 64)
    calls = len(stitched)
    assert main([*fed, "--prior-normalize", "unit"]) == 0  # the same: skipped
    assert len(stitched) == calls
    assert main([*fed, "--prior-mean", "0.5", "0.5", "0.5", "--prior-std", "1", "1", "1"]) == 0
    assert len(stitched) == calls + 1
    assert _sidecar(tmp_path / "out")["options"]["prior"]["mean"] == [0.5, 0.5, 0.5]
    code = main([*base, "--prior", str(priors["broken"])])
    assert code == 1
    assert "the prior model cannot be used" in capsys.readouterr().err
    code = main([*base, "--prior-kind", "metric_depth"])
    assert code == 2  # argparse: not a choice


def test_batch_with_a_panoramic_model(
    photo_folder: Path, room: tuple, tmp_path: Path, priors: dict[str, Path]
) -> None:
    rgb, distance, _ = room
    dmax = float(np.nanmax(distance)) * 1.05
    model = g.affine_of_mean(tmp_path / "enc.onnx", dmax, 0.0)
    options = {"kind": "panoramic", "output_kind": "distance", "input_size": (64, 128)}
    report = m360.batch.run([photo_folder], tmp_path / "out", model=str(model), progress=False,
                            normalize="unit", **options)  # fmt: skip
    assert report.exit_code == 0, report.summary()
    sidecar = _sidecar(tmp_path / "out")
    assert sidecar["model"]["kind"] == "panoramic"
    assert sidecar["batch"]["fingerprint"]["model"]["kind"] == "panoramic"
    direct = m360.estimate(rgb, str(model), normalize="unit", **options)
    saved = np.load(tmp_path / "out" / "room.depth.npy")
    np.testing.assert_array_equal(saved, direct.depth)
    with pytest.raises(InputError, match="prior goes with a tangent model"):
        m360.batch.run(
            [photo_folder],
            tmp_path / "x",
            model=str(model),
            prior=str(priors["distance"]),
            **options,
        )


# --------------------------------------------------------------------------------------------
# The Ray engine: the same bytes as the local engine.

try:
    import ray
except ImportError:  # the extra m360[ray] is not installed
    ray = None


@pytest.fixture(scope="module")
def local_ray() -> Any:
    """A local Ray of 2 CPUs whose workers can import the test helpers; yields its address."""
    with ray_helpers.local_ray() as address:
        yield address


def test_ray_engine_panoramic_model_and_prior_equal_the_local_engine(
    local_ray: Any, photo_folder: Path, tmp_path: Path
) -> None:
    model = g.affine_of_mean(tmp_path / "enc.onnx", 7.0, 0.0)
    pano = {"kind": "panoramic", "output_kind": "distance", "input_size": (64, 128)}
    runs = {}
    for engine in ("local", "ray"):
        out = tmp_path / f"pano-{engine}"
        report = m360.batch.run([photo_folder], out, model=str(model), engine=engine,
                                progress=False, normalize="unit", threads=1, **pano)  # fmt: skip
        assert report.exit_code == 0, report.summary()
        runs[engine] = out
    for name in ("room.depth.npy", "room.disparity.npy"):
        assert (runs["local"] / name).read_bytes() == (runs["ray"] / name).read_bytes()
    if not STITCH_TAKES_PRIOR:
        pytest.skip("the installed m360.stitch takes no prior yet (the alignment's prior term)")
    tangent = g.affine_of_mean(tmp_path / "tiny.onnx", 1.0, 3.0)
    for engine in ("local", "ray"):
        out = tmp_path / f"prior-{engine}"
        report = m360.batch.run([photo_folder], out, model=str(tangent), engine=engine,
                                progress=False, input_size=(64, 64), threads=1,
                                prior=str(model), prior_kind="distance",
                                prior_options={"input_size": (32, 64), "normalize": "unit"},
                                **FAST)  # fmt: skip
        assert report.exit_code == 0, report.summary()
        runs[engine] = out
    for name in ("room.depth.npy", "room.disparity.npy"):
        assert (runs["local"] / name).read_bytes() == (runs["ray"] / name).read_bytes()
    # The prior model's own options reached the model actors (its output depends on them).
    record = _sidecar(runs["ray"])["options"]["prior"]
    assert record == _sidecar(runs["local"])["options"]["prior"]
    assert (record["input_size"], record["mean"], record["std"]) == ([32, 64], [0] * 3, [1] * 3)


# --------------------------------------------------------------------------------------------
# Real networks and photos (the real-data tier; skipped where absent).


@real_data.requires_real
def test_real_networks_as_a_panoramic_model_and_as_a_prior(stitched: list) -> None:
    fast = real_data.MODELS / "fastdepth_dynamic.onnx"
    pydnet = real_data.MODELS / "mobile_pydnet_dynamic.onnx"
    # A real graph with a size rule: models check finds it on the ERP, as for tangents.
    info = m360.models.check(fast, kind="panoramic", normalize="unit")
    assert info["kind"] == "panoramic" and info["usable"]
    assert info["size_rule"] == 32  # 512 x 1024 already is a multiple: no flag needed
    rgb = m360.io.load_image(real_data.PANOS / "empty_warehouse_01_1k.tonemapped.png")
    # FastDepth run on the whole ERP: relative depth up to scale and shift.
    pano = load_estimator(
        fast, kind="panoramic", output_kind="affine_depth", normalize="unit", multiple_of=32,
        input_size=(256, 512),
    )  # fmt: skip
    alone = m360.estimate(rgb, pano)
    assert alone.depth.shape == (512, 1024) and alone.model["output_shape"] == [256, 512]
    assert np.isfinite(alone.depth).mean() > 0.99 and np.nanmin(alone.depth) > 0
    # As the prior of mobile PyDNet's tangents: the prior reaches the stitch at its size.
    res = m360.estimate(
        rgb, str(pydnet), multiple_of=64, normalize="unit", output_kind="negated_affine_disparity",
        input_size=(128, 128), prior=pano, **FAST,
    )  # fmt: skip
    assert stitched[0]["prior"].shape == (256, 512) and stitched[0]["prior_kind"] == "affine_depth"
    assert res.options["prior"]["sha256"] == m360.models.sha256_of(fast)
    assert np.isfinite(res.disparity).mean() > 0.95
