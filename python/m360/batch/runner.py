"""Batch runs over many panoramas that lose nothing: the engine behind ``m360 run``.

>>> report = m360.batch.run(["photos/"], "out/", model="midas-v21-small", workers=2)
>>> report.exit_code          # 0: all done; 1: some failed; 3: some busy in another run

What it guarantees (docs/architecture.md, batch guarantees):

- **Complete or absent.** Every file is written under a temporary name and renamed; the sidecar
  ``STEM.json`` is written last, so its presence means the set is complete.
- **Resumable.** An image whose sidecar exists, lists files that exist, was made from the same
  input file (path, size, modification time) with the same options (model and its sha256,
  its input size and output kind, every stitching option, formats …: :func:`fingerprint`) is
  skipped; the rest is done. ``resume=False`` redoes everything.
- **One failure is one line.** An image that fails is appended to ``OUT/failures.jsonl`` (input,
  output, error type, message) and the run goes on; a worker process that dies (segfault, out of
  memory) costs only its image, which is retried once alone and then recorded as
  ``WorkerCrashed``.
- **Concurrent runs share a folder.** Each image is claimed with an OS lock (``flock``) on
  ``.STEM.lock`` in its folder before any work; a run finding an image claimed skips it (it is
  reported as ``busy``, exit code 3 unless it is done by the end of the run) and the lock dies
  with its process, so a killed run blocks nothing.
- **Names the OS takes.** Lock and temporary names are hashed when long; an image whose output
  names are too long for the file system (NAME_MAX, PATH_MAX) fails alone, before any work.
- **Ctrl-C stops cleanly**: the image in progress leaves no file behind; rerunning finishes the
  rest.
- **Nothing outside OUT is written**; inputs are opened read-only; manifest output names that
  escape OUT (absolute, ``..``, a symlink out) are an :class:`m360.InputError` for that line.
  A manifest that is not one (binary, not UTF-8, absurd lines, two lines writing one output) is
  refused whole before anything is made.
- **Folder scans take photos only**: m360's own outputs and depth maps lying in a scanned
  folder are left out, each reported with the reason (``excluded``).

With ``workers > 1`` images run in separate processes (``spawn``), each loading the model and
building the per-resolution plan once; as with any spawned process, a script that calls
:func:`run` must keep its top level under ``if __name__ == "__main__":``.

With ``engine="ray"`` (``pip install "m360[ray]"``) the same images run on a Ray cluster, with
the same guarantees (docs/architecture.md, "The Ray engine").
"""

from __future__ import annotations

import contextlib
import datetime
import json
import multiprocessing
import os
import pickle
import signal
import stat
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any

from .._keywords import checked, resolved, split
from .._validate import MAX_THREADS, flag, integer
from ..errors import InputError, ReadError
from ..estimators import OnnxEstimator, estimator_kind
from ..estimators import registry as _models
from ..estimators.options import ModelKeywords, ModelOptions
from ..geometry.layout import pixel_degrees
from ..io import (
    GEOMETRY_FORMATS,
    STEREO_FORMATS,
    check_formats,
)
from ..io.decode import IMAGE_SUFFIXES
from ..io.mesh import DEFAULT_MAX_VERTICES, check_max_vertices
from ..io.stereo import StereoKeywords
from ..pipeline.options import (
    EstimateKeywords,
    JobKeywords,
    PriorKeywords,
    job_fingerprint,
    job_layout,
    refuse_layout_options,
    resolve_job,
)
from ..pipeline.prior import describe as describe_prior
from ..pipeline.prior import load_prior
from ..stitching.options import StitchKeywords, StitchOptions, build
from ._inputs import read_manifest, scan
from ._interrupt import MainThreadInterrupts, install_for_process
from .image import (
    ImageOutcome,
    Job,
    _check_masks,
    _describe_masks,
    _Settings,
    _Worker,
    check_output_names,
    failure_outcome,
    is_done,
    name_limits,
)

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "BatchReport",
    "ImageOutcome",
    "Job",
    "NoBar",
    "RunKeywords",
    "append_failure",
    "collect",
    "fingerprint",
    "is_done",
    "keyboard_interrupt_once",
    "make_output_folder",
    "ray_resources",
    "run",
]


class RunKeywords(EstimateKeywords, StereoKeywords, total=False):
    """Every keyword of :func:`run` beyond its named ones.

    :func:`m360.estimate`'s (:class:`m360.pipeline.options.EstimateKeywords`) and the stereo
    outputs' (:class:`m360.io.stereo.StereoKeywords`: ``ipd``, ``pole_fade``,
    ``median_distance``).
    """


MANIFEST_SUFFIXES = (".txt", ".csv")
FAILURES_FILE = "failures.jsonl"
#: Where :func:`run` runs images: local processes (default) or a Ray cluster (``m360[ray]``).
ENGINES = ("local", "ray")
#: Stages reported per image: reading the file, m360.estimate's stages, writing the outputs.
STAGES = ("read", "load", "project", "network", "prior", "convert", "align", "blend", "write")
#: Exit code of a run that left images to another run still writing them (none failed).
EXIT_BUSY = 3


