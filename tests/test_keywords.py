"""Options written once: one keyword list serves the signatures, docs, checks and the CLI."""

from __future__ import annotations

import argparse
import inspect
import pickle
from pathlib import Path
from typing import Annotated, TypedDict

import m360
import numpy as np
import pytest
from m360 import _keywords
from m360._keywords import Option, add_flags, definition, document, from_args
from m360.cli import build_parser
from m360.estimators import ModelKeywords, ModelOptions
from m360.pipeline.options import EstimateKeywords, JobKeywords
from m360.stitching.options import StitchKeywords, StitchTuning


def _run_parser() -> argparse.ArgumentParser:
    sub = next(
        a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)
    ).choices
    return sub["run"]  # type: ignore[no-any-return]


def _dests(parser: argparse.ArgumentParser) -> set[str]:
    return {a.dest for a in parser._actions}


def test_every_shared_keyword_is_a_flag_of_m360_run_and_read_back() -> None:
    dests = _dests(_run_parser())
    for name, option in definition(EstimateKeywords).items():
        if option.parts:
            assert {f"{name}__{k}" for k in option.parts} <= dests, name
        else:
            assert name in dests, f"{name} has no flag in m360 run"


def test_flags_give_the_same_options_as_the_api() -> None:
    argv = [
        "in.jpg", "-o", "out", "--align", "4x3,8x7", "--blend", "poisson", "--energy", "paper",
        "--solver", "lbfgs", "--iterations", "30", "--tolerance", "1e-5",
        "--sample-fraction", "0.02", "--pole-cap-deg", "5", "--smoothness", "2",
        "--scale-weight", "0.02", "--offsets", "spherical", "--loss", "huber",
        "--poisson-lam", "0.2", "--fidelity", "nn", "--poisson-iterations", "50",
        "--providers", "CPUExecutionProvider", "--threads", "2", "--input-size", "64", "96",
        "--output-kind", "metric_depth", "--mean", "0", "0", "0", "--std", "1", "1", "1",
        "--working-width", "native", "--upsample", "bilinear", "--padding", "paper",
        "--sky", "nan",
    ]  # fmt: skip
    args = _run_parser().parse_args(argv)
    stitch = from_args(args, StitchKeywords)
    api = m360.StitchOptions(
        [(4, 3), (8, 7)],
        "poisson",
        energy="paper",
        solver="lbfgs",
        iterations=30,
        tolerance=1e-5,
        sample_fraction=0.02,
        pole_cap_deg=5.0,
        smoothness=2.0,
        scale_weight=0.02,
        offsets="spherical",
        loss="huber",
        blend_options={"lam": 0.2, "fidelity": "nn", "iterations": 50},
    )
    assert m360.StitchOptions(**stitch) == api
    model = ModelOptions(**from_args(args, ModelKeywords))
    assert model == ModelOptions(
        providers=["CPUExecutionProvider"],
        threads=2,
        input_size=(64, 96),
        output_kind="metric_depth",
        mean=(0, 0, 0),
        std=(1, 1, 1),
    )
    assert from_args(args, JobKeywords) == {
        "working_width": "native",
        "upsample": "bilinear",
        "padding": "paper",
        "sky": "nan",
    }
    # Flags left out are not keywords (the API's defaults apply).
    bare = _run_parser().parse_args(["in.jpg", "-o", "out"])
    assert from_args(bare, EstimateKeywords) == {}


def test_signatures_read_as_a_few_named_objects_plus_one_keyword_list() -> None:
    for func, most in ((m360.estimate, 12), (m360.batch.run, 20)):
        params = inspect.signature(func).parameters.values()
        named = [p for p in params if p.kind is not inspect.Parameter.VAR_KEYWORD]
        assert len(named) <= most, f"{func.__name__}: {len(named)} named parameters"
        assert any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params)
        shared = set(definition(EstimateKeywords))
        assert not shared & {p.name for p in named}, "an option written twice"


@pytest.mark.parametrize(
    "call",
    [
        lambda: m360.estimate(np.zeros((8, 16, 3), np.uint8), blnd="mean"),
        lambda: m360.batch.run(["nowhere"], "out", thread=2),
        lambda: m360.StitchOptions(enregy="paper"),
        lambda: ModelOptions(thread=1),
    ],
)
def test_an_unknown_keyword_is_a_type_error_naming_it(call: object) -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        call()  # type: ignore[operator]


