"""The network's batches span frames (``frame_batch``): frames prepared and predicted ahead.

Frame t's *network prediction* does not depend on frame t−1; only what follows it does (the
temporal term, from frame t−1's result). So the local engine takes K decoded frames, prepares
each (:func:`m360.pipeline.estimate.prepare`: checks, working-width resize, projection), runs
the estimator ONCE on their K·N tangents, and then finishes the frames one by one, in order,
with the temporal term (:func:`m360.pipeline.estimate.finish`), exactly as a run frame by
frame does: the same bytes.

- A group whose network call fails is not lost: each of its frames runs its own network call
  at its turn (the call ``m360.estimate`` makes), so a bad frame fails alone. When every frame
  of such a group then succeeds, the estimator does not take several frames' tangents at once:
  the rest of the run goes one frame at a time, with a note.
- Frames ahead hold their tangents and the network's output: K is capped so that they fit next
  to one frame's estimate (:func:`m360.pipeline.memory.estimate_memory`) in the memory
  available (:func:`m360.pipeline.memory.available_memory`), with a note when it is.
- Frames skipped as done, frames that could not be read and frames whose preparation failed
  are left to the per-frame path (which skips or fails them as before).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..batch import Job
from ..geometry.layout import default_layout
from ..pipeline import memory as _memory
from ..pipeline.estimate import Prepared, _predict, prepare
from ._frame import _done, _Plan
from .reader import Frame

#: The most frames one network call takes (``frame_batch``'s upper bound).
MAX_FRAME_BATCH = 64


@dataclass
class Ahead:
    """A frame prepared before its turn, with its share of the group's network output.

    ``raw`` is None when the group's call failed (or the frame's layout is not the group's):
    the frame then runs its own network call at its turn, on ``prepared``'s tangents.
    """

    prepared: Prepared
    raw: np.ndarray | None = None
    seconds: float = 0.0

    def predict(self) -> tuple[np.ndarray, float]:
        """Give the frame's network output and its seconds (its own call when it has none)."""
        if self.raw is not None:
            return self.raw, self.seconds
        t0 = time.perf_counter()
        raw = _predict(self.prepared.estimator, self.prepared.release(), self.prepared.layout)
        return raw, time.perf_counter() - t0


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
        self._fell_back = False

    def cap(self, frame: Frame) -> None:
        """Lower :attr:`size` to what memory holds, once, from the first readable frame."""
        if self._capped or frame.rgb is None or self.size == 1:
            return
        height, width = frame.rgb.shape[:2]
        if frame.rgb.ndim != 3 or width != 2 * height:
            return  # not a panorama: it fails alone; the next frame sets the cap
        self._capped = True
        available = _memory.available_memory()
        if available is None:
            return
        work = _memory.working_width_for(self.plan.job["working_width"], width)
        layout = default_layout(work, self.plan.job["padding"])
        h, w = layout.tangent_shape
        # Per frame ahead: its tangents (uint8 RGB), the network's output (float32), the
        # decoded frame and its working-resolution copy.
        per_frame = len(layout) * h * w * (3 + 4) + frame.rgb.nbytes * (1 + (work != width))
        one = _memory.estimate_memory(width, work, self.plan.options.method, layout)
        fits = max(1, 1 + (available - one) // per_frame)
        if fits < self.size:
            self.notes.append(
                f"frame_batch {self.size} lowered to {fits}: {fits} frames of tangents and "
                f"network output ({per_frame / 2**20:.0f} MB each) fit in the "
                f"{available / 2**30:.1f} GiB available"
            )
            self.size = int(fits)

    def predict(self, group: Sequence[tuple[Frame, Job]]) -> dict[int, Ahead]:
        """Prepare the group's frames to compute and run one network call on them.

        Returns
        -------
        dict
            Frame index -> :class:`Ahead` for each frame prepared; the others (unreadable,
            done, or failing to prepare) take the per-frame path at their turn.
        """
        plan = self.plan
        self._fell_back = False
        aheads: dict[int, Ahead] = {}
        for frame, job in group:
            if frame.error is not None or frame.rgb is None:
                continue
            if plan.resume and _done(plan, job):
                continue
            try:
                prepared = prepare(frame.rgb, plan.estimator, options=plan.options, **plan.job)
            except Exception:  # the frame fails alone at its turn, with the same error
                continue
            aheads[frame.index] = Ahead(prepared)
        if not aheads:
            return aheads
        first = next(iter(aheads.values())).prepared.layout
        together = [a for a in aheads.values() if a.prepared.layout == first]
        if len(together) < 2:
            return aheads
        tangents = np.concatenate([a.prepared.release() for a in together])
        count = len(first)
        t0 = time.perf_counter()
        try:
            raw = _predict(plan.estimator, tangents, first, frames=len(together))
        except Exception:
            # Each frame runs its own call at its turn: only a bad frame fails.
            for k, ahead in enumerate(together):
                ahead.prepared.tangents = tangents[k * count : (k + 1) * count]
            self._fell_back = True
            return aheads
        seconds = (time.perf_counter() - t0) / len(together)
        for k, ahead in enumerate(together):
            ahead.raw, ahead.seconds = raw[k * count : (k + 1) * count], seconds
        return aheads

    def settle(self, statuses: Sequence[str]) -> None:
        """After a group: if its call failed but each frame's own call succeeded, stop batching.

        ``statuses`` are the outcomes of the frames the group prepared.
        """
        if self._fell_back and statuses and all(s == "done" for s in statuses):
            name = getattr(self.plan.estimator, "name", type(self.plan.estimator).__name__)
            self.notes.append(
                f"the estimator {name} failed on {len(statuses)} frames' tangents in one call "
                "and succeeded on each frame alone: the run went on one frame at a time "
                "(frame_batch 1)"
            )
            self.size = 1
        self._fell_back = False
