# Stub of the compiled module m360._core (rust/m360-py); checked by `mypy.stubtest m360._core`.
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "CHOICES",
    "DEFAULTS",
    "LIMITS",
    "PLAN_FILE_SUFFIX",
    "PLAN_FORMAT",
    "Plan",
    "__version__",
    "bilinear_upsample",
    "get_num_threads",
    "guided_fit",
    "guided_upsample",
    "icosahedron_cameras",
    "ods_defaults",
    "ods_stereo",
    "poisson_blend",
    "refine_edges",
    "set_num_threads",
    "stitch_options",
    "upsample_planes",
]
__version__: str
# Option names per kind, the first the default: blend, fidelity, poisson_solver, energy, solver,
# offsets, loss, weights.
CHOICES: dict[str, tuple[str, ...]]
# max_threads, max_iterations, min_poisson_tolerance, max_pole_cap_deg.
LIMITS: dict[str, Any]
# align, blend (the resolved defaults), poisson (the Poisson blend's options), and per energy or
# solver: schedules, iterations, weights (smoothness, scale_weight), offsets, losses.
DEFAULTS: dict[str, Any]
# Plan cache files: their extension, and "v<format>-<version>+<core source hash>" in their names.
PLAN_FILE_SUFFIX: str
PLAN_FORMAT: str

def set_num_threads(threads: int | None = None) -> None: ...
def get_num_threads() -> int: ...
def icosahedron_cameras(
    erp_width: int, padding: float = 0.3, tangent_width: int | None = None, subdivisions: int = 0
) -> tuple[
    npt.NDArray[np.float64], npt.NDArray[np.float64], tuple[int, int], npt.NDArray[np.float64]
]: ...
def stitch_options(
    align: dict[str, Any] | None,
    blend: dict[str, Any],
    tangent_shape: tuple[int, int] | None = None,
) -> tuple[dict[str, Any] | None, dict[str, Any]]: ...

@final
class Plan:
    def __new__(
        cls,
        erp_shape: tuple[int, int],
        rotations: npt.NDArray[np.float64],
        intrinsics: npt.NDArray[np.float64],
        tangent_shape: tuple[int, int],
    ) -> Plan: ...
    def prepare(self, which: str = "all") -> None: ...
    def set_cache_dir(self, path: str | os.PathLike[str] | None = None) -> None: ...
    def cache_dir(self) -> Path | None: ...
    def cache_stats(self) -> dict[str, int]: ...
    def memory_bytes(self) -> int: ...
    def coverage(self) -> npt.NDArray[np.uint8]: ...
    def erp_to_tangents(
        self, erp: npt.NDArray[np.uint8] | npt.NDArray[np.float32]
    ) -> npt.NDArray[np.uint8] | npt.NDArray[np.float32]: ...
    def tangents_to_erp(
        self, tangents: npt.NDArray[np.float32], sampling: str = "bilinear"
    ) -> npt.NDArray[np.float32]: ...
    def spherical_disparity(
        self, perspective: npt.NDArray[np.float32], mask: npt.NDArray[np.bool_] | None = None
    ) -> npt.NDArray[np.float32]: ...
    def ray_lengths(self) -> npt.NDArray[np.float32]: ...
    def align(
        self, maps: npt.NDArray[np.float32], align: dict[str, Any], in_place: bool = False
    ) -> tuple[
        npt.NDArray[np.float32], list[dict[str, Any]], list[npt.NDArray[np.float64]], str
    ]: ...
    def align_with_prior(
        self,
        maps: npt.NDArray[np.float32],
        align: dict[str, Any],
        prior: npt.NDArray[np.float32],
        prior_confidence: npt.NDArray[np.float32] | None = None,
        absolute: bool = False,
        in_place: bool = False,
    ) -> tuple[
        npt.NDArray[np.float32],
        list[dict[str, Any]],
        list[npt.NDArray[np.float64]],
        str,
        dict[str, Any] | None,
    ]: ...
    def alignment_energy(
        self,
        maps: npt.NDArray[np.float32],
        grid: tuple[int, int],
        align: dict[str, Any],
        x: Sequence[float] | npt.NDArray[np.float64] | None = None,
        prior: npt.NDArray[np.float32] | None = None,
        prior_confidence: npt.NDArray[np.float32] | None = None,
        reweight_at: Sequence[float] | npt.NDArray[np.float64] | None = None,
    ) -> tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
    def alignment_problem(
        self, maps: npt.NDArray[np.float32], grid: tuple[int, int], align: dict[str, Any]
    ) -> dict[str, Any]: ...
    def blend(
        self,
        tangents: npt.NDArray[np.float32],
        blend: dict[str, Any],
        confidence: bool = True,
        prior: npt.NDArray[np.float32] | None = None,
        prior_confidence: npt.NDArray[np.float32] | None = None,
        prior_affine: tuple[float, float] = ...,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None, dict[str, Any]]: ...
    def blend_weights(self, kind: str) -> npt.NDArray[np.float32]: ...

def poisson_blend(
    values: npt.NDArray[np.float32],
    weights: npt.NDArray[np.float32],
    target: npt.NDArray[np.float32],
    blend: dict[str, Any] | None = None,
) -> tuple[npt.NDArray[np.float64], dict[str, Any]]: ...
def upsample_planes(
    planes: npt.NDArray[np.float32],
    out_shape: tuple[int, int],
    grey: npt.NDArray[np.uint8] | None = None,
) -> npt.NDArray[np.float32]: ...
def guided_fit(
    disparity: npt.NDArray[np.float32],
    grey: npt.NDArray[np.uint8],
    radius: int,
    eps: float,
    edge_low: float,
    edge_high: float,
) -> npt.NDArray[np.float32]: ...
def guided_upsample(
    disparity: npt.NDArray[np.float32],
    grey: npt.NDArray[np.uint8],
    grey_full: npt.NDArray[np.uint8],
    radius: int,
    eps: float,
    edge_low: float,
    edge_high: float,
) -> npt.NDArray[np.float32]: ...
def refine_edges(
    disparity: npt.NDArray[np.float32],
    rgb: npt.NDArray[np.uint8],
    radius: int,
    colour_sigma: float,
    transition: float,
    jump: float,
) -> npt.NDArray[np.float32]: ...
def ods_stereo(
    rgb: npt.NDArray[np.uint8],
    depth: npt.NDArray[np.float32],
    ipd: float,
    pole_fade: float,
    max_depth_ratio: float,
) -> tuple[
    npt.NDArray[np.uint8],
    npt.NDArray[np.uint8],
    npt.NDArray[np.bool_],
    npt.NDArray[np.bool_],
    int,
    int,
]: ...
def ods_defaults() -> dict[str, float]: ...
def bilinear_upsample(
    disparity: npt.NDArray[np.float32], out_shape: tuple[int, int]
) -> npt.NDArray[np.float32]: ...
