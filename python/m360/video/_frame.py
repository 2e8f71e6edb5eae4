"""One frame of a video run: estimate and smooth (:func:`_compute`), then write (:func:`_write`).

Shared by the local engine (:mod:`m360.video.runner`) and the chunked / Ray engine
(:mod:`m360.video.chunks`), so both write the same files, state and sidecar.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._keywords import definition
from ..batch import Job, is_done
from ..estimators.options import ModelOptions
from ..io import remove_stale_temporaries, save
from ..io.files import temporary_prefix
from ..pipeline.options import EstimateKeywords
from ..stitching.depth import depth_of
from ..stitching.options import StitchOptions
from .reader import Frame, Source
from .temporal import Correction, Temporal, TemporalState

if TYPE_CHECKING:
    from ._ahead import Ahead

#: Suffix of a frame's temporal state (``OUT/000123.temporal.npy``).
STATE_SUFFIX = ".temporal.npy"


def frame_stem(index: int) -> str:
    """Give the output stem of frame ``index``: six digits at least (``000123``)."""
    return f"{index:06d}"


@dataclass(frozen=True)
class _Plan:
    """What every frame of a run shares."""

    out: Path
    source: Source
    estimator: Any
    options: StitchOptions
    job: dict[str, Any]
    formats: tuple[str, ...]
    preview: bool
    confidence: bool
    fingerprint: dict[str, Any]
    run_id: str
    resume: bool
    temporal: Temporal
    tangent_model: bool = True  # a panoramic model runs alone: no prior goes with it
    model: Any = None  # what a chunk worker loads its estimator from (the run's ``model``)
    model_options: ModelOptions | None = None

    @property
    def prior_from_previous(self) -> bool:
        """Whether a frame's stitch may take the previous frame as its prior.

        Then a frame's estimate depends on the frame before it; otherwise only the temporal
        term after the estimate does (so estimates may run ahead, :mod:`m360.video._ahead`).
        """
        return (
            self.temporal.prior
            and self.temporal.mode != "none"
            and self.options.align is not None  # a prior acts through the alignment
            and self.tangent_model
        )


def _input_of(plan: _Plan, frame: Frame) -> Path:
    """Give the file a frame comes from (its image in a folder, else the video)."""
    return frame.path if frame.path is not None else plan.source.path


def _job(plan: _Plan, frame: Frame) -> Job:
    name = frame_stem(frame.index)
    return Job(_input_of(plan, frame), plan.out / name, name, f"{plan.source.path}#{frame.index}")


def _state_path(stem: Path) -> Path:
    return stem.with_name(stem.name + STATE_SUFFIX)


def _done(plan: _Plan, job: Job) -> bool:
    done = is_done(job, plan.fingerprint)
    return done and (plan.temporal.mode == "none" or _state_path(job.stem).is_file())


@dataclass
class _Computed:
    """A frame estimated and smoothed, not yet written (what :func:`_write` takes)."""

    result: Any
    state: TemporalState
    extra: dict[str, Any]
    timings: dict[str, float]
    #: The temporal term's full-size step, left to :func:`_write` (None: applied or none).
    correction: Correction | None = None
    #: The frame's photo, hashed into the sidecar by :func:`_write` (on the writer thread).
    rgb: np.ndarray | None = None

    def corrected(self) -> _Computed:
        """The frame with its temporal correction applied (itself when there is none)."""
        if self.correction is None:
            return self
        t0 = time.perf_counter()
        disparity = self.correction.apply(self.result.disparity)
        result = dataclasses.replace(self.result, disparity=disparity, depth=depth_of(disparity))
        timings = {**self.timings, "temporal": self.timings["temporal"] + time.perf_counter() - t0}
        return dataclasses.replace(self, result=result, timings=timings, correction=None)

    def with_gauge(self, a: float, b: float) -> _Computed:
        """The same frame in another gauge: disparity and state mapped by ``a·D + b``."""
        if self.correction is not None:
            return self.corrected().with_gauge(a, b)
        if (a, b) == (1.0, 0.0):
            return self
        disparity = self.result.disparity * np.float32(a) + np.float32(b)
        result = dataclasses.replace(self.result, disparity=disparity, depth=depth_of(disparity))
        state = self.state
        state = TemporalState(
            state.disparity * np.float32(a) + np.float32(b),
            state.grey,
            None if state.velocity is None else state.velocity * np.float32(a),
        )
        return dataclasses.replace(self, result=result, state=state)


def _compute(
    plan: _Plan,
    frame: Frame,
    job: Job,
    previous: TemporalState | None,
    missing: str,
    ahead: Ahead | None = None,
    *,
    defer: bool = False,
) -> _Computed:
    """Estimate and smooth one frame (nothing written).

    ``ahead``: the frame prepared, and usually predicted, before its turn
    (:mod:`m360.video._ahead`); it is finished here as :func:`m360.estimate` would, unless it
    was finished ahead (no prior from the previous frame). With
    ``defer`` the temporal term's full-size step is left to :func:`_write` (the state the
    next frame needs is ready without it).
    """
    from ..pipeline.estimate import estimate, finish

    assert frame.rgb is not None
    t0 = time.perf_counter()
    grey, confidence, record = plan.temporal.prepare(frame.rgb, previous, missing=missing)
    prior = {}
    if plan.prior_from_previous:
        prior = plan.temporal.prior_keywords(previous, confidence, _estimate_keywords())
    record["prior"] = bool(prior)
    earlier = 0.0  # seconds of this frame's estimate spent before its turn
    if ahead is None:
        result = estimate(frame.rgb, plan.estimator, options=plan.options, **plan.job, **prior)
    elif ahead.result is not None:  # estimated ahead: nothing in it depends on ``previous``
        assert not plan.prior_from_previous
        earlier, result = ahead.earlier, ahead.result
    else:
        assert ahead.prepared is not None
        earlier = ahead.earlier
        raw, seconds = ahead.predict()
        result = finish(ahead.prepared, raw, seconds=seconds, **prior)
    t_estimate = time.perf_counter()
    state, correction, applied = plan.temporal.advance(
        result.disparity,
        grey,
        confidence,
        None if confidence is None else previous,
        relative=result.units == "relative",
    )
    t_temporal = time.perf_counter()
    extra = {
        "frame": {"index": frame.index, "time": frame.time, "video": str(plan.source.path)},
        "temporal": {"mode": plan.temporal.mode, **record, **applied},
        "batch": {"fingerprint": plan.fingerprint, "run": plan.run_id},
    }
    timings = {
        **{k: v for k, v in result.timings.items() if k != "total"},
        "estimate": t_estimate - t0 + earlier,
        "temporal": t_temporal - t_estimate,
    }
    computed = _Computed(result, state, extra, timings, correction, frame.rgb)
    return computed if defer else computed.corrected()


def _write(plan: _Plan, job: Job, frame: _Computed) -> dict[str, float]:
    """Write one computed frame atomically, its sidecar last; its timings.

    A deferred temporal correction is applied first (on the run's writer thread).
    """
    frame = frame.corrected()
    t0 = time.perf_counter()
    # Temporaries a killed run left for this frame (the run's claim is held, so none is live).
    remove_stale_temporaries(job.stem)
    state_name = _state_path(job.stem).name
    for tmp in job.stem.parent.glob(f"{glob.escape(temporary_prefix(state_name))}{'?' * 8}.tmp"):
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    stat = job.input.stat()
    source = {"path": str(job.input), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    if frame.rgb is not None:
        photo = np.ascontiguousarray(frame.rgb)
        source["rgb_sha256"] = hashlib.sha256(photo.data).hexdigest()  # no copy
    extra = {**frame.extra, "input": source}
    if plan.temporal.mode != "none":
        frame.state.save(_state_path(job.stem))  # before the sidecar: a done frame has its state
    save(
        frame.result,
        job.stem,
        formats=plan.formats,
        preview=plan.preview,
        extra=extra,
        confidence=plan.confidence,
    )
    return {**frame.timings, "write": time.perf_counter() - t0}


def _estimate_keywords() -> set[str]:
    """List the keyword names :func:`m360.estimate` takes (its own and its keyword lists')."""
    import inspect

    from ..pipeline.estimate import estimate

    names = set(inspect.signature(estimate).parameters)
    return names | set(definition(EstimateKeywords))
