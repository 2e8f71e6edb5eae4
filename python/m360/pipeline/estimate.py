"""The end-to-end job: ERP image in, ERP disparity and depth out (:func:`estimate`).

:func:`estimate` projects the panorama onto the layout's tangents, runs an estimator
(:mod:`m360.estimators`), converts its output to perspective disparity and stitches
(:func:`m360.stitch`), with a global prior when one is given (:mod:`m360.pipeline.prior`). A
panoramic estimator instead runs once on the whole ERP at its own size, and its map is
upsampled along the photo's edges. :func:`prepare` and :func:`finish` are :func:`estimate` split
around its network call (``estimate`` is ``prepare``, the network, ``finish``), for engines that
run the network for several panoramas at once (``m360.video.run``'s ``frame_batch``) or
elsewhere. The estimators lived here before; their old names still
import from here, with a DeprecationWarning pointing to :mod:`m360.estimators`.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from .. import estimators as _estimators
from .._compat import moved
from .._keywords import checked, split
from .._validate import as_array, check_erp_shape
from ..errors import InputError, M360Error, ModelError
from ..estimators import kinds as _kinds
from ..estimators import registry as _models
from ..estimators.options import ModelKeywords, ModelOptions
from ..geometry.layout import Layout, erp_to_tangents, pixel_degrees
from ..stitching.edges import edges_for, refine_edges
from ..stitching.options import StitchKeywords, StitchOptions, build
from ..stitching.stitch import StitchResult
from ..stitching.upsample import guided_upsample
from . import masks as _masks
from . import memory as _memory
from . import prior as _prior
from .checks import stitch_checked
from .options import EstimateKeywords, JobKeywords, PriorKeywords, job_layout, resolve_job
from .scale import depth_of, scale_disparity

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["EstimateResult", "Prepared", "estimate", "finish", "prepare"]

_log = logging.getLogger("m360")

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
        Spherical disparity 1/distance (relative: up to a global scale and shift, in the
        tangents' own frame, unless the model is metric, ``metric_depth`` or ``distance``:
        then in 1/metres, the network's own scale); NaN where no tangent has an estimate.
    depth : (H, W) float32
        Radial depth 1/disparity where disparity > 0, NaN elsewhere (relative unless metric).
    confidence : (H, W) float32
        Overlap disagreement from :func:`m360.stitch` (lower = more consistent); a panoramic
        model's single pass has none: 0 where the disparity is valid.
    tangents : (N, h, w) float32 or None
        Per-tangent perspective disparity given to the stitcher (after kind conversion); None
        for a panoramic model.
    timings : dict
        Seconds per stage: ``load`` (model), ``project``, ``network``, ``prior`` (the prior
        model's pass, with a prior), ``convert``, ``align``, ``blend``, ``check`` (anchoring,
        result checks, fallback stitches), ``upsample``, ``total``. A panoramic model: ``load``,
        ``project`` (resizing to the network), ``network``, ``convert``, ``upsample``.
    model : dict
        ``name``, ``sha256``, ``output_kind``, ``providers``, ``threads`` (what ran).
    units : str
        ``"relative"`` or ``"metres"`` (for depth; disparity is in 1/units).
    options : dict
        The stitching options used (:meth:`StitchOptions.as_dict`: ``align``, ``blend``), the
        ``layout`` and the ``erp_shape``; with a prior, ``prior``: its kind, its source
        (``"model"`` with name and sha256, or ``"array"`` with shape and sha256) and the
        ``shape`` it was given to the stitch at.
    layout : Layout or None
        None for a panoramic model.
    stitch : StitchResult or None
        The stitcher's full report; None for a panoramic model.
    scale : dict or None
        Where the metric scale came from: :meth:`m360.scale.ScaleFit.as_dict` when ``scale=``
        was given; for a ``metric_depth`` or ``distance`` network ``{"method": "network",
        "aligned": ...}``, with the ``scale`` and ``offset`` of the anchoring that put the
        aligned result back on the network's own metres when alignment ran; None otherwise.
    checks : dict
        What was checked before the result was trusted (docs/method.md, "Checking the
        network's output"): ``tangents`` (:func:`m360.estimators.kinds.sanitise`'s
        ``dropped``, ``outlier_pixels``, ``valid_fraction`` per tangent), ``result`` (per try:
        the ``anchor`` fitted, the share of reachable pixels lost, negative share, dynamic
        range against the tangents' and alignment scale spread, and the ``problems``),
        ``anchor`` (the kept try's global ``scale``, ``offset`` and ``pixels``, None without
        alignment), ``fallback`` (``"none"``, or the options that replaced the asked ones, e.g.
        ``"coarser alignment"`` or ``"no alignment"``; then ``stitched_with`` holds the options
        used, while ``options`` keeps those asked) and ``valid_fraction`` (share of the
        output's pixels with a finite, positive disparity).
    """

    disparity: np.ndarray
    depth: np.ndarray
    confidence: np.ndarray
    tangents: np.ndarray | None
    timings: dict[str, float]
    model: dict[str, Any]
    units: str
    options: dict[str, Any]
    layout: Layout | None
    stitch: StitchResult | None = field(repr=False)
    scale: dict[str, Any] | None = None
    checks: dict[str, Any] = field(default_factory=dict)


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
    options: StitchOptions | None = None,
    model_options: ModelOptions | None = None,
    layout: Layout | None = None,
    mask: Any = None,
    scale: Any = None,
    **keywords: Unpack[EstimateKeywords],
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
        ``predict(tangents) -> (N, h, w)`` and ``output_kind`` (or a panoramic one, see below).
    options : StitchOptions, optional
        Every stitching option at once (then give none of them as a keyword).
    model_options : ModelOptions, optional
        Every model option at once (then give none of them as a keyword).
    layout : Layout, optional
        Tangent layout; default ``Layout.icosahedron(W, padding)`` at the working width W.
    mask : optional
        ERP pixels to leave out (:mod:`m360.masks`): an (H, W) bool array (True = use),
        ``m360.masks.nadir(deg)`` / ``zenith(deg)``, or a list of them. Masked pixels take no
        part in alignment or blending and are NaN in the outputs. An (N, h, w) bool array is a
        tangent mask, passed to :func:`m360.stitch` as it is.
    scale : scaler, optional
        Metric scale (:mod:`m360.scale`: ``camera_height(1.6)``, ``points(...)``,
        ``metric_map(...)``), fitted on the final disparity; the result is then in metres and
        records the fit in ``scale``. A failed fit raises :class:`m360.ScaleError`.
    **keywords
        Any option of :class:`m360.pipeline.options.EstimateKeywords` (None or absent: its
        default), one list shared with :func:`m360.batch.run` and ``m360 run``:

        - the stitching options, as for :func:`m360.stitch`: ``align``, ``blend``,
          ``energy``, ``solver``, ``iterations``, ``tolerance``, ``sample_fraction``,
          ``pole_cap_deg``, ``smoothness``, ``scale_weight``, ``offsets``, ``loss``,
          ``blend_options`` (defaults: the core's, the method's ``"multiscale"`` alignment and
          ``"consensus"`` blend);
        - the model options (ONNX models only, :class:`m360.ModelOptions`): ``providers``,
          ``threads``, ``input_size``, ``output_kind``, ``mean``, ``std``;
        - ``working_width`` (int or ``"native"``): the ERP width projection, network,
          alignment and blend run at, the disparity then upsampled to the input's resolution
          (``upsample``: ``"guided"`` follows the photo's edges at depth discontinuities,
          :func:`m360.upsample.guided_upsample`; or ``"bilinear"``). Default: the input's
          width up to 8192, above it 4096; ``"native"`` always runs at the input's width;
        - ``padding`` of the default layout's tangents in gnomonic units (not with
          ``layout``): default 0.7 (:data:`m360.geometry.DEFAULT_PADDING`), wider than the
          paper's 0.3, so more tangents see each pixel and the consensus blend can vote down a
          network's local errors; 0.7 measured about a third lower AbsRel than 0.3 under
          simulated content errors at the same network cost, with wider (≈ 125°) tiles
          (docs/method.md). ``padding="paper"`` is the paper's layout;
        - ``subdivisions`` of the default layout (not with ``layout``): 1 splits each face into
          4, 80 tangents half as wide in angle (padding 0.3 unless given), which a network of a
          fixed input size sees at twice the angular resolution: sharper depth edges for 4x the
          network calls (docs/method.md, "Where the detail comes from");
        - ``edges``: ``"photo"`` makes the depth edges the network smeared sharp along the
          photo's, at the output's resolution (:func:`m360.stitching.refine_edges`; measured
          on simulated rooms and real photos in docs/method.md); ``"network"`` keeps them as
          the network gave them; default ``"auto"``: ``"photo"`` for a tangent network that
          sees its tile 4 or more times smaller (``result.model["network_size"]``),
          ``"network"`` otherwise and for simulated and panoramic models;
        - ``sky``: ``"nan"`` makes pixels whose disparity is at or below
          ``m360.masks.SKY_THRESHOLD`` times its 90th percentile (the sky, or beyond) NaN
          instead of a huge fake distance; default ``"keep"``;
        - the global prior (:class:`m360.pipeline.options.PriorKeywords`, tangent models
          only): ``prior``, an ERP map (Hp, 2 Hp) of any resolution (NaN = unknown: another
          tool's output, a LiDAR map, the previous video frame) or a panoramic model (a
          :class:`m360.estimators.PanoramicEstimator`, or a path or registry name loaded with
          ``kind="panoramic"`` and the model options' ``providers`` and ``threads``, run once on
          the working-resolution photo at its own size); ``prior_kind``, what it holds
          (``affine_disparity``, ``disparity``, ``affine_depth``, ``distance``; required for a
          map, a model's output kind otherwise); ``prior_confidence``, a map's per-pixel trust
          in [0, 1]; ``prior_options``, how a model given by path or name is fed (an
          :class:`m360.ModelOptions` or a dict of its ``input_size``, ``resize``,
          ``multiple_of``, ``normalize``, ``mean``, ``std``). The prior is fitted to the job
          (an ERP grid no larger than the working ERP, NaN under the masks) and given to
          :func:`m360.stitch`, whose alignment follows it (``align="none"`` is refused with a
          prior); a prior in metres (``disparity``, ``distance``) gives the result its metres.
          ``options["prior"]`` records it (kind, model name and sha256, or ``"array"``).

        With a panoramic model (``kind="panoramic"``, or a panoramic estimator object) the
        network runs once on the whole photo at its own size and its map is upsampled to the
        photo's resolution (``upsample``); ERP masks, ``sky`` and ``scale`` apply as above,
        while ``layout``, ``padding``, ``subdivisions``, a tangent mask and a prior do not (the
        stitching options and ``working_width`` are ignored).

    Returns
    -------
    EstimateResult
        ``disparity`` (H, W) spherical disparity, ``depth`` (H, W) radial depth,
        ``confidence``, ``tangents``, ``timings`` per stage and what ran.
    """
    t_start = time.perf_counter()
    call = _check_call(erp, model_options, keywords, "estimate")
    if _role(model, call.model_options) == "panoramic":
        if layout is not None or call.job["padding"] is not None or call.job["subdivisions"]:
            raise InputError(
                "a panoramic model runs once on the whole ERP: layout, padding and "
                "subdivisions do not apply"
            )
        if call.prior_given:
            raise InputError(
                "a prior goes with a tangent model (the tangents give the detail, the prior the "
                "low frequencies); a panoramic model is used alone: model=<panoramic model>, or "
                "model=<tangent model>, prior=<panoramic model>"
            )
        return _estimate_panoramic(
            call.rgb, model, call.model_options, t_start, mask=mask, scale=scale, job=call.job
        )
    prepared = _prepare(call, model, options, layout, mask, scale, t_start)
    t_project = time.perf_counter()
    raw = _predict(prepared.estimator, prepared.release(), prepared.layout)
    return finish(prepared, raw, seconds=time.perf_counter() - t_project)


@dataclass
class _Call:
    """The checked arguments of :func:`estimate` / :func:`prepare` (before the model's role)."""

    rgb: np.ndarray
    stitch_keywords: dict[str, Any]
    job: dict[str, Any]
    prior_given: dict[str, Any]
    model_options: ModelOptions


def _check_call(erp: Any, model_options: ModelOptions | None, keywords: Any, where: str) -> _Call:
    """Check what :func:`estimate` and :func:`prepare` take before the model's role is known."""
    stitch_keywords, model_keywords, job_keywords, prior_keywords = split(
        keywords, StitchKeywords, ModelKeywords, JobKeywords, PriorKeywords, where=where
    )
    rgb = _check_erp_rgb(erp)
    job = resolve_job(job_keywords)
    prior_given = checked(prior_keywords, PriorKeywords)
    model_opts = ModelOptions.build(model_options, **model_keywords)
    return _Call(rgb, dict(stitch_keywords), job, prior_given, model_opts)


@dataclass
class Prepared:
    """A panorama made ready for a tangent network by :func:`prepare`; :func:`finish` does the rest.

    Everything :func:`estimate` does before its network call: the checks, the working-width
    resize, the layout, the masks, the projection and the memory check. An engine that runs
    the network elsewhere or for many panoramas at once (``m360.video.run``'s ``frame_batch``)
    prepares each panorama, runs the network on their tangents and finishes each; the result
    has the bytes :func:`estimate` gives.

    Attributes
    ----------
    tangents : (N, h, w, 3) or None
        The network's input (RGB tangent images); None once :meth:`release` gave them away.
    estimator : object
        The loaded tangent estimator (:func:`m360.estimators.load_estimator`).
    layout : Layout
        The tangent layout, at the working width.
    erp_shape : (int, int)
        The output's (H, W), the input's.
    timings : dict
        Seconds of ``load`` (checks, resize, model) and ``project``.
    """

    tangents: np.ndarray | None
    estimator: Any
    layout: Layout
    erp_shape: tuple[int, int]
    timings: dict[str, float]
    options: StitchOptions = field(repr=False)
    photo: np.ndarray = field(repr=False)  # the working-resolution RGB (a prior model's input)
    guide: np.ndarray | None = field(repr=False)  # the full-resolution RGB, to upsample
    mask: np.ndarray | None = field(repr=False)
    erp_valid: np.ndarray | None = field(repr=False)
    job: dict[str, Any] = field(repr=False)
    scale: Any = field(repr=False)
    prior: _prior.Prior | None = field(repr=False)
    model_options: ModelOptions | None = field(repr=False, default=None)

    def release(self) -> np.ndarray:
        """Give the tangents away (to the network) and drop them here.

        The RGB tiles are not needed by the stitch (133 MB at 8K): dropped before it.
        """
        if self.tangents is None:
            raise InputError("the tangents of this prepared panorama were already released")
        tangents, self.tangents = self.tangents, None
        return tangents


def prepare(
    erp: np.ndarray,
    model: str | os.PathLike[str] | _estimators.Estimator = _models.DEFAULT_MODEL,
    *,
    options: StitchOptions | None = None,
    model_options: ModelOptions | None = None,
    layout: Layout | None = None,
    mask: Any = None,
    scale: Any = None,
    **keywords: Unpack[EstimateKeywords],
) -> Prepared:
    """Do the part of :func:`estimate` before its network: checks, resize, layout, projection.

    Takes the arguments of :func:`estimate` (tangent models only: a panoramic model is an
    :class:`InputError`). Run the network on :attr:`Prepared.tangents` (several panoramas'
    tangents may go in one call), then :func:`finish` each with its share of the output.

    Returns
    -------
    Prepared
    """
    t_start = time.perf_counter()
    call = _check_call(erp, model_options, keywords, "prepare")
    if _role(model, call.model_options) == "panoramic":
        raise InputError(
            "prepare/finish are for tangent models; a panoramic model runs once on the whole "
            "ERP: use m360.estimate"
        )
    return _prepare(call, model, options, layout, mask, scale, t_start)


def _prepare(
    call: _Call,
    model: Any,
    options: StitchOptions | None,
    layout: Layout | None,
    mask: Any,
    scale: Any,
    t_start: float,
) -> Prepared:
    rgb, job = call.rgb, call.job
    height, width = rgb.shape[:2]
    working_width = job["working_width"]
    work_width = _memory.working_width_for(working_width, width)
    if layout is None:
        layout = job_layout(work_width, job)
    elif job["padding"] is not None or job["subdivisions"]:
        raise InputError(
            "give either layout or padding and subdivisions (the default layout's), not both"
        )
    elif not isinstance(layout, Layout):
        raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
    elif layout.erp_shape[1] != work_width and working_width is not None:
        raise InputError(
            f"layout is for ERP width {layout.erp_shape[1]} but working_width is {work_width}"
        )
    else:
        work_width = layout.erp_shape[1]
    opts = build(options, layout.subdivisions or 0, **call.stitch_keywords)
    prior = _load_prior(call.prior_given, opts, call.model_options)
    _check_memory(rgb, work_width, opts, layout, prior)
    mask, erp_valid = _split_mask(mask, layout, (height, width))
    guide = None
    if work_width != width:
        guide = rgb  # the full-resolution photo guides the upsampling
        rgb = cv2.resize(rgb, (work_width, work_width // 2), interpolation=cv2.INTER_AREA)
    estimator = _estimators.load_estimator(model, model_options=call.model_options)
    t_load = time.perf_counter()
    tangents = erp_to_tangents(rgb, layout)
    t_project = time.perf_counter()
    return Prepared(
        tangents=tangents,
        estimator=estimator,
        layout=layout,
        erp_shape=(height, width),
        timings={"load": t_load - t_start, "project": t_project - t_load},
        options=opts,
        photo=rgb,
        guide=guide,
        mask=mask,
        erp_valid=erp_valid,
        job=job,
        scale=scale,
        prior=prior,
        model_options=call.model_options,
    )


def _load_prior(
    given: dict[str, Any], opts: StitchOptions, model_opts: ModelOptions | None
) -> _prior.Prior | None:
    if given.get("prior") is not None and opts.align is None:
        raise InputError("a prior acts through the alignment: give align other than 'none'")
    return _prior.load_prior(
        given.get("prior"),
        given.get("prior_kind"),
        given.get("prior_confidence"),
        prior_options=given.get("prior_options"),
        providers=None if model_opts is None else model_opts.providers,
        threads=None if model_opts is None else model_opts.threads,
    )


def _check_memory(
    rgb: np.ndarray,
    work_width: int,
    opts: StitchOptions,
    layout: Layout,
    prior: _prior.Prior | None,
) -> None:
    height, width = rgb.shape[:2]
    _memory.check_memory(
        _memory.estimate_memory(
            width, work_width, opts.method, layout, prior_pixels=_prior_pixels(prior, rgb)
        ),
        f"m360.estimate of a {width}x{height} panorama at working width {work_width}",
    )


def finish(
    prepared: Prepared,
    raw: np.ndarray,
    *,
    seconds: float = 0.0,
    **prior_keywords: Unpack[PriorKeywords],
) -> EstimateResult:
    """Do the part of :func:`estimate` after its network: convert, stitch, upsample, scale.

    Parameters
    ----------
    prepared : Prepared
        From :func:`prepare`.
    raw : (N, h, w) float
        The network's output on ``prepared``'s tangents (its share of a larger call).
    seconds : float
        The network's time for this panorama (its share of a larger call), for ``timings``.
    **prior_keywords
        A global prior known only now (:class:`m360.pipeline.options.PriorKeywords`: the
        previous video frame's result), when :func:`prepare` was given none; the same as
        giving it to :func:`estimate`.

    Returns
    -------
    EstimateResult
        The bytes :func:`estimate` gives for the same arguments; ``timings["total"]`` is the
        sum of the stages (time at work on this panorama, not waiting for the others).
    """
    if not isinstance(prepared, Prepared):
        raise InputError(f"prepared must come from prepare(), got {type(prepared).__name__}")
    t_finish = time.perf_counter()
    layout, estimator = prepared.layout, prepared.estimator
    raw = _checked_output(estimator, raw, layout)
    prior = prepared.prior
    given = {k: v for k, v in checked(dict(prior_keywords), PriorKeywords).items() if v is not None}
    if given.get("prior") is not None:
        if prior is not None:
            raise InputError("the prior was given to prepare() already: give it once")
        prior = _load_prior(given, prepared.options, prepared.model_options)
        photo = prepared.guide if prepared.guide is not None else prepared.photo
        _check_memory(photo, prepared.layout.erp_shape[1], prepared.options, layout, prior)
    elif given:
        raise InputError(f"{', '.join(sorted(given))} without a prior: give prior= too")
    timings = {**prepared.timings, "network": float(seconds)}
    prior_map = None
    if prior is not None:
        # The prior model sees the working-resolution photo (as the Ray engine ships it to
        # its model actors), resized to the network's size.
        t_prior = time.perf_counter()
        prior_map = _prior_map(prior, prepared.photo, prior_input=None)
        timings["prior"] = time.perf_counter() - t_prior
    result = _from_network(
        raw,
        estimator.output_kind,
        layout,
        prepared.options,
        prepared.erp_shape,
        _model_info(estimator, layout),
        timings,
        mask=prepared.mask,
        erp_valid=prepared.erp_valid,
        sky_mode=prepared.job["sky"],
        scale=prepared.scale,
        # The photo at the output's resolution: it guides the upsampling and the edges.
        guide=prepared.guide if prepared.guide is not None else prepared.photo,
        upsample=prepared.job["upsample"],
        edges=prepared.job["edges"],
        prior=prior_map,
    )
    stages = sum(prepared.timings.values()) + float(seconds)
    result.timings["total"] = stages + time.perf_counter() - t_finish
    return result


def _role(model: Any, model_opts: ModelOptions) -> str:
    """Tell whether ``model`` is a tangent or a panoramic model, without loading it."""
    if model_opts.kind is not None:
        return str(model_opts.kind)
    if isinstance(model, (str, os.PathLike)):
        entry = _models.REGISTRY.get(os.fspath(model))
        return entry.kind if entry is not None else "tangent"
    return _estimators.estimator_kind(model)


@dataclass(frozen=True)
class PriorMap:
    """A prior as one image's stitch takes it: the map, its kind, trust and sidecar record."""

    values: np.ndarray
    kind: str
    confidence: np.ndarray | None
    record: dict[str, Any]

    @property
    def metric(self) -> bool:
        """Whether the prior is in metres (its scale is kept)."""
        return self.kind in _prior.METRIC_PRIOR_KINDS


def _prior_pixels(prior: _prior.Prior | None, rgb: np.ndarray) -> int:
    """Pixels of the prior's map (a model's: its network input) for the memory estimate."""
    if prior is None:
        return 0
    if prior.array is not None:
        return int(prior.array.size)
    if isinstance(prior.estimator, _estimators.OnnxEstimator):
        h, w = prior.estimator.network_size(rgb.shape[:2])
        return h * w
    return int(rgb.shape[0] * rgb.shape[1])


def _prior_map(
    prior: _prior.Prior,
    photo: np.ndarray | None,
    *,
    prior_input: np.ndarray | None,
    raw: np.ndarray | None = None,
) -> PriorMap:
    """Give the prior of one image: the array, or the prior model's output on the photo.

    ``prior_input`` is the model's input when made elsewhere (:func:`m360.pipeline.prior.
    prior_input`, the Ray engine's first stage), ``raw`` its output when run elsewhere (the
    Ray engine's model actors); else the model runs here on ``photo``.
    """
    record = _prior.describe(prior)
    if prior.array is not None:
        return PriorMap(prior.array, prior.kind, prior.confidence, record)
    if raw is None:
        if prior_input is None:
            if photo is None:
                raise InputError("a prior model needs the photo")
            prior_input = _prior.prior_input(prior.estimator, photo)
        raw = _prior.run_prior(prior.estimator, prior_input)
    return PriorMap(raw, prior.kind, None, record)


def _estimate_panoramic(
    rgb: np.ndarray,
    model: Any,
    model_opts: ModelOptions,
    t_start: float,
    *,
    mask: Any,
    scale: Any,
    job: dict[str, Any],
) -> EstimateResult:
    """:func:`estimate` with a panoramic model: one pass at its size, then upsampling."""
    height, width = rgb.shape[:2]
    if mask is not None and not isinstance(mask, (_masks.Cap, list, tuple)) and np.ndim(mask) != 2:
        raise InputError(
            "a panoramic model takes ERP masks ((H, W) bool arrays, nadir/zenith caps), not a "
            "tangent mask"
        )
    estimator = _estimators.load_estimator(model, model_options=model_opts)
    t_load = time.perf_counter()
    network_input = _prior.prior_input(estimator, rgb)
    _memory.check_memory(
        _memory.estimate_panoramic_memory(width, network_input.shape[:2]),
        f"m360.estimate of a {width}x{height} panorama with a panoramic model",
    )
    t_project = time.perf_counter()
    raw = _prior.run_prior(estimator, network_input, "panoramic model")
    t_network = time.perf_counter()
    timings = {
        "load": t_load - t_start,
        "project": t_project - t_load,
        "network": t_network - t_project,
    }
    erp_valid = None if mask is None else _masks.erp_mask(mask, height, width)
    result = _from_panoramic(
        raw,
        estimator.output_kind,
        (height, width),
        _model_info(estimator, None, network_input.shape[:2]),
        timings,
        guide=rgb,
        erp_valid=erp_valid,
        sky_mode=job["sky"],
        scale=scale,
        upsample=job["upsample"],
        edges=job["edges"],
    )
    result.timings["total"] = time.perf_counter() - t_start
    return result


def _from_panoramic(
    raw: np.ndarray,
    kind: str,
    erp_shape: tuple[int, int],
    model_info: dict[str, Any],
    timings: dict[str, float],
    *,
    guide: np.ndarray,
    erp_valid: np.ndarray | None = None,
    sky_mode: str = "keep",
    scale: Any = None,
    upsample: str = "guided",
    edges: str = "network",
) -> EstimateResult:
    """Do the rest of :func:`estimate` after a panoramic model (convert, upsample, masks, scale).

    The map is converted to spherical disparity at the network's resolution, resized to an
    ERP grid (h, 2h) if the network's output is not one, then upsampled to ``erp_shape`` with
    the photo ``guide`` (``upsample``: guided or bilinear; shrunk by area when the network's
    map is larger than the photo); ``edges="photo"`` then makes its edges sharp along the
    photo's (:func:`m360.stitching.refine_edges`); ``"auto"`` keeps them (the map is already
    upsampled along the photo).
    """
    t0 = time.perf_counter()
    edges = edges_for(edges, None, None)
    network_shape = list(raw.shape)
    disparity = _estimators.to_spherical_disparity(raw, kind)
    valid_before = float(np.isfinite(disparity).mean())
    if valid_before < _kinds.MIN_VALID_FRACTION:
        raise ModelError(
            f"the panoramic model's {kind} output has too few valid pixels "
            f"({valid_before:.1%} < {_kinds.MIN_VALID_FRACTION:.0%})"
        )
    h = disparity.shape[0]
    if disparity.shape[1] != 2 * h:
        h = max(2, (disparity.shape[0] + disparity.shape[1] // 2) // 2)
        disparity = _prior.fit_to_job(disparity, None, (h, 2 * h), None)[0]
    t_convert = time.perf_counter()
    height, width = erp_shape
    if h < height:
        disparity = guided_upsample(disparity, guide, method=upsample)
    elif h > height:
        disparity = _prior.fit_to_job(disparity, None, erp_shape, None)[0]
    else:
        disparity = disparity.copy()
    if edges == "photo":
        disparity = refine_edges(disparity, guide)
    t_upsampled = time.perf_counter()
    if erp_valid is not None:
        disparity[~erp_valid] = np.nan
    if sky_mode == "nan":
        disparity[_masks.sky(disparity)] = np.nan
    metric = kind in _prior.METRIC_PRIOR_KINDS
    scale_fit: dict[str, Any] | None = {"method": "network"} if metric else None
    if scale is not None:
        disparity, fit = scale_disparity(disparity, scale, affine=not metric)
        metric, scale_fit = True, fit.as_dict()
    with np.errstate(invalid="ignore"):
        valid_fraction = float((disparity > 0).mean())
    confidence = np.where(np.isfinite(disparity), np.float32(0), np.float32(np.nan))
    return EstimateResult(
        disparity=disparity,
        depth=depth_of(disparity),
        confidence=confidence.astype(np.float32, copy=False),
        tangents=None,
        timings={
            **timings,
            "convert": t_convert - t0,
            "upsample": t_upsampled - t_convert,
        },
        model={**model_info, "kind": "panoramic", "output_shape": network_shape},
        units="metres" if metric else "relative",
        options={
            "kind": "panoramic",
            "erp_shape": [height, width],
            "network_output_shape": network_shape,
            "upsample": upsample if h < height else None,
            **({"edges": "photo"} if edges == "photo" else {}),
            **({} if erp_valid is None else {"masked_fraction": float(1 - erp_valid.mean())}),
            **({"sky": "nan"} if sky_mode == "nan" else {}),
        },
        layout=None,
        stitch=None,
        scale=scale_fit,
        checks={"valid_fraction": valid_fraction, "network_valid_fraction": valid_before},
    )


def _split_mask(
    mask: Any, layout: Layout, erp_shape: tuple[int, int]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Split ``estimate``'s ``mask`` into (tangent mask, ERP mask).

    An ERP mask (array, caps) at the output's ``erp_shape`` gives both; at a smaller working
    width a working pixel is used only when every output pixel it covers is. A tangent mask
    (N, h, w) passes through alone.
    """
    if mask is not None and (isinstance(mask, (_masks.Cap, list, tuple)) or np.ndim(mask) == 2):
        erp_valid = _masks.erp_mask(mask, *erp_shape)
        working = erp_valid
        if layout.erp_shape != erp_shape:
            size = (layout.erp_shape[1], layout.erp_shape[0])
            area = cv2.resize(erp_valid.astype(np.float32), size, interpolation=cv2.INTER_AREA)
            working = area >= 1.0 - 1e-6
        return _masks.tangent_mask(working, layout), erp_valid
    return mask, None


def _predict(estimator: Any, tangents: np.ndarray, layout: Layout, frames: int = 1) -> np.ndarray:
    """Run the network on the tangents; any failure or a wrong output is a ModelError.

    ``tangents`` hold ``frames`` panoramas' tangents one after the other (one network call
    for several panoramas; the output is checked for all of them).
    An estimator made for one layout (it has a ``layout``, as the simulated network does) is
    refused for another: tangents of the same shape would pass unnoticed with wrong values.
    """
    made_for = getattr(estimator, "layout", None)
    if isinstance(made_for, Layout) and made_for != layout:
        raise InputError(
            f"the estimator was made for {made_for!r} but the stitch uses {layout!r}: pass "
            "layout= (the default is m360.geometry.default_layout(W), padding 0.7)"
        )
    try:
        raw = estimator.predict(tangents)
    except M360Error:
        raise
    except Exception as exc:  # a user estimator may raise anything; a batch loop needs M360Error
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ModelError(f"estimator {name} failed: {type(exc).__name__}: {exc}") from exc
    out = _checked_output(estimator, raw, layout, frames)
    _check_follows_input(estimator, tangents, out)
    return out


#: Outputs this close (max |difference| relative to the largest |value|) count as one map.
_SAME_MAP = 1e-5


def _check_follows_input(estimator: Any, tangents: np.ndarray, out: np.ndarray) -> None:
    """Refuse (ModelError) one and the same map for tangents whose pixels differ.

    A network fed values far outside what it was trained on (raw 0-255 pixels into a network
    trained on [0, 1], found on the shared FastDepth) saturates and returns its own bias, the
    same map for every tile: a panorama of garbage that passes every later check.
    """
    if out.shape[0] < 2:
        return
    first = out[0]
    scale = float(np.nanmax(np.abs(first), initial=0.0))
    if not np.isfinite(scale) or scale == 0.0:
        return  # a blank output is sanitise's business, per tangent
    for k in range(1, out.shape[0]):
        with np.errstate(invalid="ignore"):
            difference = np.abs(out[k] - first)
        compared = difference[np.isfinite(difference)]
        if compared.size == 0 or compared.max() > _SAME_MAP * scale:
            return  # not the same map (or nothing to compare: sanitise's business)
    if all(np.array_equal(tangents[k], tangents[0]) for k in range(1, tangents.shape[0])):
        return  # one photo in every tile (a blank panorama): one map is the right answer
    name = getattr(estimator, "name", type(estimator).__name__)
    normalization = getattr(estimator, "normalization", None)
    fed = ""
    if normalization is not None:
        mean, std = (", ".join(f"{v:.4g}" for v in t) for t in normalization.feed())
        fed = f" ((RGB in [0, 1] - ({mean})) / ({std}))"
    raise ModelError(
        f"estimator {name} returned the same map for all {out.shape[0]} tangents although "
        f"their pixels differ: the network ignores its input, most likely because its input "
        f"normalisation{fed} is not the one it was trained with and saturates it. A network "
        "trained on RGB in [0, 1] needs normalize='unit' (--normalize unit), one trained with "
        "the ImageNet statistics 'imagenet'; `m360 models check MODEL` measures which one the "
        "network follows"
    )


def _checked_output(estimator: Any, raw: Any, layout: Layout, frames: int = 1) -> np.ndarray:
    """Give the network's output as an array; a ModelError unless (frames·N, h, w) float."""
    h, w = layout.tangent_shape
    raw_array = np.asarray(raw)
    expected = (frames * len(layout), h, w)
    if raw_array.shape != expected or raw_array.dtype.kind != "f":
        raise ModelError(
            f"estimator {getattr(estimator, 'name', type(estimator).__name__)} returned "
            f"{raw_array.dtype} of shape {raw_array.shape}; expected float (N, h, w) = "
            f"{expected}"
        )
    return raw_array


def _from_network(
    raw: np.ndarray,
    kind: str,
    layout: Layout,
    opts: StitchOptions,
    erp_shape: tuple[int, int],
    model_info: dict[str, Any],
    timings: dict[str, float],
    *,
    mask: np.ndarray | None = None,
    erp_valid: np.ndarray | None = None,
    sky_mode: str = "keep",
    scale: Any = None,
    guide: np.ndarray | None = None,
    upsample: str = "guided",
    edges: str = "auto",
    prior: PriorMap | None = None,
) -> EstimateResult:
    """Do the rest of :func:`estimate` after the network (stitch, upsample, masks, scale).

    Convert, stitch, upsample to the output's size, apply the masks and the sky, scale, depth.
    Split out so that an engine running the network elsewhere (m360.batch's Ray engine) makes
    the same bytes. ``timings`` holds the earlier stages; ``total`` is left to the caller.
    ``erp_shape`` is the output's shape; when the layout's is smaller (a working width),
    ``guide`` is the full-resolution RGB photo that guides the upsampling, and with
    ``edges="photo"`` the edge refinement (:func:`m360.stitching.refine_edges`, at the output's
    resolution, after the upsampling; then needed at any width); ``"auto"`` is ``"photo"`` when
    ``model_info``'s network input is at most a quarter of the tile's width
    (:func:`m360.stitching.edges.edges_for`). ``mask`` is the
    tangent mask and ``erp_valid`` the output-sized ERP mask (see :func:`_split_mask`).
    ``prior`` is the image's prior map (:func:`_prior_map`): fitted to the job (2:1, masked
    with ``erp_valid``, no larger than the layout's ERP) and given to every stitch; a prior in
    metres is kept as the result's scale (no anchoring on the tangents).
    """
    t_network = time.perf_counter()
    network_size = model_info.get("network_size")
    edges = edges_for(edges, layout.tangent_shape[1], network_size[1] if network_size else None)
    prior_args: dict[str, Any] = {}
    prior_record = None
    if prior is not None:
        values, trust = _prior.fit_to_job(
            prior.values, prior.confidence, layout.erp_shape, erp_valid
        )
        prior_args = {"prior": values, "prior_kind": prior.kind}
        if trust is not None:
            prior_args["prior_confidence"] = trust
        prior_record = {**prior.record, "used_shape": list(values.shape)}
    perspective = _estimators.to_perspective_disparity(raw, kind, layout)
    perspective, tangent_checks = _kinds.sanitise(perspective, kind, raw=raw)
    t_convert = time.perf_counter()
    dropped = {d["tangent"] for d in tangent_checks["dropped"]}
    if dropped:
        # The core aligns only tangents with valid pixels: stitch the others on their own
        # layout (the same ERP grid, the kept cameras).
        kept = [k for k in range(len(layout)) if k not in dropped]
        stitch_layout = Layout.from_cameras([layout.cameras[k] for k in kept], layout.erp_shape)
        stitch_mask = None if mask is None else np.ascontiguousarray(mask[kept])
        details, checks = stitch_checked(
            np.ascontiguousarray(perspective[kept]),
            stitch_layout,
            stitch_mask,
            opts,
            prior=prior_args,
            anchor=prior is None or not prior.metric,
        )
    else:
        details, checks = stitch_checked(
            perspective,
            layout,
            mask,
            opts,
            prior=prior_args,
            anchor=prior is None or not prior.metric,
        )
    checks["tangents"] = tangent_checks
    used = details.options if details.options is not None else opts
    if checks["fallback"] != "none":
        checks["stitched_with"] = used.as_dict()  # ``options`` keeps what was asked
    disparity, confidence = details.disparity, details.confidence
    anchor = checks.get("anchor")
    t_stitched = time.perf_counter()
    height, width = erp_shape
    work_width = layout.erp_shape[1]
    if work_width != width:
        if guide is None:
            raise InputError(f"upsampling {work_width} -> {width} needs the photo as its guide")
        disparity = guided_upsample(disparity, guide, method=upsample)
        confidence = guided_upsample(confidence, guide, method="bilinear")
    if anchor is not None:  # in place: no second output-sized pair of maps
        disparity *= np.float32(anchor["scale"])
        disparity += np.float32(anchor["offset"])
        confidence *= np.float32(anchor["scale"])
    if edges == "photo":
        if guide is None:
            raise InputError("edges='photo' needs the photo at the output's resolution")
        disparity = refine_edges(disparity, guide)
    t_upsampled = time.perf_counter()
    if erp_valid is not None:
        disparity[~erp_valid] = np.nan
    if sky_mode == "nan":
        disparity[_masks.sky(disparity)] = np.nan
    st = details.timings
    metric = kind in _kinds.DEPTH_KINDS
    scale_fit: dict[str, Any] | None = None
    if prior is not None and prior.metric:
        # The stitch put the result on the prior's metres; nothing anchored it elsewhere.
        metric, scale_fit = True, {"method": "prior", "prior_kind": prior.kind}
    elif metric:
        # The anchoring fitted the result to the network's own metres (scale and offset).
        scale_fit = {"method": "network", "aligned": anchor is not None}
        if anchor is not None:
            scale_fit.update(scale=anchor["scale"], offset=anchor["offset"])
    if scale is not None:
        affine = not metric
        disparity, fit = scale_disparity(disparity, scale, affine=affine)
        metric, scale_fit = True, fit.as_dict()
    with np.errstate(invalid="ignore"):
        checks["valid_fraction"] = float((disparity > 0).mean())
    depth = depth_of(disparity)
    return EstimateResult(
        disparity=disparity,
        depth=depth,
        confidence=confidence,
        tangents=perspective,
        timings={
            **timings,
            "convert": t_convert - t_network + st.get("convert", 0.0),
            "align": st.get("align", 0.0),
            "blend": st.get("blend", 0.0),
            # The anchoring, the result checks and any stitch tried before a fallback.
            "check": max(0.0, t_stitched - t_convert - sum(st.values())),
            "upsample": t_upsampled - t_stitched,
        },
        model=model_info,
        units="metres" if metric else "relative",
        options={
            **opts.as_dict(),
            "layout": repr(layout),
            "erp_shape": [height, width],
            "working_width": work_width,
            "upsample": upsample if work_width != width else None,
            **({"edges": "photo"} if edges == "photo" else {}),
            **({} if erp_valid is None else {"masked_fraction": float(1 - erp_valid.mean())}),
            **({"sky": "nan"} if sky_mode == "nan" else {}),
            **({} if prior_record is None else {"prior": prior_record}),
        },
        layout=layout,
        stitch=details,
        scale=scale_fit,
        checks=checks,
    )


def _model_info(
    estimator: Any, layout: Layout | None, image_shape: tuple[int, int] | None = None
) -> dict[str, Any]:
    """Describe what ran (result, sidecar); ``image_shape``: what a panoramic model saw."""
    info: dict[str, Any] = {
        "name": getattr(estimator, "name", type(estimator).__name__),
        "output_kind": estimator.output_kind,
    }
    if isinstance(estimator, _estimators.OnnxEstimator):
        shape = layout.tangent_shape if layout is not None else image_shape
        network_size = None if shape is None else estimator.network_size(shape)
        info.update(
            sha256=estimator.sha256,
            path=str(estimator.path),
            providers=list(estimator.providers),
            threads=estimator.threads,
            network_size=None if network_size is None else list(network_size),
            degrees_per_pixel=None
            if network_size is None
            else round(pixel_degrees(layout, network_size[1]), 4),
            input_size=None if estimator.input_size is None else list(estimator.input_size),
            resize=estimator.resize_policy,
            multiple_of=estimator.multiple_of,
            normalize=estimator.normalize,
            mean=[float(v) for v in estimator.mean],
            std=[float(v) for v in estimator.std],
            normalization=estimator.normalization.as_dict(),
        )
    else:
        info["sha256"] = None
    return info
