"""A simulated network for the demo and the tests: exact disparity, distorted per tangent."""

from __future__ import annotations

from typing import Any

import numpy as np

from .._compat import renamed
from ..errors import InputError
from ..geometry.layout import Layout

__all__ = ["SimulatedEstimator"]


class SimulatedEstimator:
    """NOT a network: exact tangent disparity of a synthetic scene, distorted per tangent.

    It returns what a *perfect* affine-invariant network would give on
    :mod:`m360.synthetic` scenes: the ray-cast perspective disparity of each tangent, with a
    random scale and shift per tangent and optional gaussian noise
    (:func:`m360.synthetic.distort`). The tangents it is given are only checked for shape. Used by
    ``m360 demo`` and the tests; never by ``m360 run``.

    Parameters
    ----------
    scene : m360.synthetic.Scene
    layout : Layout
        The layout :func:`estimate` will use (its cameras are ray cast).
    seed : int
        Seed of the distortion.
    scale : (float, float)
        Range of the log-uniform scale per tangent.
    shift : float
        Shift amplitude relative to each tangent's median disparity.
    noise : float
        Relative gaussian noise std.
    """

    output_kind = "affine_disparity"

    def __init__(
        self,
        scene: Any,
        layout: Layout,
        *,
        seed: int = 0,
        scale: tuple[float, float] = (0.5, 2.0),
        shift: float = 0.3,
        noise: float = 0.0,
    ) -> None:
        from ..evaluation import synthetic

        if not isinstance(layout, Layout):
            raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
        self.layout = layout
        self.exact = synthetic.tangent_perspective_disparity(scene, layout.cameras)
        self._tangents = synthetic.distort(self.exact, seed, scale=scale, shift=shift, noise=noise)
        self.name = f"simulated (exact disparity, per-tangent affine, noise {noise:g})"

    @renamed(tiles="tangents")
    def predict(self, tangents: np.ndarray) -> np.ndarray:
        """Return the distorted exact disparities (N, h, w) float32 of the layout's tangents.

        K panoramas' tangents in one call (K·N of them) give the same N maps K times.
        """
        n, tile = len(self.layout), self.layout.tangent_shape
        shape = tuple(np.shape(tangents)[:3])
        if len(shape) != 3 or not shape[0] or shape[0] % n or shape[1:] != tile:
            raise InputError(
                f"SimulatedEstimator was built for tangents of shape {(n, *tile)} (or K "
                f"panoramas': K·{n}), got {np.shape(tangents)}"
            )
        return np.tile(self._tangents, (shape[0] // n, 1, 1))
