"""Frames of a 360° video file or of a folder of images: :func:`frames`, :func:`probe`.

Video files are decoded with PyAV (FFmpeg's libraries; extra ``m360[video]``), not OpenCV's
``VideoCapture``: measured on clips encoded in the tests, both agree on constant-frame-rate
MP4 and WebM, but on a variable-frame-rate MKV OpenCV reported 53 frames for 50 (its count is
the duration times the nominal rate) and ``CAP_PROP_POS_FRAMES`` landed one or two frames early
for 4 of 8 targets, while PyAV's decoded frames were exact, each with its own presentation
time. A frame's index here is its position in decoding (presentation) order, counted from the
first frame, so it is exact for any stream; frames before ``start`` are decoded but not
converted to RGB.

A folder of images is a video whose frames are its image files (``IMAGE_SUFFIXES``) in
natural name order (``frame2`` before ``frame10``); a frame's time is ``index / fps`` when
``fps`` is given, else None.
"""

from __future__ import annotations

import bisect
import os
import queue
import re
import stat
import threading
from collections.abc import Callable, Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from .._validate import integer
from ..errors import InputError, M360Error, ReadError
from ..io.decode import IMAGE_SUFFIXES, decode_image, read_input_bytes

__all__ = ["VIDEO_SUFFIXES", "Frame", "Source", "check_selection", "frames", "prefetch", "probe"]

#: File suffixes taken as video (anything FFmpeg reads is tried when named directly).
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".webm", ".avi", ".insv", ".ts", ".mts")

_T = TypeVar("_T")


def _av() -> Any:
    """Import PyAV, or tell how to get it."""
    try:
        import av
    except ImportError as exc:
        raise InputError(
            f"reading video files needs PyAV, which cannot be imported ({exc}): "
            'pip install "m360[video]" (a folder of frames needs nothing more)'
        ) from exc
    return av


@dataclass(frozen=True)
class Frame:
    """One frame of a video.

    Attributes
    ----------
    index : int
        Position in the video, from 0 (decoding order; a folder's sorted files).
    time : float or None
        Presentation time in seconds (None for a folder without ``fps``).
    rgb : (H, W, 3) uint8 or None
        The frame; None when it could not be read (``error`` says why).
    path : Path or None
        The image file of a folder's frame.
    error : M360Error or None
        Why the frame could not be read (only with ``on_error="yield"``).
    """

    index: int
    time: float | None
    rgb: np.ndarray | None
    path: Path | None = None
    error: M360Error | None = None


@dataclass(frozen=True)
class Source:
    """What :func:`probe` found: a video file or a folder of frames.

    ``frames`` is exact for a folder and for a video whose container records it; otherwise
    the duration times the rate, an estimate (``exact`` False), used only for progress.
    """

    path: Path
    kind: str  # "video" or "folder"
    frames: int
    exact: bool
    fps: float | None
    width: int | None
    height: int | None
    codec: str | None = None


def _natural_key(path: Path) -> list[Any]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def _folder_files(folder: Path) -> list[Path]:
    files = [
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
    ]
    return sorted(files, key=_natural_key)


def _kind(path: Path) -> str:
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError) as exc:
        raise ReadError(f"video {path} does not exist or cannot be read") from exc
    if stat.S_ISDIR(mode):
        return "folder"
    if stat.S_ISREG(mode):
        return "video"
    raise ReadError(f"video {path} is neither a file nor a folder")


def _open(path: Path) -> Any:
    av = _av()
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as exc:  # not a video, truncated header, unknown container
        raise ReadError(f"cannot open {path} as a video: {exc}") from exc
    if not container.streams.video:
        container.close()
        raise ReadError(f"{path} has no video stream")
    return container