@dataclass
class BatchReport:
    """The result of :func:`run`.

    Attributes
    ----------
    outcomes : list of ImageOutcome
        One per input image (and per unusable manifest line, and per file a folder scan left
        out), the unusable and left-out ones first, then the images in input order.
    seconds : float
        Wall time of the run.
    interrupted : bool
        True if Ctrl-C stopped the run; rerunning finishes the rest.
    failures_file : Path
        ``OUT/failures.jsonl`` (appended only when something failed).
    model_error : str or None
        Why the run stopped early: the model failed (a ModelError) on the first image tried,
        before any image succeeded, so it would fail every image; the rest were not tried.
    notes : list of str
        What else the run has to say (e.g. ``failures.jsonl`` could not be written).
    """

    outcomes: list[ImageOutcome]
    seconds: float
    interrupted: bool
    failures_file: Path
    model_error: str | None = None
    notes: list[str] = field(default_factory=list)

    def _with(self, status: str) -> list[ImageOutcome]:
        return [o for o in self.outcomes if o.status == status]

    @property
    def done(self) -> list[ImageOutcome]:
        """Images processed in this run."""
        return self._with("done")

    @property
    def skipped(self) -> list[ImageOutcome]:
        """Images already complete with the same input and options."""
        return self._with("skipped")

    @property
    def busy(self) -> list[ImageOutcome]:
        """Images another run was still processing at the end of this run (rerun to finish)."""
        return self._with("busy")

    @property
    def excluded(self) -> list[ImageOutcome]:
        """Files a folder scan left out: m360 outputs and depth maps (``message``: why)."""
        return self._with("excluded")

    @property
    def failed(self) -> list[ImageOutcome]:
        """Images that failed (also in ``failures.jsonl``)."""
        return self._with("failed")

    @property
    def exit_code(self) -> int:
        """Give the exit code of ``m360 run``.

        0: every image done (or already done); 1: some failed; 2: the model failed on the first
        image (``model_error``): the run stopped there; 3 (:data:`EXIT_BUSY`): none failed but
        some were still being written by another run (rerun to finish them); 130: interrupted.
        """
        if self.interrupted:
            return 130
        if self.model_error is not None:
            return 2
        if self.failed:
            return 1
        return EXIT_BUSY if self.busy else 0

    def stage_seconds(self) -> dict[str, float]:
        """Total seconds per stage over the images done in this run."""
        totals = dict.fromkeys(STAGES, 0.0)
        for outcome in self.done:
            for stage, seconds in outcome.timings.items():
                if stage in totals:
                    totals[stage] += seconds
        return totals

    def summary(self) -> str:
        """Describe the run in a few lines: counts, rate and time per stage."""
        counts = (
            f"{len(self.done)} done, {len(self.skipped)} already done, "
            f"{len(self.failed)} failed"
            + (f", {len(self.busy)} busy in another run" * bool(self.busy))
        )
        lines = [f"m360 run: {counts} in {self.seconds:.1f} s"]
        if self.done:
            rate = len(self.done) / max(self.seconds, 1e-9) * 3600.0
            per_image = {k: v / len(self.done) for k, v in self.stage_seconds().items() if v > 0}
            stages = ", ".join(f"{k} {v:.3f}" for k, v in per_image.items())
            lines.append(f"  {rate:.0f} images/hour; mean seconds per image: {stages}")
        if self.failed:
            lines.append(f"  failures: {self.failures_file}")
        if self.busy:
            n = len(self.busy)
            lines.append(
                f"  {n} image{'s' * (n > 1)} {'were' if n > 1 else 'was'} being written by "
                f"another run: rerun to finish {'them' if n > 1 else 'it'}"
            )
        if self.excluded:
            shown = "; ".join(f"{o.input}: {o.message}" for o in self.excluded[:3])
            more = len(self.excluded) - 3
            lines.append(
                f"  left out of folder scans: {len(self.excluded)} file(s) ({shown}"
                + (f"; and {more} more" if more > 0 else "")
                + ")"
            )
        lines += [f"  {note}" for note in self.notes]
        if self.interrupted:
            lines.append("  interrupted: rerun the same command to finish the rest")
        if self.model_error is not None:
            lines.append(
                "  stopped: the model failed on the first image, so it would fail every image; "
                f"no other image was tried: {self.model_error}"
            )
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Inputs.


