"""End-to-end m360.estimate per stage at 2K / 4K with a MiDaS-small-sized ONNX graph.

The network is a random-weight CNN (tests/onnx_graphs.py ``conv_net``): a stride-2 3x3 stem to
32 channels, ``--layers`` 3x3 conv + ReLU blocks at half resolution, a 1x1 head and a bilinear
x2 upsample, on a fixed 256x256 input like MiDaS v2.1 small. Random weights do not change the
time of a dense graph. It is sized by measurement, not by architecture: the number of blocks
was raised until one 256² tile took about 50 ms on this 2-core machine (the issue's stand-in for
MiDaS v2.1 small on CPU); 9 blocks ≈ 2.7 GFLOP per tile. The tables print the measured ms per
tile so the sizing can be checked on any machine (``--layers`` changes it).

Tables:
1. per stage (project, network, convert, align, blend, total) at each ERP size, and the share of
   everything except the network (target ≤ 25 % at 2K), for each blend of ``--blends``:
   by default m360.estimate's default ``blend="poisson"`` (read from its signature and labelled
   "(default)") and ``blend="frustum"`` (the issue's setting, the fast seam-free blend), both
   with the default ``align="multiscale"``.
2. the network stage alone: one tangent at a time vs all 20 in one batch, threads 1 vs 2, with
   the peak RSS of a fresh interpreter doing only that: its own high-water mark (VmHWM, not
   inherited from this process), absolute and above its baseline after the imports.

Run: ``.venv/bin/python benches/bench_estimate.py [--sizes 2048 4096] [--repeats 3]``.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import _harness as h
import m360
import onnx_graphs
from m360.estimators import OnnxEstimator

STAGES = ("project", "network", "convert", "align", "blend", "total")
#: m360.estimate's own defaults, read from the options it builds (so the labels cannot drift).
DEFAULT_ALIGN = "multiscale"  # StitchOptions' align: the energy's schedule
DEFAULT_BLEND = m360.StitchOptions().method  # what blend=None selects


def conv_flops(size: int, width: int, layers: int) -> float:
    """Multiply-adds x 2 of conv_net on one size² tile."""
    half = (size // 2) ** 2
    return 2.0 * half * (3 * width * 9 + layers * width * width * 9 + width)


def panorama(width: int) -> np.ndarray:
    rgb, _ = m360.synthetic.render(m360.synthetic.room(0), 1024)
    return cv2.resize(rgb, (width, width // 2), interpolation=cv2.INTER_LINEAR)


def label(value: str, default: str) -> str:
    return f"{value} (default)" if value == default else value


def stage_table(
    model: Path, sizes: list[int], repeats: int, threads: int, blends: list[str]
) -> list[dict]:
    align = DEFAULT_ALIGN
    rows = []
    for width in sizes:
        rgb = panorama(width)
        est = OnnxEstimator(model, threads=threads, mean=(0.5,) * 3, std=(0.25,) * 3)
        for blend in blends:
            m360.estimate(rgb, est, align=align, blend=blend)  # warm-up: plans, session
            runs = [
                m360.estimate(rgb, est, align=align, blend=blend).timings for _ in range(repeats)
            ]
            med = {s: statistics.median(r[s] for r in runs) for s in STAGES}
            iqr = h.timing_of([r["total"] for r in runs]).iqr
            work = med["total"] - statistics.median(r["load"] for r in runs)
            share = (work - med["network"]) / work
            rows.append(
                {"width": width, "align_mode": align, "blend_mode": blend, **med,
                 "total_iqr": iqr, "non_network": share}
            )  # fmt: skip
    return rows


def network_table(model: Path, repeats: int) -> list[dict]:
    tiles = m360.erp_to_tangents(panorama(2048), m360.Layout.icosahedron(2048, padding=0.3))
    rows = []
    for threads in (1, 2):
        for batch in (1, 20):
            est = OnnxEstimator(model, threads=threads, batch_size=batch)
            t = h.measure(lambda est=est: est.predict(tiles), repeats=repeats, warmup=1)
            code = (
                f"est = OnnxEstimator({str(model)!r}, threads={threads}, batch_size={batch})\n"
                "est.predict(np.zeros((20, 346, 400, 3), np.uint8))\n"
            )
            setup = "import numpy as np, onnxruntime\nfrom m360.estimators import OnnxEstimator\n"
            rss = h.fresh_process_rss(code, setup=setup, timeout=600)
            per_tile = t.median / 20 * 1e3
            rows.append(
                {"threads": threads, "batch": batch, "timing": t, "per_tile_ms": per_tile,
                 "rss": rss}
            )  # fmt: skip
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(sizes=[2048, 4096], repeats=3)
    parser.add_argument("--layers", type=int, default=9, help="conv blocks of the stand-in")
    parser.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (table 1)")
    parser.add_argument(
        "--blends",
        nargs="+",
        default=[DEFAULT_BLEND, "frustum"],
        help=f"blends of table 1 (default: {DEFAULT_BLEND}, m360.estimate's default, and frustum)",
    )
    args = parser.parse_args()
    meta = h.metadata()
    with tempfile.TemporaryDirectory() as tmp:
        model = onnx_graphs.conv_net(Path(tmp) / "midas_small_sized.onnx", size=256,
                                     width=32, layers=args.layers)  # fmt: skip
        gflop = conv_flops(256, 32, args.layers) / 1e9
        print(f"stand-in network: random-weight CNN, {args.layers} blocks, {gflop:.2f} GFLOP/tile")
        stages = stage_table(model, args.sizes, args.repeats, args.threads, args.blends)
        h.print_table(
            f"m360.estimate per stage, median of {args.repeats} (s), threads={args.threads}; "
            f"(default) = m360.estimate's default",
            ["ERP", "align", "blend", *STAGES, "total IQR", "non-network share"],
            [
                [f"{r['width']}x{r['width'] // 2}", label(r["align_mode"], DEFAULT_ALIGN),
                 label(r["blend_mode"], DEFAULT_BLEND), *(r[s] for s in STAGES), r["total_iqr"],
                 f"{100 * r['non_network']:.1f} %"]
                for r in stages
            ],
        )  # fmt: skip
        nets = network_table(model, args.repeats)
    single = {r["threads"]: r["timing"].median for r in nets if r["batch"] == 1}
    h.print_table(
        f"network stage, 20 tangents of 400x346 -> 256x256, median of {args.repeats}; peak RSS "
        "of a fresh interpreter creating the session and predicting once, baseline = its peak "
        "after importing numpy, onnxruntime and m360.estimate",
        ["threads", "tangents per call", "median s", "IQR s", "ms/tile", "vs 1 at a time",
         "peak MB", "peak - baseline MB", "baseline MB"],
        [
            [r["threads"], r["batch"], r["timing"].median, r["timing"].iqr, r["per_tile_ms"],
             f"{single[r['threads']] / r['timing'].median:.2f}x", r["rss"].peak_mb,
             r["rss"].delta_mb, r["rss"].baseline_mb]
            for r in nets
        ],
    )  # fmt: skip
    print(f"\n{meta['cpu_model']}, {meta['cpu_count']} cores, commit {meta['git_commit']}")
    if args.json:
        h.write_json(args.json, [*stages, *nets], meta)


if __name__ == "__main__":
    main()
