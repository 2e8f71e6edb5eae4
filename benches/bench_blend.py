"""Blending speed and memory: every blend mode of ``m360.stitch`` at 2K / 4K / 8K.

Per mode and size: time per image (``stitch(align="none")`` on 20 tangents, median of repeats),
one-time plan cost (first call after clearing the plan cache minus the steady median: taps and
weight maps), Poisson iterations and residual, and peak RSS of a fresh interpreter running one
whole stitch: its own high-water mark (VmHWM on Linux, not inherited from this process), absolute
and above its baseline after importing numpy and m360. Baselines, measured in the same run on
the same inputs:

- frustum: per-face ``cv2.remap`` of values and weights at precomputed footprint positions, then
  ``np.bincount`` weighted sums (the numpy way to do the same blend);
- poisson: ``scipy.sparse.linalg.cg`` with a Jacobi preconditioner on the same system
  (assembled with scipy.sparse from the per-face ERP maps; assembly not timed), same start and
  tolerance; and m360's own Jacobi-preconditioned CG (``solver="fused"``, the default before
  the multigrid preconditioner). scipy is skipped above ``--scipy-max`` (its per-face ERP
  stacks need > 10 GB at 8K).

Run: ``.venv/bin/python benches/bench_blend.py [--sizes 2048 4096 8192] [--repeats 5]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import blend_scipy
import m360
from bench_resample import footprints
from m360.geometry import clear_plan_cache, plan_for

MODES = ("nn", "mean", "radial", "frustum", "poisson")


def tangents(width: int) -> np.ndarray:
    """Realistic tangents: a rendered room's disparity (2K render, resized), sampled onto the
    tangents, with residual per-tangent affine error and a smooth field (as after alignment)."""
    _, depth = m360.synthetic.render(m360.synthetic.room(0), 2048)
    disp = cv2.resize((1.0 / depth).astype(np.float32), (width, width // 2))
    tiles = m360.erp_to_tangents(disp, m360.Layout.icosahedron(width, padding=0.3))
    return m360.synthetic.distort(tiles, 1, scale=(0.97, 1.03), shift=0.02, field=0.02)


def scipy_poisson(layout: m360.Layout, tiles: np.ndarray) -> tuple[h.Timing, int, float]:
    """scipy Jacobi-CG on the Poisson system m360 solves (fidelity: the frustum blend)."""
    plan = plan_for(layout)
    spherical = plan.spherical_disparity(tiles)
    values = plan.tangents_to_erp(spherical)
    weights = plan.tangents_to_erp(plan.blend_weights("frustum"))
    target = plan.blend(spherical, "frustum")[0].astype(np.float64).ravel()
    a_mat, b = blend_scipy.scipy_system(values, weights, target, lam=0.1)
    n = len(b)
    del values, weights
    inv_diag = 1.0 / a_mat.diagonal()
    jacobi = spla.LinearOperator((n, n), matvec=lambda x: inv_diag * x)
    count = [0]

    def run() -> np.ndarray:
        count[0] = 0

        def cb(_: np.ndarray) -> None:
            count[0] += 1

        x, info = spla.cg(a_mat, b, x0=target.copy(), rtol=1e-6, M=jacobi, callback=cb)
        if info != 0:
            raise RuntimeError(f"scipy cg did not converge (info {info})")
        return x

    t = h.measure(run, repeats=2, warmup=0)
    x = run()
    rel = float(np.linalg.norm(a_mat @ x - b) / np.linalg.norm(b))
    return t, count[0], rel


def numpy_frustum(layout: m360.Layout, tiles: np.ndarray) -> h.Timing:
    """cv2.remap of values and frustum weights per face footprint + np.bincount weighted mean."""
    plan = plan_for(layout)
    spherical = plan.spherical_disparity(tiles)
    wmaps = plan.blend_weights("frustum")
    prints = footprints(layout)
    n_pixels = layout.erp_shape[0] * layout.erp_shape[1]
    flat_idx = np.concatenate([i for i, _, _ in prints])
    lin = cv2.INTER_LINEAR

    def run() -> np.ndarray:
        vals, wts = [], []
        for k, (i, x, y) in enumerate(prints):
            vals.append(cv2.remap(spherical[k], x, y, lin).ravel()[: len(i)])
            wts.append(cv2.remap(wmaps[k], x, y, lin).ravel()[: len(i)])
        v, w = np.concatenate(vals), np.concatenate(wts)
        s = np.bincount(flat_idx, weights=w * v, minlength=n_pixels)
        c = np.bincount(flat_idx, weights=w, minlength=n_pixels)
        return (s / c).reshape(layout.erp_shape)

    return h.measure(run, repeats=3)


def bench_size(size: int, repeats: int, scipy_max: int) -> list[list]:
    layout = m360.Layout.icosahedron(size, padding=0.3)
    tiles = tangents(size)
    rows = []
    baselines: dict[str, tuple[h.Timing, int | None, float | None]] = {}
    for mode in MODES:
        clear_plan_cache()
        t0 = time.perf_counter()
        res = m360.stitch(tiles, layout, align="none", blend=mode, return_details=True)
        first = time.perf_counter() - t0
        assert isinstance(res, m360.StitchResult)
        t = h.measure(
            lambda: m360.stitch(tiles, layout, align="none", blend=mode),  # noqa: B023
            repeats=repeats,
            warmup=0,
        )
        rep = res.report["blend"]
        rows.append(
            [
                size,
                mode,
                "m360",
                t.median,
                t.iqr,
                max(first - t.median, 0.0),
                rep.get("iterations", ""),
                rep.get("relative_residual", ""),
            ]
        )
    # The previous default solver (Jacobi-preconditioned CG) on the same inputs.
    jacobi = {"solver": "fused"}
    res = m360.stitch(
        tiles, layout, align="none", blend="poisson", blend_options=jacobi, return_details=True
    )
    assert isinstance(res, m360.StitchResult)
    t = h.measure(
        lambda: m360.stitch(tiles, layout, align="none", blend="poisson", blend_options=jacobi),
        repeats=repeats,
        warmup=0,
    )
    rep = res.report["blend"]
    jacobi_row = [size, "poisson", "m360 Jacobi-CG", t.median, t.iqr, "", rep["iterations"]]
    jacobi_row.append(rep["relative_residual"])
    baselines["frustum"] = (numpy_frustum(layout, tiles), None, None)
    if size <= scipy_max:
        baselines["poisson"] = scipy_poisson(layout, tiles)
    out = []
    for row in rows:
        base = baselines.get(row[1])
        ratio = row[3] / base[0].median if base else float("nan")
        out.append([*row, ratio])
        if row[1] == "poisson":
            out.append([*jacobi_row, jacobi_row[3] / base[0].median if base else float("nan")])
        if base:
            t, its, rel = base
            name = "numpy bincount" if row[1] == "frustum" else "scipy Jacobi-CG"
            out.append([size, row[1], name, t.median, t.iqr, "", its or "", rel or "", 1.0])
    clear_plan_cache()
    return out


RSS_CODE = """
lay = m360.Layout.icosahedron({w}, padding=0.3)
hh, ww = lay.tangent_shape
offsets = 1.0 + 0.01 * np.arange(20, dtype=np.float32)
tiles = offsets[:, None, None] * np.ones((20, hh, ww), np.float32)
m360.stitch(tiles, lay, align='none', blend={mode!r})
"""


def peak_rss(sizes: list[int], modes: list[str]) -> list[list]:
    """Per size and mode, a fresh interpreter imports numpy and m360 (its baseline), then runs
    one whole stitch (plan build included): [size, mode, peak MB, peak - baseline MB, baseline
    MB, counter, wall s]."""
    rows = []
    for size in sizes:
        for mode in modes:
            t0 = time.perf_counter()
            rss = h.fresh_process_rss(RSS_CODE.format(w=size, mode=mode))
            wall = time.perf_counter() - t0
            rows.append([size, mode, rss.peak_mb, rss.delta_mb, rss.baseline_mb, rss.source, wall])
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.add_argument("--scipy-max", type=int, default=4096, help="largest size for scipy CG")
    parser.add_argument(
        "--rss-modes", nargs="*", default=["frustum", "poisson"], help="modes for peak RSS"
    )
    args = parser.parse_args()
    meta = h.metadata()
    meta.update(m360_threads=m360.get_num_threads())
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else []
    print(
        f"m360 {m360.__version__} @ {meta.get('git_commit')}, {meta.get('cpu_model')}, "
        f"{meta.get('cpu_count')} cpus, m360 threads {meta['m360_threads']}, load {load}; "
        f"median of {args.repeats} runs"
    )
    # Each RSS figure is the child's own VmHWM (not ru_maxrss, which a child inherits from this
    # process across fork + exec), with the baseline after imports read in the same child.
    rss = peak_rss(args.sizes, args.rss_modes) if args.rss_modes else []
    rows = []
    for size in args.sizes:
        rows += bench_size(size, args.repeats, args.scipy_max)
    h.print_table(
        "time per image (stitch align='none'); plan = first call - median; ratio vs baseline",
        ["ERP", "mode", "impl", "median s", "IQR s", "plan s", "iters", "rel. res.", "ratio"],
        rows,
    )
    if rss:
        h.print_table(
            "peak RSS of a fresh interpreter running one whole stitch (plan build included); "
            "baseline = its peak after `import numpy, m360`, read in the same process",
            ["ERP", "mode", "peak MB", "peak - baseline MB", "baseline MB", "counter", "wall s"],
            rss,
        )
    if args.json:
        json_rows = [
            dict(
                zip(
                    [
                        "erp",
                        "mode",
                        "impl",
                        "median_s",
                        "iqr_s",
                        "plan_s",
                        "iterations",
                        "relative_residual",
                        "ratio",
                    ],
                    r,
                    strict=True,
                )
            )
            for r in rows
        ]
        json_rows += [
            {"erp": r[0], "mode": r[1], "peak_rss_mb": r[2], "peak_minus_baseline_mb": r[3],
             "baseline_rss_mb": r[4], "rss_counter": r[5]}
            for r in rss
        ]  # fmt: skip
        h.write_json(args.json, json_rows, meta)


if __name__ == "__main__":
    main()
