"""Generic checks at the Python door: types, shapes, dtypes and plain ranges of arguments.

Each failure raises :class:`m360.errors.InputError` naming the argument, what it is and what was
expected, so a batch log says what to fix. Option *values* of the stitcher (names, defaults,
limits) are the core's: :mod:`m360.options` only normalises their types here and lets
``_core.stitch_options`` judge them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from . import _core
from .errors import AspectRatioError, InputError

#: Largest ERP width m360 accepts (the core's limit, see rust/m360-core/src/layout.rs).
MAX_ERP_WIDTH = int(_core.LIMITS["max_erp_width"])
#: Largest thread count m360 (or ONNX Runtime through it) will start: absurd counts are refused
#: before any thread is spawned. The core's limit.
MAX_THREADS: int = int(_core.LIMITS["max_threads"])
#: Largest integer an option of the core can hold (a signed 64-bit count).
_MAX_INT64 = (1 << 63) - 1


def as_array(value: Any, name: str) -> np.ndarray:
    """``value`` as an ndarray, or InputError if it is not array-like."""
    if type(value) is np.ndarray and value.dtype.kind in "biuf":
        return value
    try:
        array = np.asarray(value)
    except Exception as exc:  # numpy raises many kinds for ragged or odd objects
        raise InputError(f"{name} is not an array: {type(value).__name__}") from exc
    if array.dtype.kind not in "biuf":
        raise InputError(
            f"{name} is not a numeric array: {type(value).__name__} of dtype {array.dtype}"
        )
    return array


def real_array(value: Any, name: str) -> np.ndarray:
    """``value`` as a float64 ndarray (bool, integer and float inputs), or InputError."""
    array = as_array(value, name)
    return array.astype(np.float64, copy=False)


def number(value: Any, name: str, low: float | None = None, high: float | None = None) -> float:
    """``value`` as a finite float in [low, high]; bools, strings and huge ints are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InputError(f"{name}={value!r} must be a number")
    try:
        result = float(value)
    except OverflowError:  # an int beyond the float range
        result = float("inf")
    if (
        not np.isfinite(result)
        or (low is not None and result < low)
        or (high is not None and result > high)
    ):
        bounds = f"[{low if low is not None else '-inf'}, {high if high is not None else 'inf'}]"
        raise InputError(f"{name}={value!r} must be a finite number in {bounds}")
    return result


