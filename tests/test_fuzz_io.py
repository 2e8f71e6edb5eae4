"""Fuzzing the file boundary: image decoding, array files, sidecars, save/load.

Whatever the bytes, m360 raises an ``m360.M360Error`` subclass (``ReadError`` for files) or
returns a well-formed result: never another exception, a crash or a hang. The number of
examples follows the hypothesis profile of conftest.py (a few dozen per test in CI;
``HYPOTHESIS_PROFILE=slow`` runs a thousand per test); ``pytest -k fuzz`` selects these and
tests/test_fuzz.py.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from types import SimpleNamespace

import cv2
import m360
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from m360 import io

_RNG = np.random.default_rng(5)
_SMALL = _RNG.integers(0, 256, (8, 16, 3), dtype=np.uint8)
_VALID = {
    ".png": cv2.imencode(".png", _SMALL)[1].tobytes(),
    ".jpg": cv2.imencode(".jpg", _SMALL)[1].tobytes(),
    ".tif": cv2.imencode(".tif", _SMALL)[1].tobytes(),
}
_SETTINGS = settings(suppress_health_check=[HealthCheck.too_slow])  # examples: the profile's
pytestmark = pytest.mark.fuzz


@st.composite
def mutated_files(draw: st.DrawFn) -> tuple[str, bytes]:
    """A valid small image file cut short, with bytes flipped, or random bytes."""
    suffix = draw(st.sampled_from(sorted(_VALID)))
    data = bytearray(_VALID[suffix])
    how = draw(st.sampled_from(["cut", "flip", "random", "header"]))
    if how == "cut":
        data = data[: draw(st.integers(0, len(data) - 1))]
    elif how == "flip":
        for _ in range(draw(st.integers(1, 8))):
            pos = draw(st.integers(0, len(data) - 1))
            data[pos] = draw(st.integers(0, 255))
    elif how == "random":
        data = bytearray(draw(st.binary(max_size=512)))
    else:  # a valid signature followed by junk
        data = data[:8] + bytearray(draw(st.binary(max_size=256)))
    return suffix, bytes(data)


@_SETTINGS
@given(mutated_files())
def test_fuzz_decoding_images_raises_only_read_errors(case: tuple[str, bytes]) -> None:
    suffix, data = case
    try:
        image = io.decode_image(data, f"fuzz{suffix}")
    except m360.ReadError:
        return
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3


@_SETTINGS
@given(st.sampled_from([".npy", ".pfm", ".exr", ".png"]), st.binary(max_size=512))
def test_fuzz_reading_array_files_raises_only_read_errors(suffix: str, data: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"x{suffix}"
        path.write_bytes(data)
        try:
            values = io.read_array(path)
        except m360.ReadError:
            return
    assert values.ndim == 2 and values.dtype == np.float32


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3)
    ),
    max_leaves=10,
)


@_SETTINGS
@given(
    st.one_of(
        _json_values,
        st.fixed_dictionaries({"files": _json_values}),
        st.fixed_dictionaries(
            {"files": st.fixed_dictionaries({"disparity": _json_values, "depth": _json_values})}
        ),
    )
)
def test_fuzz_loading_a_damaged_sidecar_raises_only_m360_errors(sidecar: object) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        stem = Path(tmp) / "pano"
        m360.save(
            SimpleNamespace(disparity=np.ones((4, 8), np.float32), depth=np.ones((4, 8))),
            stem,
            formats=("npy", "png16"),
            preview=False,
        )
        (Path(tmp) / "pano.json").write_text(json.dumps(sidecar))
        try:
            result = m360.load(stem)
        except m360.M360Error:
            return
    assert result.disparity.shape == result.depth.shape == (4, 8)


@_SETTINGS
@given(
    hnp.arrays(
        dtype=st.sampled_from([np.float16, np.float32, np.float64, np.int32, np.uint8]),
        shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=6),
    ),
    st.lists(st.sampled_from(["npy", "pfm", "exr", "png16", "tiff", ""]), max_size=3),
    st.booleans(),
)
def test_fuzz_save_then_load_round_trips_or_refuses(
    values: np.ndarray, formats: list[str], transpose: bool
) -> None:
    data = values.T if transpose else values  # non-contiguous too
    result = SimpleNamespace(disparity=data, depth=data)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            written = m360.save(result, Path(tmp) / "p", formats=formats, preview=True)
        except m360.InputError:
            assert not list(Path(tmp).iterdir())  # a refused save writes nothing
            return
        back = {fmt: m360.load(Path(tmp) / "p", format=fmt) for fmt in dict.fromkeys(formats)}
    assert "sidecar" in written
    with np.errstate(over="ignore"):
        exact = data.astype(np.float32)
    for fmt, loaded in back.items():
        if fmt == "png16":
            assert np.array_equal(np.isfinite(loaded.disparity), np.isfinite(exact))
        else:
            assert np.array_equal(loaded.disparity, exact, equal_nan=True), fmt


_anything = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 3), st.floats(allow_nan=True), st.text(max_size=6),
    st.lists(st.integers(0, 20), max_size=3), st.tuples(st.integers(-2, 20), st.integers(-2, 20)),
)  # fmt: skip


@_SETTINGS
@given(
    st.fixed_dictionaries(
        {},
        optional={
            "workers": _anything,
            "threads": _anything,
            "formats": _anything,
            "align": _anything,
            "blend": _anything,
            "on_outcome": _anything,
        },
    ),
    st.one_of(st.just("list.txt"), _anything),
)
def test_fuzz_batch_arguments_raise_only_m360_errors(kwargs: dict, inputs: object) -> None:
    """Bad arguments are refused up front; good ones run (here on a manifest listing a missing
    file, recorded as a failure, so nothing is computed)."""
    import batch_helpers

    with tempfile.TemporaryDirectory() as tmp:
        if inputs == "list.txt":
            inputs = Path(tmp) / "list.txt"
            inputs.write_text("missing.jpg\n")
        try:
            report = m360.batch.run(
                inputs,  # type: ignore[arg-type]
                Path(tmp) / "out",
                model=batch_helpers.CrashOnBlack(),
                progress=False,
                **kwargs,
            )
        except m360.M360Error:
            return
    assert report.exit_code == 1 and report.failed