def collect(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    recursive: bool = False,
) -> tuple[list[Job], list[ImageOutcome]]:
    """Expand ``inputs`` (image files, folders, ``.txt``/``.csv`` manifests) into jobs.

    Folders give their images (``IMAGE_SUFFIXES``, case-insensitive) in sorted order, with
    ``recursive`` their sub-folders too (the sub-path is kept under OUT); a folder scan leaves
    out m360's own outputs (``STEM.depth.*``, ``STEM.disparity.*``, ``STEM.confidence.*``,
    ``STEM.preview.png``) and depth maps (a single-channel 16-bit PNG or TIFF, a single-channel
    float EXR or TIFF), each returned as an ``excluded`` outcome saying why. A file named in
    ``inputs`` or in a manifest is always tried. A ``.txt`` manifest lists one input per line
    (blank lines and ``#`` comments skipped); a ``.csv`` manifest has ``input[,output]`` rows
    (an optional header row starting with ``input``); relative paths are relative to the
    manifest's folder and ``output`` is a stem inside OUT. Every manifest is checked whole
    first (see :mod:`m360.batch._inputs`). Returns the jobs and, as outcomes, the inputs that
    cannot become jobs (failed: an output that escapes OUT, two inputs with the same output
    stem) and the files folder scans left out (excluded).

    Raises
    ------
    m360.ReadError
        If a path in ``inputs`` itself does not exist, or a manifest cannot be read.
    m360.InputError
        If ``inputs`` is not a path or paths, or a manifest is not one: not UTF-8 text, control
        characters (binary), a line longer than two paths, two lines with the same output.
    """
    out = Path(out_dir)
    if isinstance(inputs, (str, os.PathLike)):
        items: list[Any] = [inputs]
    elif isinstance(inputs, Iterable) and not isinstance(inputs, (bytes, Mapping)):
        items = list(inputs)
    else:
        raise InputError(f"inputs must be a path or paths, got {type(inputs).__name__}")
    jobs: list[Job] = []
    problems: list[ImageOutcome] = []
    claimed: dict[Path, Path] = {}

    def add(source: Path, rel: PurePath, where: str) -> None:
        try:
            stem = _inside(out, rel, where)
        except InputError as exc:
            problems.append(failure_outcome(source, rel.as_posix(), exc))
            return
        if stem in claimed:
            clash = InputError(
                f"{where}: output {rel} is already the output of {claimed[stem]}; name it "
                "differently in a manifest"
            )
            problems.append(failure_outcome(source, rel.as_posix(), clash))
            return
        claimed[stem] = source
        jobs.append(Job(source, stem, rel.as_posix(), where))

    for item in items:
        if not isinstance(item, (str, os.PathLike)):
            raise InputError(f"inputs must be paths, got {type(item).__name__}")
        path = Path(item)
        kind = _kind(path)
        if kind == "folder":
            images, left_out = scan(path, recursive=recursive)
            for image in images:
                add(image, image.relative_to(path).with_suffix(""), str(path))
            for file, reason in left_out:
                name = file.relative_to(path).as_posix()
                problems.append(ImageOutcome(str(file), name, "excluded", None, reason))
        elif kind == "file" and path.suffix.lower() in MANIFEST_SUFFIXES:
            for number, source, rel in read_manifest(path):
                add(source, rel, f"{path}:{number}")
        elif kind == "file":
            add(path, PurePath(path.stem), str(path))
        else:
            # A path the user named that is not there is a usage error, found before any
            # model work (files listed in a manifest fail one by one when they are read).
            raise ReadError(f"input {path} does not exist (or is not a file or folder)")
    return jobs, problems


