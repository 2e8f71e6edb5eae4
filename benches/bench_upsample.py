"""Upsampling a working-resolution disparity to a 72 MP photo: the former whole-array fit against
the core's fused fit + sweep, first call and warm calls, and the upsample stage of m360.estimate.

``guided_upsample(disparity, rgb)`` with a 4096 x 2048 disparity (1 / depth of a synthetic room)
and an 11904 x 5952 photo (a 2048-wide render of the same room, resized), methods ``guided``
and ``bilinear``. ``old`` is the implementation before the fit moved into the core, kept below:
whole-array numpy/OpenCV passes at the working resolution (box filters, edge weight, the
plane stack) and then the core's full-resolution pass (``_core.upsample_planes``, unchanged);
``new`` is ``m360.upsample.guided_upsample`` (``_core.guided_upsample`` /
``_core.bilinear_upsample``).

Each (implementation, method) runs in a fresh interpreter: the first call there pays for fresh
memory (the VM's first touch of a page is slow), then ``--repeats`` warm calls (median). The
configurations alternate over ``--rounds`` rounds; the table gives the medians over rounds of
the first call and of the warm medians. With ``--estimate``: ``m360.estimate`` on the 72 MP
photo with ``working_width=4096`` (held-out-style tangents instead of a network, as in
bench_bigpano.py), old and new upsampling (the old one patched into ``m360.estimate``), its
stage timings of the first call and the warm median of the upsample stage.

Run: ``.venv/bin/python benches/bench_upsample.py [--rounds 3] [--repeats 5] [--estimate]
[--data DIR]`` (inputs are rendered once into DIR, about a minute).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
from guided_reference import old_guided_upsample  # the former whole-array fit

WIDTH, WORK = 11904, 4096
STAGES = ("load", "project", "network", "convert", "align", "blend", "upsample")

# --------------------------------------------------------------------------------------------
# Children.


def child_upsample(data: Path, impl: str, method: str, repeats: int) -> dict[str, Any]:
    """First and warm calls of one implementation and method in this (fresh) process."""
    from m360.upsample import guided_upsample

    run = guided_upsample if impl == "new" else old_guided_upsample
    rgb = np.load(data / "rgb.npy")
    disparity = np.load(data / "disparity.npy")
    t0 = time.perf_counter()
    out = run(disparity, rgb, method=method)
    first = time.perf_counter() - t0
    del out
    warm = []
    for _ in range(repeats):
        t1 = time.perf_counter()
        out = run(disparity, rgb, method=method)
        warm.append(time.perf_counter() - t1)
        del out
    return {"first": first, "warm": statistics.median(warm)}


def child_estimate(data: Path, impl: str, repeats: int) -> dict[str, Any]:
    """``m360.estimate`` at 72 MP, working width 4096, in this (fresh) process."""
    import bench_bigpano
    import m360

    if impl == "old":  # m360.estimate is also the name of the function: patch the module
        sys.modules["m360.estimate"].guided_upsample = old_guided_upsample  # type: ignore[attr-defined]
    rgb = np.load(data / "rgb.npy")
    est = bench_bigpano.HeldOut(np.load(data / "tangents.npy"))
    res = m360.estimate(rgb, est, working_width=WORK)
    first = {k: res.timings.get(k, 0.0) for k in (*STAGES, "total")}
    warm = [m360.estimate(rgb, est, working_width=WORK).timings for _ in range(repeats)]
    return {
        "first": first,
        "warm": {k: statistics.median(t.get(k, 0.0) for t in warm) for k in (*STAGES, "total")},
    }


def run_child(args: list[str]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as home:
        proc = subprocess.run(
            [sys.executable, __file__, "--child", *args],
            capture_output=True, text=True, timeout=3600,
            env={**os.environ, "M360_HOME": home},
        )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"{args} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def inputs(data: Path) -> None:
    """The photo, the working disparity and held-out tangents (rendered once)."""
    if (data / "tangents.npy").exists():
        return
    import bench_bigpano
    import m360.synthetic as syn

    scene = syn.room(0)
    small, _ = syn.render(scene, 2048)
    np.save(data / "rgb.npy", cv2.resize(small, (WIDTH, WIDTH // 2)))
    _, depth = syn.render(scene, WORK)
    np.save(data / "disparity.npy", (1.0 / depth).astype(np.float32))
    layout = bench_bigpano._default_layout(1024)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    np.save(data / "tangents.npy", syn.distort(exact, 100, field=0.1, noise=0.01))


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        kind, data, impl = sys.argv[2:5]
        if kind == "estimate":
            out = child_estimate(Path(data), impl, int(sys.argv[5]))
        else:
            out = child_upsample(Path(data), impl, kind, int(sys.argv[5]))
        print(json.dumps(out))
        return
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=5)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--estimate", action="store_true", help="m360.estimate at 72 MP too")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "m360-bench-up")
    args = parser.parse_args()
    args.data.mkdir(parents=True, exist_ok=True)
    inputs(args.data)
    results: dict[str, Any] = {}
    rows = []
    for method in ("guided", "bilinear"):
        runs: dict[str, list[dict[str, Any]]] = {"old": [], "new": []}
        for _ in range(args.rounds):
            for impl in ("old", "new"):
                runs[impl].append(run_child([method, str(args.data), impl, str(args.repeats)]))
        for impl in ("old", "new"):
            first = statistics.median(r["first"] for r in runs[impl])
            warm = statistics.median(r["warm"] for r in runs[impl])
            rows.append([method, impl, round(first, 3), round(warm, 3)])
        results[method] = runs
    h.print_table(
        f"guided_upsample {WORK} -> {WIDTH} (s; medians over {args.rounds} fresh processes)",
        ["method", "impl", "first call", "warm (median)"],
        rows,
    )
    if args.estimate:
        est_runs: dict[str, list[dict[str, Any]]] = {"old": [], "new": []}
        for _ in range(args.rounds):
            for impl in ("old", "new"):
                est_runs[impl].append(
                    run_child(["estimate", str(args.data), impl, str(args.repeats)])
                )
        rows = []
        for impl in ("old", "new"):
            for when in ("first", "warm"):
                med = {
                    k: statistics.median(r[when][k] for r in est_runs[impl])
                    for k in (*STAGES, "total")
                }
                rows.append([impl, when] + [round(med[k], 3) for k in (*STAGES, "total")])
        h.print_table(
            f"m360.estimate {WIDTH} with working_width={WORK} (s; medians)",
            ["upsample", "call", *STAGES, "total"],
            rows,
        )
        results["estimate"] = est_runs
    if args.json:
        h.write_json(args.json, [results], {**h.metadata(), "args": vars(args)})


if __name__ == "__main__":
    main()
