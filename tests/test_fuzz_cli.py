"""Fuzzing ``m360 run``: random argument lists over random input folders (issue 12).

Argument lists are built from the real flags of ``m360 run`` with valid and invalid values, and
random tokens; the input folder holds random bytes named .jpg/.png/.exr/.txt/.csv next to a
valid panorama or not; manifests hold random bytes. The model is a tiny ONNX graph made here
and the run is offline with an empty ``M360_HOME``, so nothing touches the network.
``m360.cli.main`` runs in this process (one worker: worker processes are covered by
tests/test_batch.py). Whatever the arguments:

- no exception escapes but ``SystemExit`` with code 0, 1 or 2, and stderr has no traceback;
- exit 2 is a usage error with a message, and no image was written;
- exit 1 is recorded per-image failures (``failures.jsonl``), or a model that cannot be loaded
  (``--model`` not the tiny model: a ModelError, before any image);
- exit 0 only when every image succeeded: no ``failures.jsonl`` and a sidecar per image.

Examples follow the hypothesis profile (conftest.py); ``pytest -k fuzz`` selects them.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import cv2
import m360
import onnx_graphs as g
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from m360.cli import main

pytestmark = pytest.mark.fuzz

#: 5x the profile's examples (a CI run takes about 10 s).
_SETTINGS = settings(
    max_examples=5 * settings.default.max_examples, suppress_health_check=[HealthCheck.too_slow]
)

_MODEL_DIR = Path(tempfile.mkdtemp(prefix="m360-fuzz-cli-"))
# Positive disparity for any RGB (the normalised mean is in [-2.2, 2.7]).
MODEL = g.affine_of_mean(_MODEL_DIR / "tiny.onnx", 1.0, 3.0)
_ROOM = m360.synthetic.render(m360.synthetic.room(3), 128)[0][:, :, ::-1]
PANORAMA = cv2.imencode(".png", _ROOM)[1].tobytes()
NOT_PANORAMA = cv2.imencode(".png", _ROOM[:, :96])[1].tobytes()

TOKEN = st.text(max_size=6)
INT = st.sampled_from(["-1", "0", "1", "2", "3", "17", "999999999999", "x", "1.5", ""])
FLOAT = st.sampled_from(["-1", "0", "1e-3", "0.5", "1", "3", "nan", "inf", "-inf", "1e308", "x"])


def one_of_or(values: list[str]) -> st.SearchStrategy[list[str]]:
    """One of ``values`` (3 times in 4) or a random token, as a one-token list."""
    valid = st.sampled_from(values)
    return one(st.one_of(valid, valid, valid, TOKEN))


def one(strategy: st.SearchStrategy[str]) -> st.SearchStrategy[list[str]]:
    """A one-token list."""
    return strategy.map(lambda v: [v])


#: Every flag of ``m360 run`` that takes values, with strategies for its value tokens.
VALUED: dict[str, st.SearchStrategy[list[str]]] = {
    "--model": one_of_or([str(MODEL), "midas-v21-small", "nope.onnx"]),
    "--formats": one(
        st.lists(st.sampled_from(["npy", "pfm", "exr", "png16", "tiff", ""]), max_size=4).map(
            ",".join
        )
    ),
    "--workers": one(st.sampled_from(["-1", "0", "1", "x"])),
    "--threads": one(INT),
    "--engine": one_of_or(["local", "ray"]),
    "--input-size": st.lists(
        st.sampled_from(["-1", "0", "8", "16", "24", "5000", "x"]), min_size=2, max_size=2
    ),
    "--output-kind": one_of_or(["affine_disparity", "metric_depth", "distance"]),
    "--providers": one_of_or(["CPUExecutionProvider", "CUDAExecutionProvider", ","]),
    "--align": one_of_or(["none", "multiscale", "4x3", "4x3,8x7", "0x0", "1x1", "x"]),
    "--blend": one_of_or(["poisson", "frustum", "radial", "mean", "nn"]),
    "--energy": one_of_or(["normalized", "paper"]),
    "--solver": one_of_or(["newton", "lbfgs"]),
    "--iterations": one(INT),
    "--tolerance": one(FLOAT),
    "--sample-fraction": one(FLOAT),
    "--pole-cap-deg": one(FLOAT),
    "--smoothness": one(FLOAT),
    "--scale-weight": one(FLOAT),
    "--offsets": one_of_or(["perspective", "spherical"]),
    "--poisson-fidelity": one_of_or(["frustum", "nn", "mean"]),
    "--poisson-lam": one(FLOAT),
    "--poisson-tolerance": one(FLOAT),
    "--poisson-iterations": one(INT),
    "--poisson-solver": one_of_or(["cg", "fused", "x"]),
}
SWITCHES = ["--no-preview", "--resume", "--overwrite", "--recursive", "--fix-aspect", "--bogus"]

#: A flag with its values (most often), a switch, or a random token.
_FLAG = st.sampled_from(sorted(VALUED)).flatmap(lambda f: VALUED[f].map(lambda v: [f, *v]))
OPTION = st.one_of(
    _FLAG,
    _FLAG,
    _FLAG,
    _FLAG,
    st.sampled_from(SWITCHES).map(lambda s: [s]),
    TOKEN.map(lambda t: [t]),
)

#: Files of the input folder: name stem, suffix, content.
FILE = st.tuples(
    st.sampled_from(["a", "b", "pano", "list"]),
    st.sampled_from([".jpg", ".png", ".exr", ".txt", ".csv", ".JPG"]),
    st.one_of(
        st.binary(max_size=64),
        st.just(PANORAMA),
        st.just(PANORAMA),
        st.just(PANORAMA),
        st.just(NOT_PANORAMA),
        st.binary(max_size=32).map(lambda b: b"v/1\x01" + b),  # EXR magic, junk after
        st.binary(max_size=32).map(lambda b: PANORAMA[:40] + b),  # a PNG cut short
        st.lists(
            st.sampled_from(
                [
                    "a.png",
                    "pano.jpg",
                    "missing.png",
                    "..",
                    "/",
                    "x,y",
                    "pano.png,pano.json/x",
                    "a.png,sub\x00/x",
                    "a\x00.png",
                    "pano.png,../up",
                    "b.png,/abs",
                    "input,output",
                ]
            )
        ).map(lambda lines: "\n".join(lines).encode()),
    ),
)

#: A panorama under any image name (only these: a run that can succeed).
GOOD_FILE = st.tuples(
    st.sampled_from(["a", "b", "pano"]),
    st.sampled_from([".jpg", ".png", ".exr"]),
    st.just(PANORAMA),
)

#: What goes on the command line as inputs: the folder, files in it, random tokens.
INPUT = st.one_of(
    st.just("{in}"),
    st.just("{in}"),
    st.just("{in}"),
    st.sampled_from(["a", "b", "pano", "list"]).flatmap(
        lambda stem: st.sampled_from([".jpg", ".png", ".exr", ".txt", ".csv"]).map(
            lambda suffix: "{in}/" + stem + suffix
        )
    ),
    TOKEN,
)


@contextlib.contextmanager
def offline(home: Path) -> Iterator[None]:
    env = {"M360_OFFLINE": "1", "M360_HOME": str(home), "M360_NUM_THREADS": "1"}
    drop = ("M360_MODEL_DIR", "M360_ALLOW_UNVERIFIED")
    with mock.patch.dict(os.environ, env):
        for var in drop:
            os.environ.pop(var, None)
        yield


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """``m360.cli.main(argv)`` in this process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # allowed, with a proper code
            code = exc.code  # type: ignore[assignment]
    return code, out.getvalue(), err.getvalue()


