"""Radial depth from a spherical disparity map (docs/conventions.md: depth = 1 / disparity)."""

from __future__ import annotations

import numpy as np

__all__ = ["depth_of"]


def depth_of(disparity: np.ndarray) -> np.ndarray:
    """Depth (float32) = 1 / disparity where the disparity is positive, NaN elsewhere.

    One output array, filled a block of rows (about a million pixels) at a time: no
    full-size temporaries (at 72 MP each is 288 MB, and fresh memory is slow to touch the
    first time).
    """
    depth = np.empty(disparity.shape, np.float32)
    height = len(depth)
    rows = max(1, (1 << 20) // max(1, depth.size // max(1, height)))  # ~a million pixels a block
    for start in range(0, height, rows):
        d, out = disparity[start : start + rows], depth[start : start + rows]
        positive = d > 0
        out.fill(np.nan)
        np.divide(np.float32(1), d, out=out, where=positive, casting="unsafe")
    return depth
