"""One image of a batch: claim it, read it, estimate it, write it; shared by both engines.

The local engine (:mod:`m360.batch.run`) runs these pieces in one process per image; the Ray
engine (:mod:`m360.batch._ray_engine`) runs them in separate stages, so the bytes written are the
same either way. Also the resume check (:func:`is_done`) and the per-image OS lock (:func:`claim`).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import stat
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, M360Error, ReadError
from ..estimators.options import ModelOptions
from ..io import (
    FORMAT_SUFFIXES,
    GEOMETRY_FILES,
    GEOMETRY_FORMATS,
    NORMALS_FILES,
    QUANTITIES,
    SAVE_FORMATS,
    STEREO_FILES,
    STEREO_FORMATS,
    listed_files,
    read_sidecar,
    remove_stale_temporaries,
    save,
)
from ..io.decode import (
    check_aspect_before_decoding,
    decode_image,
    fix_aspect_ratio,
    read_input_bytes,
)
from ..io.files import NAME_MAX, temporary_prefix
from ..io.gpano import place as place_crop
from ..io.gpano import read_gpano
from ..io.mesh import DEFAULT_MAX_VERTICES
from ..stitching.options import StitchOptions
from ._interrupt import deferred


@dataclass(frozen=True)
class Job:
    """One image of a batch: where it comes from and the output stem inside OUT."""

    input: Path
    stem: Path
    name: str  # the stem relative to OUT
    source: str = ""  # where the job came from (folder, manifest line) for messages


@dataclass
class ImageOutcome:
    """What happened to one image.

    ``status`` is ``done``, ``skipped`` (already done), ``busy`` (claimed by another run),
    ``failed`` (with ``error`` type name and ``message``), ``interrupted`` (Ctrl-C; nothing
    written) or ``excluded`` (a file a folder scan left out; ``message`` says why).
    """

    input: str
    stem: str
    status: str
    error: str | None = None
    message: str | None = None
    timings: dict[str, float] = field(default_factory=dict)


def failure_outcome(source: Path, stem: str, exc: BaseException) -> ImageOutcome:
    """Make the failed outcome of output ``stem`` of ``source``: the error's class and text."""
    return ImageOutcome(str(source), stem, "failed", type(exc).__name__, str(exc))


# --------------------------------------------------------------------------------------------
# One image.


@dataclass(frozen=True)
class _Settings:
    """Everything a worker needs to process images (picklable)."""

    model: Any
    model_options: ModelOptions
    options: StitchOptions
    job: dict[str, Any]  # m360.pipeline.options.JobKeywords, every entry (defaults filled in)
    formats: tuple[str, ...]
    preview: bool
    fix_aspect: bool
    resume: bool
    fingerprint: dict[str, Any]
    run_id: str
    scale: Any = None
    masks: tuple[Any, ...] = ()  # Caps and (H, W) bool arrays (m360.masks), for every image
    confidence: bool = False
    max_vertices: int | None = DEFAULT_MAX_VERTICES  # the 3D files' vertex budget
    # The global prior as given (m360.pipeline.options.PriorKeywords): a path or name, a
    # panoramic estimator or an ERP map; loaded once per worker (load_prior).
    prior: Any = None
    prior_kind: str | None = None
    prior_confidence: Any = None
    prior_options: Any = None  # how a prior model given by path or name is fed
    prior_pixels: int = 0  # the prior map's pixels, for the memory check
    panoramic: bool = False  # the model is panoramic (one pass on the whole ERP)
    stereo: dict[str, Any] = field(default_factory=dict)  # m360.io.stereo.StereoKeywords given

    @property
    def threads(self) -> int | None:
        """ONNX Runtime's threads per worker, and the core's with several workers."""
        threads: int | None = self.model_options.threads
        return threads

    def load_prior(self, threads: int | None = None) -> Any:
        """Load the run's prior (a model once per process); None without one.

        ``threads`` replaces the model options' threads (a Ray actor's own).
        """
        from ..pipeline.prior import load_prior

        return load_prior(
            self.prior,
            self.prior_kind,
            self.prior_confidence,
            prior_options=self.prior_options,
            providers=self.model_options.providers,
            threads=self.threads if threads is None else threads,
        )