def _kind(path: Path) -> str | None:
    """Tell whether ``path`` is a "folder", a "file" or neither (None); ReadError if unusable."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    except (OSError, ValueError) as exc:  # a name too long, a NUL, no permission
        reason = getattr(exc, "strerror", None) or exc
        raise ReadError(f"input {path} cannot be used: {reason}") from exc
    return "folder" if stat.S_ISDIR(mode) else "file" if stat.S_ISREG(mode) else None


def _check_names(
    jobs: list[Job], problems: list[ImageOutcome], out: Path, **outputs: Any
) -> list[Job]:
    """Keep the jobs whose output names the OS takes; the others become failed outcomes."""
    limits = name_limits(out)
    kept = []
    for job in jobs:
        problem = check_output_names(job, limits=limits, **outputs)
        if problem is None:
            kept.append(job)
        else:
            problems.append(failure_outcome(job.input, job.name, problem))
    return kept


def _inside(out: Path, rel: PurePath, where: str) -> Path:
    """``out / rel`` if it stays inside ``out`` (no absolute path, no ``..``, no symlink out)."""
    bad = "\x00" in str(rel)  # no OS takes it (and pathlib raises ValueError on it)
    if bad or rel.is_absolute() or ".." in rel.parts or not rel.parts or rel.name in ("", "."):
        raise InputError(f"{where}: output {str(rel)!r} must be a relative path inside OUT")
    stem = out / rel
    root = out.resolve()
    if not stem.parent.resolve().is_relative_to(root):
        raise InputError(f"{where}: output {rel} leads outside OUT ({out}) through a symlink")
    return stem


# --------------------------------------------------------------------------------------------
# The run.


def run(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    model: Any = _models.DEFAULT_MODEL,
    options: StitchOptions | None = None,
    model_options: ModelOptions | None = None,
    formats: Sequence[str] | str = ("npy",),
    preview: bool = True,
    confidence: bool = False,
    max_vertices: int | None = DEFAULT_MAX_VERTICES,
    workers: int = 1,
    resume: bool = True,
    recursive: bool = False,
    fix_aspect: bool = False,
    progress: bool = True,
    on_outcome: Callable[[ImageOutcome], None] | None = None,
    scale: Any = None,
    mask: Any = None,
    engine: str = "local",
    gpus_per_model: float | None = None,
    cpus_per_stitch: float = 1.0,
    **keywords: Unpack[RunKeywords],
) -> BatchReport:
    """Estimate the depth of many panoramas into ``out_dir``; see the module docstring.

    Parameters
    ----------
    inputs : path or paths
        Image files, folders and ``.txt``/``.csv`` manifests (see :func:`collect`).
    out_dir : path
        Output folder: ``OUT/STEM.*`` per image (see :func:`m360.save`), ``OUT/failures.jsonl``.
    model : str, path or estimator
        As for :func:`m360.estimate`. With ``workers > 1`` an estimator object must be
        picklable.
    options : StitchOptions, optional
        Every stitching option at once (then give none of them as a keyword).
    model_options : ModelOptions, optional
        Every model option at once (then give none of them as a keyword).
    formats : sequence of str
        Array formats, see :func:`m360.save`; ``preview`` adds the colour preview.
    confidence : bool
        Also write each image's confidence map (``STEM.confidence.EXT``, see :func:`m360.save`).
    max_vertices : int or None
        The most vertices of each 3D file (``ply``, ``glb``): larger images are strided to fit
        (see :func:`m360.save`; default :data:`m360.mesh.DEFAULT_MAX_VERTICES`, None = every
        pixel).
    workers : int
        Processes working on images at once (1 = in this process); with ``engine="ray"`` the
        number of model actors (one network session each).
    resume : bool
        Skip images already done with the same input and options (default); False redoes them.
    recursive : bool
        Also collect images in sub-folders of folder inputs.
    fix_aspect : bool
        Resize panoramas that are not W == 2H to W x W/2 instead of failing them.
    progress : bool
        Show a progress bar (tqdm) over the images.
    on_outcome : callable, optional
        Called in this process with each :class:`ImageOutcome` as it arrives.
    scale : scaler, optional
        Metric scale per image (:mod:`m360.scale`, e.g. ``camera_height(1.6)``); an image whose
        fit fails is a failure (``ScaleError``), nothing of it is written in metres.
    mask : optional
        ERP pixels to leave out of every image (:mod:`m360.masks`): ``nadir(deg)`` /
        ``zenith(deg)`` caps, (H, W) bool arrays (True = use; an image of another size fails),
        or a list of them; combined with a partial panorama's own mask.
    engine : {"local", "ray"}
        Where images run: local processes, or a Ray cluster (``pip install "m360[ray]"``; the
        cluster in ``RAY_ADDRESS``, else a local one). Same outputs, resume, failures, claims
        and exit codes either way.
    gpus_per_model : float, optional
        Ray only: GPUs per model actor (default 1 if ``providers`` asks for CUDA, else 0).
    cpus_per_stitch : float
        Ray only: CPUs per align + blend task (also the core's threads in it).
    **keywords
        Every option of :func:`m360.estimate` beyond its named ones, for every image: one list,
        :class:`m360.pipeline.options.EstimateKeywords` (the stitching options, the model
        options, ``working_width``, ``upsample``, ``padding``, ``subdivisions``, ``sky``, and
        the global prior ``prior``, ``prior_kind``, ``prior_confidence``, ``prior_options``).
        ``threads`` is also the core's threads per worker with ``workers > 1`` (default: the CPU
        count divided among the workers). A prior model (a path or registry name, loaded with
        ``kind="panoramic"`` and ``prior_options``) is loaded once before any image (a
        :class:`m360.ModelError` if it cannot be) and runs on each photo; a prior map applies
        to every image. The resume fingerprint holds the prior (a model's name, sha256, output
        kind and preprocessing; a map's sha256), so a rerun with another prior redoes the
        images. Also the stereo formats' ``ipd``, ``pole_fade`` and ``median_distance``
        (:class:`m360.io.stereo.StereoKeywords`; see :func:`m360.save`).

    Returns
    -------
    BatchReport
        Per-image outcomes, failures, time per stage; ``exit_code`` as ``m360 run`` uses it.
    """
    from ..estimators import load_estimator

    started = time.perf_counter()
    if not isinstance(out_dir, (str, os.PathLike)):
        raise InputError(f"out_dir must be a path, got {type(out_dir).__name__}")
    out = Path(out_dir)
    if "\x00" in str(out):  # the OS refuses such a name (ValueError deep in pathlib)
        raise InputError(f"output folder {str(out)!r} is not a valid path: it contains a NUL")
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} exists and is not a folder")
    stitch_keywords, model_keywords, job_keywords, prior_keywords, stereo_keywords = split(
        keywords,
        StitchKeywords,
        ModelKeywords,
        JobKeywords,
        PriorKeywords,
        StereoKeywords,
        where="run",
    )
    model_opts = ModelOptions.build(model_options, **model_keywords)
    job_options = resolve_job(job_keywords)
    workers = integer(workers, "workers", low=1, high=MAX_THREADS)
    resources = ray_resources(
        engine, workers, gpus_per_model, cpus_per_stitch, model_opts.providers
    )
    chosen = check_formats(formats)
    masks = _check_masks(mask)
    confidence = flag(confidence, "confidence")
    max_vertices = check_max_vertices(max_vertices)
    opts = build(options, job_options["subdivisions"], **stitch_keywords)
    if on_outcome is not None and not callable(on_outcome):
        raise InputError(f"on_outcome must be callable, got {type(on_outcome).__name__}")
    jobs, problems = collect(inputs, out, recursive=recursive)
    if not jobs and not any(p.status == "failed" for p in problems):
        left_out = "".join(f"; left out {p.input}: {p.message}" for p in problems[:3])
        raise InputError(
            f"no images found in {inputs} (looked for {', '.join(IMAGE_SUFFIXES)}){left_out}"
        )
    jobs = _check_names(
        jobs, problems, out, formats=chosen, preview=bool(preview), confidence=confidence
    )

    # Resolve (download, verify) the model once, here: a bad model fails the run, not each image.
    estimator = load_estimator(model, model_options=model_opts)
    panoramic = estimator_kind(estimator) == "panoramic"
    prior_given = checked(prior_keywords, PriorKeywords)
    if panoramic and prior_given:
        raise InputError("a prior goes with a tangent model; a panoramic model is used alone")
    if prior_given.get("prior") is not None and opts.align is None:
        raise InputError("a prior acts through the alignment: give align other than 'none'")
    if panoramic:
        refuse_layout_options(job_options)
    # The prior too: a prior model that cannot be loaded is one ModelError before any image.
    prior = load_prior(
        prior_given.get("prior"),
        prior_given.get("prior_kind"),
        prior_given.get("prior_confidence"),
        prior_options=prior_given.get("prior_options"),
        providers=model_opts.providers,
        threads=model_opts.threads,
    )
    settings = _Settings(
        model=model,
        model_options=model_opts,
        options=opts,
        job=job_options,
        formats=chosen,
        preview=bool(preview),
        fix_aspect=bool(fix_aspect),
        resume=bool(resume),
        fingerprint=fingerprint(
            estimator,
            opts,
            chosen,
            preview=bool(preview),
            fix_aspect=bool(fix_aspect),
            confidence=confidence,
        ),
        run_id=uuid.uuid4().hex[:12],
        scale=scale,
        masks=masks,
        confidence=confidence,
        max_vertices=max_vertices,
        # A map travels as the array read here (a file named once is read once, and a Ray
        # node need not see it); a model as it was given, loaded by each worker.
        prior=prior.array
        if prior is not None and prior.array is not None
        else prior_given.get("prior"),
        prior_kind=prior_given.get("prior_kind"),
        prior_confidence=None if prior is None else prior.confidence,
        prior_options=prior_given.get("prior_options"),
        prior_pixels=_prior_pixels(prior),
        panoramic=panoramic,
        stereo=checked(stereo_keywords, StereoKeywords),
    )
    # A rerun with another prior (model bytes, its options, its kind; a map's values) redoes
    # the image; absent without one, so the fingerprints of earlier runs stay valid.
    if prior is not None:
        settings.fingerprint["prior"] = describe_prior(prior)
        align = opts.as_dict()["align"] or {}
        settings.fingerprint["prior_options"] = {
            name: align[name] for name in PRIOR_OPTIONS if name in align
        }
    # A rerun with other stereo options must not be skipped (absent without a stereo format).
    if any(f in STEREO_FORMATS for f in chosen):
        settings.fingerprint["stereo"] = resolved(stereo_keywords, StereoKeywords)
    # A rerun with another vertex budget must not be skipped (absent when default, as below).
    if max_vertices != DEFAULT_MAX_VERTICES and any(f in GEOMETRY_FORMATS for f in chosen):
        settings.fingerprint["max_vertices"] = max_vertices
    # A rerun with another scale, mask or sky must not be skipped (absent when unused, so the
    # fingerprints of earlier runs stay valid).
    if scale is not None:
        from ..pipeline.scale import describe

        settings.fingerprint["scale"] = describe(scale)
    if masks:
        settings.fingerprint["mask"] = _describe_masks(masks)
    # The job's options that differ from their defaults (absent otherwise, as above).
    settings.fingerprint.update(job_fingerprint(job_options))
    if workers > 1 or resources is not None:
        _check_picklable(settings)
    make_output_folder(out)
    failures = out / FAILURES_FILE
    order = {job: k for k, job in enumerate(jobs)}
    outcomes: dict[int, ImageOutcome] = {}
    bar = _progress_bar(len(jobs) + len(problems), progress)
    counts = {"done": 0, "skipped": 0, "failed": 0}

    detail = _detail_note(estimator, prior, job_options)
    notes: list[str] = [] if detail is None else [detail]
    unwritten: list[str] = []  # the first failure that could not be appended, said once

    def record(outcome: ImageOutcome, index: int | None) -> None:
        if outcome.status == "failed":
            try:
                append_failure(failures, outcome, settings.run_id)
            except OSError as exc:  # a full disk: the failure is still reported here
                if not unwritten:
                    unwritten.append(f"{failures} could not be written: {exc.strerror or exc}")
                    notes.append(unwritten[0])
        if index is not None:
            outcomes[index] = outcome
        if outcome.status in counts:
            counts[outcome.status] += 1
        bar.set_postfix(counts, refresh=False)
        bar.update(1)
        if on_outcome is not None:
            on_outcome(outcome)
        # A model that fails on the first image tried (and none succeeded) fails them all:
        # stop here, whichever engine runs (each stops on an exception from record).
        if (
            outcome.status == "failed"
            and outcome.error == "ModelError"
            and index is not None
            and counts["done"] == counts["skipped"] == 0
        ):
            raise _ModelUnusable(outcome.message or "the model failed")

    interrupted = False
    model_error: str | None = None
    try:
        for problem in problems:
            record(problem, None)
        if resources is not None:
            from ._ray_engine import run_jobs

            del estimator, prior  # each model actor loads its own
            with MainThreadInterrupts(keyboard_interrupt_once()):  # the driver has many threads
                run_jobs(jobs, settings, lambda job, o: record(o, order[job]), resources)
        elif workers == 1 or len(jobs) <= 1:
            worker = _Worker(settings, estimator, prior)
            with MainThreadInterrupts(keyboard_interrupt_once()):
                for job in jobs:
                    record(worker.process(job), order[job])
        else:
            del estimator, prior  # each worker loads its own
            interrupted = _run_pool(jobs, settings, workers, lambda job, o: record(o, order[job]))
    except KeyboardInterrupt:
        interrupted = True
    except _ModelUnusable as exc:
        model_error = str(exc)
    finally:
        bar.close()
    # A worker that got Ctrl-C (and not this process) reports its image as interrupted.
    interrupted = interrupted or any(o.status == "interrupted" for o in outcomes.values())
    _recheck_busy(outcomes, jobs, settings)
    report = BatchReport(
        outcomes=[*problems, *(outcomes[k] for k in sorted(outcomes))],
        seconds=time.perf_counter() - started,
        interrupted=interrupted,
        failures_file=failures,
        model_error=model_error,
        notes=notes,
    )
    return report


def _prior_pixels(prior: Any) -> int:
    """Pixels of a prior's map for the memory check (a model's: its input for a 2:1 photo)."""
    if prior is None:
        return 0
    if prior.array is not None:
        return int(prior.array.size)
    if isinstance(prior.estimator, OnnxEstimator):
        h, w = prior.estimator.network_size((1024, 2048))
        return h * w
    return 0


def _detail_note(estimator: Any, prior: Any, job: dict[str, Any]) -> str | None:
    """Say so when the tangent network sees no finer in angle than the prior.

    Its depth edges are then about as sharp as the prior's brought up along the photo
    (docs/method.md, "Where the detail comes from"). Only for ONNX models (and maps), whose
    input size is known; both angles hold for any ERP width (the network's input is fixed).
    """
    if prior is None or not isinstance(estimator, OnnxEstimator):
        return None
    if prior.array is not None:
        prior_degrees = pixel_degrees(None, prior.array.shape[1])
    elif isinstance(prior.estimator, OnnxEstimator):
        prior_degrees = pixel_degrees(None, prior.estimator.network_size((1024, 2048))[1])
    else:
        return None
    layout = job_layout(2048, job)
    degrees = pixel_degrees(layout, estimator.network_size(layout.tangent_shape)[1])
    if degrees < prior_degrees:
        return None
    return (
        f"detail: the tangent network sees {degrees:.2f}° per pixel at a tile's centre, no "
        f"finer than the prior's {prior_degrees:.2f}°, so depth edges come out about as sharp "
        "as the prior's; smaller tiles (subdivisions=1, 4x the network calls) or a larger "
        "input_size see finer (docs/your-own-model.md)"
    )


class _ModelUnusable(Exception):
    """Raised by a run's ``record`` to stop it: the model failed on the first image."""


def _recheck_busy(outcomes: dict[int, ImageOutcome], jobs: list[Job], settings: _Settings) -> None:
    """Count an image another run had claimed as already done if it is done by now.

    Only those still unfinished stay ``busy`` (exit code 3: rerun to finish them).
    """
    if not settings.resume:
        return
    for index, outcome in outcomes.items():
        if outcome.status == "busy" and is_done(jobs[index], settings.fingerprint):
            outcomes[index] = ImageOutcome(outcome.input, outcome.stem, "skipped")


def ray_resources(
    engine: Any,
    workers: int,
    gpus_per_model: float | None,
    cpus_per_stitch: float,
    providers: Sequence[str] | None,
) -> Any:
    """Check the engine options; the Ray resources of a Ray run, None for the local engine."""
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "local":
        if gpus_per_model is not None or cpus_per_stitch != 1.0:
            raise InputError("gpus_per_model and cpus_per_stitch apply to engine='ray' only")
        return None
    try:
        import ray  # noqa: F401  (the engine's module imports it again, at no cost)
    except ImportError as exc:
        raise InputError(
            f'the Ray engine needs Ray, which cannot be imported ({exc}): pip install "m360[ray]"'
        ) from exc
    cpus = _positive(cpus_per_stitch, "cpus_per_stitch")
    if gpus_per_model is None:
        cuda = any("CUDA" in str(p) for p in providers or ())
        gpus = 1.0 if cuda else 0.0
    else:
        gpus = _positive(gpus_per_model, "gpus_per_model", zero=True)
    from ._ray_engine import RayResources

    return RayResources(
        model_actors=workers, gpus_per_model=gpus, cpus_per_model=1.0, cpus_per_stitch=cpus
    )


def _positive(value: Any, name: str, *, zero: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok or not (value >= 0 if zero else value > 0) or value != value or value > 1024:
        bound = ">= 0" if zero else "> 0"
        raise InputError(f"{name} must be a number {bound} (and at most 1024), got {value!r}")
    return float(value)


def make_output_folder(out: Path) -> None:
    """Create OUT, or tell why it cannot be written to (an InputError: exit 2, no image run)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, no permission, read-only file system
        raise InputError(f"cannot create the output folder {out}: {exc.strerror or exc}") from exc
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f"the output folder {out} is not writable")


#: Stitching options that act only with a prior (``StitchTuning``'s ``prior_weight``,
#: ``prior_scale_deg`` and ``prior_fusion``).
PRIOR_OPTIONS = ("prior_weight", "prior_scale_deg", "prior_fusion")


def fingerprint(
    estimator: Any,
    options: StitchOptions,
    formats: Sequence[str],
    *,
    preview: bool,
    fix_aspect: bool,
    confidence: bool = False,
) -> dict[str, Any]:
    """Every option that can change a byte of an image's outputs (not threads or workers).

    The model (name, sha256, declared output kind and, for ONNX models, the preprocessing that
    feeds it: input size, normalisation, providers), the canonical stitching options
    (:meth:`m360.StitchOptions.as_dict`), the formats, the preview and the aspect fix. A rerun
    skips an image only if its sidecar holds the same fingerprint.

    Parameters
    ----------
    estimator : Estimator
        The loaded estimator.
    options : StitchOptions
        The stitching options.
    formats : sequence of str
        The array formats written.
    preview, fix_aspect : bool
        Whether the preview is written and the aspect fixed.
    confidence : bool
        Whether the confidence map is written (recorded only when it is, so the fingerprints
        of runs without it are unchanged).

    Returns
    -------
    dict
        JSON-able.
    """
    model: dict[str, Any] = {
        "name": getattr(estimator, "name", type(estimator).__name__),
        "sha256": getattr(estimator, "sha256", None),
        "output_kind": estimator.output_kind,
    }
    if estimator_kind(estimator) == "panoramic":  # absent for tangent models, as before
        model["kind"] = "panoramic"
    if isinstance(estimator, OnnxEstimator):
        # What reaches the network: a rerun with another input size must not be skipped.
        model.update(
            input_size=None if estimator.input_size is None else list(estimator.input_size),
            multiple_of=estimator.multiple_of,
            resize=estimator.resize,
            mean=[float(v) for v in estimator.mean],
            std=[float(v) for v in estimator.std],
            providers=list(estimator.providers),
        )
    stitch = options.as_dict()
    # The prior's options change nothing without a prior: kept out, so the fingerprints of
    # runs without one (and of runs from before the prior existed) stay valid; the runner
    # adds them with the prior.
    if stitch["align"] is not None:
        for name in PRIOR_OPTIONS:
            stitch["align"].pop(name, None)
    result = {
        "model": model,
        "stitch": stitch,
        "formats": sorted(formats),
        "preview": bool(preview),
        "fix_aspect": bool(fix_aspect),
    }
    if confidence:
        result["confidence"] = True
    return result


def _check_picklable(settings: _Settings) -> None:
    try:
        pickle.dumps(settings)
    except Exception as exc:
        raise InputError(
            f"with workers > 1 the model must be a name, a path or a picklable estimator: {exc}"
        ) from exc


def append_failure(path: Path, outcome: ImageOutcome, run_id: str) -> None:
    """Append one JSON line for a failure, in a single write.

    O_APPEND keeps lines whole even when two runs share the folder.
    """
    record = {
        "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "run": run_id,
        "input": outcome.input,
        "output": outcome.stem,
        "error": outcome.error,
        "message": outcome.message,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    line = (json.dumps(record, ensure_ascii=False) + "\n").encode("utf-8")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        os.write(fd, line)
    finally:
        os.close(fd)


class NoBar:
    """A progress bar that shows nothing (``progress=False``): tqdm's methods, doing nothing."""

    def update(self, n: int) -> None:
        """Count ``n`` more items (nothing shown)."""

    def set_postfix(self, values: Mapping[str, int], refresh: bool) -> None:
        """Show counts after the bar (nothing shown)."""

    def close(self) -> None:
        """End the bar (nothing to end)."""


def keyboard_interrupt_once() -> Callable[[int, Any], None]:
    """SIGINT handler of an in-process run: KeyboardInterrupt once, then nothing.

    Once is enough, and a second one could break the clean-up of the first (the handler may
    run twice for one Ctrl-C: see :mod:`m360.batch._interrupt`).
    """
    raised = False

    def handler(signum: int, frame: Any) -> None:
        nonlocal raised
        if not raised:
            raised = True
            raise KeyboardInterrupt

    return handler


def _progress_bar(total: int, show: bool) -> Any:
    if not show:
        return NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="img", desc="m360", dynamic_ncols=True, smoothing=0.1)


# Worker processes. The state lives in a module global of each worker process.
_PROCESS_WORKER: _Worker | None = None
_STOPPING = False  # set when Ctrl-C reached this worker: it takes no further image
_BUSY = False  # an image is in progress in this worker


def _on_sigint(signum: int, frame: Any) -> None:
    """Ctrl-C in a worker: interrupt the image in progress once; otherwise only stop.

    A worker may get SIGINT twice (from the terminal and forwarded by the parent): a second
    one must not interrupt the clean-up of the first, and an idle worker (waiting for its
    next image) must not die with a traceback.
    """
    global _STOPPING
    first = not _STOPPING
    _STOPPING = True
    if first and _BUSY:
        raise KeyboardInterrupt


def _init_process(settings: _Settings, core_threads: int) -> None:
    global _PROCESS_WORKER
    from .._core import set_num_threads

    install_for_process(_on_sigint)
    set_num_threads(core_threads)
    _PROCESS_WORKER = _Worker(settings)


def _process_in_worker(job: Job) -> ImageOutcome:
    global _BUSY
    if _PROCESS_WORKER is None:  # pragma: no cover - the initializer always ran
        raise RuntimeError("worker not initialised")
    try:
        _BUSY = True  # before the check: a Ctrl-C between the two still stops this image
        if not _STOPPING:
            return _PROCESS_WORKER.process(job)
    except KeyboardInterrupt:  # the image's files were cleaned up on the way out
        pass
    finally:
        _BUSY = False
    return ImageOutcome(str(job.input), job.name, "interrupted")


def _interrupt_workers(executor: ProcessPoolExecutor) -> None:
    """Forward Ctrl-C to the workers, which may not have got it.

    A SIGINT sent to this process alone (``kill -INT PID``) used to let the images in progress
    and the queued ones run to the end; now they stop at once.
    """
    processes = getattr(executor, "_processes", None) or {}  # private: {pid: Process}
    for pid in list(processes):
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGINT)


