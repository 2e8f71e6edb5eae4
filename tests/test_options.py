"""m360.StitchOptions: one validated, canonical options object whose names and defaults are the
core's; the same keywords through stitch, estimate and the CLI; old spellings still work."""

from __future__ import annotations

import importlib
import json
import pickle
import sys
import typing
from pathlib import Path

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from conftest import layout, scene, tangent_disparity
from m360 import _core
from m360.align import AlignSolver, Energy, Loss, Offsets, PriorFusion
from m360.blend import BLEND_METHODS, BlendMethod, Fidelity, PoissonSolver
from m360.errors import InputError
from m360.estimators import SimulatedEstimator
from m360.geometry.layout import TangentSampling

# ----------------------------------------------------------------- names and defaults


@pytest.mark.parametrize(
    ("literal", "kind"),
    [
        (BlendMethod, "blend"),
        (Fidelity, "fidelity"),
        (PoissonSolver, "poisson_solver"),
        (Energy, "energy"),
        (AlignSolver, "solver"),
        (Offsets, "offsets"),
        (Loss, "loss"),
        (PriorFusion, "prior_fusion"),
        (TangentSampling, "sampling"),
    ],
)
def test_literal_types_spell_the_cores_choices(literal: object, kind: str) -> None:
    """The type hints repeat the core's names (a Literal cannot be computed): kept equal here."""
    assert typing.get_args(literal) == tuple(_core.CHOICES[kind])


def test_defaults_are_the_cores_and_the_form_is_canonical() -> None:
    opts = m360.StitchOptions()
    data = opts.as_dict()
    assert json.loads(json.dumps(data)) == data
    assert data["align"]["energy"] == _core.DEFAULTS["align"]["energy"]
    assert data["blend"] == dict(_core.DEFAULTS["blend"])
    assert [tuple(g) for g in data["align"]["levels"]] == [
        tuple(g) for g in _core.DEFAULTS["schedules"][data["align"]["energy"]]
    ]
    # Spelling every default out gives the same options; so does the canonical form itself.
    explicit = m360.StitchOptions(
        align=[tuple(g) for g in data["align"]["levels"]],
        blend=data["blend"]["method"],
        **{k: v for k, v in data["align"].items() if k != "levels"},
        blend_options={k: v for k, v in data["blend"].items() if k != "method"},
    )
    assert explicit == opts and hash(explicit) == hash(opts)
    assert m360.StitchOptions.from_dict(data) == opts
    assert pickle.loads(pickle.dumps(opts)) == opts
    assert m360.StitchOptions("none", "mean").as_dict() == {
        "align": None,
        "blend": {"method": "mean"},
    }


def test_options_are_frozen_and_hand_out_copies() -> None:
    opts = m360.StitchOptions(energy="paper")
    with pytest.raises(AttributeError):
        opts.energy = "normalized"  # type: ignore[attr-defined]
    align = opts.align
    assert align is not None
    align["energy"] = "normalized"
    assert opts.align is not None and opts.align["energy"] == "paper"
    assert opts.align["levels"] == [(4, 3), (8, 7), (16, 14)]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"blend": "bogus"}, r"choose one of [\"']consensus"),
        ({"blend_options": {"lam": 0}}, "lam"),
        ({"blend_options": {"lam": True}}, "lam"),
        ({"blend_options": {"tolerance": 1e-20}}, "tolerance"),
        ({"blend_options": {"iterations": 1.5}}, "iterations"),
        ({"blend_options": {"bogus": 1}}, "unknown"),
        ({"blend": "mean", "blend_options": {"lam": 0.2}}, "poisson"),
        ({"energy": "huber"}, "energy"),
        ({"energy": 3}, "energy"),
        ({"iterations": 10**30}, "iterations"),
        ({"sample_fraction": "half"}, "sample_fraction"),
        ({"pole_cap_deg": 95.0}, "pole_cap_deg"),
        ({"align": "paper"}, "not supported"),
    ],
)
def test_bad_options_name_the_option(kwargs: dict[str, typing.Any], match: str) -> None:
    with pytest.raises(InputError, match=match):
        m360.StitchOptions(**kwargs)


