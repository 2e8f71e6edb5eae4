"""Every public entry point on fresh layouts, from many threads or processes at once.

Run as a script by ``tests/test_concurrency.py`` under a timeout (the watchdog: a deadlock kills
the script instead of hanging the test run). ``python concurrency_jobs.py MODE LAYOUTS WORKERS``
computes every job one at a time, then again with MODE ("threads", "fork" or "spawn") on fresh
plans, and exits 0 when the results are bit-identical, 1 (naming the jobs) when they are not.
MODE "first-calls" replays the recipe of the hang the watchdog guards against.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import multiprocessing
import sys

import m360
import m360.synthetic as syn
import numpy as np
from m360.estimators import SimulatedEstimator

#: What each job on a layout runs: every public entry point, every blend, both energies and
#: solvers of the alignment.
VARIANTS = (
    "erp_to_tangents",
    "tangents_to_erp",
    "stitch none/mean",
    "stitch none/nn",
    "stitch multiscale/radial",
    "stitch multiscale/frustum",
    "stitch paper lbfgs/poisson",
    "estimate",
)
THREADS = 2  # m360's own pool: results are deterministic for a fixed thread count
SCENE = syn.room(3)


def layout_of(index: int) -> m360.Layout:
    """A layout no other job index shares (so its plan starts empty)."""
    return m360.Layout.icosahedron(erp_width=128 + 16 * index)


def job(index: int, variant: str) -> str:
    """Run one entry point on layout ``index``; a digest of every output byte."""
    layout = layout_of(index)
    rng = np.random.default_rng(index)
    h, w = layout.erp_shape
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    estimator = SimulatedEstimator(SCENE, layout, seed=index, noise=0.01)
    tangents = estimator.predict(np.zeros((len(layout), *layout.tangent_shape, 3), np.uint8))
    outputs: list[np.ndarray]
    if variant == "erp_to_tangents":
        outputs = [m360.erp_to_tangents(rgb, layout)]
    elif variant == "tangents_to_erp":
        outputs = [m360.tangents_to_erp(tangents, layout)]
    elif variant == "estimate":
        result = m360.estimate(rgb, model=estimator, blend="frustum", layout=layout)
        outputs = [result.disparity, result.depth]
    else:
        _, modes = variant.split(" ", 1)
        align, blend = modes.rsplit("/", 1)
        options: dict[str, object] = {"blend": blend}
        if align == "paper lbfgs":
            options.update(align="multiscale", energy="paper", solver="lbfgs")
        else:
            options["align"] = align
        outputs = [m360.stitch(tangents, layout, **options)]  # type: ignore[arg-type]
    digest = hashlib.sha256()
    for out in outputs:
        digest.update(np.ascontiguousarray(out).tobytes())
    return digest.hexdigest()


def _job(args: tuple[int, str]) -> str:
    return job(*args)


def _init_process() -> None:
    m360.set_num_threads(THREADS)


def run_all(jobs: list[tuple[int, str]], mode: str, workers: int) -> list[str]:
    """Every job with ``mode``: "serial", "threads", "fork" or "spawn"."""
    if mode == "serial":
        return [job(*j) for j in jobs]
    if mode == "threads":
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            return list(pool.map(_job, jobs))
    context = multiprocessing.get_context(mode)
    with concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=context, initializer=_init_process
    ) as pool:
        return list(pool.map(_job, jobs))


def first_calls(trials: int) -> int:
    """The recipe that hung before plans were built outside the pool: on each fresh layout,
    one thread calls ``erp_to_tangents`` while two call ``stitch(..., blend="frustum")``."""
    for trial in range(trials):
        layout = layout_of(trial)
        rgb = np.zeros((*layout.erp_shape, 3), np.uint8)
        tangents = np.ones((len(layout), *layout.tangent_shape), np.float32)
        with concurrent.futures.ThreadPoolExecutor(3) as pool:
            futures = [pool.submit(m360.erp_to_tangents, rgb, layout)] + [
                pool.submit(m360.stitch, tangents, layout, align="none", blend="frustum")
                for _ in range(2)
            ]
            results = [f.result() for f in futures]
        if not np.array_equal(results[1], results[2], equal_nan=True):
            print(f"trial {trial}: two identical stitches differ")
            return 1
    print(f"first calls: {trials} fresh layouts, 3 threads each")
    return 0


def main(argv: list[str]) -> int:
    """Compare ``argv[0]`` mode against the serial run; print what differs."""
    mode, layouts, workers = argv[0], int(argv[1]), int(argv[2])
    m360.set_num_threads(THREADS)
    if mode == "first-calls":
        return first_calls(layouts)
    # Layout-major order: the workers start on the same fresh layout together.
    jobs = [(i, v) for i in range(layouts) for v in VARIANTS]
    serial = run_all(jobs, "serial", 1)
    m360.clear_plan_cache()
    concurrent_run = run_all(jobs, mode, workers)
    different = [j for j, a, b in zip(jobs, serial, concurrent_run, strict=True) if a != b]
    print(f"{mode}: {len(jobs)} calls on {layouts} fresh layouts, {workers} workers")
    for j in different:
        print(f"different from the serial run: layout {j[0]}, {j[1]}")
    return 1 if different else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
