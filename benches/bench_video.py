"""360° video: flicker, accuracy and throughput of ``m360.video.run`` against per-frame stills.

The sequence is synthetic (:func:`m360.evaluation.sequence.walk`): a camera walking at
0.6 m/s through a ray-cast room, 30 fps, exact depth and motion per frame, encoded to an
H.264 MP4 (CRF 12) that every run decodes. The network is the simulated one of the sequence
(:class:`m360.evaluation.sequence.SequenceEstimator`): exact tangent disparity with content
errors and a per-tangent affine ambiguity drawn anew for every frame; it recognises each
decoded frame by a thumbnail (checked: every frame is recognised as itself).

Tables:
1. Quality over the whole sequence, ``temporal="none"`` (today's still pipeline, frame by
   frame) against ``"smooth"``: flicker (median over consecutive pairs of the median
   |predicted relative depth change − true change| at points seen in both frames, after
   motion compensation with the true camera motion: :func:`m360.evaluation.sequence.flicker`);
   the same after fitting each frame's global depth scale to the truth (what is left when the
   gauge jumps are forgiven); AbsRel per frame (mean; the paper's scale-and-shift-fitted
   metric). Goals: flicker ≤ 1/3 of per-frame, AbsRel ≤ per-frame + 0.002.
2. Throughput on the first ``--throughput-frames`` frames, runs interleaved, median of
   ``--repeats``: a loop of ``m360.estimate`` over the decoded frames (``m360.video.frames``),
   with and without ``m360.save`` of each result, against ``m360.video.run`` (npy, no
   previews) with ``temporal="none"`` and ``"smooth"``, the latter with each ``frame_batch``
   of ``--frame-batches`` (frames whose tangents go to the network in one call). Goal:
   ``video.run`` / loop with save ≥ 1.0. ``--model FILE.onnx`` (with ``--output-kind``) times
   that network instead of the simulated one, whose outputs are cached (a network of no cost:
   what is left is m360's own work).

Run: ``.venv/bin/python benches/bench_video.py [--width 1024] [--frames 60] [--repeats 3]``
(``--width 2048`` is the issue's size; about 4 s a frame on 2 cores); ``--no-quality`` runs
table 2 alone (``--frames 16 --throughput-frames 16 --no-quality``: a few minutes).
"""

from __future__ import annotations

import argparse
import fractions
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import m360
from _harness import metadata, print_table, write_json
from m360.evaluation import sequence as sq
from m360.evaluation.metrics import depth_metrics
from m360.geometry import default_layout