def test_options_or_keywords_not_both() -> None:
    lay = layout(256)
    with pytest.raises(InputError, match="not both"):
        m360.stitch(tangent_disparity(0, 256), lay, energy="paper", options=m360.StitchOptions())
    with pytest.raises(InputError, match="StitchOptions"):
        m360.stitch(tangent_disparity(0, 256), lay, options={"blend": "mean"})  # type: ignore[call-overload]


def test_stitch_with_options_is_stitch_with_keywords() -> None:
    lay = layout(256)
    tangents = syn.distort(tangent_disparity(0, 256), 3, field=0.05)
    keywords = {
        "align": [(3, 3)],
        "blend": "poisson",
        "energy": "paper",
        "solver": "lbfgs",
        "iterations": 20,
        "blend_options": {"lam": 0.2, "solver": "fused"},
    }
    opts = m360.StitchOptions(**keywords)  # type: ignore[arg-type]
    by_keywords = m360.stitch(tangents, lay, return_details=True, **keywords)  # type: ignore[call-overload]
    by_options = m360.stitch(tangents, lay, options=opts, return_details=True)
    np.testing.assert_array_equal(by_keywords.disparity, by_options.disparity)
    assert by_options.options == opts
    assert by_options.report["blend"]["lam"] == 0.2
    assert by_options.report["blend"]["solver"] == "fused"
    assert by_options.report["align"][0]["grid"] == (3, 3)


def test_estimate_takes_every_stitching_option() -> None:
    lay = m360.geometry.default_layout(256)
    rgb, _ = syn.render(scene(1), 256)
    est = SimulatedEstimator(scene(1), lay, seed=2)
    res = m360.estimate(
        rgb,
        est,
        align=(4, 3),
        energy="paper",
        solver="lbfgs",
        iterations=5,
        tolerance=1e-5,
        sample_fraction=0.02,
        pole_cap_deg=3.0,
        smoothness=2.0,
        scale_weight=0.02,
        offsets="perspective",
        blend="poisson",
        blend_options={"fidelity": "mean", "lam": 0.3, "tolerance": 1e-5, "iterations": 500},
    )
    align = res.options["align"]
    assert align["levels"] == [[4, 3]] and align["energy"] == "paper"
    assert (align["solver"], align["iterations"], align["offsets"]) == ("lbfgs", 5, "perspective")
    assert (align["smoothness"], align["scale_weight"]) == (2.0, 0.02)
    assert res.options["blend"]["lam"] == 0.3 and res.options["blend"]["fidelity"] == "mean"
    assert res.stitch.report["align"][0]["iterations"] <= 5
    assert res.stitch.report["blend"]["fidelity"] == "mean"
    stitching = {"align": res.options["align"], "blend": res.options["blend"]}
    same = m360.estimate(rgb, est, options=m360.StitchOptions.from_dict(stitching))
    np.testing.assert_array_equal(same.disparity, res.disparity)


# ------------------------------------------------------------------------- old spellings


