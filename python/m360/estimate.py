"""The end-to-end job: ERP image in, ERP disparity and depth out (:func:`estimate`).

:func:`estimate` projects the panorama onto the layout's tangents, runs an estimator
(:mod:`m360.estimators`), converts its output to perspective disparity and stitches
(:func:`m360.stitch`). The estimators lived here before; their old names still import from
here, with a DeprecationWarning pointing to :mod:`m360.estimators`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import estimators as _estimators
from . import models as _models
from ._compat import moved
from ._validate import as_array, check_erp_shape
from .align import AlignSolver, Energy, Loss, Offsets
from .blend import BlendMethod
from .errors import InputError, M360Error, ModelError
from .geometry import Layout, erp_to_tangents
from .options import AlignSpec, StitchOptions, build
from .stitch import StitchResult, stitch

__all__ = ["EstimateResult", "estimate"]

#: Names that moved to :mod:`m360.estimators`; importing them from here warns.
__getattr__ = moved(
    __name__,
    {
        name: (_estimators, name)
        for name in (
            "OUTPUT_KINDS",
            "RESIZE_MODES",
            "MAX_NETWORK_SIZE",
            "Estimator",
            "OnnxEstimator",
            "SimulatedEstimator",
            "load_estimator",
            "network_size",
            "ray_norms",
            "to_perspective_disparity",
        )
    },
)


@dataclass
class EstimateResult:
    """Everything :func:`estimate` produced for one panorama.

    Attributes
    ----------
    disparity : (H, W) float32
        Spherical disparity 1/distance (relative: up to a global scale and shift, unless the
        model is metric and ``align="none"``); NaN where no tangent has an estimate.
    depth : (H, W) float32
        Radial depth 1/disparity where disparity > 0, NaN elsewhere (relative unless metric).
    confidence : (H, W) float32
        Overlap disagreement from :func:`m360.stitch` (lower = more consistent).
    tangents : (N, h, w) float32
        Per-tangent perspective disparity given to the stitcher (after kind conversion).
    timings : dict
        Seconds per stage: ``load`` (model), ``project``, ``network``, ``convert``, ``align``,
        ``blend``, ``total``.
    model : dict
        ``name``, ``sha256``, ``output_kind``, ``providers``, ``threads`` (what ran).
    units : str
        ``"relative"`` or ``"metres"`` (for depth; disparity is in 1/units).
    options : dict
        The stitching options used (:meth:`StitchOptions.as_dict`: ``align``, ``blend``), the
        ``layout`` and the ``erp_shape``.
    layout : Layout
    stitch : StitchResult
        The stitcher's full report.
    """

    disparity: np.ndarray
    depth: np.ndarray
    confidence: np.ndarray
    tangents: np.ndarray
    timings: dict[str, float]
    model: dict[str, Any]
    units: str
    options: dict[str, Any]
    layout: Layout
    stitch: StitchResult = field(repr=False)


def _check_erp_rgb(erp: Any) -> np.ndarray:
    array = as_array(erp, "erp")
    if array.ndim != 3 or array.shape[2] != 3:
        raise InputError(
            f"erp must be an RGB panorama of shape (H, W, 3), got {array.shape}"
            + (" (grey images: stack the channel three times)" if array.ndim == 2 else "")
        )
    check_erp_shape(array.shape[0], array.shape[1], "erp")
    if array.dtype == np.uint8:
        return array
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all() or array.min() < 0 or array.max() > 1:
            raise InputError(
                "a float erp must be RGB in [0, 1] without NaN (uint8 is the usual input)"
            )
        return np.ascontiguousarray(array, dtype=np.float32)
    raise InputError(f"erp has dtype {array.dtype}; use uint8 RGB (or float RGB in [0, 1])")


def estimate(
    erp: np.ndarray,
    model: str | os.PathLike[str] | _estimators.Estimator = _models.DEFAULT_MODEL,
    *,
    align: AlignSpec = "multiscale",
    blend: BlendMethod | None = None,
    energy: Energy | None = None,
    solver: AlignSolver | None = None,
    iterations: int | None = None,
    tolerance: float | None = None,
    sample_fraction: float | None = None,
    pole_cap_deg: float | None = None,
    smoothness: float | None = None,
    scale_weight: float | None = None,
    offsets: Offsets | None = None,
    loss: Loss | None = None,
    blend_options: Mapping[str, Any] | None = None,
    options: StitchOptions | None = None,
    layout: Layout | None = None,
    mask: np.ndarray | None = None,
    providers: Sequence[str] | None = None,
    threads: int | None = None,
    input_size: tuple[int, int] | None = None,
    output_kind: str | None = None,
    mean: Sequence[float] | None = None,
    std: Sequence[float] | None = None,
) -> EstimateResult:
    """Estimate the depth of an equirectangular panorama (the paper's pipeline, end to end).

    Parameters
    ----------
    erp : (H, W, 3) uint8 RGB, W == 2H
        The panorama (ERP convention of docs/conventions.md: column 0 at longitude −π, row 0 at
        the top). float RGB in [0, 1] is accepted too.
    model : str, path or estimator
        A registry name (default ``"midas-v21-small"``, downloaded and verified on first use;
        see ``m360 models``), a path to an ``.onnx`` file, or any object with
        ``predict(tangents) -> (N, h, w)`` and ``output_kind``.
    align, blend, energy, solver, iterations, tolerance, sample_fraction : optional
        The stitching options, as for :func:`m360.stitch`.
    pole_cap_deg, smoothness, scale_weight, offsets, loss, blend_options : optional
        The stitching options, as for :func:`m360.stitch` (defaults: the core's, the method's
        ``"multiscale"`` alignment and ``"consensus"`` blend).
    options : StitchOptions, optional
        All stitching options at once (then leave their keywords at their defaults).
    layout : Layout, optional
        Tangent layout; default ``Layout.icosahedron(W)``.
    mask : (N, h, w) bool, optional
        False marks tangent pixels without an estimate (passed to :func:`m360.stitch`).
    providers, threads : optional
        ONNX Runtime execution providers and intra-op threads (ONNX models only).
    input_size, output_kind, mean, std : optional
        Override the model's preprocessing / declared output (ONNX models).

    Returns
    -------
    EstimateResult
        ``disparity`` (H, W) spherical disparity, ``depth`` (H, W) radial depth,
        ``confidence``, ``tangents``, ``timings`` per stage and what ran.
    """
    t_start = time.perf_counter()
    rgb = _check_erp_rgb(erp)
    height, width = rgb.shape[:2]
    opts = build(
        options,
        align,
        blend,
        energy=energy,
        solver=solver,
        iterations=iterations,
        tolerance=tolerance,
        sample_fraction=sample_fraction,
        pole_cap_deg=pole_cap_deg,
        smoothness=smoothness,
        scale_weight=scale_weight,
        offsets=offsets,
        loss=loss,
        blend_options=blend_options,
    )
    if layout is None:
        layout = Layout.icosahedron(width)
    elif not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    estimator = _estimators.load_estimator(
        model,
        providers=providers,
        threads=threads,
        input_size=input_size,
        output_kind=output_kind,
        mean=mean,
        std=std,
    )
    kind = estimator.output_kind
    t_load = time.perf_counter()
    tangents = erp_to_tangents(rgb, layout)
    t_project = time.perf_counter()
    try:
        raw = estimator.predict(tangents)
    except M360Error:
        raise
    except Exception as exc:  # a user estimator may raise anything; a batch loop needs M360Error
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(f"estimator {name} failed: {type(exc).__name__}: {exc}") from exc
    t_network = time.perf_counter()
    h, w = layout.tangent_shape
    raw_array = np.asarray(raw)
    if raw_array.shape != (len(layout), h, w) or raw_array.dtype.kind != "f":
        raise ModelError(
            f"estimator {getattr(estimator, 'name', type(estimator).__name__)} returned "
            f"{raw_array.dtype} of shape {raw_array.shape}; expected float (N, h, w) = "
            f"{(len(layout), h, w)}"
        )
    perspective = _estimators.to_perspective_disparity(raw_array, kind, layout)
    t_convert = time.perf_counter()
    details = stitch(perspective, layout, mask=mask, options=opts, return_details=True)
    disparity = details.disparity
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(disparity > 0, 1.0 / disparity, np.nan).astype(np.float32)
    t_end = time.perf_counter()
    st = details.timings
    metric = kind != "affine_disparity" and opts.align is None
    return EstimateResult(
        disparity=disparity,
        depth=depth,
        confidence=details.confidence,
        tangents=perspective,
        timings={
            "load": t_load - t_start,
            "project": t_project - t_load,
            "network": t_network - t_project,
            "convert": t_convert - t_network + st.get("convert", 0.0),
            "align": st.get("align", 0.0),
            "blend": st.get("blend", 0.0),
            "total": t_end - t_start,
        },
        model=_model_info(estimator, layout),
        units="metres" if metric else "relative",
        options={**opts.as_dict(), "layout": repr(layout), "erp_shape": [height, width]},
        layout=layout,
        stitch=details,
    )


def _model_info(estimator: Any, layout: Layout) -> dict[str, Any]:
    info: dict[str, Any] = {
        "name": getattr(estimator, "name", type(estimator).__name__),
        "output_kind": estimator.output_kind,
    }
    if isinstance(estimator, _estimators.OnnxEstimator):
        info.update(
            sha256=estimator.sha256,
            path=str(estimator.path),
            providers=list(estimator.providers),
            threads=estimator.threads,
            network_size=list(estimator.network_size(layout.tangent_shape)),
            mean=[float(v) for v in estimator.mean],
            std=[float(v) for v in estimator.std],
            normalization=estimator.normalization.as_dict(),
        )
    else:
        info["sha256"] = None
    return info