def encode(frames: list[np.ndarray], path: Path, fps: float) -> Path:
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fractions.Fraction(fps).limit_denominator())
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "12"}
        for rgb in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def quality(out: Path, truth: list[np.ndarray], positions: np.ndarray) -> dict[str, float]:
    disparities = [np.load(out / f"{k:06d}.disparity.npy") for k in range(len(truth))]
    with np.errstate(divide="ignore", invalid="ignore"):
        depths = [np.where(d > 0, 1 / d, np.nan) for d in disparities]
    scaled = [d * np.nanmedian(t / d) for d, t in zip(depths, truth, strict=True)]
    absrel = [depth_metrics(d, t)["abs_rel"] for d, t in zip(disparities, truth, strict=True)]
    return {
        "flicker": float(np.nanmedian(sq.flicker(depths, truth, positions))),
        "flicker_scaled": float(np.nanmedian(sq.flicker(scaled, truth, positions))),
        "abs_rel": float(np.mean(absrel)),
        "abs_rel_worst": float(np.max(absrel)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1024, help="ERP width (default 1024)")
    parser.add_argument("--frames", type=int, default=60, help="frames (default 60)")
    parser.add_argument("--seed", type=int, default=2, help="room and error seed (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="throughput repeats (default 3)")
    parser.add_argument("--throughput-frames", type=int, default=20, help="(default 20)")
    parser.add_argument(
        "--frame-batches", default="1,2,4", help="video.run frame_batch values (default 1,2,4)"
    )
    parser.add_argument("--no-quality", action="store_true", help="table 2 (throughput) only")
    parser.add_argument(
        "--model", type=Path, default=None, help="an ONNX file timed in table 2 instead"
    )
    parser.add_argument("--output-kind", default=None, help="--model's output kind")
    parser.add_argument("--threads", type=int, default=None, help="--model's threads")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    batches = [int(k) for k in args.frame_batches.split(",")]

    t0 = time.perf_counter()
    walk = sq.walk(args.seed, args.frames, erp_width=args.width)
    rendered = [walk.render(k) for k in range(args.frames)]
    images = [rgb for rgb, _ in rendered]
    truth = [depth for _, depth in rendered]
    layout = default_layout(args.width)
    estimator = sq.SequenceEstimator(walk, layout, images=images)
    work = Path(tempfile.mkdtemp(prefix="bench_video_"))
    clip = encode(images, work / "walk.mp4", walk.fps)
    decoded = list(m360.video.frames(clip))
    assert len(decoded) == args.frames
    for frame in decoded:  # the simulated network knows every decoded frame; outputs cached
        tangents = m360.erp_to_tangents(frame.rgb, layout)
        assert estimator.frame_of(tangents) == frame.index, frame.index
        estimator.predict(tangents)
    print(
        f"{args.frames} frames of {args.width}x{args.width // 2}, moved "
        f"{np.linalg.norm(walk.positions[-1]):.2f} m; prepared in {time.perf_counter() - t0:.0f} s"
    )
    rows = []
    if not args.no_quality:
        quality_table(args, clip, estimator, truth, walk, rows)
    throughput_table(args, clip, estimator, layout, work, batches, rows)
    if args.json is not None:
        write_json(args.json, rows, metadata())
    shutil.rmtree(work, ignore_errors=True)


def quality_table(
    args: argparse.Namespace,
    clip: Path,
    estimator: sq.SequenceEstimator,
    truth: list[np.ndarray],
    walk: sq.Sequence,
    rows: list[dict],
) -> None:
    results = {}
    for mode in ("none", "smooth"):
        out = clip.parent / f"quality_{mode}"
        report = m360.video.run(clip, out, model=estimator, temporal=mode, progress=False)
        assert report.exit_code == 0 and len(report.done) == args.frames, report.summary()
        results[mode] = quality(out, truth, walk.positions)
        rows.append({"table": "quality", "temporal": mode, **results[mode]})
    base, smooth = results["none"], results["smooth"]
    print_table(
        f"1. quality ({args.frames} frames, {args.width} px)",
        ["temporal", "flicker", "flicker (scale fitted)", "AbsRel", "AbsRel worst frame"],
        [
            [mode, r["flicker"], r["flicker_scaled"], r["abs_rel"], r["abs_rel_worst"]]
            for mode, r in results.items()
        ],
    )
    print(
        f"flicker ratio {smooth['flicker'] / base['flicker']:.3f} (goal <= 0.333), scale-fitted "
        f"{smooth['flicker_scaled'] / base['flicker_scaled']:.3f}; AbsRel change "
        f"{smooth['abs_rel'] - base['abs_rel']:+.4f} (goal <= +0.002)"
    )


def throughput_table(
    args: argparse.Namespace,
    clip: Path,
    estimator: object,
    layout: object,
    work: Path,
    batches: list[int],
    rows: list[dict],
) -> None:
    count = min(args.throughput_frames, args.frames)
    network = "simulated (cached)"
    if args.model is not None:
        estimator = m360.estimators.load_estimator(
            args.model, output_kind=args.output_kind, threads=args.threads
        )
        network = f"{args.model.name}, threads {args.threads or 'all'}"

    def loop(save: bool) -> None:
        out = work / "loop"
        shutil.rmtree(out, ignore_errors=True)
        for frame in m360.video.frames(clip, end=count):
            result = m360.estimate(frame.rgb, estimator, layout=layout)
            if save:
                m360.save(result, out / f"{frame.index:06d}", preview=False)

    def video(mode: str, batch: int = 1) -> None:
        out = work / f"video_{mode}_{batch}"
        shutil.rmtree(out, ignore_errors=True)
        report = m360.video.run(
            clip, out, model=estimator, temporal=mode, end=count, progress=False, frame_batch=batch
        )
        assert report.exit_code == 0 and not report.notes, report.summary()

    cases = {
        "loop: estimate": lambda: loop(False),
        "loop: estimate + save": lambda: loop(True),
        "video.run, temporal none": lambda: video("none"),
    }
    for batch in batches:
        cases[f"video.run, temporal smooth, frame_batch {batch}"] = lambda b=batch: video(
            "smooth", b
        )
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeats):  # interleaved: the machine's noise hits every case alike
        for name, case in cases.items():
            start = time.perf_counter()
            case()
            times[name].append(time.perf_counter() - start)
    reference = statistics.median(times["loop: estimate + save"])
    table = []
    for name, runs in times.items():
        median = statistics.median(runs)
        table.append([name, median / count, count / median, reference / median])
        rows.append(
            {"table": "throughput", "case": name, "runs": runs, "frames": count, "net": network}
        )
    print_table(
        f"2. throughput ({count} frames of {args.width} px, network {network}, median of "
        f"{args.repeats}, interleaved)",
        ["case", "s/frame", "frames/s", "vs loop with save"],
        table,
    )


if __name__ == "__main__":
    main()