class _Worker:
    """Per-process state: the estimator is loaded once; the plan cache lives in the process."""

    def __init__(
        self, settings: _Settings, estimator: Any | None = None, prior: Any | None = None
    ) -> None:
        from ..estimators import load_estimator

        self.settings = settings
        self.estimator = estimator or load_estimator(
            settings.model, model_options=settings.model_options
        )
        self.prior = prior if prior is not None else settings.load_prior()

    def process(self, job: Job) -> ImageOutcome:
        """Claim, read, estimate and write one image; its outcome (never raises but Ctrl-C).

        The output folders this image made are removed again if it fails (when empty).
        """
        created = _missing_folders(job)
        outcome = None
        try:
            outcome = self._process(job)
        finally:
            if outcome is None or outcome.status == "failed":
                _remove_empty_folders(created)
        return outcome

    def _process(self, job: Job) -> ImageOutcome:
        from ..pipeline.estimate import estimate
        from ..pipeline.prior import as_keywords

        s = self.settings
        unusable = _make_job_folder(job)
        if unusable is not None:
            return unusable
        with contextlib.ExitStack() as held:
            try:
                claimed = held.enter_context(claim(job.stem))
            except OSError as exc:  # the lock file cannot be made: a full or read-only disk
                return error_outcome(job, exc)
            if not claimed:
                return ImageOutcome(str(job.input), job.name, "busy")
            if s.resume and is_done(job, s.fingerprint):
                return ImageOutcome(str(job.input), job.name, "skipped")
            remove_stale_temporaries(job.stem)
            try:
                t0 = time.perf_counter()
                read = _read_job(job, s)
                t_read = time.perf_counter()
                result = estimate(
                    read.rgb,
                    self.estimator,
                    options=s.options,
                    scale=s.scale,
                    mask=_image_mask(read, s),
                    **s.job,
                    **as_keywords(self.prior),
                )
                t_estimate = time.perf_counter()
                _write_job(job, result, read.records, s, read.rgb)
                t_write = time.perf_counter()
            except Exception as exc:
                return error_outcome(job, exc)
        timings = {"read": t_read - t0, **result.timings, "write": t_write - t_estimate}
        timings.pop("total", None)
        return ImageOutcome(str(job.input), job.name, "done", timings=timings)


# The pieces of one image, shared by the local engine (_Worker.process) and the Ray engine
# (m360.batch._ray_engine), which runs them in different processes: the same bytes either way.


def _missing_folders(job: Job) -> list[Path]:
    """List the folders of ``job``'s output inside OUT that do not exist yet, deepest first."""
    depth = len(Path(job.name).parts) - 1
    try:
        return [job.stem.parents[k] for k in range(depth) if not job.stem.parents[k].is_dir()]
    except (OSError, ValueError):  # a name the OS refuses: nothing can be made there
        return []


def _remove_empty_folders(folders: Sequence[Path]) -> None:
    """Remove ``folders`` (deepest first) while they are empty."""
    for folder in folders:
        try:
            os.rmdir(folder)
        except OSError:  # not empty (another image's files or lock), or already gone
            break


def _make_job_folder(job: Job) -> ImageOutcome | None:
    """Create the folder of ``job``'s outputs; a failed outcome if that is impossible.

    An input that is not a file fails first, before any folder is made: a manifest listing
    missing files leaves no empty folders behind.
    """
    problem = "does not exist (or is not a file)"
    try:
        is_file = stat.S_ISREG(os.stat(job.input).st_mode)
    except (FileNotFoundError, NotADirectoryError):
        is_file = False
    except (OSError, ValueError) as exc:  # a name too long, a NUL, no permission
        is_file, problem = False, f"cannot be read: {getattr(exc, 'strerror', None) or exc}"
    if not is_file:
        return failure_outcome(job.input, job.name, ReadError(f"input image {job.input} {problem}"))
    try:
        job.stem.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # e.g. a manifest output "a/b" where OUT/a is a file
        message = f"cannot create the folder of output {job.name}: {exc.strerror or exc}"
        return failure_outcome(job.input, job.name, InputError(message))
    return None


@dataclass
class _Read:
    """An input image as the stages need it."""

    rgb: Any  # (H, W, 3) uint8 ERP: a partial panorama is placed in its full canvas
    captured: Any  # (H, W) bool, the captured part of a partial panorama; None: all of it
    records: dict[str, Any]  # the sidecar's "input" record, and "crop" for a partial panorama


