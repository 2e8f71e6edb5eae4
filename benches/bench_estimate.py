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
   everything except the network (target ≤ 25 % at 2K). Stitching uses the default
   ``align="multiscale"`` and ``blend="frustum"`` (the issue's setting).
2. the network stage alone: one tangent at a time vs all 20 in one batch, threads 1 vs 2, with
   the peak RSS of a fresh interpreter doing only that.

Run: ``.venv/bin/python benches/bench_estimate.py [--sizes 2048 4096] [--repeats 3]``.
"""

from __future__ import annotations

import statistics
import subprocess
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
from m360.estimate import OnnxEstimator
from m360.stitch import ALIGN_MODES, BLEND_MODES

STAGES = ("project", "network", "convert", "align", "blend", "total")


def conv_flops(size: int, width: int, layers: int) -> float:
    """Multiply-adds x 2 of conv_net on one size² tile."""
    half = (size // 2) ** 2
    return 2.0 * half * (3 * width * 9 + layers * width * width * 9 + width)


def peak_rss_mb(code: str) -> float:
    """Peak RSS (VmHWM) of a fresh interpreter running ``code``, in MB.

    Read from /proc/self/status in the child: unlike ``ru_maxrss`` it is not inherited from the
    parent across fork + exec, so a large benchmark process does not inflate it.
    """
    wrapper = (
        code + "\nimport re\n"
        "print('VmHWM', re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())[1])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", wrapper], capture_output=True, text=True, timeout=600, check=True
    )
    return int(out.stdout.split("VmHWM")[-1]) / 1024


def panorama(width: int) -> np.ndarray:
    rgb, _ = m360.synthetic.render(m360.synthetic.room(0), 1024)
    return cv2.resize(rgb, (width, width // 2), interpolation=cv2.INTER_LINEAR)


def stage_table(model: Path, sizes: list[int], repeats: int, threads: int) -> list[dict]:
    align = "multiscale" if "multiscale" in ALIGN_MODES else "none"
    blend = "frustum" if "frustum" in BLEND_MODES else "mean"
    rows = []
    for width in sizes:
        rgb = panorama(width)
        est = OnnxEstimator(model, threads=threads, mean=(0.5,) * 3, std=(0.25,) * 3)
        m360.estimate(rgb, est, align=align, blend=blend)  # warm-up: plans, session
        runs = [m360.estimate(rgb, est, align=align, blend=blend).timings for _ in range(repeats)]
        med = {s: statistics.median(r[s] for r in runs) for s in STAGES}
        work = med["total"] - statistics.median(r["load"] for r in runs)
        share = (work - med["network"]) / work
        rows.append(
            {"width": width, "align_mode": align, "blend_mode": blend, **med, "non_network": share}
        )
    return rows


def network_table(model: Path, repeats: int) -> list[dict]:
    tiles = m360.erp_to_tangents(panorama(2048), m360.Layout.icosahedron(2048))
    rows = []
    for threads in (1, 2):
        for batch in (1, 20):
            est = OnnxEstimator(model, threads=threads, batch_size=batch)
            t = h.measure(lambda est=est: est.predict(tiles), repeats=repeats, warmup=1)
            code = (
                "import numpy as np\n"
                "from m360.estimate import OnnxEstimator\n"
                f"est = OnnxEstimator({str(model)!r}, threads={threads}, batch_size={batch})\n"
                "est.predict(np.zeros((20, 346, 400, 3), np.uint8))\n"
            )
            rss = peak_rss_mb(code)
            per_tile = t.median / 20 * 1e3
            rows.append(
                {"threads": threads, "batch": batch, "timing": t, "per_tile_ms": per_tile,
                 "peak_rss_mb": rss}
            )  # fmt: skip
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(sizes=[2048, 4096], repeats=3)
    parser.add_argument("--layers", type=int, default=9, help="conv blocks of the stand-in")
    parser.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (table 1)")
    args = parser.parse_args()
    meta = h.metadata()
    with tempfile.TemporaryDirectory() as tmp:
        model = onnx_graphs.conv_net(Path(tmp) / "midas_small_sized.onnx", size=256,
                                     width=32, layers=args.layers)  # fmt: skip
        gflop = conv_flops(256, 32, args.layers) / 1e9
        print(f"stand-in network: random-weight CNN, {args.layers} blocks, {gflop:.2f} GFLOP/tile")
        stages = stage_table(model, args.sizes, args.repeats, args.threads)
        h.print_table(
            f"m360.estimate per stage, median of {args.repeats} (s), threads={args.threads}",
            ["ERP", "align", "blend", *STAGES, "non-network share"],
            [
                [f"{r['width']}x{r['width'] // 2}", r["align_mode"], r["blend_mode"],
                 *(r[s] for s in STAGES), f"{100 * r['non_network']:.1f} %"]
                for r in stages
            ],
        )  # fmt: skip
        nets = network_table(model, args.repeats)
    single = {r["threads"]: r["timing"].median for r in nets if r["batch"] == 1}
    h.print_table(
        f"network stage, 20 tangents of 400x346 -> 256x256, median of {args.repeats}",
        ["threads", "tangents per call", "median s", "IQR s", "ms/tile", "vs 1 at a time",
         "peak RSS MB"],
        [
            [r["threads"], r["batch"], r["timing"].median, r["timing"].iqr, r["per_tile_ms"],
             f"{single[r['threads']] / r['timing'].median:.2f}x", r["peak_rss_mb"]]
            for r in nets
        ],
    )  # fmt: skip
    print(f"\n{meta['cpu_model']}, {meta['cpu_count']} cores, commit {meta['git_commit']}")
    if args.json:
        h.write_json(args.json, [*stages, *nets], meta)


if __name__ == "__main__":
    main()