def probe(path: str | os.PathLike[str], *, fps: float | None = None) -> Source:
    """Describe a video file or a folder of frames without decoding it.

    Parameters
    ----------
    path : path
        A video file or a folder of images.
    fps : float, optional
        Frame rate of a folder's frames (videos carry their own).

    Raises
    ------
    m360.ReadError
        If the path is missing, not a video, or a folder without images.
    """
    p = Path(path)
    if _kind(p) == "folder":
        files = _folder_files(p)
        if not files:
            raise ReadError(f"folder {p} holds no frames (looked for {', '.join(IMAGE_SUFFIXES)})")
        return Source(p, "folder", len(files), True, fps, None, None)
    container = _open(p)
    try:
        stream = container.streams.video[0]
        rate = float(stream.average_rate or stream.guessed_rate or 0) or None
        count, exact = int(stream.frames or 0), bool(stream.frames)
        if not count:
            seconds = (
                float(stream.duration * stream.time_base)
                if stream.duration is not None
                else (container.duration or 0) / 1e6
            )
            count = round(seconds * rate) if rate else 0
        return Source(
            p,
            "video",
            count,
            exact,
            rate,
            stream.codec_context.width,
            stream.codec_context.height,
            stream.codec_context.name,
        )
    finally:
        container.close()


def _bound(value: Any, name: str) -> int | float | None:
    """``start``/``end``: None, a frame index (int ≥ 0) or seconds (float ≥ 0)."""
    if value is None:
        return None
    if isinstance(value, float) and not isinstance(value, bool):
        if not (value >= 0 and value < float("inf")):
            raise InputError(f"{name} must be a frame index or seconds >= 0, got {value!r}")
        return value
    return integer(value, name)


def check_selection(
    every: Any, start: Any, end: Any, fps: Any = None
) -> tuple[int, int | float | None, int | float | None]:
    """Check a frame selection (see :func:`frames`); returns (every, start, end)."""
    every = integer(every, "every", low=1)
    lo, hi = _bound(start, "start"), _bound(end, "end")
    if fps is not None and (
        isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps < 1e6
    ):
        raise InputError(f"fps must be a number > 0, got {fps!r}")
    return every, lo, hi


def _selector(
    every: int, start: int | float | None, end: int | float | None
) -> Callable[[int, float | None], str]:
    """Tell of a frame (index, time): "take", "skip" or "stop"."""
    first: list[int] = []

    def select(index: int, time: float | None) -> str:
        if time is None and (isinstance(start, float) or isinstance(end, float)):
            raise InputError("start/end in seconds need frame times (give fps for a folder)")
        if isinstance(end, float) and time is not None and time >= end:
            return "stop"
        if isinstance(end, int) and index >= end:
            return "stop"
        if isinstance(start, float) and time is not None and time < start:
            return "skip"
        if isinstance(start, int) and index < start:
            return "skip"
        if not first:
            first.append(index)
        return "take" if (index - first[0]) % every == 0 else "skip"

    return select


def frames(
    path: str | os.PathLike[str],
    every: int = 1,
    start: int | float | None = None,
    end: int | float | None = None,
    *,
    fps: float | None = None,
    on_error: str = "raise",
) -> Iterator[Frame]:
    """Yield the frames of a video file or a folder of images, in order.

    Parameters
    ----------
    path : path
        A video file (anything FFmpeg reads: MP4, MOV, MKV, WebM …; ``pip install
        "m360[video]"``) or a folder of images (one frame per image, natural name order).
    every : int
        Take every N-th frame from the first one taken (default 1: all).
    start, end : int or float, optional
        First frame taken and first frame no longer taken (end exclusive): an int is a frame
        index, a float seconds of presentation time.
    fps : float, optional
        Frame rate of a folder's frames (gives them times).
    on_error : {"raise", "yield"}
        A frame that cannot be read (a corrupt image in a folder): raise its ReadError, or
        yield it with ``rgb=None`` and ``error`` set, and go on.

    Yields
    ------
    Frame
        ``index``, ``time`` (seconds), ``rgb`` (H, W, 3) uint8.

    Raises
    ------
    m360.InputError
        For bad arguments, or a video without PyAV installed.
    m360.ReadError
        If the path is missing or not a video, or (``on_error="raise"``) a frame is unreadable.
    """
    every, lo, hi = check_selection(every, start, end, fps)
    if on_error not in ("raise", "yield"):
        raise InputError(f"on_error must be 'raise' or 'yield', got {on_error!r}")
    select = _selector(every, lo, hi)
    p = Path(path)
    if _kind(p) == "folder":
        source = probe(p, fps=fps)
        yield from _folder_frames(p, source, select, on_error)
    else:
        yield from _video_frames(p, select, on_error)