def _read_job(job: Job, s: _Settings) -> _Read:
    """Read and decode ``job``'s image.

    A partial panorama with GPano crop metadata goes into its full canvas, the rest masked;
    without metadata W != 2H is refused (or resized, ``fix_aspect``) as before.
    """
    data = read_input_bytes(job.input)
    stat = job.input.stat()
    crop = read_gpano(data, str(job.input))
    # Refused by its header where it has one, before decoding: a wrong aspect, or an image
    # too large for the memory (the whole run's: decoding, estimate, every output).
    header = check_aspect_before_decoding(data, job.input, fix=s.fix_aspect or crop is not None)
    if header is not None:
        _check_run_memory(job, s, header, len(data), header.width, header.height, crop)
    rgb = decode_image(data, job.input)
    original = rgb.shape[:2]
    if header is None:  # no readable header: checked on the decoded size instead
        _check_run_memory(job, s, None, len(data), original[1], original[0], crop)
    captured = None
    if crop is not None:
        rgb, captured = place_crop(rgb, crop, str(job.input))
    else:
        rgb = fix_aspect_ratio(rgb, job.input, fix=s.fix_aspect)
    source = {
        "path": str(job.input),
        "sha256": hashlib.sha256(data).hexdigest(),
        "size": stat.st_size,
        "mtime_ns": stat.st_mtime_ns,
        "shape": list(original),
        "aspect_fixed": crop is None and tuple(original) != rgb.shape[:2],
        "exif_orientation": "ignored",
    }
    records = {"input": source} | ({} if crop is None else {"crop": crop.as_dict()})
    return _Read(rgb, captured, records)


def _check_run_memory(
    job: Job,
    s: _Settings,
    header: Any,
    file_bytes: int,
    width: int,
    height: int,
    crop: Any,
) -> None:
    """Refuse ``job`` if its whole run cannot fit in memory (:func:`m360.memory.check_memory`).

    ``width`` x ``height`` is the file's image; the panorama is its canvas (a partial
    panorama's full width) or its aspect-fixed size.
    """
    from ..pipeline.memory import check_memory, estimate_memory, working_width_for
    from ..pipeline.options import job_layout

    pano = int(getattr(crop, "full_width", 0) or 0) or width + width % 2
    work = working_width_for(s.job["working_width"], pano)
    try:
        layout = job_layout(work, s.job)
    except M360Error:  # a width no layout takes: the estimate says why, after decoding
        layout = None
    needed = estimate_memory(
        pano,
        work,
        s.options.method,
        layout,
        formats=s.formats,
        preview=s.preview,
        confidence=s.confidence,
        max_vertices=s.max_vertices,
        header=header,
        file_bytes=file_bytes,
        prior_pixels=s.prior_pixels,
    )
    check_memory(
        needed,
        f"{job.input} ({width}x{height}, working width {work}, formats {','.join(s.formats)})",
        hint="use a smaller working_width (e.g. --working-width 4096), a row blend "
        "(--blend frustum), fewer formats or a smaller --max-vertices",
    )


def _image_mask(read: _Read, s: _Settings) -> list[Any] | None:
    """Give the masks of one image for :func:`m360.estimate`: its captured part and the run's."""
    masks = [*([] if read.captured is None else [read.captured]), *s.masks]
    return masks or None


def _check_masks(mask: Any) -> tuple[Any, ...]:
    """Check ``run``'s ``mask``; returns a tuple of caps and (H, W) bool arrays.

    They are not combined: images may differ in size, and a cap fits any.
    """
    from ..pipeline.masks import Cap

    if mask is None:
        return ()
    items = list(mask) if isinstance(mask, (list, tuple)) else [mask]
    for item in items:
        if isinstance(item, Cap):
            continue
        if not isinstance(item, np.ndarray) or item.ndim != 2 or item.dtype != np.bool_:
            raise InputError(
                "mask must be m360.masks.nadir/zenith caps or (H, W) bool arrays (True = use), "
                f"got {type(item).__name__}"
                + (f" {item.dtype} of shape {item.shape}" if isinstance(item, np.ndarray) else "")
            )
    return tuple(items)


def _describe_masks(masks: Sequence[Any]) -> list[dict[str, Any]]:
    """Describe the masks as JSON for the resume fingerprint (arrays by sha256)."""
    return [
        {"array": hashlib.sha256(np.packbits(m).tobytes()).hexdigest(), "shape": list(m.shape)}
        if isinstance(m, np.ndarray)
        else {"cap": m.pole, "degrees": m.degrees}
        for m in masks
    ]


def _needs_rgb(s: _Settings) -> bool:
    """Whether writing needs the panorama's colours (the 3D and stereo formats)."""
    return any(fmt in GEOMETRY_FORMATS or fmt in STEREO_FORMATS for fmt in s.formats)


