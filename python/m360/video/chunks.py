"""Chunked video runs: the Ray engine of :func:`m360.video.run`, and its chunks run here.

``engine="ray"`` runs chunks on Ray; ``engine="local"`` with ``chunk=`` runs the same chunks in
this process (the same bytes).

The temporal term makes frames sequential, so a video is split into chunks of ``chunk``
consecutive selected frames. Each chunk runs in order on one worker from a fresh temporal state
started ``overlap`` frames early (its *warm-up*: the previous chunk's last frames, estimated
again and not written), so the chunk's own first frame already has a settled state. Chunks run
in parallel; only their writes go in order, because a chunk's **gauge** (the affine map
``a·D + b`` of a relative result, which a fresh state takes from its first frame) is fitted on
the overlap: the warm-up frames' states against the states the previous chunk wrote for the
same frames (weighted least squares, refitted without the worst 20 %, as the temporal term's
own gauge step). Every frame of the chunk up to its first reset (a scene cut, a failed frame)
is mapped by that fit, so a chunk boundary does not jump; after a reset a frame starts afresh,
as in the local engine.

Each frame is written by the worker that finished it, with the local engine's writer
(:func:`m360.video._frame._write`: the same files, state, sidecar last, atomic), and is skipped
when it is already done with the run's fingerprint, whichever engine made it. The chunking is
not in the fingerprint, so a local run and a Ray run resume each other's frames; the sidecar's
``temporal.chunk`` records the chunk and the gauge. A chunk with every frame done is not run; a
chunk with some frames done is recomputed from its warm-up and writes only the others, so the
bytes do not depend on where a run stopped or on the number of workers.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..batch import ImageOutcome, error_outcome, failure_outcome
from ..errors import ModelError, ReadError
from ._frame import _compute, _Computed, _done, _job, _Plan, _state_path, _write, frame_stem
from .reader import Frame
from .temporal import TemporalState, _fit_gauge

__all__ = ["DEFAULT_CHUNK", "DEFAULT_OVERLAP", "Chunk", "ChunkRunner", "chunks_of"]

#: Frames per chunk of a Ray run (a worker holds a chunk's results until its gauge is known).
DEFAULT_CHUNK = 32
#: Warm-up frames a chunk starts before its own (the previous chunk's last frames).
DEFAULT_OVERLAP = 4

Gauge = tuple[float, float]
Tail = dict[int, np.ndarray]  # frame index -> written state disparity (the run's gauge)


@dataclass
class Chunk:
    """Consecutive selected frames: ``warmup`` frames of the previous chunk, then its own."""

    number: int
    frames: list[Frame]
    warmup: int

    @property
    def own(self) -> list[Frame]:
        """The chunk's own frames (written by it), after the warm-up."""
        return self.frames[self.warmup :]


@dataclass
class _Summary:
    """What a computed chunk tells the driver: its warm-up states (local gauge), by index."""

    warm: dict[int, np.ndarray] = field(default_factory=dict)
    relative: bool = True


def chunks_of(frames: Iterable[Frame], size: int, overlap: int) -> Iterator[Chunk]:
    """Cut the frames into chunks of ``size`` own frames, each after ``overlap`` warm-up ones."""
    own: list[Frame] = []
    warm: list[Frame] = []
    number = 0
    for frame in frames:
        own.append(frame)
        if len(own) == size:
            yield Chunk(number, warm + own, len(warm))
            warm, own, number = own[len(own) - overlap :] if overlap else [], [], number + 1
    if own:
        yield Chunk(number, warm + own, len(warm))


