"""Throughput of ``m360.estimate`` called from 1, 2 and 4 Python threads at once.

A web service or a Ray actor calls m360 from several threads; on a machine with few cores this
must not get slower than calling it from one thread (the calls share m360's thread pool, and
each releases the GIL while the core works). Every thread runs the whole pipeline (project →
network → convert → align → blend) on its own panorama with the simulated network (exact
ray-cast disparity, per-tangent affine error: no weights needed). The baseline is the same
images from one thread, in the same run. Each configuration is timed ``--repeats`` times;
the table gives the median images per second, the IQR, and the ratio to one thread.

    python benches/bench_threads.py [--width 1024] [--images 8] [--threads 1 2 4] [--json]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import time

import m360
import m360.synthetic as syn
import numpy as np
from _harness import metadata, timing_of
from m360.estimators import SimulatedEstimator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1024, help="ERP width of every image")
    parser.add_argument("--images", type=int, default=8, help="images per timed batch")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", action="store_true", help="print the results as JSON too")
    args = parser.parse_args()

    layout = m360.geometry.default_layout(args.width)
    scene = syn.room(2)
    rng = np.random.default_rng(0)
    h, w = layout.erp_shape
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(args.images)]
    estimators = [SimulatedEstimator(scene, layout, seed=i, noise=0.01) for i in range(args.images)]

    def one(i: int) -> np.ndarray:
        return m360.estimate(images[i], model=estimators[i]).disparity

    reference = [one(i) for i in range(args.images)]  # also builds the plan: timed runs are warm
    rows = []
    for threads in args.threads:
        runs = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            with concurrent.futures.ThreadPoolExecutor(threads) as pool:
                results = list(pool.map(one, range(args.images)))
            runs.append(time.perf_counter() - t0)
            same = all(
                np.array_equal(a, b, equal_nan=True)
                for a, b in zip(results, reference, strict=True)
            )
            assert same, f"{threads} threads gave results different from one thread"
        stats = timing_of(runs)
        rows.append(
            {
                "threads": threads,
                "images_per_second": args.images / stats.median,
                "median": stats.median,
                "iqr": stats.iqr,
            }
        )

    base = rows[0]["images_per_second"]
    print(f"m360.estimate throughput, {args.images} images at {w}x{h}, simulated network")
    print(f"core threads {m360.get_num_threads()}, cpus {os.cpu_count()}; {metadata()}")
    print("| Python threads | images/s (median) | batch s (median) | IQR s | vs 1st row |")
    print("| --- | --- | --- | --- | --- |")
    for row in rows:
        print(
            f"| {row['threads']} | {row['images_per_second']:.2f} | {row['median']:.2f} "
            f"| {row['iqr']:.2f} | {row['images_per_second'] / base:.2f}x |"
        )
    if args.json:
        print(json.dumps(rows))


if __name__ == "__main__":
    main()
