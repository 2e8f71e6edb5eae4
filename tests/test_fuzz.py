"""Hypothesis fuzzing of m360's public input boundary (issue 7).

Every public function is fed generated arguments: right and wrong shapes, dtypes, NaN/inf,
empty, huge (declared sizes only: nothing huge is allocated), non-contiguous, read-only and
big-endian arrays, and wrong types. Each call must either return a sane result (checked, with a
numpy oracle where one is cheap) or raise an :class:`m360.M360Error` subclass; any other
exception, a warning (pytest turns warnings into errors), a crash or a hang fails the test.

Run the fuzz tests alone (CI profile, a few hundred examples, well under a minute)::

    pytest -k fuzz

The slow profile (>= 10,000 examples over these tests) with hypothesis' statistics::

    HYPOTHESIS_PROFILE=slow pytest tests/test_fuzz.py --hypothesis-show-statistics
    pytest tests/test_fuzz.py --hypothesis-profile=slow

Every example has a hypothesis deadline, and a watchdog (faulthandler) kills the process with
every thread's traceback if one example runs longer than ``HANG_SECONDS``: a hang in the
compiled core, which no Python-level timeout could interrupt, still ends the run.
"""

from __future__ import annotations

import contextlib
import faulthandler
import functools
import sys
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import m360
import m360.synthetic as syn
import numpy as np
import onnx_graphs
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from m360 import M360Error, eval, models
from m360.blend import BLEND_METHODS
from m360.estimators import OnnxEstimator, SimulatedEstimator, to_perspective_disparity
from m360.geometry import Layout

pytestmark = pytest.mark.fuzz

#: Seconds one example may run before the watchdog aborts the whole run as hung.
HANG_SECONDS = 300


def budget(weight: float) -> settings:
    """Settings of a fuzz test worth ``weight`` x the profile's ``max_examples``."""
    return settings(max_examples=max(3, round(settings.default.max_examples * weight)))