class ChunkRunner:
    """Runs chunks on one estimator: a Ray actor, or an object in this process.

    :meth:`compute` holds a chunk's frames, :meth:`write` writes them in the gauge the driver
    fitted.
    """

    def __init__(self, plan: _Plan, threads: int | None = None) -> None:
        from ..estimators import ModelOptions, load_estimator

        if threads is not None:
            from .._core import get_num_threads, set_num_threads

            if get_num_threads() != threads:
                set_num_threads(threads)
        if plan.estimator is None:
            given = {} if plan.model_options is None else plan.model_options.keywords()
            if threads is not None and given.get("threads") is None:
                given["threads"] = threads
            estimator = load_estimator(plan.model, model_options=ModelOptions(**given))
            plan = _replace_estimator(plan, estimator)
        self.plan = plan
        self.chunk: Chunk | None = None
        self.kept: list[tuple[Any, _Computed | ImageOutcome, bool]] = []

    def ready(self) -> bool:
        """Tell the driver the model loaded (a failure is the constructor's exception)."""
        return True

    def compute(self, chunk: Chunk) -> _Summary:
        """Estimate and smooth the chunk's frames in order; keep its own ones for :meth:`write`."""
        plan = self.plan
        state: TemporalState | None = None
        missing = "first frame" if chunk.number == 0 else "chunk start"
        anchored = True  # no reset since the chunk's first frame: the fitted gauge applies
        summary = _Summary()
        self.chunk, self.kept = chunk, []
        for position, frame in enumerate(chunk.frames):
            own = position >= chunk.warmup
            job = _job(plan, frame)
            computed: _Computed | None = None
            if frame.error is not None or frame.rgb is None:
                error = frame.error or ReadError(f"frame {frame.index} could not be read")
                outcome: ImageOutcome = failure_outcome(job.input, job.name, error)
            else:
                try:
                    computed = _compute(plan, frame, job, state, missing)
                except Exception as exc:  # a frame fails alone
                    outcome = error_outcome(job, exc)
            if computed is None:
                state, missing, anchored = None, "previous frame failed", False
                if own:
                    self.kept.append((job, outcome, False))
                continue
            if position > 0 and computed.extra["temporal"]["gauge"] is None:
                anchored = False  # a fresh start inside the chunk (a scene cut): its own gauge
            summary.relative = computed.result.units == "relative"
            state = computed.state
            if own:
                self.kept.append((job, computed, anchored))
            elif anchored:
                summary.warm[frame.index] = computed.state.disparity
        return summary

    def write(self, gauge: Gauge | None, overlap: int) -> tuple[list[ImageOutcome], Tail]:
        """Write the kept frames (``gauge`` on those before the first reset) but done ones.

        Returns the outcomes and the written states of the last ``overlap`` frames.
        """
        plan, chunk = self.plan, self.chunk
        assert chunk is not None
        outcomes: list[ImageOutcome] = []
        tail: Tail = {}
        last = set(_tail_indices(chunk, overlap))
        for job, item, anchored in self.kept:
            if isinstance(item, ImageOutcome):
                outcomes.append(item)
                continue
            index = item.extra["frame"]["index"]
            if plan.resume and _done(plan, job):
                outcomes.append(ImageOutcome(str(job.input), job.name, "skipped"))
                if index in last:
                    tail.update(written_states(plan, [index]))
                continue
            a, b = gauge if (anchored and gauge is not None) else (1.0, 0.0)
            frame = item.with_gauge(a, b)
            record = {"number": chunk.number, "gauge": [a, b] if anchored else None}
            frame.extra = {**frame.extra, "temporal": {**frame.extra["temporal"], "chunk": record}}
            try:
                timings = _write(plan, job, frame)
            except Exception as exc:  # a frame fails alone
                outcomes.append(error_outcome(job, exc))
                continue
            outcomes.append(ImageOutcome(str(job.input), job.name, "done", timings=timings))
            if index in last:
                tail[index] = frame.state.disparity
        self.chunk, self.kept = None, []
        return outcomes, tail


def _replace_estimator(plan: _Plan, estimator: Any) -> _Plan:
    return dataclasses.replace(plan, estimator=estimator)


def written_states(plan: _Plan, indices: Iterable[int]) -> Tail:
    """Read the state disparities that done frames left in OUT (unreadable ones left out)."""
    tail: Tail = {}
    for index in indices:
        with contextlib.suppress(ReadError):
            path = _state_path(plan.out / frame_stem(index))
            tail[index] = TemporalState.load(path).disparity
    return tail


def fit_gauge(summary: _Summary, previous: Tail) -> Gauge | None:
    """Fit the chunk's gauge: its warm-up states to the previous chunk's written ones."""
    if not summary.relative:
        return None  # metric results keep their metres
    shared = sorted(set(summary.warm) & set(previous))
    if not shared:
        return None
    source = np.stack([summary.warm[k] for k in shared])
    target = np.stack([previous[k] for k in shared])
    return _fit_gauge(source, target, np.ones(source.shape, np.float32))


def _skippable(plan: _Plan, chunk: Chunk) -> list[ImageOutcome] | None:
    """Give the outcomes of a chunk with nothing to do (all done or unreadable), else None."""
    if not plan.resume:
        return None
    outcomes = []
    for frame in chunk.own:
        job = _job(plan, frame)
        if frame.error is not None or frame.rgb is None:
            error = frame.error or ReadError(f"frame {frame.index} could not be read")
            outcomes.append(failure_outcome(job.input, job.name, error))
        elif _done(plan, job):
            outcomes.append(ImageOutcome(str(job.input), job.name, "skipped"))
        else:
            return None
    return outcomes