def _write_job(
    job: Job, result: Any, records: dict[str, Any], s: _Settings, rgb: Any | None
) -> None:
    """Write ``job``'s outputs atomically, the sidecar (with input and fingerprint) last.

    ``rgb`` colours the 3D formats; it may be None when :func:`_needs_rgb` is False.
    """
    save(
        result,
        job.stem,
        formats=s.formats,
        preview=s.preview,
        extra={**records, "batch": {"fingerprint": s.fingerprint, "run": s.run_id}},
        rgb=rgb,
        confidence=s.confidence,
        max_vertices=s.max_vertices,
        **s.stereo,
    )


#: Write errors that are the disk's, not m360's: what happened and what to do.
_DISK_ERRORS = {
    errno.ENOSPC: ("no space left on device", "free space and rerun"),
    errno.EROFS: ("read-only file system", "write to a writable OUT and rerun"),
}
if hasattr(errno, "EDQUOT"):  # not on Windows
    _DISK_ERRORS[errno.EDQUOT] = ("disk quota exceeded", "free space and rerun")


def error_outcome(job: Job, exc: Exception) -> ImageOutcome:
    """Make the failed outcome of ``job`` for an exception raised while processing it.

    A full disk (ENOSPC, EDQUOT) or a read-only one (EROFS) is named as such; the image's
    temporary and partial files are already gone (:func:`m360.io.files.atomic_path`,
    :func:`m360.save`).
    """
    outcome = failure_outcome(job.input, job.name, exc)
    if isinstance(exc, OSError) and exc.errno in _DISK_ERRORS:
        what, todo = _DISK_ERRORS[exc.errno]
        code = errno.errorcode.get(exc.errno, str(exc.errno))
        outcome.message = f"{what} ({code}) while writing {job.stem}.*: {todo}"
    elif not isinstance(exc, M360Error):  # a bug or a library error: still only this image fails
        outcome.message = f"{exc} (unexpected; please report it)"
    return outcome


# --------------------------------------------------------------------------------------------
# Names the file system can take.

#: PATH_MAX of most systems: the longest path (bytes, with the final NUL) the OS takes.
PATH_MAX = 4096


def name_limits(folder: Path) -> tuple[int, int]:
    """Give NAME_MAX and PATH_MAX (bytes) of the file system ``folder`` is (or will be) on.

    Asked of its nearest existing folder (``os.pathconf``); 255 and 4096 where the OS does not
    say (Windows).
    """
    probe = folder.absolute()
    with contextlib.suppress(OSError, ValueError):
        while not probe.is_dir() and probe != probe.parent:
            probe = probe.parent
    try:
        limits = os.pathconf(probe, "PC_NAME_MAX"), os.pathconf(probe, "PC_PATH_MAX")
    except (AttributeError, OSError, ValueError):
        return NAME_MAX, PATH_MAX
    name_max, path_max = limits
    return (name_max if name_max > 0 else NAME_MAX), (path_max if path_max > 0 else PATH_MAX)


def output_names(
    stem: str, formats: Sequence[str], *, preview: bool, confidence: bool
) -> list[str]:
    """Give the names of the files :func:`m360.save` writes for ``stem`` (a file name)."""
    quantities = (*QUANTITIES, *(["confidence"] if confidence else []))
    names = [
        f"{stem}.{quantity}{FORMAT_SUFFIXES[fmt]}"
        for fmt in formats
        if fmt in SAVE_FORMATS
        for quantity in quantities
    ]
    names += [f"{stem}.preview.png"] * bool(preview)
    names += [stem + GEOMETRY_FILES[fmt][1] for fmt in formats if fmt in GEOMETRY_FILES]
    names += [stem + tail for tail in NORMALS_FILES.values()] * ("normals" in formats)
    names += [stem + STEREO_FILES[fmt][1] for fmt in formats if fmt in STEREO_FILES]
    return [*names, f"{stem}.json"]


def _abbreviated(name: str) -> str:
    return name if len(name) <= 64 else f"{name[:32]}…{name[-24:]}"


