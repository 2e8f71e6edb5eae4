"""Depth for every frame of a 360° video, resumable: :func:`run`, the engine of ``m360 video``.

>>> report = m360.video.run("walk.mp4", "out/walk/", model="midas-v21-small")
>>> report.exit_code          # 0: all done; 1: some frames failed; 3: another run holds OUT

Frame by frame, with the batch's guarantees (docs/architecture.md, "Batch guarantees"):

- **One output set per frame**: ``OUT/000123.disparity.npy`` … and its sidecar
  ``OUT/000123.json`` (written last, so a sidecar means a complete frame), the frame's
  ``index``, ``time`` and what the temporal term did in it; plus ``OUT/000123.temporal.npy``,
  the small state the next frame starts from (:class:`m360.video.temporal.TemporalState`).
  One sidecar per frame, not one per run: a frame is complete or absent on its own (a run
  index would be a file every frame rewrites, which a kill can leave behind the frames), and
  ``m360.load("OUT/000123")`` reads any frame alone. ``OUT/video.json`` describes the run
  (source, selection, the preview's colour scale).
- **Resumable**: a frame is skipped when its sidecar holds the same fingerprint (the batch's,
  plus the temporal mode and the frame selection), was made from the same video file (path,
  size, modification time) and its files and state exist; a rerun after a kill redoes only
  the unfinished frames, from the state the last finished frame left, so it writes the same
  bytes as a run that was never stopped.
- **One claim per run**: the temporal term makes frames sequential, so a run claims the whole
  folder (an OS lock on ``OUT/.video.lock``); a second run into it finds it busy (exit 3).
- **One failure is one line** in ``OUT/failures.jsonl``; the next frame starts afresh (no
  temporal term across a failed frame) and the run goes on.
- **Progress** with frames per second and the time left (tqdm).
- **Frames estimated ahead**: two frames' estimates run at once on worker threads, their
  network calls one at a time in frame order, while the temporal term takes the frames in
  order (:mod:`m360.video._ahead`); with ``frame_batch=K``, K frames' tangents go to the
  network in one call. The same bytes as frame by frame.

``engine="ray"`` runs the frames in chunks on a Ray cluster, each chunk started a few frames
early with its gauge fitted to the previous chunk's on them (:mod:`m360.video.chunks`), with
the same files, resume and failures; the engines resume each other's frames.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from .._keywords import split
from .._validate import MAX_THREADS, integer
from ..batch import (
    FAILURES_FILE,
    BatchReport,
    ImageOutcome,
    Job,
    MainThreadInterrupts,
    NoBar,
    append_failure,
    claim,
    error_outcome,
    failure_outcome,
    fingerprint,
    keyboard_interrupt_once,
    make_output_folder,
    ray_resources,
)
from ..errors import InputError, M360Error, ModelError, ReadError
from ..estimators import estimator_kind
from ..estimators import registry as _models
from ..estimators.options import ModelKeywords, ModelOptions
from ..io import check_formats
from ..io.files import atomic_path, save_json
from ..pipeline.options import (
    EstimateKeywords,
    JobKeywords,
    PriorKeywords,
    job_fingerprint,
    refuse_layout_options,
    resolve_job,
)
from ..stitching.options import StitchKeywords, StitchOptions, build
from ._ahead import MAX_FRAME_BATCH, Ahead, Estimates, FrameBatcher
from ._frame import (
    STATE_SUFFIX,
    _compute,
    _done,
    _job,
    _Plan,
    _state_path,
    _write,
    frame_stem,
)
from .reader import Frame, Source, check_selection, frames, prefetch, probe
from .temporal import TEMPORAL_MODES, Temporal, TemporalState

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["RUN_FILE", "STATE_SUFFIX", "VideoReport", "frame_stem", "run"]

#: The run's own description in OUT.
RUN_FILE = "video.json"
#: How many decoded frames wait for the network at most.
READ_AHEAD = 4


@dataclass
class VideoReport(BatchReport):
    """The result of :func:`run`: a :class:`m360.batch.BatchReport` of frames, and more.

    Attributes
    ----------
    source : Source or None
        What was read (:func:`m360.video.probe`).
    preview_video : Path or None
        ``OUT/preview.mp4`` when written.
    colour_scale : (float, float) or None
        The preview's disparity range, fixed for the whole run.
    """

    source: Source | None = None
    preview_video: Path | None = None
    colour_scale: tuple[float, float] | None = None

    def summary(self) -> str:
        """Describe the run in a few lines: counts, frames per second, notes."""
        counts = (
            f"{len(self.done)} done, {len(self.skipped)} already done, "
            f"{len(self.failed)} failed" + (", folder busy in another run" * bool(self.busy))
        )
        lines = [f"m360 video: {counts} in {self.seconds:.1f} s"]
        if self.done:
            lines.append(f"  {len(self.done) / max(self.seconds, 1e-9):.2f} frames/s")
        if self.failed:
            lines.append(f"  failures: {self.failures_file}")
        if self.preview_video is not None:
            lines.append(f"  preview video: {self.preview_video}")
        lines += [f"  {note}" for note in self.notes]
        if self.busy:
            lines.append("  another run is writing this folder: rerun when it has finished")
        if self.interrupted:
            lines.append("  interrupted: rerun the same command to finish the rest")
        if self.model_error is not None:
            lines.append(f"  stopped: the model failed on the first frame: {self.model_error}")
        return "\n".join(lines)


def run(
    src: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    model: Any = _models.DEFAULT_MODEL,
    options: StitchOptions | None = None,
    model_options: ModelOptions | None = None,
    temporal: str | Temporal = "smooth",
    every: int = 1,
    start: int | float | None = None,
    end: int | float | None = None,
    fps: float | None = None,
    formats: Sequence[str] | str = ("npy",),
    preview: bool = False,
    preview_video: bool = False,
    confidence: bool = False,
    resume: bool = True,
    progress: bool = True,
    on_outcome: Callable[[ImageOutcome], None] | None = None,
    engine: str = "local",
    workers: int = 1,
    chunk: int | None = None,
    overlap: int | None = None,
    gpus_per_model: float | None = None,
    cpus_per_stitch: float = 1.0,
    frame_batch: int = 1,
    **keywords: Unpack[EstimateKeywords],
) -> VideoReport:
    """Estimate the depth of every (selected) frame of a 360° video into ``out_dir``.

    See the module docstring for what is written and guaranteed, and docs/video.md.

    Parameters
    ----------
    src : path
        A video file (``pip install "m360[video]"``) or a folder of frames.
    out_dir : path
        Output folder: ``OUT/000123.*`` per frame, ``OUT/video.json``, ``OUT/failures.jsonl``.
    model : str, path or estimator
        As for :func:`m360.estimate`.
    options, model_options :
        Every stitching / model option at once, as for :func:`m360.estimate`.
    temporal : {"smooth", "none"} or Temporal
        ``"smooth"`` (default): each frame kept consistent with the previous one where the
        image did not change, restarted at scene cuts (:mod:`m360.video.temporal`);
        ``"none"``: every frame on its own, as stills; or a :class:`Temporal` itself.
    every, start, end, fps :
        Frame selection, as for :func:`m360.video.frames`.
    formats : sequence of str
        Array formats per frame, see :func:`m360.save`.
    preview : bool
        Also write each frame's colour preview PNG (coloured per frame).
    preview_video : bool
        Write ``OUT/preview.mp4``, the disparity in colour with one colour scale for the whole
        run (the 2nd and 98th percentiles of every frame's disparity).
    confidence : bool
        Also write each frame's confidence map.
    resume : bool
        Skip frames already done with the same input and options (default).
    progress : bool
        Show a progress bar with frames per second and the time left.
    on_outcome : callable, optional
        Called with each frame's :class:`m360.batch.ImageOutcome` as it arrives.
    engine : {"local", "ray"}
        Where frames run: in this process, in order (default), or on a Ray cluster
        (``pip install "m360[ray]"``; the cluster in ``RAY_ADDRESS``, else a local one) in
        chunks of consecutive frames (:mod:`m360.video.chunks`). Same files, resume, failures
        and exit codes either way; each engine resumes the other's frames.
    workers : int
        Ray only: chunk workers (Ray actors, one estimator each) running at once.
    chunk : int, optional
        Frames per chunk (Ray default :data:`~m360.video.chunks.DEFAULT_CHUNK`, 32). With the
        local engine, ``chunk=`` runs the same chunks in this process (the Ray engine's bytes);
        without it the whole video is one sequence.
    overlap : int, optional
        Warm-up frames each chunk starts before its own, on which its gauge is fitted to the
        previous chunk's (default :data:`~m360.video.chunks.DEFAULT_OVERLAP`, 4; at most
        ``chunk``).
    gpus_per_model : float, optional
        Ray only: GPUs per chunk worker (default 1 if ``providers`` asks for CUDA, else 0).
    cpus_per_stitch : float
        Ray only: CPUs per chunk worker (also the core's threads in it).
    frame_batch : int
        Local engine, tangent models: frames whose tangents go to the estimator in ONE call
        (K·N tangents), decoded and projected ahead, then finished and taken in order with the
        temporal term: the bytes of ``frame_batch=1``, and the same resume fingerprint. Default
        1: on CPU the ONNX models run one tangent at a time, so a larger call gains nothing and
        holds K frames' tangents (docs/video.md, "Network calls that span frames"); on a GPU
        with a batched model (``batch_size``) it fills the device. Lowered to what fits in
        memory (a note says so); a failed call is retried frame by frame, so a bad frame fails
        alone. Not with ``engine="ray"`` or ``chunk=``; a panoramic model runs per frame.
    **keywords
        Every option of :func:`m360.estimate` beyond its named ones
        (:class:`m360.pipeline.options.EstimateKeywords`).

    Returns
    -------
    VideoReport
        Per-frame outcomes; ``exit_code`` as ``m360 video`` uses it.
    """
    from ..estimators import load_estimator

    started = time.perf_counter()
    if not isinstance(out_dir, (str, os.PathLike)):
        raise InputError(f"out_dir must be a path, got {type(out_dir).__name__}")
    if not isinstance(src, (str, os.PathLike)):
        raise InputError(f"src must be a path, got {type(src).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} exists and is not a folder")
    if not isinstance(temporal, Temporal):
        if temporal not in TEMPORAL_MODES:
            choices = ", ".join(TEMPORAL_MODES)
            raise InputError(f"temporal must be one of {choices}, got {temporal!r}")
        temporal = Temporal(temporal)
    if on_outcome is not None and not callable(on_outcome):
        raise InputError(f"on_outcome must be callable, got {type(on_outcome).__name__}")
    stitch_keywords, model_keywords, job_keywords, prior_keywords = split(
        keywords, StitchKeywords, ModelKeywords, JobKeywords, PriorKeywords, where="video.run"
    )
    if prior_keywords:
        raise InputError(
            f"video.run takes no prior of its own ({', '.join(sorted(prior_keywords))}): the "
            'temporal term uses the previous frame (temporal=Temporal("smooth", prior=True))'
        )
    model_opts = ModelOptions.build(model_options, **model_keywords)
    job_options = resolve_job(job_keywords)
    opts = build(options, job_options["subdivisions"], **stitch_keywords)
    chosen = check_formats(formats)
    workers = integer(workers, "workers", low=1, high=MAX_THREADS)
    resources = ray_resources(
        engine, workers, gpus_per_model, cpus_per_stitch, model_opts.providers
    )
    if resources is None and workers != 1:
        raise InputError(
            "the local video engine runs frames in order in one process: workers apply to "
            "engine='ray' only"
        )
    chunking = _chunking(chunk, overlap, ray=resources is not None)
    frame_batch = integer(frame_batch, "frame_batch", low=1, high=MAX_FRAME_BATCH)
    if chunking is not None and frame_batch != 1:
        raise InputError(
            "frame_batch applies to the local engine's one sequence, not to chunked runs "
            "(engine='ray' or chunk=)"
        )
    # The selection is checked (and the source opened) before anything is made.
    every, start, end = check_selection(every, start, end, fps)
    source = probe(src, fps=fps)
    if source.width is not None and source.height is not None and source.width != 2 * source.height:
        raise InputError(
            f"{source.path} is {source.width}x{source.height}: an equirectangular 360° video has "
            "W == 2H (convert dual-fisheye or cube-map footage to equirectangular first)"
        )
    if preview_video:
        from .reader import _av

        _av()  # the preview video is encoded with PyAV: say so before any frame
    estimator = load_estimator(model, model_options=model_opts)
    if estimator_kind(estimator) == "panoramic":
        refuse_layout_options(job_options)
    fp = fingerprint(
        estimator, opts, chosen, preview=bool(preview), fix_aspect=False, confidence=confidence
    )
    fp.update(job_fingerprint(job_options))
    # With the temporal term a frame depends on the frames before it: the selection counts.
    fp["video"] = {"temporal": temporal.describe(), "every": every, "start": start, "end": end}
    plan = _Plan(
        out=out,
        source=source,
        estimator=estimator,
        options=opts,
        job=job_options,
        formats=chosen,
        preview=bool(preview),
        confidence=bool(confidence),
        fingerprint=fp,
        run_id=uuid.uuid4().hex[:12],
        resume=bool(resume),
        temporal=temporal,
        tangent_model=estimator_kind(estimator) != "panoramic",
        model=model,
        model_options=model_opts,
    )
    make_output_folder(out)
    report = VideoReport(
        outcomes=[], seconds=0.0, interrupted=False, failures_file=out / FAILURES_FILE
    )
    report.source = source
    with contextlib.ExitStack() as stack:
        if not stack.enter_context(claim(out / "video")):
            report.outcomes.append(ImageOutcome(str(src), str(out), "busy"))
            report.seconds = time.perf_counter() - started
            return report
        selection = (every, start, end, fps)
        if chunking is None:
            _run_frames(plan, src, selection, report, progress, on_outcome, frame_batch)
        else:
            _run_chunks(plan, src, selection, report, progress, on_outcome, chunking, resources)
        if preview_video and not report.interrupted:
            stems = [out / o.stem for o in report.outcomes if o.status in ("done", "skipped")]
            rate = (source.fps or 30.0) / every
            try:
                report.preview_video, report.colour_scale = _write_preview_video(
                    stems, out / "preview.mp4", rate
                )
            except M360Error as exc:
                report.notes.append(f"the preview video could not be written: {exc}")
        ran: dict[str, Any] = {"engine": "local" if resources is None else "ray"}
        if chunking is not None:
            ran.update(chunk=chunking[0], overlap=chunking[1])
        else:
            ran["frame_batch"] = frame_batch  # asked for (a cap or a fallback is in the notes)
        _write_run_file(plan, report, (every, start, end, fps), ran)
    report.seconds = time.perf_counter() - started
    return report


@dataclass
class _Turn:
    """A frame read, waiting for its turn: its job, whether it is done, its estimate ahead."""

    frame: Frame
    job: Job
    done: bool
    ahead: Future[Ahead] | None = None


def _run_frames(
    plan: _Plan,
    src: str | os.PathLike[str],
    selection: tuple[Any, ...],
    report: VideoReport,
    progress: bool,
    on_outcome: Callable[[ImageOutcome], None] | None,
    frame_batch: int = 1,
) -> None:
    """Process the frames in order, recording each outcome in ``report``.

    Three threads beside this one: the decoder reads ahead (:func:`m360.video.prefetch`), the
    estimates run ahead (:class:`m360.video._ahead.Estimates`, two frames at once), and a
    writer writes each frame while the next is estimated. This thread takes the frames in
    order: the temporal term, then the frame's files to the writer. With ``frame_batch`` K > 1
    (tangent models), K frames are prepared and predicted in one network call before their
    estimates are finished (:mod:`m360.video._ahead`).
    """
    every, start, end, fps = selection
    total = _expected_frames(plan.source, every, start, end)
    bar = _progress_bar(total, progress)
    state: TemporalState | None = None
    missing = "first frame"  # why there is no state (recorded in the next frame's sidecar)
    done_before: Path | None = None  # the last frame skipped as done: its state, if needed
    tried = False
    job: Job | None = None
    estimates = Estimates(plan, report.notes)
    batcher = None
    if frame_batch > 1 and plan.tangent_model:
        batcher = FrameBatcher(plan, frame_batch, report.notes)
    elif frame_batch > 1:
        report.notes.append(
            "frame_batch applies to tangent models: a panoramic model runs per frame"
        )

    def record(outcome: ImageOutcome) -> None:
        _record(plan, report, bar, on_outcome, outcome)

    # A frame's full-size temporal step and its files are done on this thread while the next
    # frame is estimated (its state, all the next frame needs, is ready before). At most one
    # frame is in flight, and outcomes are recorded in frame order.
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="m360-video-write")
    pending: list[tuple[Job, Future[dict[str, float]]]] = []

    def settle() -> bool:
        """Wait for the frame in flight and record its outcome; True when it failed."""
        if not pending:
            return False
        written, future = pending.pop()
        try:
            timings = future.result()
        except Exception as exc:  # its files could not be written: it fails alone
            record(error_outcome(written, exc))
            return True
        record(ImageOutcome(str(written.input), written.name, "done", timings=timings))
        return False

    def one(turn: _Turn) -> str:
        """Run one frame in its turn: done, failed, skipped, or stop (the model failed first)."""
        nonlocal state, missing, done_before, tried, job
        frame, job = turn.frame, turn.job
        if frame.error is not None or frame.rgb is None:
            settle()
            error = frame.error or ReadError(f"frame {frame.index} could not be read")
            record(failure_outcome(job.input, job.name, error))
            state, done_before, missing = None, None, "previous frame failed"
            return "failed"
        if turn.done:
            settle()
            record(ImageOutcome(str(job.input), job.name, "skipped"))
            state, done_before = None, job.stem
            return "skipped"
        if state is None and done_before is not None and plan.temporal.mode != "none":
            try:
                state = TemporalState.load(_state_path(done_before))
            except ReadError:
                missing = "previous frame's state unreadable"
        done_before = None
        try:
            ahead = None if turn.ahead is None else turn.ahead.result()
            computed = _compute(plan, frame, job, state, missing, ahead, defer=True)
            if settle() and state is not None:
                # The previous frame failed to write after all: as a run that wrote it in
                # line, this one starts afresh (with a prior from it, its own network call
                # again: rare, same bytes).
                missing = "previous frame failed"
                again = ahead if ahead is not None and ahead.result is not None else None
                computed = _compute(plan, frame, job, None, missing, again, defer=True)
        except ModelError as exc:
            settle()
            if not tried and not report.done:
                report.model_error = str(exc)
                return "stop"
            record(error_outcome(job, exc))
            state, missing = None, "previous frame failed"
            return "failed"
        except Exception as exc:  # a frame fails alone
            settle()
            record(error_outcome(job, exc))
            state, missing = None, "previous frame failed"
            return "failed"
        finally:
            tried = True
        state = computed.state
        pending.append((job, writer.submit(_write, plan, job, computed)))
        return "done"

    turns: deque[_Turn] = deque()  # frames read, in order, waiting for their turn

    def take(keep: int) -> bool:
        """Run the frames whose turn it is until ``keep`` wait; False when the run must stop."""
        while len(turns) > keep:
            if one(turns.popleft()) == "stop":
                return False
        return True

    def run_group(frames_read: list[Frame]) -> bool:
        """Start the estimates of frames read (one network call for a group), take turns."""
        read = [_Turn(frame, _job(plan, frame), False) for frame in frames_read]
        # The frames to compute: readable and not done (the others take their turn as such).
        todo = []
        for turn in read:
            if turn.frame.error is None and turn.frame.rgb is not None:
                turn.done = plan.resume and _done(plan, turn.job)
                if not turn.done:
                    todo.append(turn)
        group = None
        if batcher is not None and len(todo) > 1:
            group = estimates.submit_group(batcher, [(t.frame, t.job) for t in todo])
        for turn in todo:
            turn.ahead = estimates.submit(turn.frame, group)
        turns.extend(read)
        frames_read.clear()
        # The frames still waiting keep the estimate workers busy while this thread works.
        return take(estimates.depth - 1)

    read_error: M360Error | None = None
    try:
        with MainThreadInterrupts(keyboard_interrupt_once()):
            reader = frames(src, every, start, end, fps=fps, on_error="yield")
            group: list[Frame] = []  # the frames read, held while the group is read
            with contextlib.closing(prefetch(reader, READ_AHEAD)) as stream:
                while True:
                    try:
                        frame = next(stream)
                    except StopIteration:
                        break
                    except M360Error as exc:  # a damaged container: the frames after it are lost
                        read_error = exc
                        break
                    group.append(frame)
                    estimates.cap(frame)
                    if batcher is not None:
                        batcher.cap(frame, estimates.depth)
                    if len(group) >= (1 if batcher is None else batcher.size):
                        if not run_group(group):
                            return
            if group and not run_group(group):
                return
            if not take(0):
                return
            settle()
            if read_error is not None:
                name = "video" if job is None else f"after {job.name}"
                record(failure_outcome(plan.source.path, name, read_error))
    except KeyboardInterrupt:
        report.interrupted = True
    except M360Error as exc:  # the reader cannot go on: the rest is lost
        take(0)
        settle()
        name = "video" if job is None else f"after {job.name}"
        record(failure_outcome(plan.source.path, name, exc))
    finally:
        try:
            settle()  # the frame in flight is finished and recorded, also when interrupted
        finally:
            estimates.close()
            writer.shutdown(wait=True)
            bar.close()


def _record(
    plan: _Plan,
    report: VideoReport,
    bar: Any,
    on_outcome: Callable[[ImageOutcome], None] | None,
    outcome: ImageOutcome,
) -> None:
    """Record a frame's outcome: the report, the progress bar, ``failures.jsonl``, the callback."""
    report.outcomes.append(outcome)
    bar.update(1)
    if outcome.status == "failed":
        try:
            append_failure(report.failures_file, outcome, plan.run_id)
        except OSError as exc:
            report.notes.append(f"failures.jsonl could not be written ({exc})")
    if on_outcome is not None:
        on_outcome(outcome)


def _chunking(chunk: Any, overlap: Any, *, ray: bool) -> tuple[int, int] | None:
    """(chunk, overlap) of a chunked run, or None for the local engine's one sequence."""
    from .chunks import DEFAULT_CHUNK, DEFAULT_OVERLAP

    if chunk is None and not ray:
        if overlap is not None:
            raise InputError("overlap applies to chunked runs only (engine='ray' or chunk=)")
        return None
    size = DEFAULT_CHUNK if chunk is None else integer(chunk, "chunk", low=1)
    warm = min(DEFAULT_OVERLAP, size) if overlap is None else integer(overlap, "overlap", low=0)
    if warm > size:
        raise InputError(f"overlap must be at most chunk ({size}), got {warm}")
    return size, warm


def _run_chunks(
    plan: _Plan,
    src: str | os.PathLike[str],
    selection: tuple[Any, ...],
    report: VideoReport,
    progress: bool,
    on_outcome: Callable[[ImageOutcome], None] | None,
    chunking: tuple[int, int],
    resources: Any,
) -> None:
    """Run the frames in chunks (:mod:`m360.video.chunks`), in this process or on Ray."""
    from .chunks import chunks_of, run_local, run_ray

    every, start, end, fps = selection
    bar = _progress_bar(_expected_frames(plan.source, every, start, end), progress)
    last: list[str] = []
    tried: list[bool] = []  # whether a frame reached the model yet

    def record(outcome: ImageOutcome) -> None:
        if outcome.status in ("done", "failed") and outcome.error != "ReadError" and not tried:
            tried.append(True)
            if outcome.error == "ModelError" and not report.done:
                # As the local engine: the model failing on the first frame stops the run.
                raise ModelError(outcome.message or "the model failed")
        last[:] = [outcome.stem]
        _record(plan, report, bar, on_outcome, outcome)

    read_error: list[M360Error] = []

    def selected() -> Iterator[Frame]:
        try:
            yield from frames(src, every, start, end, fps=fps, on_error="yield")
        except M360Error as exc:  # a damaged container: the frames after it are lost
            read_error.append(exc)

    size, overlap = chunking
    if plan.temporal.mode == "none":
        overlap = 0  # frames on their own: nothing to warm up or fit
    chunks = chunks_of(prefetch(selected(), READ_AHEAD), size, overlap)
    try:
        with MainThreadInterrupts(keyboard_interrupt_once()):
            if resources is None:
                run_local(plan, chunks, overlap, record)
            else:
                run_ray(plan, chunks, overlap, record, resources)
            if read_error:
                name = f"after {last[0]}" if last else "video"
                record(failure_outcome(plan.source.path, name, read_error[0]))
    except KeyboardInterrupt:
        report.interrupted = True
    except ModelError as exc:
        if report.done:
            raise
        report.model_error = str(exc)
    finally:
        bar.close()


def _expected_frames(source: Source, every: int, start: Any, end: Any) -> int | None:
    """How many frames the selection takes, for the progress bar (None if unknown)."""
    if not source.frames or isinstance(start, float) or isinstance(end, float):
        return None
    first = start or 0
    last = source.frames if end is None else min(end, source.frames)
    return max(0, -(-(last - first) // every))


def _progress_bar(total: int | None, show: bool) -> Any:
    if not show:
        return NoBar()
    from tqdm import tqdm

    # tqdm shows frames per second and, with a total, the time left.
    return tqdm(total=total, unit="frame", desc="m360 video", dynamic_ncols=True, smoothing=0.1)


def _fixed_colours(disparity: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Colour a disparity map with a fixed range: (H, W, 3) uint8 RGB, NaN black."""
    finite = np.isfinite(disparity)
    scaled = np.clip((np.nan_to_num(disparity) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    grey = (scaled * 255.0 + 0.5).astype(np.uint8)
    colours = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
    colours[~finite] = 0
    return cv2.cvtColor(colours, cv2.COLOR_BGR2RGB)  # type: ignore[no-any-return]


#: Width of the preview video at most (encoders and players take it).
PREVIEW_WIDTH = 2048


def _write_preview_video(
    stems: Sequence[Path], path: Path, rate: float
) -> tuple[Path | None, tuple[float, float] | None]:
    """Encode the frames' disparity in colour with one scale for all; (path, scale).

    Two passes over the written frames: the 2nd and 98th percentiles of a sample of every
    frame's disparity fix the scale (a scale per frame would itself flicker), then each frame
    is coloured and encoded (H.264, else MPEG-4 Part 2), atomically.
    """
    from fractions import Fraction

    from ..io import load
    from .reader import _av

    if not stems:
        return None, None
    samples = []
    for stem in stems:
        disparity = load(stem).disparity
        step = max(1, int(np.sqrt(disparity.size / 20_000)))
        sample = disparity[::step, ::step]
        samples.append(sample[np.isfinite(sample)])
    values = np.concatenate(samples)
    if not values.size:
        return None, None
    lo, hi = (float(v) for v in np.percentile(values, (2.0, 98.0)))
    av = _av()
    codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
    with atomic_path(path) as tmp:
        container = av.open(str(tmp), "w", format="mp4")
        try:
            stream = container.add_stream(codec, rate=Fraction(rate).limit_denominator(1001))
            first = load(stems[0]).disparity
            width = min(PREVIEW_WIDTH, first.shape[1]) // 2 * 2
            height = max(2, round(width * first.shape[0] / first.shape[1]) // 2 * 2)
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            for stem in stems:
                disparity = load(stem).disparity
                colours = _fixed_colours(disparity, lo, hi)
                colours = cv2.resize(colours, (width, height), interpolation=cv2.INTER_AREA)
                frame = av.VideoFrame.from_ndarray(colours, format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
        finally:
            container.close()
    return path, (lo, hi)


def _write_run_file(
    plan: _Plan, report: VideoReport, selection: tuple[Any, ...], engine: dict[str, Any]
) -> None:
    """Write ``OUT/video.json``: the source, the selection, the run's counts and scale."""
    every, start, end, fps = selection
    record = {
        "source": {
            "path": str(plan.source.path),
            "kind": plan.source.kind,
            "frames": plan.source.frames,
            "frames_exact": plan.source.exact,
            "fps": plan.source.fps,
            "codec": plan.source.codec,
        },
        "selection": {"every": every, "start": start, "end": end, "fps": fps},
        "temporal": plan.temporal.mode,
        "engine": engine,  # how this run ran (chunk and overlap when chunked)
        "frames": sorted(o.stem for o in report.outcomes if o.status in ("done", "skipped")),
        "failed": sorted(o.stem for o in report.failed),
        "preview_video": None
        if report.preview_video is None
        else {"file": report.preview_video.name, "disparity_range": report.colour_scale},
        "run": plan.run_id,
    }
    try:
        save_json(plan.out / RUN_FILE, json.loads(json.dumps(record)))
    except OSError as exc:
        report.notes.append(f"{RUN_FILE} could not be written ({exc})")