def _tail_indices(chunk: Chunk, overlap: int) -> list[int]:
    return [frame.index for frame in chunk.own[len(chunk.own) - overlap :]] if overlap else []


def run_local(
    plan: _Plan,
    chunks: Iterable[Chunk],
    overlap: int,
    record: Callable[[ImageOutcome], None],
) -> None:
    """Run the chunks one after another in this process (the Ray engine's bytes, no Ray)."""
    runner = ChunkRunner(plan)
    previous: Tail = {}
    for chunk in chunks:
        skipped = _skippable(plan, chunk)
        if skipped is not None:
            for outcome in skipped:
                record(outcome)
            previous = written_states(plan, _tail_indices(chunk, overlap))
            continue
        summary = runner.compute(chunk)
        outcomes, previous = runner.write(fit_gauge(summary, previous), overlap)
        for outcome in outcomes:
            record(outcome)


def run_ray(
    plan: _Plan,
    chunks: Iterable[Chunk],
    overlap: int,
    record: Callable[[ImageOutcome], None],
    resources: Any,
) -> None:
    """Run the chunks on Ray: ``resources.model_actors`` workers, one chunk each at a time.

    Chunks are computed in parallel and written in order (a chunk's gauge needs the previous
    chunk's written states); a worker takes its next chunk once its chunk is written.
    """
    import ray as _ray

    ray: Any = _ray
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    threads = max(1, math.ceil(resources.cpus_per_stitch))
    actor_class = ray.remote(ChunkRunner).options(
        num_cpus=resources.cpus_per_stitch,
        num_gpus=resources.gpus_per_model,
        max_restarts=0,
        max_task_retries=0,
    )
    shipped = plan if _picklable_model(plan) else _replace_estimator(plan, None)
    actors: list[Any] = []
    try:
        actors = [actor_class.remote(shipped, threads) for _ in range(resources.model_actors)]
        try:
            ray.get([actor.ready.remote() for actor in actors])
        except ray.exceptions.RayError as exc:
            raise ModelError(f"the chunk workers could not load the model: {exc}") from exc
        idle: deque[Any] = deque(actors)
        entries: deque[tuple[Chunk, Any, Any]] = deque()
        source = iter(chunks)
        exhausted = False
        previous: Tail = {}
        while True:
            # Few chunks wait at once: each holds its decoded frames.
            while idle and not exhausted and len(entries) < 2 * len(actors):
                chunk = next(source, None)
                if chunk is None:
                    exhausted = True
                    break
                skipped = _skippable(plan, chunk)
                if skipped is not None:
                    entries.append((chunk, None, skipped))
                    continue
                actor = idle.popleft()
                entries.append((chunk, actor, actor.compute.remote(chunk)))
            if not entries:
                break
            chunk, actor, ref = entries.popleft()
            if actor is None:  # every frame done: recorded now, in order
                for outcome in ref:
                    record(outcome)
                previous = written_states(plan, _tail_indices(chunk, overlap))
                continue
            try:
                summary = ray.get(ref)
                outcomes, previous = ray.get(
                    actor.write.remote(fit_gauge(summary, previous), overlap)
                )
            except ray.exceptions.RayError as exc:
                outcomes, previous = _crashed(plan, chunk, exc), {}
                with contextlib.suppress(Exception):
                    ray.kill(actor)
                actors.remove(actor)
                actor = actor_class.remote(shipped, threads)
                actors.append(actor)
            idle.append(actor)
            for outcome in outcomes:
                record(outcome)
    finally:
        for actor in actors:
            with contextlib.suppress(Exception):
                ray.kill(actor)
        if started_here:
            ray.shutdown()


def _picklable_model(plan: _Plan) -> bool:
    """Ship the estimator object itself unless the run named a model (a worker loads it)."""
    import os

    return not isinstance(plan.model, (str, os.PathLike))


def _crashed(plan: _Plan, chunk: Chunk, exc: BaseException) -> list[ImageOutcome]:
    """Every own frame of a chunk whose worker died fails (WorkerCrashed), unless done."""
    from ..batch._ray_engine import _ANSI

    cause = _ANSI.sub("", str(exc)).strip().partition("\n")[0][:200]
    outcomes = []
    for frame in chunk.own:
        job = _job(plan, frame)
        if plan.resume and frame.rgb is not None and _done(plan, job):
            outcomes.append(ImageOutcome(str(job.input), job.name, "skipped"))
            continue
        message = f"the Ray worker died while running chunk {chunk.number}: {cause}"
        outcomes.append(ImageOutcome(str(job.input), job.name, "failed", "WorkerCrashed", message))
    return outcomes