def check_output_names(
    job: Job, formats: Sequence[str], *, preview: bool, confidence: bool, limits: tuple[int, int]
) -> InputError | None:
    """Tell why the OS cannot take ``job``'s output names; None if it can.

    Every folder of the output and every file :func:`m360.save` would write must be a name of
    at most NAME_MAX bytes, and every path m360 opens (the files, their temporaries, the lock)
    shorter than PATH_MAX, with ``limits`` = (NAME_MAX, PATH_MAX) from :func:`name_limits`.
    Checked before any work, so such an image fails alone with this message instead of an
    ``OSError`` half-way.
    """
    name_max, path_max = limits
    relative = Path(job.name)
    names = output_names(job.stem.name, formats, preview=preview, confidence=confidence)
    for name in [*relative.parts[:-1], *names]:
        size = len(os.fsencode(name))
        if size > name_max:
            return InputError(
                f"output name {_abbreviated(name)} is {size} bytes, over the file system's "
                f"limit of {name_max} bytes per name (NAME_MAX): give this image a shorter "
                "output name (a .csv manifest: input,output)"
            )
    temporaries = [temporary_prefix(n) + "XXXXXXXX.tmp" for n in names]
    longest = max([*names, *temporaries, _lock_path(job.stem).name], key=lambda n: len(n))
    size = len(os.fsencode(str(job.stem.parent / longest)))
    if size >= path_max:
        return InputError(
            f"output path {_abbreviated(str(job.stem.parent / longest))} is {size} bytes, over "
            f"the OS limit of {path_max - 1} bytes per path (PATH_MAX): use a shorter OUT or "
            "output name"
        )
    return None


def is_done(job: Job, fingerprint: Mapping[str, Any]) -> bool:
    """Tell whether ``job`` is already done with these options.

    True if its sidecar exists, its files exist, and it was made from the same input file (path,
    size, mtime) with the same ``fingerprint`` (see :func:`fingerprint`).
    """
    try:
        meta = read_sidecar(job.stem)
        stat = job.input.stat()
    except (M360Error, OSError):
        return False
    source = meta.get("input")
    batch = meta.get("batch")
    if not isinstance(source, dict) or not isinstance(batch, dict):
        return False
    if batch.get("fingerprint") != json.loads(json.dumps(fingerprint)):
        return False
    same_input = (source.get("path"), source.get("size"), source.get("mtime_ns")) == (
        str(job.input),
        stat.st_size,
        stat.st_mtime_ns,
    )
    try:
        names = [n for listed in listed_files(meta, job.stem).values() for n in listed.values()]
    except M360Error:
        return False
    for extra in ("preview", "normals", "stereo", *(kind for kind, _ in GEOMETRY_FILES.values())):
        entry = meta["files"].get(extra)  # a file name, or {format: file name} for 3D files
        for name in entry.values() if isinstance(entry, dict) else [entry]:
            if isinstance(name, str) and Path(name).name == name:
                names.append(name)
    return same_input and bool(names) and all((job.stem.parent / n).is_file() for n in names)


@contextlib.contextmanager
def claim(stem: Path) -> Iterator[bool]:
    """Hold an exclusive OS lock on ``.NAME.lock`` next to ``stem`` (hashed if long).

    Yields False if another process holds it. The OS releases the lock when its process dies,
    so a killed run blocks nothing. The lock file is removed while still held, after the work;
    a claimer that locked a file which was removed meanwhile retries on the new one, so two
    claimers never both hold it. Ctrl-C is held back while the claim is taken and released
    (:func:`m360.batch._interrupt.deferred`): arriving between creating the file and the ``try``
    that removes it, it used to leave the file behind.
    """
    stem.parent.mkdir(parents=True, exist_ok=True)
    path = _lock_path(stem)
    fd: int | None = None
    try:
        with deferred():  # a Ctrl-C held back here is raised inside the try
            for attempt in range(3):
                try:
                    fd = _lock_current(path)
                    break
                except FileNotFoundError:  # a failed image of another run removed the folder
                    if attempt == 2:
                        raise
                    stem.parent.mkdir(parents=True, exist_ok=True)
        yield fd is not None
    finally:
        if fd is not None:
            with deferred():
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(path)
                os.close(fd)


def _lock_path(stem: Path) -> Path:
    """Give the lock file of ``stem``: ``.NAME.lock``, or ``.SHA1[:16].lock`` when too long."""
    name = f".{stem.name}.lock"
    if len(os.fsencode(name)) > NAME_MAX:
        name = f".{hashlib.sha1(os.fsencode(stem.name)).hexdigest()[:16]}.lock"
    return stem.with_name(name)


def _lock_current(path: Path) -> int | None:
    """Open and lock the lock file now at ``path``; None if another claimer holds it."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        if not _try_lock(fd):
            os.close(fd)
            return None
        try:
            current = os.stat(path).st_ino
        except FileNotFoundError:
            current = -1
        if current == os.fstat(fd).st_ino:
            return fd
        os.close(fd)  # locked a file its holder had just removed: take the current one


def _try_lock(fd: int) -> bool:
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)  # type: ignore[attr-defined]
        except OSError:
            return False
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True