def _run_pool(
    jobs: Sequence[Job],
    settings: _Settings,
    workers: int,
    record: Callable[[Job, ImageOutcome], None],
) -> bool:
    """Run ``jobs`` on ``workers`` spawned processes; survive a worker that dies.

    After a crash every image that was in flight is a suspect: suspects are retried one at a
    time in a fresh pool, and one that kills its worker again is recorded as ``WorkerCrashed``.
    Ctrl-C starts nothing new and stops the images in flight (the workers clean up); returns
    True if that happened. The handler only sets a flag and signals the workers, so no
    KeyboardInterrupt can land inside the executor's own code.
    """
    core_threads = settings.threads or max(1, (os.cpu_count() or 1) // workers)
    # spawn, not fork: the core's thread pool does not survive fork().
    context = multiprocessing.get_context("spawn")
    queue = deque(jobs)
    suspects: deque[Job] = deque()
    crashes: dict[Job, int] = {}
    stopping = threading.Event()
    pools: list[ProcessPoolExecutor] = []

    def on_sigint(signum: int, frame: Any) -> None:
        stopping.set()
        for pool in pools:
            _interrupt_workers(pool)

    with MainThreadInterrupts(on_sigint):
        while (queue or suspects) and not stopping.is_set():
            executor = ProcessPoolExecutor(
                workers, context, initializer=_init_process, initargs=(settings, core_threads)
            )
            pools[:] = [executor]
            inflight: dict[Future[ImageOutcome], Job] = {}
            broken = False
            try:
                while (queue or suspects or inflight) and not broken and not stopping.is_set():
                    while not broken and not stopping.is_set() and (suspects or queue):
                        if suspects:
                            if inflight:
                                break  # a suspect runs alone
                            job = suspects.popleft()
                        elif len(inflight) < 2 * workers:
                            job = queue.popleft()
                        else:
                            break
                        inflight[executor.submit(_process_in_worker, job)] = job
                    finished, _ = wait(inflight, return_when=FIRST_COMPLETED)
                    for future in finished:
                        job = inflight.pop(future)
                        try:
                            outcome = future.result()
                        except BrokenProcessPool:
                            broken = True
                            _suspect(job, crashes, suspects, record)
                            continue
                        record(job, outcome)
                if stopping.is_set():
                    # Queued images never start; a worker spawned after the signal gets it now.
                    for future in inflight:
                        future.cancel()
                    _interrupt_workers(executor)
                # Count what finished; after a crash the others in flight finished or broke too.
                lost = _record_finished(inflight, record)
            finally:
                executor.shutdown(wait=True, cancel_futures=True)
                pools.clear()
            if not stopping.is_set():
                for job in lost:
                    _suspect(job, crashes, suspects, record)
    return stopping.is_set()


def _record_finished(
    inflight: Mapping[Future[ImageOutcome], Job], record: Callable[[Job, ImageOutcome], None]
) -> list[Job]:
    """Wait for ``inflight`` and record every outcome but "interrupted".

    Returns the jobs whose future failed (their worker died) or was cancelled.
    """
    wait(inflight)
    lost = []
    for future, job in inflight.items():
        if future.cancelled() or future.exception() is not None:
            lost.append(job)
        elif future.result().status != "interrupted":
            record(job, future.result())
    return lost


def _suspect(
    job: Job,
    crashes: dict[Job, int],
    suspects: deque[Job],
    record: Callable[[Job, ImageOutcome], None],
) -> None:
    crashes[job] = crashes.get(job, 0) + 1
    if crashes[job] >= 2:
        message = "the worker process died while processing this image (twice)"
        record(job, ImageOutcome(str(job.input), job.name, "failed", "WorkerCrashed", message))
    else:
        suspects.append(job)