def test_old_keywords_and_names_warn_and_still_work() -> None:
    lay = layout(256)
    tangents = tangent_disparity(0, 256)
    want = m360.stitch(tangents, lay, align="none", blend="mean")
    with pytest.warns(DeprecationWarning, match="tangents"):
        old = m360.stitch(tangent_disparity=tangents, layout=lay, align="none", blend="mean")
    np.testing.assert_array_equal(old, want)
    with pytest.raises(InputError, match="not both"), pytest.warns(DeprecationWarning):
        m360.stitch(tangents, lay, tangent_disparity=tangents)  # type: ignore[call-overload]

    with pytest.warns(DeprecationWarning, match="blend_options key"):
        old_keys = m360.StitchOptions(blend_options={"tol": 1e-5, "max_iterations": 50})
    assert old_keys == m360.StitchOptions(blend_options={"tolerance": 1e-5, "iterations": 50})
    with pytest.raises(InputError, match="both"), pytest.warns(DeprecationWarning):
        m360.StitchOptions(blend_options={"tol": 1e-5, "tolerance": 1e-5})

    stitch_module = importlib.import_module("m360.stitch")  # m360.stitch is the function
    with pytest.warns(DeprecationWarning, match=r"m360\.stitching\.blend\.BLEND_METHODS"):
        modes = stitch_module.BLEND_MODES
    assert modes == BLEND_METHODS
    with pytest.warns(DeprecationWarning, match=r"m360\.stitching\.blend\.MIN_POISSON_TOLERANCE"):
        assert stitch_module.MIN_POISSON_TOL == _core.LIMITS["min_poisson_tolerance"]

    with pytest.warns(DeprecationWarning, match=r"m360\.estimators\.OnnxEstimator"):
        from m360.estimate import OnnxEstimator
    assert OnnxEstimator is m360.estimators.OnnxEstimator
    with pytest.warns(DeprecationWarning, match="tangents"):
        erp = m360.tangents_to_erp(tiles=tangents, layout=lay)  # type: ignore[call-arg]
    np.testing.assert_array_equal(erp, m360.tangents_to_erp(tangents, lay))
    with pytest.warns(DeprecationWarning, match="tangents"):
        syn.distort(tiles=tangents, seed=1)  # type: ignore[call-arg]
    with pytest.warns(DeprecationWarning, match="tangent_shape"):
        size = m360.estimators.network_size(tile_shape=(346, 400), input_size=(256, 256))  # type: ignore[call-arg]
    assert size == m360.estimators.network_size((346, 400), (256, 256))
    simulated = SimulatedEstimator(scene(0), lay)
    rgb = np.zeros((20, *lay.tangent_shape, 3), np.uint8)
    with pytest.warns(DeprecationWarning, match="tangents"):
        old_predict = simulated.predict(tiles=rgb)  # type: ignore[call-arg]
    np.testing.assert_array_equal(old_predict, simulated.predict(rgb))


def test_input_decoding_moved_but_io_still_has_it() -> None:
    assert m360.io.load_image is m360.decode.load_image
    assert m360.io.read_image is m360.decode.read_image
    assert m360.io.IMAGE_SUFFIXES == m360.decode.IMAGE_SUFFIXES


def test_old_report_keys_are_gone() -> None:
    lay = layout(256)
    res = m360.stitch(
        tangent_disparity(0, 256), lay, align="none", blend="poisson", return_details=True
    )
    report = res.report["blend"]
    assert report["method"] == "poisson" and "lam" in report
    assert "mode" not in report and "lambda" not in report


# --------------------------------------------------------------------------------- CLI


def test_cli_help_shows_the_cores_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    from m360.cli import main

    assert main(["run", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    blend = _core.DEFAULTS["poisson"]
    for flag in (
        "--energy",
        "--solver",
        "--iterations",
        "--tolerance",
        "--sample-fraction",
        "--pole-cap-deg",
        "--offsets",
        "--smoothness",
        "--scale-weight",
        "--poisson-fidelity",
        "--poisson-lam",
        "--poisson-tolerance",
        "--poisson-iterations",
        "--poisson-solver",
        "--engine",
    ):
        assert flag in text
    assert f"default {blend['lam']:g}" in text and f"default {blend['solver']}" in text
    assert f"default {_core.DEFAULTS['blend']['method']}" in text
    assert "--loss" in text and f"normalized {_core.DEFAULTS['losses']['normalized']}" in text


def test_cli_engine_ray_without_ray_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from m360.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` does when not installed
    code = main(["run", str(tmp_path), "-o", str(tmp_path / "out"), "--engine", "ray"])
    assert code == 2
    assert 'pip install "m360[ray]"' in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_cli_bad_stitching_value_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from m360.cli import main

    code = main(["run", str(tmp_path), "-o", str(tmp_path / "out"), "--poisson-lam", "0"])
    assert code == 2 and "lam" in capsys.readouterr().err
    code = main(["run", str(tmp_path), "-o", str(tmp_path / "out"), "--align", "4x"])
    assert code == 2 and "COLSxROWS" in capsys.readouterr().err