def integer(value: Any, name: str, low: int = 0, high: int | None = None) -> int:
    """``value`` as an int in [low, high]; bools, floats and strings are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name}={value!r} must be an integer")
    result = int(value)
    if result < low or (high is not None and result > high):
        bounds = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise InputError(f"{name}={value!r} must be an integer {bounds}")
    return result


def threads(value: Any, name: str = "threads") -> int | None:
    """A thread count in [1, the core's ``max_threads``], or None (the default count)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be a positive integer or None, got {value!r}")
    if not 1 <= value <= MAX_THREADS:
        raise InputError(f"{name} must be a positive integer up to {MAX_THREADS}, got {value!r}")
    return int(value)


def real(value: Any, name: str) -> float:
    """``value`` as a float (its range is the core's to judge); bools and non-numbers refused.

    An int beyond the float range becomes ``inf``, which the core refuses by name.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InputError(f"{name}={value!r} must be a number")
    try:
        return float(value)
    except OverflowError:
        return float("inf")


def count(value: Any, name: str, high: int | None = None) -> int:
    """``value`` as a non-negative int that fits the core's counters (its range is the core's).

    ``high`` only names the core's limit in the message.
    """
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not (0 <= int(value) <= _MAX_INT64)
    ):
        bound = f"in [0, {high}]" if high is not None else ">= 0"
        raise InputError(f"{name}={value!r} must be an integer {bound}")
    return int(value)


def text(value: Any, name: str, choices: Sequence[str]) -> str:
    """``value`` if it is a str (whether it is one of ``choices`` is the core's to judge)."""
    if not isinstance(value, str):
        options = ", ".join(repr(c) for c in choices)
        raise InputError(f"{name}={value!r} is not supported; choose one of {options}")
    return value


def size_pair(value: Any, name: str, high: int) -> tuple[int, int]:
    """``(height, width)`` of two ints in [1, high]; one int means a square."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        value = (value, value)
    try:
        h, w = value
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be (height, width), got {value!r}") from exc
    for v in (h, w):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= high:
            raise InputError(
                f"{name} must be two integers in [1, {high}] (height, width), got {value!r}"
            )
    return int(h), int(w)


def flag(value: Any, name: str) -> bool:
    """``value`` if it is True or False."""
    if not isinstance(value, bool):
        raise InputError(f"{name} must be True or False, got {value!r}")
    return value


def seed(value: Any, name: str = "seed") -> int | None:
    """A seed for ``np.random.default_rng``: a non-negative integer (or None: fresh entropy)."""
    if value is None:
        return None
    return integer(value, name, low=0)


def check_shape(array: np.ndarray, name: str, dims: Sequence[str], **expected: int) -> None:
    """Check ``array.ndim == len(dims)`` and every dimension named in ``expected``.

    >>> check_shape(tangents, "tangents", ("N", "h", "w"), N=20, h=346, w=400)
    """
    if array.ndim != len(dims):
        raise InputError(
            f"{name} must have {len(dims)} dimensions ({', '.join(dims)}), got shape {array.shape}"
        )
    for dim, size in zip(dims, array.shape, strict=True):
        if dim in expected and size != expected[dim]:
            want = tuple(expected.get(d, d) for d in dims)
            raise InputError(f"{name} has shape {array.shape}, expected {want} ({dim} = {size})")


def check_erp_shape(height: int, width: int, name: str) -> None:
    """ERP images are H x 2H, and not empty."""
    if height < 1 or width < 1:
        raise InputError(f"{name} is {height}x{width} (HxW): an empty image")
    if width != 2 * height:
        raise AspectRatioError(
            f"{name} is {height}x{width} (HxW) but an equirectangular image must have "
            f"W == 2H (expected width {2 * height} for height {height})"
        )


def erp_map(value: Any, name: str, *, integers: bool = False, shape: str = "(H, W)") -> np.ndarray:
    """``value`` as a 2D ERP array (W == 2H, H >= 2) of a float (or with ``integers``, an integer)
    dtype, not converted; else an InputError naming ``name`` and the ``shape`` expected."""
    array = as_array(value, name)
    if array.ndim != 2 or array.shape[0] < 2 or array.shape[1] != 2 * array.shape[0]:
        raise InputError(
            f"{name} must be an ERP map of shape {shape} with W == 2H (width = 2 x height, at "
            f"least 2 x 4), got {array.shape}"
        )
    if array.dtype.kind not in ("fiu" if integers else "f"):
        raise InputError(f"{name} must be a float array (NaN = invalid), got dtype {array.dtype}")
    return array


def float32_array(array: np.ndarray, name: str, *, allow_nan: bool = True) -> np.ndarray:
    """A C-contiguous float32 copy or view; float64/float16 are converted, infinities refused."""
    if array.dtype.kind != "f":
        raise InputError(
            f"{name} must be a float array (float32 preferred), got dtype {array.dtype}"
        )
    with np.errstate(over="ignore"):  # float64 beyond the float32 range becomes inf, refused below
        out = np.ascontiguousarray(array, dtype=np.float32)
    bad = ~np.isfinite(out) if not allow_nan else np.isinf(out)
    if bad.any():
        what = (
            "NaN or infinite (or beyond float32)"
            if not allow_nan
            else "infinite (or beyond float32)"
        )
        raise InputError(
            f"{name} has {int(bad.sum())} {what} values"
            + (" (NaN marks invalid pixels; inf is not allowed)" if allow_nan else "")
        )
    return out


def one_of(value: Any, name: str, choices: Sequence[str]) -> str:
    """``value`` if it is one of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        options = ", ".join(repr(c) for c in choices)
        raise InputError(f"{name}={value!r} is not supported; choose one of {options}")
    return value
