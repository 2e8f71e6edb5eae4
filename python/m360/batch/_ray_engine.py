"""The Ray engine of :func:`m360.batch.run` (``engine="ray"``, ``m360 run --engine ray``).

Only :mod:`m360.batch` imports this module, and only for a Ray run: ``import m360`` never
imports ray.

One image flows through three stages, each a separate Ray resource request so that a cluster
can give the network GPUs and the geometry CPUs:

1. **read + project** (CPU task): read, decode, check the panorama, sample the tangents. Only
   the uint8 tangents go on (about 1.3x the ERP's bytes), never the ERP itself.
2. **network** (an actor pool, one ONNX Runtime session per actor, ``num_gpus`` when asked):
   the raw network output of the tangents; with a prior model, also its output on the
   working-resolution photo (stage 1 ships it); a panoramic model runs on the photo instead.
3. **convert + align + blend + write** (CPU task with ``cpus_per_stitch`` cores): the rest of
   :func:`m360.estimate` and the atomic write, sidecar last.

The driver (this process) keeps the local engine's semantics by running the same pieces
(:mod:`m360.batch`: claims, resume, failures) and by holding each image's claim from before
stage 1 until its outcome is known, so a local run and a Ray run into one folder share the
work. It admits a new image only while fewer than ``window`` are in flight (back-pressure: a
slow stage never fills the object store), and gives an actor one image at a time, so a crash
in the network costs only that image. Ray's own retries are off: a stage whose worker, actor
or node dies fails with a Ray system error, and the driver redoes the whole image once (its
intermediate objects may have died with the node); an image that fails this way twice is
recorded as ``WorkerCrashed``, as in the local engine.

Why not Ray Data: its retries and error budget act on blocks, not images, and its input is
materialised up front, so neither per-image crash accounting nor claims taken when an image
enters the pipeline fit it; the three stages above are what its streaming executor would run.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import ray as _ray

from ..errors import InputError, ModelError
from ..io import remove_stale_temporaries
from . import image as _image
from ._interrupt import deferred
from .image import ImageOutcome, Job, _Settings

# Ray's annotations are partial (untyped functions, ObjectRef not unpackable): use it untyped.
ray: Any = _ray

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
#: How many times an image may lose its worker (process, actor or node) before it fails.
MAX_CRASHES = 2
CRASH_MESSAGE = "the Ray worker (process, actor or node) died while processing this image (twice)"


@dataclass(frozen=True)
class RayResources:
    """Per-stage Ray resources of a run (see :func:`m360.batch.run`)."""

    model_actors: int
    gpus_per_model: float
    cpus_per_model: float
    cpus_per_stitch: float
    window: int | None = None  # images in flight; default from the cluster's CPUs


# --------------------------------------------------------------------------------------------
# The stages (run in Ray workers).

_LAYOUTS: dict[tuple[int, float | None, int], Any] = {}


def _layout(width: int, job: dict[str, Any]) -> Any:
    """The default layout of a width (and the job's padding and subdivisions), kept per worker
    process (its plan is cached in the core): the one :func:`m360.estimate` makes.
    """
    from ..pipeline.options import job_layout

    key = (width, job["padding"], job["subdivisions"])
    if key not in _LAYOUTS:
        _LAYOUTS[key] = job_layout(width, job)
    return _LAYOUTS[key]


def _use_threads(threads: int) -> None:
    from .._core import get_num_threads, set_num_threads

    if get_num_threads() != threads:
        set_num_threads(threads)


def _read_project(job: Job, settings: _Settings, threads: int) -> tuple[Any, Any]:
    """Stage 1: (meta, payload).

    meta is a failed ImageOutcome or (read, ERP shape, working width, timings); ``read.rgb`` is
    kept only when the 3D formats need its colours, a working width smaller than the image's
    needs it as the upsampling guide (or a panoramic model's output does), or ``edges`` other
    than ``"network"`` as the edges' guide: otherwise only the payload travels on. The payload
    is (tangents, image): the image is what a model actor runs a panoramic network on (the
    photo for a panoramic model, the working-resolution photo for a prior model; None
    otherwise). The working width is chosen as :func:`m360.estimate` chooses it, so both
    engines make the same bytes.
    """
    import cv2

    from ..geometry.layout import erp_to_tangents
    from ..pipeline.estimate import _check_erp_rgb
    from ..pipeline.memory import working_width_for
    from ..pipeline.prior import is_model

    _use_threads(threads)
    try:
        t0 = time.perf_counter()
        read = _image._read_job(job, settings)
        rgb = _check_erp_rgb(read.rgb)
        height, width = rgb.shape[:2]
        if settings.panoramic:  # one pass on the whole photo: no tangents
            t_read = time.perf_counter()
            read.rgb = rgb  # the upsampling's guide
            timings = {"read": t_read - t0, "project": 0.0}
            return (read, (height, width), width, timings), (None, rgb)
        work_width = working_width_for(settings.job["working_width"], width)
        working = rgb
        if work_width != width:
            size = (work_width, work_width // 2)
            working = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        t_read = time.perf_counter()
        tangents = erp_to_tangents(working, _layout(work_width, settings.job))
        t_project = time.perf_counter()
    except Exception as exc:
        return _image.error_outcome(job, exc), None
    timings = {"read": t_read - t0, "project": t_project - t_read}
    # "auto" may refine along the photo: whether it does is known where the network ran.
    keep = _image._needs_rgb(settings) or work_width != width or settings.job["edges"] != "network"
    read.rgb = rgb if keep else None
    image = working if is_model(settings.prior) else None
    return (read, (height, width), work_width, timings), (tangents, image)


class _Network:
    """Stage 2: one estimator (ONNX Runtime session) per actor, loaded once; and the prior's."""

    def __init__(self, settings: _Settings, threads: int | None) -> None:
        from ..estimators import ModelOptions, load_estimator
        from ..pipeline.prior import is_model

        # The actor's threads (its reserved CPUs unless the run names them) win.
        given = {**settings.model_options.keywords(), "threads": threads}
        self.estimator = load_estimator(settings.model, model_options=ModelOptions(**given))
        self.job = settings.job
        self.prior = settings.load_prior(threads) if is_model(settings.prior) else None

    def ready(self) -> bool:
        """Tell the driver the model loaded (a failure is the constructor's exception)."""
        return True

    def predict(self, payload: Any, width: int) -> tuple[Any, Any]:
        """(meta, raw): meta is (model info, kind, seconds, extra) or the exception raised.

        ``extra`` holds the prior model's output (``prior``) and seconds (``prior_seconds``).
        """
        from ..pipeline.estimate import _model_info, _predict
        from ..pipeline.prior import prior_input, run_prior

        tangents, image = payload
        t0 = time.perf_counter()
        extra: dict[str, Any] = {}
        try:
            if tangents is None:  # a panoramic model on the whole photo
                network_input = prior_input(self.estimator, image)
                raw = run_prior(self.estimator, network_input, "panoramic model")
                info = _model_info(self.estimator, None, network_input.shape[:2])
                seconds = time.perf_counter() - t0
            else:
                layout = _layout(width, self.job)
                raw = _predict(self.estimator, tangents, layout)
                seconds = time.perf_counter() - t0
                info = _model_info(self.estimator, layout)
                if self.prior is not None:
                    t1 = time.perf_counter()
                    est = self.prior.estimator
                    extra["prior"] = run_prior(est, prior_input(est, image))
                    extra["prior_seconds"] = time.perf_counter() - t1
        except Exception as exc:
            return exc, None
        return (info, self.estimator.output_kind, seconds, extra), raw


def _stitch_write(
    job: Job,
    settings: _Settings,
    threads: int,
    read_meta: Any,
    network_meta: Any,
    raw: Any,
) -> ImageOutcome:
    """Stage 3: the rest of m360.estimate, then the atomic write (the driver holds the claim)."""
    from ..pipeline import masks as _masks
    from ..pipeline.estimate import (
        PriorMap,
        _from_network,
        _from_panoramic,
        _prior_map,
        _split_mask,
    )

    _use_threads(threads)
    if isinstance(network_meta, Exception):
        return _image.error_outcome(job, network_meta)
    read, erp_shape, work_width, timings = read_meta
    info, kind, network_seconds, extra = network_meta
    try:
        # The sidecar's timings are m360.estimate's stages, as the local engine writes them.
        before = {"load": 0.0, "project": timings["project"], "network": network_seconds}
        if settings.panoramic:
            masks = _image._image_mask(read, settings)
            result = _from_panoramic(
                raw,
                kind,
                erp_shape,
                info,
                before,
                guide=read.rgb,
                erp_valid=None if masks is None else _masks.erp_mask(masks, *erp_shape),
                sky_mode=settings.job["sky"],
                scale=settings.scale,
                upsample=settings.job["upsample"],
                edges=settings.job["edges"],
            )
        else:
            layout = _layout(work_width, settings.job)
            mask, erp_valid = _split_mask(_image._image_mask(read, settings), layout, erp_shape)
            prior = None
            if "prior" in extra:  # the model actor ran the prior model
                record = settings.fingerprint["prior"]
                prior = PriorMap(extra["prior"], record["kind"], None, record)
                before["prior"] = extra["prior_seconds"]
            elif settings.prior is not None:  # a map: cheap to load here
                prior = _prior_map(settings.load_prior(), None, prior_input=None)
                before["prior"] = 0.0
            result = _from_network(
                raw,
                kind,
                layout,
                settings.options,
                erp_shape,
                info,
                before,
                mask=mask,
                erp_valid=erp_valid,
                sky_mode=settings.job["sky"],
                scale=settings.scale,
                guide=read.rgb,
                upsample=settings.job["upsample"],
                edges=settings.job["edges"],
                prior=prior,
            )
        result.timings["total"] = sum(result.timings.values())  # time at work, not waiting
        t_write = time.perf_counter()
        # An earlier attempt at this image lost its worker mid-write; the claim is still ours.
        remove_stale_temporaries(job.stem)
        _image._write_job(job, result, read.records, settings, read.rgb)
        write = time.perf_counter() - t_write
    except Exception as exc:
        return _image.error_outcome(job, exc)
    stages = {"read": timings["read"], **result.timings, "write": write}
    stages.pop("total")
    return ImageOutcome(str(job.input), job.name, "done", timings=stages)


# --------------------------------------------------------------------------------------------
# The driver.


@dataclass
class _Image:
    """An image in flight: its job, its claim, and how often it lost its worker."""

    job: Job
    claim: contextlib.ExitStack
    crashes: int = 0
    read_meta: Any = None
    tangents: Any = None


def run_jobs(
    jobs: Sequence[Job],
    settings: _Settings,
    record: Callable[[Job, ImageOutcome], None],
    resources: RayResources,
) -> None:
    """Run ``jobs`` on Ray (the cluster in ``RAY_ADDRESS``, else a local one); see the module."""
    started_here = not ray.is_initialized()
    if started_here:
        # RAY_ADDRESS, when set, names the cluster; otherwise this starts a local one.
        # Ray's INFO lines would tear the progress bar; its warnings still show.
        ray.init(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    try:
        _Driver(jobs, settings, record, resources).run()
    finally:
        if started_here:
            ray.shutdown()


def _check_cluster(res: RayResources) -> int:
    """The cluster's CPUs; an InputError if the actors would leave no room for the tasks.

    Ray queues what does not fit forever, so a run that cannot progress must not start. The
    check sees the cluster as it is now (an autoscaler may add nodes later).
    """
    total = ray.cluster_resources()
    cpus, gpus = float(total.get("CPU", 0)), float(total.get("GPU", 0))
    stitch = max(1.0, res.cpus_per_stitch)  # the read task takes 1 CPU
    needed = res.model_actors * res.cpus_per_model + stitch
    if cpus < needed:
        raise InputError(
            f"the Ray cluster has {cpus:g} CPUs: {res.model_actors} model actor(s) of "
            f"{res.cpus_per_model:g} CPU and a stitch task of {stitch:g} need {needed:g}; use "
            "fewer workers (model actors) or a smaller cpus_per_stitch"
        )
    if gpus < res.model_actors * res.gpus_per_model:
        raise InputError(
            f"the Ray cluster has {gpus:g} GPUs: {res.model_actors} model actor(s) of "
            f"{res.gpus_per_model:g} GPU do not fit; use fewer workers or gpus_per_model 0"
        )
    return int(cpus)


class _Driver:
    def __init__(
        self,
        jobs: Sequence[Job],
        settings: _Settings,
        record: Callable[[Job, ImageOutcome], None],
        resources: RayResources,
    ) -> None:
        self.queue: deque[Job] = deque(jobs)
        self.settings = settings
        self.record = record
        self.res = resources
        self.stitch_threads = max(1, math.ceil(resources.cpus_per_stitch))
        model_threads = settings.threads
        if model_threads is None and isinstance(settings.model, (str, os.PathLike)):
            model_threads = max(1, math.ceil(resources.cpus_per_model))  # its reserved CPUs
        cpus = _check_cluster(resources)
        # Enough images in flight to keep every CPU and actor busy, and no more.
        self.window = resources.window or max(2, 2 * cpus + resources.model_actors)
        self.read_task = ray.remote(_read_project).options(num_cpus=1, num_returns=2, max_retries=0)
        self.stitch_task = ray.remote(_stitch_write).options(
            num_cpus=resources.cpus_per_stitch, max_retries=0
        )
        self.actor_class = ray.remote(_Network).options(
            num_cpus=resources.cpus_per_model,
            num_gpus=resources.gpus_per_model,
            max_restarts=-1,
            max_task_retries=0,
        )
        self.model_threads = model_threads
        self.shared_settings = ray.put(settings)  # stored once, not pickled with every task
        self.actors = [
            self.actor_class.remote(settings, model_threads) for _ in range(resources.model_actors)
        ]
        self._check_actors()
        self.idle: deque[Any] = deque(self.actors)
        self.waiting_for_network: deque[_Image] = deque()
        # Ray object reference → (stage, image, actor); no image for an actor's restart.
        self.pending: dict[Any, tuple[str, _Image | None, Any]] = {}
        self.in_flight = 0
        self.replaced = 0  # model actors replaced after dying for good
        self.claims: set[contextlib.ExitStack] = set()  # every claim this driver holds

    def _check_actors(self) -> None:
        """Wait for the model actors: a model that cannot load fails the run, not each image."""
        try:
            ray.get([actor.ready.remote() for actor in self.actors])
        except ray.exceptions.RayActorError as exc:
            for actor in self.actors:
                with contextlib.suppress(Exception):
                    ray.kill(actor)
            cause = _ANSI.sub("", str(exc)).strip()
            raise ModelError(f"the model actors could not load the model: {cause}") from exc

    def run(self) -> None:
        try:
            while self.queue or self.waiting_for_network or self._images_pending():
                self._admit()
                self._dispatch_network()
                if not self.pending:
                    continue
                ready, _ = ray.wait(list(self.pending), num_returns=1)
                for ref in ready:
                    self._finish(ref)
        except BaseException:
            # Ctrl-C (or a lost cluster): stop what is in flight, release every claim. A task
            # cancelled mid-write removes its own files (m360.save cleans up on the way out).
            for ref, (stage, _, _) in self.pending.items():
                if stage != "network":
                    with contextlib.suppress(Exception):
                        ray.cancel(ref)
            for claim in list(self.claims):
                self._release(claim)
            raise
        finally:
            for actor in self.actors:
                with contextlib.suppress(Exception):
                    ray.kill(actor)

    def _images_pending(self) -> bool:
        return any(image is not None for _, image, _ in self.pending.values())

    def _release(self, claim: contextlib.ExitStack) -> None:
        claim.close()  # before forgetting it: a Ctrl-C between the two finds it again
        self.claims.discard(claim)

    def _admit(self) -> None:
        """Claim and submit images while fewer than ``window`` are in flight."""
        s = self.settings
        while self.queue and self.in_flight < self.window:
            job = self.queue.popleft()
            unusable = _image._make_job_folder(job)
            if unusable is not None:
                self.record(job, unusable)
                continue
            claim = contextlib.ExitStack()
            self.claims.add(claim)  # first: Ctrl-C from here on still releases it
            with deferred():  # Ctrl-C lands once the claim is in the stack, not halfway
                claimed = claim.enter_context(_image.claim(job.stem))
            if not claimed:
                self._release(claim)
                self.record(job, ImageOutcome(str(job.input), job.name, "busy"))
                continue
            if s.resume and _image.is_done(job, s.fingerprint):
                self._release(claim)
                self.record(job, ImageOutcome(str(job.input), job.name, "skipped"))
                continue
            remove_stale_temporaries(job.stem)
            self.in_flight += 1
            self._submit_read(_Image(job, claim))

    def _submit_read(self, image: _Image) -> None:
        meta, payload = self.read_task.remote(image.job, self.shared_settings, self.stitch_threads)
        image.tangents = payload
        self.pending[meta] = ("read", image, None)

    def _dispatch_network(self) -> None:
        while self.idle and self.waiting_for_network:
            image = self.waiting_for_network.popleft()
            actor = self.idle.popleft()
            width = image.read_meta[2]  # the working width
            meta, raw = actor.predict.options(num_returns=2).remote(image.tangents, width)
            image.tangents = None  # the actor has the reference; free it when it is done
            done = self.stitch_task.remote(
                image.job, self.shared_settings, self.stitch_threads, image.read_meta, meta, raw
            )
            self.pending[meta] = ("network", image, actor)
            self.pending[done] = ("stitch", image, None)

    def _finish(self, ref: Any) -> None:
        stage, image, actor = self.pending.pop(ref)
        if stage == "network":
            # The image's fate is told by its stitch task, which gets the network's error as
            # its own. The actor is free again, or, if it died, once it has restarted.
            try:
                ray.get(ref)
            except ray.exceptions.RayError:
                self._await_restart(actor)
            else:
                self.idle.append(actor)
            return
        if stage == "restarted":
            try:
                ray.get(ref)
            except ray.exceptions.RayError as exc:  # dead for good: replace it, a few times
                self.replaced += 1
                if self.replaced > 3 * len(self.actors):
                    cause = _ANSI.sub("", str(exc)).strip().partition("\n")[0]
                    raise ModelError(f"the model actors keep dying for good: {cause}") from exc
                self.actors.remove(actor)
                actor = self.actor_class.remote(self.settings, self.model_threads)
                self.actors.append(actor)
                self._await_restart(actor)
            else:
                self.idle.append(actor)
            return
        assert image is not None
        try:
            value = ray.get(ref)
        except ray.exceptions.RayError as exc:
            self._crashed(image, exc)
            return
        if stage == "read":
            if isinstance(value, ImageOutcome):
                self._done(image, value)
            else:
                image.read_meta = value
                self.waiting_for_network.append(image)
            return
        self._done(image, value)

    def _await_restart(self, actor: Any) -> None:
        """Give ``actor`` no image until it is alive again (Ray restarts it, on another node
        if its node is gone): an image sent to a restarting actor would fail unseen.
        """
        ready = actor.ready.options(max_task_retries=-1).remote()
        self.pending[ready] = ("restarted", None, actor)

    def _crashed(self, image: _Image, exc: BaseException) -> None:
        image.crashes += 1
        if image.crashes >= MAX_CRASHES:
            job = image.job
            last = _ANSI.sub("", str(exc)).strip().partition("\n")[0]
            message = f"{CRASH_MESSAGE}; last: {type(exc).__name__}: {last[:200]}"
            outcome = ImageOutcome(str(job.input), job.name, "failed", "WorkerCrashed", message)
            self._done(image, outcome)
            return
        image.read_meta = image.tangents = None
        self._submit_read(image)  # redo it from the start, still under its claim

    def _done(self, image: _Image, outcome: ImageOutcome) -> None:
        self._release(image.claim)
        self.in_flight -= 1
        self.record(image.job, outcome)