@_SETTINGS
@given(
    files=st.one_of(st.lists(FILE, max_size=5), st.lists(GOOD_FILE, min_size=1, max_size=3)),
    inputs=st.lists(INPUT, min_size=1, max_size=3),
    options=st.lists(OPTION, max_size=6),
    out_is_a_file=st.booleans(),
    out_name=st.one_of(
        st.sampled_from(["out", "out", "out", "in/a.png/out", "in/pano.png", "in"]),
        TOKEN.filter(lambda t: "/" not in t and t not in (".", "..")),
    ),
)
def test_fuzz_run_exits_0_1_or_2_and_never_with_a_traceback(
    files: list[tuple[str, str, bytes]],
    inputs: list[str],
    options: list[list[str]],
    out_is_a_file: bool,
    out_name: str,
) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        folder = root / "in"
        folder.mkdir()
        for stem, suffix, data in files:
            (folder / f"{stem}{suffix}").write_bytes(data)
        out = root / out_name
        if out_is_a_file and "\x00" not in out_name and out.parent.is_dir() and not out.exists():
            out.write_bytes(b"x")
        argv = ["run", *(i.replace("{in}", str(folder)) for i in inputs), "-o", str(out)]
        argv += ["--model", str(MODEL), "--no-progress"]  # defaults; options may override them
        argv += [token for option in options for token in option]
        with offline(root / "home"):
            code, stdout, stderr = run_cli(argv)
        event(f"exit {code}")
        assert code in (0, 1, 2), (code, argv, stderr)
        assert "Traceback" not in stderr and "Traceback" not in stdout, (argv, stderr)
        usable = "\x00" not in str(out) and out.is_dir()
        failures = out / "failures.jsonl" if usable else None
        written = sorted(out.rglob("*.json")) if usable else []
        if code == 2:
            assert "error:" in stderr, (argv, stderr)
            assert not written, (argv, written)
        elif code == 1:
            if failures is not None and failures.is_file():
                records = [json.loads(line) for line in failures.read_text().splitlines()]
                assert records and all(r["error"] and r["input"] for r in records)
            else:  # the model could not be loaded: only another --model does that
                models = [o[1] for o in options if o[0] == "--model" and len(o) > 1]
                assert models and models[-1] != str(MODEL), (argv, stderr)
                assert "m360: error:" in stderr and not written, (argv, stderr)
        elif "usage:" not in stdout:  # exit 0 that is not --help
            assert failures is not None and not failures.exists(), (argv, stderr)
            assert written and "0 failed" in stderr, (argv, stderr)
