"""Fuzzing the edges of ``m360.batch.run`` (issue 23): file names up to the OS limit (255 bytes,
multi-byte UTF-8 included) and manifests of random bytes, long lines and duplicate outputs.

Whatever the names and manifests:

- ``run`` raises nothing but :class:`m360.InputError` (a usage error), and then OUT was never
  made (no folder is left behind by a refused manifest);
- a manifest is refused exactly when it is not UTF-8, holds a control character, has a line
  longer than two paths (8192 bytes) or two lines writing one output;
- otherwise each image fails alone: an image whose output names pass 255 bytes fails with an
  InputError naming NAME_MAX, one whose input is missing with a ReadError, the rest are done;
  no lock or temporary file and no empty folder is left in OUT.

The model is a tiny ONNX graph; examples follow the hypothesis profile (conftest.py).
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path, PurePath

import cv2
import m360
import onnx_graphs as g
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

pytestmark = pytest.mark.fuzz

_SETTINGS = settings(suppress_health_check=[HealthCheck.too_slow])
_MODEL_DIR = Path(tempfile.mkdtemp(prefix="m360-fuzz-batch-"))
MODEL = g.affine_of_mean(_MODEL_DIR / "tiny.onnx", 1.0, 3.0)
PANORAMA = cv2.imencode(".png", m360.synthetic.render(m360.synthetic.room(3), 64)[0])[1].tobytes()
OPTIONS = {"model": str(MODEL), "align": "none", "blend": "mean", "input_size": (32, 48)}
NAME_MAX = 255
#: The longest name m360 writes for a stem: STEM.disparity.npy (npy, preview, no confidence).
LONGEST_TAIL = len(".disparity.npy")
OUTPUT_TAILS = (
    *(f".{q}{s}" for q in ("depth", "disparity", "confidence") for s in (".png", ".exr")),
    ".preview.png",
)


def _utf8_size(text: str) -> int:
    return len(text.encode("utf-8"))


#: File stems of up to 251 bytes (the name with ".png" up to 255), 1 to 4 bytes per character.
STEM = st.one_of(
    st.text(st.characters(codec="utf-8", exclude_characters="/\x00"), min_size=1, max_size=80),
    st.integers(1, 251).map(lambda n: "a" * n),
    st.integers(235, 251).map(lambda n: "a" * n),  # around the limit of 241 (+ ".disparity.npy")
    st.integers(115, 125).map(lambda n: "é" * n),  # 2 bytes each
    st.integers(57, 62).map(lambda n: "😀" * n),  # 4 bytes each
    st.tuples(st.integers(0, 240), st.text(st.characters(codec="utf-8"), max_size=4)).map(
        lambda t: "b" * t[0] + t[1].replace("/", "").replace("\x00", "")
    ),
).filter(
    lambda s: (
        0 < _utf8_size(s) <= 251
        and s not in (".", "..")
        and not (s + ".png").lower().endswith(OUTPUT_TAILS)
    )
)


def _leftovers(out: Path, done: list[str]) -> list[str]:
    """Files in ``out`` but the outputs of the images ``done`` (stems) and failures.jsonl (a
    lock or temporary file), and empty folders."""
    tails = (".disparity.npy", ".depth.npy", ".preview.png", ".json")
    expected = {out / "failures.jsonl", *(out / f"{stem}{tail}" for stem in done for tail in tails)}
    files = [str(p) for p in out.rglob("*") if p.is_file() and p not in expected]
    empty = [str(p) for p in out.rglob("*") if p.is_dir() and not any(p.iterdir())]
    return files + empty


@_SETTINGS
@given(stems=st.lists(STEM, min_size=1, max_size=3, unique=True))
def test_fuzz_file_names_up_to_the_os_limit_fail_alone(stems: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "in"
        folder.mkdir()
        for stem in stems:
            (folder / f"{stem}.png").write_bytes(PANORAMA)
        out = Path(tmp) / "out"
        report = m360.batch.run(folder, out, progress=False, **OPTIONS)
        too_long = {s for s in stems if _utf8_size(s) + LONGEST_TAIL > NAME_MAX}
        event(f"{len(too_long)} of {len(stems)} names too long")
        assert {o.stem for o in report.failed} == too_long, report.outcomes
        for outcome in report.failed:
            assert outcome.error == "InputError" and "NAME_MAX" in (outcome.message or "")
        assert {o.stem for o in report.done} == set(stems) - too_long
        assert report.exit_code == (1 if too_long else 0)
        for stem in set(stems) - too_long:
            assert m360.load(out / stem).disparity.shape == (32, 64)
        leftovers = _leftovers(out, [o.stem for o in report.done])
        assert not leftovers, leftovers


#: Manifest lines: the panorama, missing files, long names, long lines, comments, junk.
LINE = st.one_of(
    st.sampled_from(
        [
            "pano.png",
            "pano.png,copy",
            "pano.png,sub/deeper/copy",
            "missing.png",
            "missing.png,sub/missing",
            "# a comment",
            "",
            "input,output",
        ]
    ),
    STEM.map(lambda stem: f"pano.png,{stem}"),  # an output name up to (and past) the limit
    STEM.map(lambda stem: f"{stem}.png"),  # a missing file with a long name
    st.integers(8150, 8250).map(lambda n: "pano.png," + "x" * n),  # around the line limit
    st.text(max_size=20),
)
MANIFEST = st.one_of(
    st.binary(max_size=200),
    st.lists(LINE, max_size=6).map(lambda lines: "\n".join(lines).encode()),
    st.lists(LINE, max_size=4).map(lambda lines: "\r\n".join(lines).encode("utf-8")),
)


def _refused(data: bytes, suffix: str) -> bool | None:
    """Whether a manifest must be refused: an independent reading of the rules (None: a CSV
    with quotes, left to the csv module)."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return True
    lines = re.split(r"\r\n|\r|\n", text)
    if any(_utf8_size(line) > 8192 for line in lines):
        return True
    if any(re.search(r"[\x00-\x08\x0b-\x1f\x7f]", line) for line in lines):  # \t is text
        return True
    outputs: list[str] = []
    for number, line in enumerate(lines, 1):
        entry = line.strip()
        if suffix == ".txt":
            if entry and not entry.startswith("#"):
                outputs.append(str(PurePath(PurePath(entry).stem)))
            continue
        if '"' in line:
            return None
        cells = [c.strip() for c in line.split(",")]
        header = number == 1 and cells[0].lower() == "input"
        if not cells[0] or cells[0].startswith("#") or header:
            continue
        output = cells[1] if len(cells) > 1 and cells[1] else PurePath(cells[0]).stem
        outputs.append(str(PurePath(output)))
    return len(outputs) != len(set(outputs))


@_SETTINGS
@given(data=MANIFEST, suffix=st.sampled_from([".txt", ".csv"]))
def test_fuzz_manifests_are_refused_whole_or_fail_line_by_line(data: bytes, suffix: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "pano.png").write_bytes(PANORAMA)
        manifest = root / f"list{suffix}"
        manifest.write_bytes(data)
        out = root / "out"
        expected = _refused(data, suffix)
        try:
            report = m360.batch.run(manifest, out, progress=False, **OPTIONS)
        except m360.InputError as exc:
            event("refused" if "manifest" in str(exc) else "no images")
            if expected:
                assert str(exc).startswith(f"manifest {manifest}"), (data, exc)
            elif expected is False:
                assert "no images found" in str(exc), (data, exc)
            assert not out.exists(), "a refused manifest left OUT behind"
            return
        event("ran")
        assert not expected, data
        for outcome in report.outcomes:
            assert outcome.status in ("done", "failed"), outcome
            if outcome.status == "failed":
                assert outcome.error in ("InputError", "ReadError"), outcome
        for outcome in report.done:
            assert m360.load(out / outcome.stem).disparity.shape == (32, 64)
        leftovers = _leftovers(out, [o.stem for o in report.done])
        assert not leftovers, leftovers