@contextlib.contextmanager
def watchdog() -> Iterator[None]:
    faulthandler.dump_traceback_later(HANG_SECONDS, exit=True, file=sys.stderr)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def outcome(call: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``call``'s result, or the M360Error it raised; any other exception propagates."""
    with watchdog():
        try:
            result = call(*args, **kwargs)
        except M360Error as err:
            event(f"refused: {type(err).__name__}")  # tallied by --hypothesis-show-statistics
            return err
    event("returned")
    return result


# --------------------------------------------------------------------------------------------
# Strategies.

HUGE_INTS = st.sampled_from([2**31, 2**63, 10**9, 10**12, 10**30, -(10**30), 2**64 + 1])


def opaque(*strategies: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """One of ``strategies`` with equal odds, as a single branch: ``st.one_of`` flattens nested
    one_of's, so a 20-way junk one_of next to one valid strategy would win 20 times in 21."""
    return st.integers(0, len(strategies) - 1).flatmap(lambda k: strategies[k])


#: Values of the wrong type (or absurd) for any argument.
JUNK = opaque(
    st.none(),
    st.booleans(),
    st.integers(-5, 5),
    HUGE_INTS,
    st.floats(allow_nan=True, allow_infinity=True),
    st.complex_numbers(max_magnitude=10),
    st.text(max_size=8),
    st.binary(max_size=8),
    st.just([[1, 2], [3]]),
    st.just([]),
    st.just({}),
    st.just({"a": 1}),
    st.just(object()),
    st.just(np.float64("nan")),
    st.just(np.int64(-3)),
    st.just(np.array(3.0)),
    st.just(np.array(["a", "b"])),
    st.just(np.zeros((2, 2), dtype=object)),
    st.just(np.zeros((2, 2), dtype=complex)),
    st.just(np.zeros(3, dtype="M8[s]")),
)

DTYPES = [
    np.uint8,
    np.int8,
    np.int32,
    np.int64,
    np.uint16,
    np.float16,
    np.float32,
    np.float64,
    np.dtype(">f4"),
    np.dtype(">f8"),
    np.bool_,
    np.complex64,
]

#: Dtypes, mostly the one m360 works in.
FLOATY = st.one_of(st.just(np.float32), st.just(np.float32), st.sampled_from(DTYPES))

#: Float values that break naive numerics (the first three are NaN and the infinities).
SPECIALS = [
    np.nan,
    np.inf,
    -np.inf,
    0.0,
    -0.0,
    1e-45,
    5e-324,
    3.4e38,
    -3.4e38,
    1e300,
    -1e300,
]


@st.composite
def arrays(draw: st.DrawFn, shape: tuple[int, ...], dtype: Any = None) -> np.ndarray:
    """An array of ``shape``: random, constant, with special values, extreme or mixed; in any
    memory layout (C, Fortran, strided view, read-only)."""
    dtype = np.dtype(draw(FLOATY) if dtype is None else dtype)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    kind = draw(st.sampled_from(["random", "constant", "specials", "extreme", "positive"]))
    size = int(np.prod(shape))
    magnitude = 10.0 ** draw(st.integers(-40, 40))
    if kind == "constant":
        values = np.full(size, draw(st.floats(-1e3, 1e3)))
    elif kind == "positive":
        values = rng.uniform(0.1, 10.0, size)
    else:
        values = rng.normal(0.0, 1.0, size) * (magnitude if kind == "extreme" else 1.0)
    if kind == "specials" and size:
        picks = rng.integers(0, size, max(1, size // 20))
        finite_only = draw(st.booleans())  # infinities are refused: often leave them out
        values[picks] = rng.choice(SPECIALS[3:] if finite_only else SPECIALS, picks.size)
    with np.errstate(all="ignore"):
        if dtype.kind in "iu":
            info = np.iinfo(dtype)
            values = np.clip(np.nan_to_num(values * 100), info.min, info.max)
        elif dtype.kind == "b":
            values = values > 0
        array = values.astype(dtype).reshape(shape)
    layout = draw(st.sampled_from(["C", "F", "strided", "readonly"]))
    if layout == "F":
        array = np.asfortranarray(array)
    elif layout == "strided" and array.ndim:
        array = np.repeat(array, 2, axis=-1)[..., ::2]
    elif layout == "readonly":
        array = array.copy()
        array.flags.writeable = False
    return array


@functools.lru_cache(maxsize=8)
def layout(erp_width: int) -> Layout:
    return Layout.icosahedron(erp_width)


@functools.lru_cache(maxsize=2)
def distorted_tangents(erp_width: int) -> np.ndarray:
    """Tangent disparity of a synthetic room, per-tangent affinely distorted (valid input)."""
    lay = layout(erp_width)
    exact = syn.tangent_perspective_disparity(syn.room(1), lay.cameras)
    out = syn.distort(exact, 2, noise=0.01)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4)
def ray_lengths(erp_width: int) -> np.ndarray:
    """|q| of every tangent pixel, by numpy from the cameras' intrinsics (oracle)."""
    lay = layout(erp_width)
    h, w = lay.tangent_shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack(
        [
            np.sqrt(((cols - c.cx) / c.fx) ** 2 + ((rows - c.cy) / c.fy) ** 2 + 1.0)
            for c in lay.cameras
        ]
    )


ERP_WIDTHS = st.sampled_from([64, 96, 128])


def near(value: int) -> st.SearchStrategy[int]:
    """A size equal to ``value`` most of the time, else off by a little or absurd."""
    return st.one_of(
        st.just(value), st.just(value), st.integers(0, value + 3), st.sampled_from([0, 1])
    )


def maybe(strategy: st.SearchStrategy[Any], valid: st.SearchStrategy[Any]) -> Any:
    """``valid`` values three times in four, else ``strategy`` (the junk)."""
    return st.integers(0, 3).flatmap(lambda k: strategy if k == 0 else valid)


# --------------------------------------------------------------------------------------------
# Layouts.


@budget(1.0)
@given(
    erp_width=maybe(
        st.one_of(st.integers(-10, 300), HUGE_INTS, st.integers(16_000, 17_000), JUNK),
        st.sampled_from([64, 96, 128, 256, 2048, 16384]),
    ),
    padding=maybe(st.one_of(st.floats(-1, 3), JUNK), st.floats(0.0, 2.0)),
    tangent_width=maybe(
        st.one_of(st.integers(-2, 7), HUGE_INTS, JUNK), st.one_of(st.none(), st.integers(8, 64))
    ),
)
def test_fuzz_layout_icosahedron(erp_width: Any, padding: Any, tangent_width: Any) -> None:
    lay = outcome(Layout.icosahedron, erp_width, padding, tangent_width)
    if isinstance(lay, M360Error):
        return
    assert lay.erp_shape == (erp_width // 2, erp_width)
    assert len(lay) == 20
    h, w = lay.tangent_shape
    assert h >= 2 and w >= 2
    if tangent_width is not None:
        assert w == tangent_width


CAMERA_FIELDS = st.sampled_from(["rotation", "fx", "fy", "cx", "cy", "width", "height"])


@budget(0.6)
@given(
    erp_width=ERP_WIDTHS,
    changes=st.lists(
        st.tuples(st.integers(0, 19), CAMERA_FIELDS, st.one_of(JUNK, st.integers(-3, 10**6))),
        max_size=3,
    ),
    erp_shape=st.one_of(
        st.none(),
        st.tuples(st.integers(-2, 10**9), st.integers(-2, 2 * 10**9)),
        st.tuples(HUGE_INTS, HUGE_INTS),
        JUNK,
    ),
    cameras_junk=st.one_of(st.none(), JUNK, st.lists(JUNK, min_size=1, max_size=2)),
)
def test_fuzz_layout_from_cameras(
    erp_width: int, changes: list[Any], erp_shape: Any, cameras_junk: Any
) -> None:
    base = layout(erp_width)
    cameras: Any = list(base.cameras)
    for k, name, value in changes:
        cameras[k] = replace(cameras[k], **{name: value})
    if cameras_junk is not None:
        cameras = cameras_junk
    shape = base.erp_shape if erp_shape is None else erp_shape
    lay = outcome(Layout.from_cameras, cameras, shape)
    if isinstance(lay, M360Error):
        return
    assert isinstance(lay, Layout)
    h, w = lay.tangent_shape
    height, width = lay.erp_shape
    # Only use small layouts: a declared 8K ERP is legal but its (N, H, W) output is 10 GB.
    if len(lay) * height * width <= 1 << 22 and len(lay) * h * w <= 1 << 22:
        out = outcome(m360.tangents_to_erp, np.ones((len(lay), h, w), np.float32), lay)
        if not isinstance(out, M360Error):
            assert out.shape == (len(lay), height, width)


# --------------------------------------------------------------------------------------------
# Resampling.


@st.composite
def erp_images(draw: st.DrawFn) -> np.ndarray:
    height = draw(st.sampled_from([0, 1, 16, 31, 32, 48, 64]))
    width = draw(st.one_of(st.just(2 * height), st.just(2 * height), st.integers(0, 130)))
    channels = draw(st.sampled_from([(), (), (1,), (3,), (4,), (0,), (5,)]))
    extra = draw(st.sampled_from([(), (), (), (2,)]))
    return draw(arrays((height, width, *channels, *extra)))


@budget(1.0)
@given(
    erp=st.one_of(erp_images(), erp_images(), JUNK),
    which=st.sampled_from(["default", "matching", "matching", "other", "junk"]),
    junk=JUNK,
)
def test_fuzz_erp_to_tangents(erp: Any, which: str, junk: Any) -> None:
    shape = np.shape(erp) if isinstance(erp, np.ndarray) else ()
    width = shape[1] if len(shape) >= 2 else 0
    lay: Any = {
        "default": None,
        "matching": layout(width) if width in (64, 96, 128) else None,
        "other": layout(128),
        "junk": junk,
    }[which]
    out = outcome(m360.erp_to_tangents, erp, lay)
    if isinstance(out, M360Error):
        return
    used = lay if lay is not None else layout(width)
    assert out.shape == (len(used), *used.tangent_shape, *shape[2:])
    assert out.dtype == (np.uint8 if erp.dtype == np.uint8 else np.float32)
    # Oracle: bilinear sampling of a constant image is that constant.
    if erp.size and np.all(erp == erp.flat[0]) and np.isfinite(erp.flat[0]):
        if erp.dtype == np.uint8:
            assert np.abs(out.astype(int) - int(erp.flat[0])).max() <= 1
        else:
            np.testing.assert_allclose(out, np.float32(erp.flat[0]), rtol=1e-6)


@budget(1.0)
@given(
    erp_width=ERP_WIDTHS,
    n=near(20),
    dh=st.sampled_from([0, 0, 0, 1, -1]),
    dtype=FLOATY,
    data=st.data(),
    junk_layout=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_tangents_to_erp(
    erp_width: int, n: int, dh: int, dtype: Any, data: st.DataObject, junk_layout: Any
) -> None:
    lay = layout(erp_width)
    h, w = lay.tangent_shape
    tangents = data.draw(arrays((n, max(0, h + dh), w), dtype))
    out = outcome(m360.tangents_to_erp, tangents, lay if junk_layout is None else junk_layout)
    if isinstance(out, M360Error):
        return
    assert out.shape == (20, *lay.erp_shape) and out.dtype == np.float32
    assert not np.isinf(out).any()
    if np.all(
        tangents == tangents.flat[0]
    ):  # a constant face maps to that constant (or NaN: unseen)
        seen = np.isfinite(out)
        np.testing.assert_allclose(out[seen], np.float32(tangents.flat[0]), rtol=1e-6)


# --------------------------------------------------------------------------------------------
# Stitching.

GRIDS = st.tuples(st.integers(-2, 30), st.integers(-2, 30))
ALIGN = st.one_of(
    st.sampled_from(["none", "none", "multiscale", "paper", ""]),
    GRIDS,
    st.lists(GRIDS, max_size=3),
    st.tuples(HUGE_INTS, st.integers(2, 4)),
    st.just((4.0, 3.0)),
    JUNK,
)
BLEND_OPTIONS = st.one_of(
    st.none(),
    st.dictionaries(
        st.sampled_from(["fidelity", "lam", "tolerance", "iterations", "solver", "nope"]),
        st.one_of(
            st.sampled_from(["frustum", "nn", "mean", "fused", "faer"]),
            st.floats(1e-8, 10.0),
            st.integers(1, 3000),
            HUGE_INTS,
            JUNK,
        ),
        max_size=3,
    ),
    JUNK,
)


#: Valid values of every stitch option (kept cheap: small iteration caps, loose tolerances).
STITCH_VALID = {
    "align": st.sampled_from(["none", "multiscale", (2, 2), (4, 3), [(2, 2), (4, 3)]]),
    "blend": st.sampled_from(BLEND_METHODS),
    "energy": st.sampled_from(["normalized", "paper"]),
    "solver": st.sampled_from(["newton", "lbfgs"]),
    "iterations": st.one_of(st.none(), st.integers(0, 60)),
    "tolerance": st.floats(1e-9, 1e3),
    "sample_fraction": st.floats(0.0, 1.0),
    "pole_cap_deg": st.floats(0.0, 89.0),
    "smoothness": st.one_of(st.none(), st.floats(0.0, 1e6)),
    "scale_weight": st.one_of(st.none(), st.floats(1e-6, 1e6)),
    "offsets": st.sampled_from([None, "perspective", "spherical"]),
    "blend_options": st.one_of(
        st.none(),
        st.fixed_dictionaries(
            {},
            optional={
                "fidelity": st.sampled_from(["frustum", "nn", "mean"]),
                "lam": st.floats(1e-6, 1e3),
                "tolerance": st.floats(1e-8, 0.5),
                "iterations": st.integers(1, 3000),
                "solver": st.sampled_from(["fused", "faer"]),
            },
        ),
    ),
    "mask": st.sampled_from(["none", "random"]),
    "return_details": st.booleans(),
}
#: Invalid (or edge) values of each option.
STITCH_INVALID = {
    "align": ALIGN,
    "blend": st.one_of(st.sampled_from(["", "Poisson", "mean "]), JUNK),
    "energy": JUNK,
    "solver": JUNK,
    "iterations": st.one_of(HUGE_INTS, st.integers(-3, -1), JUNK),
    "tolerance": st.one_of(st.floats(-1, 0), JUNK),
    "sample_fraction": st.one_of(st.floats(-1, 2), JUNK),
    "pole_cap_deg": st.one_of(st.floats(-10, 100), JUNK),
    "smoothness": st.one_of(st.floats(-1, 1e308), JUNK),
    "scale_weight": st.one_of(st.floats(-1, 1e308), JUNK),
    "offsets": JUNK,
    "blend_options": BLEND_OPTIONS,
    "mask": st.sampled_from(["all-false", "int", "wrong-shape", "junk"]),
    "return_details": JUNK,
}


@budget(1.5)
@given(
    erp_width=st.sampled_from([64, 128]),
    valid=st.fixed_dictionaries(STITCH_VALID),
    broken=st.lists(st.sampled_from(sorted(STITCH_INVALID)), max_size=2, unique=True),
    data=st.data(),
)
def test_fuzz_stitch_options(
    erp_width: int, valid: dict[str, Any], broken: list[str], data: st.DataObject
) -> None:
    """Every option valid, then zero to two of them replaced by invalid or edge values."""
    options = dict(valid)
    for name in broken:
        options[name] = data.draw(STITCH_INVALID[name], label=name)
    lay = layout(erp_width)
    tangents = distorted_tangents(erp_width)
    rng = np.random.default_rng(0)
    masks: dict[str, Any] = {
        "none": None,
        "random": rng.random(tangents.shape) > 0.1,
        "all-false": np.zeros(tangents.shape, bool),
        "int": np.ones(tangents.shape, int),
        "wrong-shape": np.ones(tangents.shape[1:], bool),
        "junk": "mask",
    }
    options["mask"] = masks[options["mask"]]
    if "blend" not in broken and "blend_options" not in broken and options["blend"] != "poisson":
        options["blend_options"] = None
    out = outcome(m360.stitch, tangents, lay, **options)
    if isinstance(out, M360Error):
        return
    disparity = out.disparity if options["return_details"] else out
    assert disparity.shape == lay.erp_shape and disparity.dtype == np.float32
    assert not np.isinf(disparity).any()


@budget(1.0)
@given(
    erp_width=ERP_WIDTHS,
    n=near(20),
    dtype=FLOATY,
    data=st.data(),
    align=st.sampled_from(["none", "none", "multiscale", (2, 2)]),
    blend=st.sampled_from(BLEND_METHODS),
    junk_layout=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_stitch_tangents(
    erp_width: int,
    n: int,
    dtype: Any,
    data: st.DataObject,
    align: Any,
    blend: str,
    junk_layout: Any,
) -> None:
    lay = layout(erp_width)
    tangents = data.draw(arrays((n, *lay.tangent_shape), dtype))
    target = lay if junk_layout is None else junk_layout
    out = outcome(m360.stitch, tangents, target, align=align, blend=blend)
    if isinstance(out, M360Error):
        return
    assert out.shape == lay.erp_shape and out.dtype == np.float32
    assert not np.isinf(out).any()


@budget(0.8)
@given(
    erp_width=ERP_WIDTHS,
    value=st.floats(1e-3, 1e3),
    holes=st.one_of(st.just(0.0), st.floats(0.0, 0.02)),
    seed=st.integers(0, 2**16),
    blend=st.sampled_from(BLEND_METHODS),
    fidelity=st.sampled_from(["frustum", "nn", "mean"]),
)
def test_fuzz_stitch_keeps_working_on_valid_input(
    erp_width: int, value: float, holes: float, seed: int, blend: str, fidelity: str
) -> None:
    """A sphere around the camera: perspective disparity value·|q| on every tangent, i.e. the
    spherical disparity `value` everywhere. Whatever the blend and the holes, the stitch is
    that value wherever it is defined (oracle: |q| by numpy from the intrinsics)."""
    lay = layout(erp_width)
    tangents = (value * ray_lengths(erp_width)).astype(np.float32)
    tangents[np.random.default_rng(seed).random(tangents.shape) < holes] = np.nan
    options = {"fidelity": fidelity} if blend == "poisson" else None
    out = outcome(m360.stitch, tangents, lay, align="none", blend=blend, blend_options=options)
    assert not isinstance(out, M360Error), out
    seen = np.isfinite(out)
    assert seen.all() if holes == 0 else seen.mean() > 0.8
    np.testing.assert_allclose(out[seen], value, rtol=2e-5)


# --------------------------------------------------------------------------------------------
# End to end.


class _Misbehaving:
    """A user estimator that returns junk (or raises)."""

    output_kind = "affine_disparity"

    def __init__(self, result: Any) -> None:
        self.result = result

    def predict(self, tangents: np.ndarray) -> Any:
        if isinstance(self.result, Exception):
            raise self.result
        if callable(self.result):
            return self.result(tangents)
        return self.result


@pytest.fixture(scope="module")
def offline(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """No network, an empty model cache, and a tiny ONNX model: the folder holding it."""
    folder = tmp_path_factory.mktemp("fuzz-models")
    onnx_graphs.affine_of_mean(folder / "tiny.onnx", 1.0, 0.5)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("M360_OFFLINE", "1")
        mp.setenv("M360_HOME", str(folder / "home"))
        mp.delenv("M360_MODEL_DIR", raising=False)
        mp.delenv("M360_ALLOW_UNVERIFIED", raising=False)
        yield folder


@functools.lru_cache(maxsize=1)
def panorama() -> tuple[np.ndarray, SimulatedEstimator]:
    rgb, _ = syn.render(syn.room(3), 128)
    return rgb, SimulatedEstimator(syn.room(3), layout(128), seed=1)


MODEL_KINDS = [
    "simulated",
    "simulated",
    "onnx",
    "registry",
    "unknown",
    "long-name",
    "nul",
    "folder",
    "misbehaving",
    "junk",
]
MISBEHAVIOUR = st.sampled_from(
    [
        "string",
        np.zeros((20, 3, 3), np.float32),
        np.zeros((20, 11, 12), np.int32),
        ValueError("boom"),
        MemoryError(),
        lambda t: np.full(t.shape[:3], np.inf, np.float32),
        lambda t: np.full(t.shape[:3], np.nan, np.float32),
        lambda t: np.full(t.shape[:3], 1e-45, np.float32),
        lambda t: np.ones(t.shape[:3], np.float64) * 1e300,
    ]
)


@budget(0.5)
@given(
    erp=maybe(st.one_of(st.sampled_from(["float", "grey"]), erp_images(), JUNK), st.just("valid")),
    model=maybe(st.sampled_from(MODEL_KINDS), st.sampled_from(["simulated", "onnx"])),
    misbehaviour=MISBEHAVIOUR,
    kind=st.sampled_from(["affine_disparity", "metric_depth", "distance"]),
    align=maybe(st.sampled_from(["bad", (1, 1)]), st.sampled_from(["none", "multiscale"])),
    blend=maybe(st.sampled_from(["", 3]), st.sampled_from(["mean", "nn", "frustum", "poisson"])),
    options=maybe(
        st.dictionaries(
            st.sampled_from(
                [
                    "layout",
                    "mask",
                    "providers",
                    "threads",
                    "input_size",
                    "output_kind",
                    "mean",
                    "std",
                ]
            ),
            st.one_of(
                JUNK, st.integers(1, 64), st.tuples(st.integers(-1, 64), st.integers(-1, 64))
            ),
            min_size=1,
            max_size=2,
        ),
        st.just({}),
    ),
    junk=JUNK,
)
def test_fuzz_estimate(
    offline: Path,
    erp: Any,
    model: str,
    misbehaviour: Any,
    kind: str,
    align: str,
    blend: Any,
    options: dict[str, Any],
    junk: Any,
) -> None:
    rgb, simulated = panorama()
    if isinstance(erp, str):
        erp = {"valid": rgb, "float": rgb / 255.0, "grey": rgb[..., 0]}.get(erp, erp)
    misbehaving = _Misbehaving(misbehaviour)
    misbehaving.output_kind = kind
    chosen: Any = {
        "simulated": simulated,
        "onnx": offline / "tiny.onnx",
        "registry": "midas-v21-small",
        "unknown": "midas-v9",
        "long-name": "x" * 5000 + ".onnx",
        "nul": "a\x00b.onnx",
        "folder": str(offline),
        "misbehaving": misbehaving,
        "junk": junk,
    }[model]
    options = dict(options)  # st.just({}) hands out one shared dict
    if model == "onnx":
        options.setdefault("input_size", (32, 32))  # keep the tiny network cheap
    result = outcome(m360.estimate, erp, chosen, align=align, blend=blend, **options)
    if isinstance(result, M360Error):
        return
    assert result.disparity.shape == (64, 128) and result.disparity.dtype == np.float32
    assert result.depth.shape == (64, 128)
    assert not np.isinf(result.disparity).any()


@budget(0.3)
@given(
    path=st.sampled_from(["tiny", "tiny", "missing", "folder", "long", "nul", "junk"]),
    kwargs=st.dictionaries(
        st.sampled_from(
            [
                "output_kind",
                "input_size",
                "mean",
                "std",
                "multiple_of",
                "resize",
                "providers",
                "threads",
                "batch_size",
                "name",
                "sha256",
            ]
        ),
        st.one_of(
            JUNK,
            st.integers(1, 64),
            st.just((0.5, 0.5, 0.5)),
            st.just(["CPUExecutionProvider"]),
            st.just((1e-300, 1.0, 1.0)),
            st.just((1e300, 0.0, 0.0)),
        ),
        max_size=3,
    ),
    tangents=st.one_of(st.integers(0, 4).flatmap(lambda h: arrays((1, h, 4, 3))), JUNK),
    junk=JUNK,
)
def test_fuzz_onnx_estimator(
    offline: Path, path: str, kwargs: dict[str, Any], tangents: Any, junk: Any
) -> None:
    chosen = {
        "tiny": offline / "tiny.onnx",
        "missing": offline / "missing.onnx",
        "folder": offline,
        "long": "y" * 5000,
        "nul": "a\x00b",
        "junk": junk,
    }[path]
    kwargs.setdefault("input_size", (16, 16))
    estimator = outcome(OnnxEstimator, chosen, **kwargs)
    if isinstance(estimator, M360Error):
        return
    out = outcome(estimator.predict, tangents)
    if not isinstance(out, M360Error):
        assert out.shape == np.shape(tangents)[:3] and out.dtype == np.float32


@budget(0.4)
@given(
    values=st.one_of(st.integers(-1, 1).flatmap(lambda d: arrays((20, 22 + d, 25))), JUNK),
    kind=st.one_of(st.sampled_from(["affine_disparity", "metric_depth", "distance"]), JUNK),
    junk_layout=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_to_perspective_disparity(values: Any, kind: Any, junk_layout: Any) -> None:
    lay = layout(128) if junk_layout is None else junk_layout
    out = outcome(to_perspective_disparity, values, kind, lay)
    if not isinstance(out, M360Error):
        assert out.shape == (20, 22, 25) and out.dtype == np.float32
        if kind != "affine_disparity":
            assert not np.isinf(out).any()


@budget(0.5)
@given(
    function=st.sampled_from(["get", "is_cached", "ensure", "fetch", "sha256_of", "verify"]),
    name=st.one_of(st.sampled_from(models.names()), st.text(max_size=12), JUNK),
    path=st.sampled_from(["file", "missing", "folder", "nul", "long", "junk"]),
    junk=JUNK,
)
def test_fuzz_models(offline: Path, function: str, name: Any, path: str, junk: Any) -> None:
    paths: dict[str, Any] = {
        "file": offline / "tiny.onnx",
        "missing": offline / "missing.onnx",
        "folder": offline,
        "nul": "a\x00b",
        "long": "z" * 5000,
        "junk": junk,
    }
    if function == "sha256_of":
        out = outcome(models.sha256_of, paths[path])
        if not isinstance(out, M360Error):
            assert len(out) == 64
    elif function == "verify":
        entry = models.REGISTRY.get(name, junk) if isinstance(name, str) else junk
        out = outcome(models.verify, entry, paths[path])
        assert isinstance(out, M360Error)  # nothing here matches a registered hash
    else:
        out = outcome(getattr(models, function), name)
        assert function in ("get", "is_cached") or isinstance(out, M360Error)  # offline


@budget(0.3)
@given(threads=st.one_of(st.integers(1, 4), st.integers(-3, 0), HUGE_INTS, JUNK))
def test_fuzz_set_num_threads(threads: Any) -> None:
    before = m360.get_num_threads()
    try:
        out = outcome(m360.set_num_threads, threads)
        if not isinstance(out, M360Error) and threads is not None:
            assert m360.get_num_threads() == threads
    finally:
        m360.set_num_threads(before)


# --------------------------------------------------------------------------------------------
# Evaluation.


@budget(0.8)
@given(
    height=st.sampled_from([0, 1, 4, 16]),
    wide=st.sampled_from([2, 2, 2, 1, 3]),
    data=st.data(),
    valid=st.sampled_from(["none", "random", "int", "wrong-shape", "junk"]),
    pole_cap_deg=maybe(st.one_of(JUNK, st.floats(-10, 200)), st.floats(0.0, 89.0)),
    weighting=maybe(JUNK, st.sampled_from(["uniform", "solid_angle"])),
    junk=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_depth_metrics(
    height: int,
    wide: int,
    data: st.DataObject,
    valid: str,
    pole_cap_deg: Any,
    weighting: Any,
    junk: Any,
) -> None:
    shape = (height, wide * height)
    pred = data.draw(arrays(shape))
    gt = data.draw(arrays(shape))
    masks: dict[str, Any] = {
        "none": None,
        "random": np.random.default_rng(height).random(shape) > 0.2,
        "int": np.ones(shape, int),
        "wrong-shape": np.ones((1, 2), bool),
        "junk": "valid",
    }
    out = outcome(
        eval.depth_metrics,
        pred if junk is None else junk,
        gt,
        valid=masks[valid],
        pole_cap_deg=pole_cap_deg,
        weighting=weighting,
    )
    if isinstance(out, M360Error):
        return
    for key in ("abs_rel", "mae", "rmse", "rmse_log10"):
        assert out[key] >= 0  # inf when the fit overflows, never NaN
    for key in ("delta1", "delta2", "delta3", "coverage"):
        assert 0 <= out[key] <= 1
    assert 1 <= out["n_valid"] <= pred.size


@budget(0.8)
@given(
    size=st.integers(0, 50),
    data=st.data(),
    weights=st.sampled_from(["none", "random", "zero", "negative", "wrong-shape", "junk"]),
    junk=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_fit_scale_shift(size: int, data: st.DataObject, weights: str, junk: Any) -> None:
    pred = data.draw(arrays((size,)))
    gt = data.draw(arrays((size,)))
    w: Any = {
        "none": None,
        "random": np.random.default_rng(size).random(size),
        "zero": np.zeros(size),
        "negative": -np.ones(size),
        "wrong-shape": np.ones(size + 1),
        "junk": "w",
    }[weights]
    out = outcome(eval.fit_scale_shift, pred if junk is None else junk, gt, w)
    if not isinstance(out, M360Error):
        assert all(np.isfinite(out))


@budget(0.6)
@given(
    size=st.integers(2, 40),
    exponent=st.integers(-150, 150),
    scale=st.floats(-1e3, 1e3).filter(lambda s: abs(s) > 1e-3),
    shift=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**16),
)
def test_fuzz_fit_scale_shift_recovers_an_exact_affine_map(
    size: int, exponent: int, scale: float, shift: float, seed: int
) -> None:
    """Valid input at any magnitude: gt = scale·pred + shift exactly ⇒ the fit returns them."""
    pred = np.random.default_rng(seed).normal(size=size) * 10.0**exponent
    if np.ptp(pred) == 0:
        return
    unit = 10.0**exponent
    gt = scale * pred + shift * unit
    fitted_scale, fitted_shift = outcome(eval.fit_scale_shift, pred, gt)
    assert fitted_scale == pytest.approx(scale, rel=1e-6)
    assert fitted_shift == pytest.approx(shift * unit, rel=1e-6, abs=1e-6 * abs(scale) * unit)


@budget(0.5)
@given(
    data=st.data(),
    dw=st.sampled_from([0, 0, 0, 2]),
    band=maybe(st.one_of(HUGE_INTS, JUNK, st.integers(-3, 100)), st.integers(0, 4)),
    junk_layout=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_seam_score(data: st.DataObject, dw: int, band: Any, junk_layout: Any) -> None:
    lay = layout(128)
    shape = (64, 128 + dw)
    pred = data.draw(arrays(shape))
    gt = data.draw(arrays(shape))
    out = outcome(eval.seam_score, pred, gt, lay if junk_layout is None else junk_layout, band=band)
    if not isinstance(out, M360Error):
        assert set(out) == {"borders", "triangles", "elsewhere"}
        assert not out["elsewhere"] < 0


# --------------------------------------------------------------------------------------------
# Synthetic scenes.


@budget(0.6)
@given(
    seed=st.one_of(st.integers(0, 2**40), st.integers(-5, -1), HUGE_INTS, JUNK),
    erp_width=st.one_of(st.sampled_from([8, 16, 32]), st.integers(-4, 9), HUGE_INTS, JUNK),
    junk_scene=st.one_of(st.none(), st.none(), JUNK),
)
def test_fuzz_room_and_render(seed: Any, erp_width: Any, junk_scene: Any) -> None:
    scene = outcome(syn.room, seed)
    if isinstance(scene, M360Error):
        return
    out = outcome(syn.render, scene if junk_scene is None else junk_scene, erp_width)
    if not isinstance(out, M360Error):
        rgb, depth = out
        assert rgb.shape == (erp_width // 2, erp_width, 3) and rgb.dtype == np.uint8
        assert np.all(np.isfinite(depth)) and np.all(depth > 0)


NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-3, 3), JUNK)
VECTORS = st.one_of(
    st.lists(st.floats(-5, 5), min_size=3, max_size=3),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3),
    st.just([-1e300, 1e300, 0.0]),
    JUNK,
)


@budget(0.8)
@given(
    part=st.sampled_from(["scene", "box", "sphere", "material", "light", "rotation"]),
    first=VECTORS,
    second=VECTORS,
    number=NUMBERS,
    flag=st.one_of(st.booleans(), JUNK),
    items=st.one_of(st.none(), JUNK, st.lists(JUNK, max_size=2)),
)
def test_fuzz_scene_parts(
    part: str, first: Any, second: Any, number: Any, flag: Any, items: Any
) -> None:
    """Scene building blocks with junk fields; a built scene must render (16 px) and ray cast."""
    build: dict[str, Callable[[], Any]] = {
        "scene": lambda: syn.Scene(
            room_min=first,
            room_max=second,
            boxes=() if items is None else items,
            ambient=number,
            shadows=flag,
        ),
        "box": lambda: syn.Scene(
            room_min=[-3, -3, -3],
            room_max=[3, 3, 3],
            boxes=(syn.Box(center=first, half_size=second, rotation=np.eye(3)),),
        ),
        "sphere": lambda: syn.Scene(
            room_min=[-3, -3, -3],
            room_max=[3, 3, 3],
            spheres=(syn.Sphere(center=first, radius=number),),
        ),
        "material": lambda: syn.Material(albedo=first, period=number, phase=second),
        "light": lambda: syn.Scene(
            room_min=[-3, -3, -3],
            room_max=[3, 3, 3],
            lights=(syn.Light(position=first, intensity=number),),
        ),
        "rotation": lambda: syn.rotation_matrix(number, 0.0, 0.0),
    }
    built = outcome(build[part])
    if isinstance(built, syn.Scene):
        out = outcome(syn.render, built, 16)
        if not isinstance(out, M360Error):
            assert np.all(np.isfinite(out[1]))
        cams = layout(64).cameras
        distance = outcome(syn.tangent_distance, built, cams)
        if not isinstance(distance, M360Error):
            assert np.all(np.isfinite(distance))


@budget(0.6)
@given(
    n=st.integers(0, 3),
    data=st.data(),
    seed=st.one_of(st.integers(0, 100), JUNK),
    scale=maybe(
        st.one_of(JUNK, st.just((1e308, 1e308)), st.tuples(st.floats(-1, 4), st.floats(-1, 4))),
        st.tuples(st.floats(0.1, 1), st.floats(1, 4)),
    ),
    shift=maybe(NUMBERS, st.floats(0, 1)),
    field=maybe(NUMBERS, st.floats(0, 0.9)),
    noise=maybe(NUMBERS, st.floats(0, 0.1)),
)
def test_fuzz_distort(
    n: int, data: st.DataObject, seed: Any, scale: Any, shift: Any, field: Any, noise: Any
) -> None:
    tangents = data.draw(st.one_of(arrays((n, 3, 4)), arrays((n, 3)), JUNK))
    out = outcome(syn.distort, tangents, seed, scale=scale, shift=shift, field=field, noise=noise)
    if not isinstance(out, M360Error):
        assert out.shape == (n, 3, 4) and out.dtype == np.float32


@budget(0.5)
@given(
    changes=st.lists(
        st.tuples(CAMERA_FIELDS, st.one_of(JUNK, st.integers(-3, 300), HUGE_INTS)),
        max_size=2,
    ),
    cameras_junk=st.one_of(st.none(), st.none(), JUNK, st.lists(JUNK, min_size=1, max_size=2)),
    function=st.sampled_from(["distance", "perspective"]),
)
def test_fuzz_tangent_ground_truth(changes: list[Any], cameras_junk: Any, function: str) -> None:
    camera: Any = layout(64).cameras[0]
    for name, value in changes:
        camera = replace(camera, **{name: value})
    cameras = [camera] if cameras_junk is None else cameras_junk
    call = syn.tangent_distance if function == "distance" else syn.tangent_perspective_disparity
    out = outcome(call, syn.room(0), cameras)
    if not isinstance(out, M360Error):
        assert out.shape == (1, int(camera.height), int(camera.width))
        assert np.all(np.isfinite(out))
