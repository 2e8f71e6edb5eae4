"""Frames estimated ahead of their turn: on worker threads, and in groups (``frame_batch``).

Frame t's *estimate* does not depend on frame t−1; only the temporal term that follows it does
(:mod:`m360.video.temporal`), unless that term hands the previous frame to the stitch as a prior
(``Temporal(prior=True)``). So the local engine runs the estimates of the frames read on worker
threads (:class:`Estimates`), :data:`ESTIMATES_IN_FLIGHT` frames at once, while its main thread
takes the frames in order: the temporal term, then the files (:mod:`m360.video.runner`). With a
prior from the previous frame, only the projection and the network run ahead, and the stitch
waits for the frame's turn.

- **One network call at a time, in frame order** (:class:`NetworkTurns`): an estimator object
  need not be thread-safe, a GPU is not shared between calls, and the calls an estimator sees
  do not depend on thread timing. The stitches of two frames overlap; on a CPU that fills the
  cores one frame's alignment leaves idle (its solver steps are serial between the parallel
  energy evaluations).
- **The same bytes**: nothing a frame computes depends on the thread that computes it or on what
  runs beside it (the core's parallel loops reduce in a fixed order), so each frame is what a
  run frame by frame writes.
- **Memory**: each frame in flight holds an estimate's peak memory; their number is lowered to
  what fits (:func:`m360.pipeline.memory.available_memory`), with a note.

``frame_batch=K`` (:class:`FrameBatcher`): K decoded frames are prepared (checks, working-width
resize, projection: :func:`m360.pipeline.estimate.prepare`), the estimator runs ONCE on their
K·N tangents, and each frame is finished with its share (:func:`m360.pipeline.estimate.finish`):
again the bytes of a run frame by frame.

- A group whose call fails is not lost: each of its frames runs its own call, so a bad frame
  fails alone. When every frame's own call then succeeds, the estimator does not take several
  frames' tangents at once: the rest of the run goes one frame at a time, with a note.
- Frames ahead hold their tangents and the network's output: K is capped so that they fit next
  to one frame's estimate (:func:`m360.pipeline.memory.estimate_memory`) in the memory
  available, with a note when it is.
- Frames skipped as done, frames that could not be read and frames whose preparation failed
  are left to the per-frame path (which skips or fails them as before).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..batch import Job
from ..geometry.layout import Layout
from ..pipeline import estimate as _pipeline
from ..pipeline import memory as _memory
from ..pipeline.estimate import EstimateResult, Prepared, _predict, prepare
from ..pipeline.options import job_layout
from ._frame import _Plan
from .reader import Frame

#: The most frames one network call takes (``frame_batch``'s upper bound).
MAX_FRAME_BATCH = 64
#: Frames the local engine estimates at once (:class:`Estimates`): two fill the cores that one
#: frame's alignment leaves idle (docs/video.md, "Throughput"); lowered to what fits in memory.
ESTIMATES_IN_FLIGHT = 2


def _sizes(plan: _Plan, frame: Frame) -> tuple[int, int, Layout] | None:
    """The (width, working width, layout) a frame runs at; None when it is not a panorama.

    A frame that is not one fails alone, and the next readable one sets the memory caps.
    """
    if frame.rgb is None or frame.rgb.ndim != 3:
        return None
    height, width = frame.rgb.shape[:2]
    if width != 2 * height:
        return None
    work = _memory.working_width_for(plan.job["working_width"], width)
    return width, work, job_layout(work, plan.job)


class NetworkTurns:
    """One network call at a time, in the order of the tickets handed out (frame order).

    :meth:`ticket` is called by the thread that submits the work, in order; each ticket is
    then used once (:meth:`call`) or given up (:meth:`release`), whichever thread holds it.
    A ticket waits only for the tickets before it, whose work was submitted (and, on a
    first-in first-out pool, started) before its own, so the turns cannot deadlock.
    """

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._issued = 0
        self._turn = 0
        self._closed = False

    def ticket(self) -> int:
        """Give the next ticket."""
        with self._changed:
            self._issued += 1
            return self._issued - 1

    @contextlib.contextmanager
    def call(self, ticket: int) -> Iterator[None]:
        """Wait for ``ticket``'s turn, hold it during the ``with`` block, then pass it on."""
        with self._changed:
            self._changed.wait_for(lambda: self._turn == ticket or self._closed)
            if self._closed:
                raise CancelledError("the run stopped")
        try:
            yield
        finally:
            self._advance(ticket)

    def release(self, ticket: int) -> None:
        """Give ``ticket``'s turn up when it comes (nothing when it was used)."""
        with self._changed:
            self._changed.wait_for(lambda: self._turn >= ticket or self._closed)
        self._advance(ticket)

    def _advance(self, ticket: int) -> None:
        with self._changed:
            if self._turn == ticket:
                self._turn += 1
                self._changed.notify_all()

    def close(self) -> None:
        """Wake every waiting ticket: the run stopped and no call is made any more."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()


@dataclass
class Ahead:
    """A frame prepared before its turn, with its network output or its whole estimate.

    ``raw`` is None when the frame's network has not run (its group's call failed, or the
    frame's layout is not the group's): :meth:`predict` then runs its own call on
    ``prepared``'s tangents. ``result`` is the finished estimate when it could be made ahead
    (no prior from the previous frame); ``prepared`` is then None (released).
    """

    prepared: Prepared | None
    raw: np.ndarray | None = None
    seconds: float = 0.0
    result: EstimateResult | None = None
    #: The frame's own network call failed (its group's call had failed before): its error.
    error: Exception | None = None

    def predict(
        self, network: contextlib.AbstractContextManager[Any] | None = None
    ) -> tuple[np.ndarray, float]:
        """Give the frame's network output and its seconds (its own call when it has none).

        ``network``: entered for the call (the frame's turn), not counted in its seconds.
        """
        if self.error is not None:
            raise self.error
        if self.raw is not None:
            return self.raw, self.seconds
        assert self.prepared is not None
        with network or contextlib.nullcontext():
            t0 = time.perf_counter()
            raw = _predict(self.prepared.estimator, self.prepared.release(), self.prepared.layout)
            return raw, time.perf_counter() - t0

    @property
    def earlier(self) -> float:
        """Seconds of the frame's estimate already spent (before its turn)."""
        if self.result is not None:
            return float(self.result.timings["total"])
        assert self.prepared is not None
        return sum(self.prepared.timings.values()) + (self.seconds if self.raw is not None else 0)


@dataclass
class Group:
    """What :meth:`FrameBatcher.predict` gave for a group of frames.

    ``aheads``: frame index -> :class:`Ahead` for each frame prepared (the others, unreadable,
    done or failing to prepare, take the per-frame path).
    """

    aheads: dict[int, Ahead]


class FrameBatcher:
    """Prepare and predict groups of frames for the local engine (see the module).

    Parameters
    ----------
    plan : _Plan
        The run's plan (estimator, options, job keywords, resume fingerprint).
    size : int
        Frames per network call asked for (``frame_batch``); capped by memory at the first
        readable frame (:meth:`cap`).
    notes : list of str
        The report's notes: a cap or a return to one frame at a time is said there.
    """

    def __init__(self, plan: _Plan, size: int, notes: list[str]) -> None:
        self.plan = plan
        self.size = size
        self.notes = notes
        self._capped = False

    def cap(self, frame: Frame, in_flight: int = 1) -> None:
        """Lower :attr:`size` to what memory holds, once, from the first readable frame.

        ``in_flight``: the frames estimated at once (:attr:`Estimates.depth`), each holding an
        estimate's memory beside the frames ahead.
        """
        sizes = None if self._capped or self.size == 1 else _sizes(self.plan, frame)
        if sizes is None:
            return
        self._capped = True
        available = _memory.available_memory()
        if available is None:
            return
        width, work, layout = sizes
        assert frame.rgb is not None
        h, w = layout.tangent_shape
        # Per frame ahead: its tangents (uint8 RGB), the network's output (float32), the
        # decoded frame and its working-resolution copy.
        per_frame = len(layout) * h * w * (3 + 4) + frame.rgb.nbytes * (1 + (work != width))
        one = _memory.estimate_memory(width, work, self.plan.options.method, layout)
        fits = max(1, 1 + (available - in_flight * one) // per_frame)
        if fits < self.size:
            self.notes.append(
                f"frame_batch {self.size} lowered to {fits}: {fits} frames of tangents and "
                f"network output ({per_frame / 2**20:.0f} MB each) fit in the "
                f"{available / 2**30:.1f} GiB available"
            )
            self.size = int(fits)

    def predict(
        self,
        group: Sequence[tuple[Frame, Job]],
        network: contextlib.AbstractContextManager[Any] | None = None,
    ) -> Group:
        """Prepare the group's frames and run one network call on them.

        ``group``: readable frames not done (the caller checked). ``network`` is entered for
        the group's calls (its turn). When the group's call fails, each frame runs its own
        there, and when each succeeds the batching stops (a note).
        """
        plan = self.plan
        aheads: dict[int, Ahead] = {}
        for frame, _ in group:
            if frame.rgb is None:
                continue
            try:
                ready = prepare(frame.rgb, plan.estimator, options=plan.options, **plan.job)
            except Exception:  # the frame fails alone at its turn, with the same error
                continue
            aheads[frame.index] = Ahead(ready)
        layouts = [a.prepared.layout for a in aheads.values() if a.prepared is not None]
        together = [a for a in aheads.values() if a.prepared and a.prepared.layout == layouts[0]]
        if len(together) < 2:
            return Group(aheads)
        tangents = [a.prepared.release() for a in together if a.prepared is not None]
        with network or contextlib.nullcontext():
            try:
                t0 = time.perf_counter()
                raw = _predict(
                    plan.estimator, np.concatenate(tangents), layouts[0], frames=len(together)
                )
                seconds = (time.perf_counter() - t0) / len(together)
            except Exception:  # each frame runs its own call: only a bad frame fails
                self._one_by_one(together, tangents)
                return Group(aheads)
        count = len(layouts[0])
        for k, ahead in enumerate(together):
            ahead.raw, ahead.seconds = raw[k * count : (k + 1) * count], seconds
        return Group(aheads)

    def _one_by_one(self, together: list[Ahead], tangents: list[np.ndarray]) -> None:
        """Run each frame's own call after its group's failed; stop batching if all succeed."""
        for ahead, own in zip(together, tangents, strict=True):
            assert ahead.prepared is not None
            ahead.prepared.tangents = own
            try:
                ahead.raw, ahead.seconds = ahead.predict()
            except Exception as exc:  # the frame fails alone at its turn
                ahead.error = exc
        if all(ahead.error is None for ahead in together):
            name = getattr(self.plan.estimator, "name", type(self.plan.estimator).__name__)
            self.notes.append(
                f"the estimator {name} failed on {len(together)} frames' tangents in one call "
                "and succeeded on each frame alone: the run went on one frame at a time "
                "(frame_batch 1)"
            )
            self.size = 1


class Estimates:
    """Frames estimated ahead of their turn on worker threads (see the module).

    Parameters
    ----------
    plan : _Plan
        The run's plan.
    notes : list of str
        The report's notes: a lowered number of frames in flight is said there.
    """

    def __init__(self, plan: _Plan, notes: list[str]) -> None:
        self.plan = plan
        self.notes = notes
        self.depth = ESTIMATES_IN_FLIGHT
        self.network = NetworkTurns()
        # With a prior from the previous frame the stitch waits for that frame: only the
        # projection and the network run ahead.
        self.finish_ahead = not plan.prior_from_previous
        self._pool: ThreadPoolExecutor | None = None
        self._capped = False

    def cap(self, frame: Frame) -> None:
        """Lower :attr:`depth` to what memory holds, once, from the first readable frame."""
        sizes = None if self._capped or self.depth == 1 else _sizes(self.plan, frame)
        if sizes is None:
            return
        self._capped = True
        available = _memory.available_memory()
        if available is None:
            return
        width, work, layout = sizes
        one = _memory.estimate_memory(width, work, self.plan.options.method, layout)
        fits = int(max(1, available // one))
        if fits < self.depth:
            self.notes.append(
                f"{fits} frame estimated at a time, not {self.depth}: one takes "
                f"{one / 2**30:.1f} GiB of the {available / 2**30:.1f} GiB available"
            )
            self.depth = fits

    def submit_group(
        self, batcher: FrameBatcher, group: Sequence[tuple[Frame, Job]]
    ) -> Future[Group]:
        """Start a group's preparation and network call (:meth:`FrameBatcher.predict`)."""
        ticket = self.network.ticket()

        def predict() -> Group:
            try:
                return batcher.predict(group, self.network.call(ticket))
            finally:
                self.network.release(ticket)

        return self._workers().submit(predict)

    def submit(self, frame: Frame, group: Future[Group] | None = None) -> Future[Ahead]:
        """Start a frame's estimate; ``group``: its group's call, submitted before it.

        The future gives the frame's :class:`Ahead`, its estimate finished when nothing in
        it waits for the previous frame.
        """
        return self._workers().submit(self._estimate, frame, group, self.network.ticket())

    def _workers(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.depth, thread_name_prefix="m360-video-estimate")
        return self._pool

    def _estimate(self, frame: Frame, group: Future[Group] | None, ticket: int) -> Ahead:
        plan = self.plan
        assert frame.rgb is not None
        try:
            # The group's task was submitted first, so it has started: no deadlock.
            ahead = None if group is None else group.result().aheads.get(frame.index)
            if not plan.tangent_model:  # a panoramic model: the whole estimate is its network
                with self.network.call(ticket):
                    result = _pipeline.estimate(
                        frame.rgb, plan.estimator, options=plan.options, **plan.job
                    )
                return Ahead(None, result=result)
            if ahead is None:
                ahead = Ahead(prepare(frame.rgb, plan.estimator, options=plan.options, **plan.job))
            raw, seconds = ahead.predict(self.network.call(ticket))
        finally:
            self.network.release(ticket)  # the next frame's call need not wait for the stitch
        assert ahead.prepared is not None
        if not self.finish_ahead:
            ahead.raw, ahead.seconds = raw, seconds
            return ahead
        return Ahead(None, result=_pipeline.finish(ahead.prepared, raw, seconds=seconds))

    def close(self) -> None:
        """Stop: frames not started are dropped, the ones running are finished and dropped.

        Waiting for them is what a run frame by frame does too when Ctrl-C comes in the middle
        of a stitch (the core's work is not interruptible); no thread outlives the run.
        """
        self.network.close()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