def _folder_frames(
    folder: Path, source: Source, select: Callable[[int, float | None], str], on_error: str
) -> Iterator[Frame]:
    for index, file in enumerate(_folder_files(folder)):
        time = None if source.fps is None else index / source.fps
        verdict = select(index, time)
        if verdict == "stop":
            return
        if verdict == "skip":
            continue
        try:
            rgb = decode_image(read_input_bytes(file), file)
        except ReadError as exc:
            if on_error == "raise":
                raise
            yield Frame(index, time, None, file, exc)
            continue
        yield Frame(index, time, rgb, file)


def _video_frames(
    path: Path, select: Callable[[int, float | None], str], on_error: str
) -> Iterator[Frame]:
    """Decode ``path``; a frame's index is the rank of its timestamp among the packets'.

    A video packet holds one frame, so ranking the frames' presentation timestamps among the
    packets demuxed so far numbers them as the encoder did, even where the decoder drops a
    frame it cannot decode (FFmpeg conceals or drops damaged frames without an error: a count
    of decoded frames would then shift every later index). The decoder outputs a frame only
    after every packet that comes before it in presentation order, so the rank is final when
    the frame arrives; a rank skipped is a frame lost, reported as such. Streams without
    timestamps are counted instead.
    """
    av = _av()
    container = _open(path)
    try:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"  # FFmpeg's own frame threads (they release the GIL)
        rate = float(stream.average_rate or 0) or None
        base = stream.time_base
        timestamps: list[int] = []  # every packet's pts so far, sorted
        counted = 0  # the next index where timestamps are missing
        next_index = 0  # the index the next frame should have: below it, every frame was seen

        def lost(upto: int, reason: str) -> Iterator[Frame]:
            nonlocal next_index
            while next_index < upto:
                index = next_index
                next_index += 1
                time = float(timestamps[index] * base) if base is not None else None
                if select(index, time) != "take":
                    continue
                error = ReadError(f"frame {index} of {path} cannot be decoded ({reason})")
                if on_error == "raise":
                    raise error
                yield Frame(index, time, None, None, error)

        for packet in _packets(container, stream, path):
            problem = None
            if packet.pts is not None and packet.size:
                bisect.insort(timestamps, packet.pts)
            try:
                decoded = packet.decode()
            except av.error.FFmpegError as exc:  # a damaged packet: its frame is lost
                decoded, problem = [], str(exc)
            for frame in decoded:
                if frame.pts is not None and timestamps:
                    index = bisect.bisect_left(timestamps, frame.pts)
                else:
                    index, counted = counted, counted + 1
                yield from lost(index, problem or "dropped by the decoder")
                time = float(frame.time) if frame.time is not None else None
                if time is None and rate:
                    time = index / rate
                next_index = max(next_index, index + 1)
                verdict = select(index, time)
                if verdict == "stop":
                    return
                if verdict == "take":
                    yield Frame(index, time, frame.to_ndarray(format="rgb24"))
        yield from lost(len(timestamps), "dropped by the decoder")
    finally:
        container.close()


def _packets(container: Any, stream: Any, path: Path) -> Iterator[Any]:
    """Yield the stream's packets; a damaged container is a ReadError where it stops."""
    av = _av()
    packets = container.demux(stream)
    while True:
        try:
            packet = next(packets)
        except StopIteration:
            return
        except av.error.FFmpegError as exc:
            raise ReadError(f"cannot read {path} further: {exc}") from exc
        yield packet


_DONE = object()


def prefetch(items: Iterable[_T], size: int = 4) -> Generator[_T, None, None]:
    """Iterate ``items`` on a background thread, at most ``size`` ahead of the consumer.

    Decoding runs ahead of the network this way (PyAV and OpenCV release the GIL while they
    decode). An exception of the producer is raised in the consumer at its place in the
    sequence; closing the iterator early stops the producer.
    """
    size = integer(size, "size", low=1)
    buffer: queue.Queue[Any] = queue.Queue(maxsize=size)
    stop = threading.Event()

    def put(item: Any) -> bool:
        while not stop.is_set():
            try:
                buffer.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put((item, None)):
                    return
        except BaseException as exc:  # handed to the consumer, raised there
            put((None, exc))
            return
        put((_DONE, None))

    thread = threading.Thread(target=produce, name="m360-decode", daemon=True)
    thread.start()
    try:
        while True:
            item, error = buffer.get()
            if error is not None:
                raise error
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)