def test_model_options_are_checked_frozen_comparable_and_picklable() -> None:
    opts = ModelOptions(input_size=224, mean=[0, 0, 0], providers="CPUExecutionProvider")
    assert opts.input_size == (224, 224) and opts.mean == (0.0, 0.0, 0.0)
    assert opts.providers == ("CPUExecutionProvider",) and opts.threads is None
    assert opts.as_dict() == {
        "input_size": [224, 224],
        "mean": [0.0, 0.0, 0.0],
        "providers": ["CPUExecutionProvider"],
    }
    assert pickle.loads(pickle.dumps(opts)) == opts and hash(opts) == hash(
        ModelOptions(**opts.keywords())
    )
    with pytest.raises(AttributeError):
        opts.threads = 2  # type: ignore[misc]
    for bad, message in (
        ({"threads": 0}, "threads"),
        ({"input_size": (0, 5)}, "input_size"),
        ({"output_kind": "depthish"}, "output_kind"),
        ({"mean": (1, 2)}, "mean"),
        ({"providers": [3]}, "providers"),
    ):
        with pytest.raises(m360.InputError, match=message):
            ModelOptions(**bad)  # type: ignore[arg-type]
    with pytest.raises(m360.InputError, match="not both"):
        ModelOptions.build(opts, threads=2)
    assert ModelOptions.build(opts, threads=None) is opts


def test_the_lists_document_every_keyword() -> None:
    for keywords in (StitchTuning, StitchKeywords, ModelKeywords, JobKeywords, EstimateKeywords):
        doc = keywords.__doc__ or ""
        for name in definition(keywords):
            assert f"\n    {name}\n" in doc, f"{keywords.__name__} does not document {name}"


def test_adding_an_option_is_one_entry() -> None:
    # An option added to a list reaches the flags, the parsed keywords, the docs and the checks.
    @document
    class Extra(TypedDict, total=False):
        """A list with one new option."""

        radius: Annotated[
            int | None,
            Option("guide radius in pixels", parse=int, check=lambda v, n: int(v), default=8),
        ]

    parser = argparse.ArgumentParser()
    add_flags(parser, Extra)
    assert from_args(parser.parse_args(["--radius", "3"]), Extra) == {"radius": 3}
    assert "guide radius in pixels" in (Extra.__doc__ or "")
    assert _keywords.resolved({}, Extra) == {"radius": 8}
    assert _keywords.resolved({"radius": 5.0}, Extra) == {"radius": 5}


def test_an_entry_without_its_option_is_refused() -> None:
    class Broken(TypedDict, total=False):
        radius: int | None

    with pytest.raises(TypeError, match=r"Broken\.radius needs exactly one Option"):
        definition(Broken)


def test_cli_help_is_plain_text() -> None:
    parser = build_parser()
    texts = [parser.format_help()]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                texts.append(sub.format_help())
                texts += [
                    s.format_help()
                    for a in sub._actions
                    if isinstance(a, argparse._SubParsersAction)
                    for s in a.choices.values()
                ]
    for text in texts:
        assert "``" not in text and ":func:" not in text and ":mod:" not in text, text[:200]
    assert (
        _keywords.plain_text("``m360 run`` is :func:`m360.batch.run`")
        == "m360 run is m360.batch.run"
    )


def test_one_default_padding_for_the_layout_estimate_uses() -> None:
    from m360.geometry import DEFAULT_PADDING, PAPER_PADDING, default_layout

    assert m360.Layout.icosahedron(512) == default_layout(512)
    assert m360.Layout.icosahedron(512).padding == DEFAULT_PADDING == 0.7
    paper = m360.Layout.icosahedron(512, padding="paper")
    assert paper.padding == PAPER_PADDING == 0.3 and paper == m360.Layout.icosahedron(512, 0.3)
    assert m360.Layout.icosahedron(2048, padding="paper").tangent_shape == (346, 400)
    with pytest.raises(m360.InputError, match="'paper'"):
        m360.Layout.icosahedron(512, padding="papr")
    # What estimate runs on is what Layout.icosahedron(W) gives.
    rgb = np.full((128, 256, 3), 128, np.uint8)
    rng = np.random.default_rng(0)

    class Flat:
        output_kind = "affine_disparity"

        def predict(self, tangents: np.ndarray) -> np.ndarray:
            return rng.uniform(1, 2, tangents.shape[:3]).astype(np.float32)

    res = m360.estimate(rgb, Flat(), align="none", blend="mean")
    assert res.layout == m360.Layout.icosahedron(256)
    assert m360.estimate(
        rgb, Flat(), align="none", padding="paper"
    ).layout == paper.__class__.icosahedron(256, padding=0.3)


def test_multiple_of_reaches_the_network_from_the_api_and_the_cli(tmp_path: Path) -> None:
    # The option added through its one entry (ModelKeywords.multiple_of) and load_estimator.
    from m360.estimators import load_estimator
    from onnx_graphs import channel

    path = channel(tmp_path / "dyn.onnx", 0)
    plain = load_estimator(path, input_size=(200, 200))
    assert plain.network_size((346, 400)) == (173, 200)
    by32 = load_estimator(path, input_size=(200, 200), multiple_of=32)
    assert by32.multiple_of == 32 and by32.network_size((346, 400)) == (160, 192)
    args = _run_parser().parse_args(["x.jpg", "-o", "o", "--multiple-of", "32"])
    assert from_args(args, ModelKeywords) == {"multiple_of": 32}
    with pytest.raises(m360.InputError, match="multiple_of"):
        ModelOptions(multiple_of=0)
