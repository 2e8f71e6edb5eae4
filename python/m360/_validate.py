"""Checks at the Python door: every user argument is validated here before it reaches the core.

Each failure raises :class:`m360.errors.InputError` naming the argument, what it is and what was
expected, so a batch log says what to fix.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import AspectRatioError, InputError


def as_array(value: Any, name: str) -> np.ndarray:
    """``value`` as an ndarray, or InputError if it is not array-like."""
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
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


def check_shape(array: np.ndarray, name: str, dims: Sequence[str], **expected: int) -> None:
    """Check ``array.ndim == len(dims)`` and every dimension named in ``expected``.

    >>> check_shape(tiles, "tiles", ("N", "h", "w"), N=20, h=346, w=400)
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
    """ERP images are H x 2H."""
    if width != 2 * height:
        raise AspectRatioError(
            f"{name} is {height}x{width} (HxW) but an equirectangular image must have "
            f"W == 2H (expected width {2 * height} for height {height})"
        )


def float32_array(array: np.ndarray, name: str, *, allow_nan: bool = True) -> np.ndarray:
    """A C-contiguous float32 copy or view; float64/float16 are converted, infinities refused."""
    if array.dtype.kind != "f":
        raise InputError(
            f"{name} must be a float array (float32 preferred), got dtype {array.dtype}"
        )
    out = np.ascontiguousarray(array, dtype=np.float32)
    bad = ~np.isfinite(out) if not allow_nan else np.isinf(out)
    if bad.any():
        what = "NaN or infinite" if not allow_nan else "infinite"
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
