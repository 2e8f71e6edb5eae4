"""Alignment speed and accuracy at 2K / 4K / 8K on synthetic rooms.

For each size: the overlap sampling (once per plan), per-level problem build and solve, final
energy and AbsRel (blend="mean") for
- the default (normalized energy, perspective offsets, Newton to convergence, 4x3 → 8x7 → 16x14),
- ``energy="paper"`` with 50 L-BFGS iterations per level (the paper's recipe),
- the default energy with m360's L-BFGS run to convergence,
- the paper energy solved to convergence by Newton;
and, in the same run, the baseline: scipy ``L-BFGS-B`` on the same energy and gradient built
with scipy.sparse (benches/align_scipy.py), 50 iterations on the 16x14 level, compared per
iteration with m360's L-BFGS on the same level.

Tangents are ray-cast exactly, then distorted per tangent as a network errs: scale ×[0.5, 2],
shift ±30 % of the median, a smooth ±10 % multiplicative field and 1 % noise.

Run: ``.venv/bin/python benches/bench_align.py [--sizes 2048 4096 8192] [--repeats 3]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import scipy.optimize

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import align_scipy
import m360
import m360._sphere as sph
import m360.synthetic as syn
from m360.geometry import clear_plan_cache, plan_for

METHODS = {
    "default (newton)": {},
    "paper, L-BFGS 50/level": {"energy": "paper", "solver": "lbfgs"},
    "default energy, L-BFGS conv.": {"solver": "lbfgs", "iterations": 5000},
    "paper, Newton conv.": {"energy": "paper", "solver": "newton"},
}


def scene_inputs(width: int, seed: int) -> tuple[m360.Layout, np.ndarray, np.ndarray]:
    layout = m360.Layout.icosahedron(width)
    scene = syn.room(seed)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    tiles = syn.distort(exact, seed + 100, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01)
    depth = scene.distance(sph.erp_directions(*layout.erp_shape))
    return layout, tiles, depth


def bench_size(width: int, repeats: int, seed: int) -> tuple[list, list, list, list]:
    """All measurements at one ERP width: (rows, level rows, baseline rows, json rows)."""
    rows: list = []
    level_rows: list = []
    base_rows: list = []
    json_rows: list = []
    layout, tiles, depth = scene_inputs(width, seed)
    clear_plan_cache()
    plan = plan_for(layout)
    t0 = time.perf_counter()
    plan.align(
        plan.spherical_disparity(tiles),
        [(2, 2)],
        "normalized",
        1.0,
        0.01,
        "newton",
        0,
        1e-6,
        0.01,
        0.0,
        "perspective",
    )
    sampling = time.perf_counter() - t0  # overlap sampling dominates a 0-iteration 2x2 run
    for name, kwargs in METHODS.items():
        result: list[m360.StitchResult] = []

        def run(kwargs: dict = kwargs, result: list = result) -> None:
            res = m360.stitch(tiles, layout, blend="mean", return_details=True, **kwargs)
            assert isinstance(res, m360.StitchResult)
            result[:] = [res]

        t = h.measure(run, repeats=repeats)
        res = result[0]
        levels = res.report["align"]
        metrics = m360.eval.depth_metrics(res.disparity, depth)
        rows.append(
            [
                width,
                name,
                t.median,
                res.timings["align"],
                sum(lvl["iterations"] for lvl in levels),
                all(lvl["converged"] for lvl in levels),
                levels[-1]["energy"],
                metrics["abs_rel"],
            ]
        )
        for lvl in levels:
            level_rows.append(
                [
                    width,
                    name,
                    f"{lvl['grid'][0]}x{lvl['grid'][1]}",
                    lvl["samples"],
                    lvl["build_seconds"],
                    lvl["solve_seconds"],
                    lvl["iterations"],
                    lvl["converged"],
                    lvl["energy"],
                ]
            )
        json_rows.append(
            {
                "erp_width": width,
                "method": name,
                "timing": t,
                "levels": levels,
                "abs_rel": metrics["abs_rel"],
            }
        )

    # Baseline: scipy L-BFGS-B, same energy and gradient (scipy.sparse), 16x14 level, 50 its.
    spherical = plan.spherical_disparity(tiles)
    problem = plan.alignment_problem(
        spherical, (16, 14), "paper", 40.0, 0.007, 0.01, 0.0, "spherical"
    )
    f = align_scipy.energy_function(problem)
    x0 = align_scipy.identity(problem)
    bounds = [(1e-6, None) if i % 2 == 0 else (None, None) for i in range(len(x0))]
    its: list[int] = []

    def scipy_run() -> None:
        out = scipy.optimize.minimize(
            f,
            x0,
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxiter": 50, "gtol": 0.0, "ftol": 0.0},
        )
        its[:] = [out.nit]

    t_scipy = h.measure(scipy_run, repeats=repeats)
    m360_runs: list[dict] = []

    def m360_run() -> None:
        res = m360.stitch(
            tiles,
            layout,
            (16, 14),
            "mean",
            energy="paper",
            solver="lbfgs",
            iterations=50,
            tolerance=0.0,
            return_details=True,
        )
        assert isinstance(res, m360.StitchResult)
        m360_runs[:] = [res.report["align"][0]]

    h.measure(m360_run, repeats=repeats)
    lvl = m360_runs[0]
    per_scipy = t_scipy.median / max(its[0], 1)
    per_m360 = lvl["solve_seconds"] / max(lvl["iterations"], 1)
    base_rows.append(
        [
            width,
            problem["unknowns"],
            len(problem["nodes"]),
            its[0],
            per_scipy,
            lvl["iterations"],
            per_m360,
            per_scipy / per_m360,
        ]
    )
    print(f"  done {width} (sampling {sampling:.3f} s)", flush=True)

    return rows, level_rows, base_rows, json_rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    meta = h.metadata()
    print(
        f"m360 {m360.__version__} @ {meta.get('git_commit')}, {meta.get('cpu_model')}, "
        f"threads {m360.get_num_threads()}; median of {args.repeats} runs"
    )
    rows, level_rows, base_rows, json_rows = [], [], [], []
    for width in args.sizes:
        r, lr, br, jr = bench_size(width, args.repeats, args.seed)
        rows += r
        level_rows += lr
        base_rows += br
        json_rows += jr

    h.print_table(
        "whole alignment (align='multiscale') + mean blend, distorted tangents",
        [
            "ERP",
            "method",
            "stitch s",
            "align s",
            "iterations",
            "converged",
            "final energy",
            "AbsRel",
        ],
        rows,
    )
    h.print_table(
        "per level",
        [
            "ERP",
            "method",
            "grid",
            "samples",
            "build s",
            "solve s",
            "iterations",
            "converged",
            "energy",
        ],
        level_rows,
    )
    h.print_table(
        "L-BFGS per iteration on the 16x14 paper energy: scipy L-BFGS-B (scipy.sparse) vs m360",
        [
            "ERP",
            "unknowns",
            "samples",
            "scipy its",
            "scipy s/it",
            "m360 its",
            "m360 s/it",
            "speed-up",
        ],
        base_rows,
    )
    if args.json:
        h.write_json(args.json, json_rows, meta)


if __name__ == "__main__":
    main()
