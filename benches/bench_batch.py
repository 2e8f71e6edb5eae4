"""Batch throughput at 2K (images per hour) and the overhead of the batch machinery.

The network is the MiDaS-small-sized stand-in of bench_estimate.py (tests/onnx_graphs.py
``conv_net``, random weights, fixed 256x256 input), made as slow as MiDaS v2.1 small: about
1.1 s for the 20 tangents of a 2K panorama, one at a time, on a 2-core machine without GPU. That
1.1 s is a measurement made before m360's core was written, when the authors' reference
implementation (manurare/360monodepth) was studied and each stage prototyped on such a machine
with a MiDaS-small-class network at 256x256; it is listed in docs/reference-pitfalls.md,
"Reference timings and floors". ``--layers 33`` was chosen by measurement to take about that long
here; table 3 prints the stand-in's measured network seconds per image, so the sizing can be
checked on any machine.
Panoramas are synthetic 2048x1024 JPEGs (quality 95).

Tables:
1. ``m360.batch.run`` on ``--images`` panoramas into a fresh folder, ``workers`` 1 and 2 (threads
   split between them: 1 worker x 2 threads, 2 workers x 1 thread), blends frustum and poisson:
   wall time and images per hour (median of ``--repeats``).
2. Overhead of the machinery (job collection, locks, resume checks, input sha256, sidecar,
   progress bookkeeping) against the same work written as a plain loop, workers = 1, same
   threads: ``load_image`` + ``m360.estimate`` (+ ``m360.save``) per image. Runs are interleaved
   so machine noise hits both alike, but on this shared machine identical runs still differ by
   ±10 %, so:
3. the machinery's share measured inside each ``workers=1`` run: wall time minus the time spent
   in the per-image stages (read, m360.estimate's stages, write), which are the loop's work.
   Target ≤ 3 %.

With ``--engine ray`` (needs ``m360[ray]``) it measures the Ray engine instead, against the local
engine in the same process, runs interleaved:

4. images per hour, local engine (1 worker x 2 threads; 2 workers x 1 thread) vs Ray engine on a
   local Ray of 2 CPUs (one model actor of 1 CPU, align + blend tasks of 1 CPU), median of
   ``--repeats``; each Ray run includes starting its model actor (Ray itself is started once,
   its start-up is printed apart).
5. seconds per image and stage in the Ray runs (one thread each: the costs an N-node estimate
   starts from; docs/architecture.md, "The Ray engine").
6. the engines' ceiling: tiny 128x64 panoramas with a tiny network, so that nearly all the time
   is the engine's own (scheduling, claims, sidecars): images per second of each engine, and
   the Ray driver's own CPU time per image (what bounds one driver however big the cluster).

Run: ``.venv/bin/python benches/bench_batch.py [--images 8] [--repeats 3] [--layers 33]
[--engine ray]``.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import _harness as h
import m360
import onnx_graphs
from m360.estimators import OnnxEstimator


def make_panoramas(folder: Path, count: int, width: int) -> list[Path]:
    rgb, _ = m360.synthetic.render(m360.synthetic.room(0), 1024)
    base = cv2.resize(rgb, (width, width // 2), interpolation=cv2.INTER_LINEAR)
    paths = []
    for k in range(count):
        path = folder / f"pano_{k:03d}.jpg"
        image = np.roll(base, 97 * k, axis=1)[:, :, ::-1]
        cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        paths.append(path)
    return paths


#: Per run of workers=1: (wall seconds, seconds inside the per-image stages read ... write,
#: median network seconds per image).
IN_RUN: dict[str, list[tuple[float, float, float]]] = {}


def batch_seconds(inputs: Path, out: Path, model: Path, blend: str, workers: int) -> float:
    start = time.perf_counter()
    report = m360.batch.run(
        inputs, out, model=str(model), blend=blend, workers=workers,
        threads=max(1, 2 // workers), progress=False,
    )  # fmt: skip
    if report.exit_code != 0:
        raise RuntimeError(report.summary())
    wall = time.perf_counter() - start
    if workers == 1:
        stages = sum(sum(o.timings.values()) for o in report.done)
        network = statistics.median(o.timings["network"] for o in report.done)
        IN_RUN.setdefault(blend, []).append((wall, stages, network))
    return wall


def loop_seconds(paths: list[Path], out: Path, model: Path, blend: str, save: bool) -> float:
    start = time.perf_counter()
    estimator = OnnxEstimator(model, threads=2)
    for path in paths:
        result = m360.estimate(m360.io.load_image(path), estimator, blend=blend)
        if save:
            m360.save(result, out / path.stem)
    return time.perf_counter() - start


def engine_run(
    inputs: Path, out: Path, model: Path | str, engine: str, workers: int, **options: object
) -> m360.batch.BatchReport:
    threads = None if engine == "ray" else max(1, 2 // workers)
    report = m360.batch.run(
        inputs, out, model=str(model), engine=engine, workers=workers, threads=threads,
        progress=False, **options,  # type: ignore[arg-type]
    )  # fmt: skip
    if report.exit_code != 0:
        raise RuntimeError(report.summary())
    return report


def ray_tables(args: object, tmp: Path, model: Path, meta: dict) -> list[dict]:
    import ray

    started = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    startup = time.perf_counter() - started
    images: int = args.images  # type: ignore[attr-defined]
    repeats: int = args.repeats  # type: ignore[attr-defined]
    setups = [("local", 1), ("local", 2), ("ray", 1)]
    runs = 0

    def fresh() -> Path:
        nonlocal runs
        runs += 1
        return tmp / f"ray_out{runs}"

    walls: dict[tuple[str, int], list[float]] = {s: [] for s in setups}
    stages: list[dict[str, float]] = []
    engine_run(tmp / "in", fresh(), model, "ray", 1)  # warm the workers' imports
    for _ in range(repeats):  # interleaved
        for engine, workers in setups:
            start = time.perf_counter()
            report = engine_run(tmp / "in", fresh(), model, engine, workers)
            walls[(engine, workers)].append(time.perf_counter() - start)
            if engine == "ray":
                stages.append({k: v / images for k, v in report.stage_seconds().items()})
    rows = [
        {"engine": e, "workers": w, "seconds": statistics.median(walls[(e, w)]),
         "per_hour": images / statistics.median(walls[(e, w)]) * 3600, "runs": walls[(e, w)]}
        for e, w in setups
    ]  # fmt: skip
    h.print_table(
        f"local engine vs Ray engine, {images} panoramas {args.width}x{args.width // 2}, "  # type: ignore[attr-defined]
        f"poisson, median of {repeats} (Ray start-up {startup:.1f} s, not included)",
        ["engine", "setup", "seconds", "s/image", "images/hour", "vs local 1x2"],
        [
            [r["engine"], "1 model actor (1 CPU) + tasks (1 CPU)" if r["engine"] == "ray"
             else f"{r['workers']} x {max(1, 2 // r['workers'])}", r["seconds"],
             r["seconds"] / images, f"{r['per_hour']:.0f}",
             f"{100 * (rows[0]['seconds'] / r['seconds'] - 1):+.1f} %"]
            for r in rows
        ],
    )  # fmt: skip
    per_stage = {k: statistics.median(s[k] for s in stages) for k in stages[0]}
    cpu = sum(v for k, v in per_stage.items() if k != "network")
    h.print_table(
        "Ray engine: seconds per image and stage (1 thread each), median over the Ray runs",
        [*per_stage, "CPU stages"],
        [[*per_stage.values(), cpu]],
    )
    # The driver's ceiling: everything but the engine made nearly free.
    tiny_model = onnx_graphs.affine_of_mean(tmp / "tiny.onnx", 1.0, 0.1)
    tiny_in = tmp / "tiny_in"
    tiny_in.mkdir()
    rgb, _ = m360.synthetic.render(m360.synthetic.room(1), 128)
    for k in range(args.tiny):  # type: ignore[attr-defined]
        cv2.imwrite(str(tiny_in / f"t{k:04d}.png"), np.roll(rgb, k, axis=1)[:, :, ::-1])
    tiny = {"align": "none", "blend": "frustum", "input_size": (64, 96)}
    ceiling: dict[str, list[float]] = {"local": [], "ray": []}
    driver_ms: list[float] = []  # CPU time of this process (the Ray driver) per image
    for _ in range(repeats):
        for engine in ceiling:
            start, cpu = time.perf_counter(), time.process_time()
            engine_run(tiny_in, fresh(), tiny_model, engine, 1, **tiny)
            ceiling[engine].append(args.tiny / (time.perf_counter() - start))  # type: ignore[attr-defined]
            if engine == "ray":
                driver_ms.append((time.process_time() - cpu) * 1000 / args.tiny)  # type: ignore[attr-defined]
    h.print_table(
        f"engine ceiling: {args.tiny} tiny 128x64 panoramas, tiny network, median of {repeats}",  # type: ignore[attr-defined]
        ["engine", "images/s", "ms/image", "driver CPU ms/image"],
        [
            [e, statistics.median(v), 1000 / statistics.median(v),
             statistics.median(driver_ms) if e == "ray" else "-"]
            for e, v in ceiling.items()
        ],
    )  # fmt: skip
    ray.shutdown()
    summary = {"ray_stage_seconds_per_image": per_stage, "ray_startup_s": startup,
               "ceiling_images_per_s": ceiling, "driver_cpu_ms_per_image": driver_ms}  # fmt: skip
    return [*rows, summary]


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=8, help="panoramas per run")
    parser.add_argument("--width", type=int, default=2048, help="ERP width")
    parser.add_argument("--layers", type=int, default=33, help="conv blocks of the stand-in")
    parser.add_argument(
        "--engine", choices=("local", "ray"), default="local", help="ray: tables 4-6 instead"
    )
    parser.add_argument("--tiny", type=int, default=200, help="tiny panoramas of table 6")
    parser.set_defaults(repeats=3)
    args = parser.parse_args()
    meta = h.metadata()
    if args.engine == "ray":
        with tempfile.TemporaryDirectory() as tmp_name:
            tmp = Path(tmp_name)
            model = onnx_graphs.conv_net(tmp / "midas_small_sized.onnx", size=256, width=32,
                                         layers=args.layers)  # fmt: skip
            (tmp / "in").mkdir()
            make_panoramas(tmp / "in", args.images, args.width)
            rows = ray_tables(args, tmp, model, meta)
        print(f"\n{meta['cpu_model']}, {meta['cpu_count']} cores, commit {meta['git_commit']}")
        if args.json:
            h.write_json(args.json, rows, meta)
        return
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        model = onnx_graphs.conv_net(tmp / "midas_small_sized.onnx", size=256, width=32,
                                     layers=args.layers)  # fmt: skip
        (tmp / "in").mkdir()
        paths = make_panoramas(tmp / "in", args.images, args.width)
        m360.batch.run(paths[:1], tmp / "warm", model=str(model), progress=False)  # warm caches
        runs = 0

        def fresh() -> Path:
            nonlocal runs
            runs += 1
            return tmp / f"out{runs}"

        throughput = []
        for blend in ("frustum", "poisson"):
            for workers in (1, 2):
                times = [
                    batch_seconds(tmp / "in", fresh(), model, blend, workers)
                    for _ in range(args.repeats)
                ]
                med = statistics.median(times)
                row = {"blend": blend, "workers": workers, "seconds": med,
                       "per_hour": args.images / med * 3600, "runs": times}  # fmt: skip
                throughput.append(row)
        h.print_table(
            f"m360.batch.run, {args.images} panoramas {args.width}x{args.width // 2}, "
            f"median of {args.repeats}",
            ["blend", "workers x threads", "seconds", "s/image", "images/hour"],
            [
                [r["blend"], f"{r['workers']} x {max(1, 2 // r['workers'])}", r["seconds"],
                 r["seconds"] / args.images, f"{r['per_hour']:.0f}"]
                for r in throughput
            ],
        )  # fmt: skip

        overhead = []
        for blend in ("frustum", "poisson"):
            timing: dict[str, list[float]] = {"loop": [], "loop+save": [], "batch": []}
            for _ in range(args.repeats):  # interleaved
                timing["loop"].append(loop_seconds(paths, fresh(), model, blend, save=False))
                timing["loop+save"].append(loop_seconds(paths, fresh(), model, blend, save=True))
                timing["batch"].append(batch_seconds(tmp / "in", fresh(), model, blend, 1))
            med = {k: statistics.median(v) for k, v in timing.items()}
            overhead.append({"blend": blend, **med, "runs": timing})
        h.print_table(
            f"batch machinery overhead, workers=1, 2 threads, median of {args.repeats} (s)",
            ["blend", "loop: load+estimate", "loop + save", "batch.run", "vs loop", "vs loop+save"],
            [
                [r["blend"], r["loop"], r["loop+save"], r["batch"],
                 f"{100 * (r['batch'] / r['loop'] - 1):+.1f} %",
                 f"{100 * (r['batch'] / r['loop+save'] - 1):+.1f} %"]
                for r in overhead
            ],
        )  # fmt: skip
        # The same question without cross-run noise: inside each workers=1 run, the time spent
        # outside the per-image stages (read, estimate's stages, write) is the machinery's.
        h.print_table(
            "batch machinery inside each workers=1 run: wall - sum of per-image stages",
            ["blend", "runs", "median wall s", "median machinery s", "median share",
             "network s/image"],
            [
                [blend, len(runs), statistics.median(w for w, _, _ in runs),
                 statistics.median(w - s for w, s, _ in runs),
                 f"{100 * statistics.median((w - s) / w for w, s, _ in runs):.2f} %",
                 statistics.median(n for _, _, n in runs)]
                for blend, runs in IN_RUN.items()
            ],
        )  # fmt: skip
        rows = [*throughput, *overhead]
    print(f"\n{meta['cpu_model']}, {meta['cpu_count']} cores, commit {meta['git_commit']}")
    if args.json:
        h.write_json(args.json, rows, meta)


if __name__ == "__main__":
    main()
