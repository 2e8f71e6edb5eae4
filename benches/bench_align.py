"""Alignment speed and accuracy at 2K / 4K / 8K on synthetic rooms.

Tables:
1. whole alignment + mean blend per size: stitch and align seconds, iterations, final energy
   (energies of different energies are not comparable) and AbsRel against the exact distance,
   for
   - no alignment (``align="none"``): the distorted tangents blended as they are,
   - the default (normalized energy, perspective offsets, Newton to convergence, 4x3 → 8x7),
   - the default with a third 16x14 level (the schedule the default stops short of),
   - ``energy="paper"`` with 50 L-BFGS iterations per level (the paper's recipe, 4x3 → 8x7 →
     16x14),
   - the default energy with m360's L-BFGS run to convergence,
   - the paper energy solved to convergence by Newton;
   then the median AbsRel of each method over the sizes run (same scene per size for all rows).
2. per level: samples, build and solve seconds, iterations, energy.
3. time to the same energy, against a baseline in the same run. One problem per size: the paper
   energy's 16x14 level, from identity, on the distorted tangents (8,960 unknowns), as m360
   builds it; scipy gets it from ``plan.alignment_problem`` (energy and gradient with
   scipy.sparse, benches/align_scipy.py; checked against m360's reported energies). Targets:
   the energy m360's L-BFGS reaches after 50 iterations (the paper's cap), and a fraction f of
   the way from the initial energy E0 to the optimum E* (Newton to convergence), E0 - f (E0 -
   E*) for f in ``--fractions``. Per target, the median over repeats of the time each solver
   takes to first reach it:
   - scipy ``L-BFGS-B`` (bounds s ≥ 1e-6, gtol = ftol = 0): wall time from the call to the
     callback of the first iteration at or below the target (stopped once all are reached);
   - m360 L-BFGS and m360 Newton: the solver's own ``solve_seconds`` in a run capped at the
     fewest iterations that reach the target (found by bisection on the cap; the solvers are
     deterministic, so a capped run is the start of a longer one).
   Problem build is not in these times (m360's build seconds and scipy's assembly are printed
   apart). Ratio = scipy seconds / m360 seconds (> 1: m360 faster). Iterations are not units of
   equal work (an L-BFGS-B iteration may evaluate the energy several times, a Newton iteration
   factors the Hessian), which is why the table compares times to an energy, not per iteration.

Tangents are ray-cast exactly, then distorted per tangent as a network errs: scale ×[0.5, 2],
shift ±30 % of the median, a smooth ±10 % multiplicative field and 1 % noise.

With ``--robust`` only one table runs instead: robustness to content errors. On ``--scenes``
rooms per size, under two distortions — the affine one above, and content errors
(``m360.synthetic.content_errors``: 1-3 regions per tangent of 3-17 % of the tile, ±10-30 %,
blur of 1 px per 2048 of ERP width) followed by the same affine one — the median AbsRel and
median stitch time (alignment + blend) of: the defaults before robustness (least squares,
Poisson blend), robust alignment alone (Cauchy loss), the consensus blend alone, both (the
default), the frustum blend with least squares (what Poisson is compared with), Poisson with
the consensus target, and the default with icosahedron layouts of larger padding (more
overlap; the same 20 tangents, so the same network cost: 20 tiles × the stand-in's ~50 ms of
benches/bench_estimate.py).

Run: ``.venv/bin/python benches/bench_align.py [--sizes 2048 4096 8192] [--repeats 3]``.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.optimize

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import align_scipy
import m360
import m360._core
import m360.synthetic as syn
from m360.geometry import clear_plan_cache, plan_for
from m360.geometry import sphere as sph

METHODS = {
    "no alignment": {"align": "none"},
    "default (newton)": {},
    "default + 16x14 level": {"align": [(4, 3), (8, 7), (16, 14)]},
    "paper, L-BFGS 50/level": {"energy": "paper", "solver": "lbfgs"},
    "default energy, L-BFGS conv.": {"solver": "lbfgs", "iterations": 5000},
    "paper, Newton conv.": {"energy": "paper", "solver": "newton"},
}
#: The level of the solver comparison and the paper energy's options (stitch's defaults).
GRID = (16, 14)
PAPER = {"energy": "paper"}  # every other option: the core's default for this energy
#: Largest iteration cap m360's L-BFGS is searched over for a target.
LBFGS_CAP = 5000
NEWTON_CAP = 100


def scene_inputs(width: int, seed: int) -> tuple[m360.Layout, np.ndarray, np.ndarray]:
    layout = m360.Layout.icosahedron(width, padding=0.3)
    scene = syn.room(seed)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    tiles = syn.distort(exact, seed + 100, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01)
    depth = scene.distance(sph.erp_directions(*layout.erp_shape))
    return layout, tiles, depth


def _align_options(levels: list, options: dict, solver: str, iterations: int, tol: float) -> dict:
    return {"levels": levels, "solver": solver, "iterations": iterations, "tolerance": tol,
            **options}  # fmt: skip


def plan_align(
    plan: Any, maps: np.ndarray, levels: list, options: dict, solver: str, its: int, tol: float
) -> tuple:
    """``plan.align`` with these levels, options, solver, iteration cap and tolerance."""
    return plan.align(maps, _align_options(levels, options, solver, its, tol))


def alignment_problem(plan: Any, maps: np.ndarray, grid: tuple, options: dict) -> dict:
    """The first-level problem of ``maps`` on ``grid`` with ``options`` (see ``_core.Plan``)."""
    return plan.alignment_problem(maps, grid, _align_options([grid], options, "newton", 0, 0))


class CappedSolver:
    """m360's solver on one level, run with an iteration cap (tolerance 0); runs are memoised."""

    def __init__(self, plan: Any, maps: np.ndarray, solver: str) -> None:
        self.plan, self.maps, self.solver = plan, maps, solver
        self.runs: dict[int, tuple[dict, np.ndarray]] = {}

    def run(self, cap: int) -> tuple[dict, np.ndarray]:
        """(level report, node values x in align_scipy's order) after at most ``cap`` steps."""
        _, levels, grids, _ = plan_align(self.plan, self.maps, [GRID], PAPER, self.solver, cap, 0.0)
        return levels[0], np.asarray(grids[0], np.float64).reshape(-1)

    def energy(self, cap: int) -> float:
        if cap not in self.runs:
            self.runs[cap] = self.run(cap)
        return float(self.runs[cap][0]["energy"])

    def first_reaching(self, target: float, limit: int) -> int | None:
        """Fewest iterations whose iterate has energy ≤ target (None if not within ``limit``)."""
        lo, hi = 0, 1  # energy(lo) > target
        while self.energy(hi) > target:
            if hi >= limit:
                return None
            lo, hi = hi, min(2 * hi, limit)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if self.energy(mid) <= target else (mid, hi)
        return int(self.runs[hi][0]["iterations"])

    def solve_timing(self, cap: int, repeats: int) -> h.Timing:
        return h.timing_of([float(self.run(cap)[0]["solve_seconds"]) for _ in range(repeats)])


def _first_hits(targets: list[float], hits: dict[int, tuple[float, int]], t0: float) -> Any:
    """An L-BFGS-B callback recording, per target index, (seconds since t0, iteration) of the
    first iterate at or below it; stops the solver once every target is reached."""
    count = [0]

    def callback(intermediate_result: scipy.optimize.OptimizeResult) -> None:
        t = time.perf_counter() - t0
        count[0] += 1
        for i, target in enumerate(targets):
            if i not in hits and intermediate_result.fun <= target:
                hits[i] = (t, count[0])
        if len(hits) == len(targets):
            raise StopIteration

    return callback


def scipy_race(
    f: Any, x0: np.ndarray, targets: list[float], maxiter: int, repeats: int
) -> tuple[list[h.Timing | None], list[int | None]]:
    """Per target: scipy L-BFGS-B's time to its first iterate with energy ≤ target (None if not
    reached in ``maxiter`` iterations), and that iteration's number. One warm-up run."""
    bounds = [(1e-6, None) if i % 2 == 0 else (None, None) for i in range(len(x0))]
    times: list[list[float]] = [[] for _ in targets]
    its: list[int | None] = [None] * len(targets)
    for rep in range(repeats + 1):
        hits: dict[int, tuple[float, int]] = {}
        callback = _first_hits(targets, hits, time.perf_counter())
        scipy.optimize.minimize(
            f, x0, jac=True, method="L-BFGS-B", bounds=bounds, callback=callback,
            options={"maxiter": maxiter, "gtol": 0.0, "ftol": 0.0},
        )  # fmt: skip
        if rep == 0:
            continue  # warm-up
        for i, (t, n) in hits.items():
            times[i].append(t)
            its[i] = n
    return [h.timing_of(t) if len(t) == repeats else None for t in times], its


def solver_race(
    plan: Any, tiles: np.ndarray, width: int, repeats: int, fractions: list[float], maxiter: int
) -> tuple[list, list, list]:
    """The time-to-energy comparison at one size: (problem rows, race rows, json rows)."""
    maps = plan.spherical_disparity(tiles)
    t0 = time.perf_counter()
    problem = alignment_problem(plan, maps, GRID, PAPER)
    t1 = time.perf_counter()
    f = align_scipy.energy_function(problem)
    assembly = time.perf_counter() - t1
    x0 = align_scipy.identity(problem)
    lbfgs = CappedSolver(plan, maps, "lbfgs")
    newton = CappedSolver(plan, maps, "newton")
    # E*: Newton to convergence (tolerance 1e-9).
    _, levels, grids, _ = plan_align(plan, maps, [GRID], PAPER, "newton", NEWTON_CAP, 1e-9)
    e_star, e_star_converged = float(levels[0]["energy"]), bool(levels[0]["converged"])
    e0 = lbfgs.energy(0)
    targets = [("m360 L-BFGS after 50 its", lbfgs.energy(50))]
    targets += [(f"{100 * fr:g} % of E0 -> E*", e0 - fr * (e0 - e_star)) for fr in fractions]
    # m360's reported energy against scipy's evaluation of the same node values.
    check = max(
        abs(f(x)[0] - float(rep["energy"])) / abs(float(rep["energy"]))
        for rep, x in (lbfgs.runs[0], lbfgs.runs[50], (levels[0], np.ravel(grids[0])))
    )
    scipy_t, scipy_its = scipy_race(f, x0, [e for _, e in targets], maxiter, repeats)
    build = statistics.median(float(r["build_seconds"]) for r, _ in lbfgs.runs.values())
    problem_rows = [[width, problem["unknowns"], len(problem["nodes"]), e0, e_star,
                     e_star_converged, build, t1 - t0, assembly, check]]  # fmt: skip
    rows, json_rows = [], []
    for (name, target), ts, its in zip(targets, scipy_t, scipy_its, strict=True):
        row: list = [width, name, target, its if ts else f"not in {maxiter}"]
        row += [ts.median, ts.iqr] if ts else [math.nan, math.nan]
        entry: dict = {"erp_width": width, "target": name, "target_energy": target,
                       "scipy": {"iterations": its, "timing": ts}}  # fmt: skip
        medians = []
        for solver, limit in ((lbfgs, LBFGS_CAP), (newton, NEWTON_CAP)):
            k = solver.first_reaching(target, limit)
            if k is None:
                row += [f"not in {limit}", math.nan, math.nan]
                medians.append(math.nan)
                entry[f"m360_{solver.solver}"] = {"iterations": None, "timing": None}
                continue
            t = solver.solve_timing(k, repeats)
            row += [k, t.median, t.iqr]
            medians.append(t.median)
            entry[f"m360_{solver.solver}"] = {"iterations": k, "timing": t}
        scipy_med = ts.median if ts else math.nan
        row += [scipy_med / m for m in medians]
        rows.append(row)
        json_rows.append(entry)
    return problem_rows, rows, json_rows


def bench_size(
    width: int, repeats: int, seed: int, fractions: list[float], maxiter: int, race: bool
) -> tuple[list, ...]:
    """All measurements at one ERP width: (rows, level rows, problem rows, race rows, json)."""
    rows: list = []
    level_rows: list = []
    json_rows: list = []
    layout, tiles, depth = scene_inputs(width, seed)
    clear_plan_cache()
    plan = plan_for(layout)
    t0 = time.perf_counter()
    normalized = {"energy": "normalized"}
    plan_align(plan, plan.spherical_disparity(tiles), [(2, 2)], normalized, "newton", 0, 1e-6)
    sampling = time.perf_counter() - t0  # overlap sampling dominates a 0-iteration 2x2 run
    for name, kwargs in METHODS.items():
        result: list[m360.StitchResult] = []

        def run(kwargs: dict = kwargs, result: list = result) -> None:
            res = m360.stitch(tiles, layout, blend="mean", return_details=True, **kwargs)
            assert isinstance(res, m360.StitchResult)
            result[:] = [res]

        t = h.measure(run, repeats=repeats)
        res = result[0]
        levels = res.report.get("align", [])
        metrics = m360.eval.depth_metrics(res.disparity, depth)
        rows.append(
            [
                width,
                name,
                t.median,
                t.iqr,
                res.timings["align"],
                sum(lvl["iterations"] for lvl in levels) if levels else "-",
                all(lvl["converged"] for lvl in levels) if levels else "-",
                levels[-1]["energy"] if levels else "-",
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
                "kwargs": kwargs,
                "timing": t,
                "levels": levels,
                "abs_rel": metrics["abs_rel"],
            }
        )

    problem_rows, race_rows = [], []
    if race:
        problem_rows, race_rows, race_json = solver_race(
            plan, tiles, width, repeats, fractions, maxiter
        )
        json_rows += race_json
    print(f"  done {width} (sampling {sampling:.3f} s)", flush=True)
    return rows, level_rows, problem_rows, race_rows, json_rows


#: (label, stitch keywords, icosahedron padding) of the robustness table.
ROBUST_METHODS = [
    ("before: least squares + poisson", {"loss": "squared", "blend": "poisson"}, 0.3),
    ("robust alignment alone (cauchy + poisson)", {"blend": "poisson"}, 0.3),
    ("consensus blend alone (least squares)", {"loss": "squared", "blend": "consensus"}, 0.3),
    ("both: cauchy + consensus (default)", {}, 0.3),
    ("least squares + frustum", {"loss": "squared", "blend": "frustum"}, 0.3),
    ("cauchy + poisson, consensus target", {"blend_options": {"fidelity": "consensus"}}, 0.3),
    ("default, padding 0.5", {}, 0.5),
    ("default, padding 0.7", {}, 0.7),
    ("default, padding 1.0", {}, 1.0),
]


def robust_table(sizes: list[int], scenes: int, repeats: int) -> list[list]:
    """Median AbsRel and stitch seconds per (size, distortion, method) over ``scenes`` rooms."""
    rows = []
    for width in sizes:
        results: dict[tuple[str, str], tuple[list[float], list[float]]] = {}
        for seed in range(scenes):
            scene = syn.room(seed)
            depth = scene.distance(sph.erp_directions(width // 2, width))
            inputs: dict[float, tuple[Any, list[tuple[str, np.ndarray]]]] = {}
            for label, kwargs, padding in ROBUST_METHODS:
                if padding not in inputs:  # ray cast and distort once per layout
                    lay = m360.Layout.icosahedron(width, padding=padding)
                    exact = syn.tangent_perspective_disparity(scene, lay.cameras)
                    wrong = syn.content_errors(exact, seed + 200, blur=width / 2048)
                    inputs[padding] = (lay, [
                        (name, syn.distort(base, seed + 100, scale=(0.5, 2.0), shift=0.3,
                                           field=0.1, noise=0.01))
                        for name, base in (("affine", exact), ("content errors", wrong))
                    ])  # fmt: skip
                layout, distorted = inputs[padding]
                for distortion, tiles in distorted:
                    out: list[np.ndarray] = []

                    def run(
                        tiles: np.ndarray = tiles,
                        kw: dict = kwargs,
                        lay: Any = layout,
                        out: list = out,
                    ) -> None:
                        out[:] = [m360.stitch(tiles, lay, **kw)]  # fmt: skip

                    t = h.measure(run, repeats=repeats)
                    err = m360.eval.depth_metrics(out[0], depth)["abs_rel"]
                    acc = results.setdefault((distortion, label), ([], []))
                    acc[0].append(err)
                    acc[1].append(t.median)
        for (distortion, label), (errs, times) in results.items():
            rows.append([width, distortion, label, statistics.median(errs), max(errs),
                         statistics.median(times)])  # fmt: skip
        print(f"  done {width}", flush=True)
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--fractions",
        type=float,
        nargs="*",
        default=[0.9, 0.99, 0.999],
        help="targets E0 - f (E0 - E*) of the solver comparison (default 0.9 0.99 0.999)",
    )
    parser.add_argument(
        "--scipy-maxiter", type=int, default=1000, help="scipy L-BFGS-B iteration cap (1000)"
    )
    parser.add_argument(
        "--no-race", action="store_true", help="skip the time-to-energy solver comparison"
    )
    parser.add_argument(
        "--robust", action="store_true", help="only the robustness-to-content-errors table"
    )
    parser.add_argument("--scenes", type=int, default=4, help="rooms per size of --robust (4)")
    args = parser.parse_args()
    meta = h.metadata()
    if args.robust:
        rows = robust_table(args.sizes, args.scenes, args.repeats)
        h.print_table(
            f"robustness: median AbsRel (and worst scene) over {args.scenes} rooms and median "
            f"stitch seconds (median of {args.repeats} runs per room), by distortion",
            ["ERP", "distortion", "method", "AbsRel", "worst", "stitch s"],
            rows,
        )
        if args.json:
            h.write_json(args.json, rows, meta)
        return
    print(
        f"m360 {m360.__version__} @ {meta.get('git_commit')}, {meta.get('cpu_model')}, "
        f"threads {m360.get_num_threads()}; median of {args.repeats} runs"
    )
    rows, level_rows, problem_rows, race_rows, json_rows = [], [], [], [], []
    for width in args.sizes:
        r, lr, pr, rr, jr = bench_size(
            width, args.repeats, args.seed, args.fractions, args.scipy_maxiter, not args.no_race
        )
        rows += r
        level_rows += lr
        problem_rows += pr
        race_rows += rr
        json_rows += jr

    h.print_table(
        f"whole alignment (align='multiscale' unless 'none') + mean blend, distorted tangents, "
        f"seed {args.seed}; median of {args.repeats}",
        [
            "ERP",
            "method",
            "stitch s",
            "IQR s",
            "align s",
            "iterations",
            "converged",
            "final energy",
            "AbsRel",
        ],
        rows,
    )
    h.print_table(
        f"median AbsRel over the {len(args.sizes)} size(s) run ({', '.join(map(str, args.sizes))})",
        ["method", "AbsRel"],
        [[m, statistics.median(r[8] for r in rows if r[1] == m)] for m in METHODS],
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
    if args.no_race:
        if args.json:
            h.write_json(args.json, json_rows, meta)
        return
    h.print_table(
        f"solver comparison problem: paper energy, {GRID[0]}x{GRID[1]} level from identity; "
        "E* = Newton to convergence; build s = m360's problem build (median of the runs), "
        "export s = plan.alignment_problem, assembly s = scipy.sparse matrices; "
        "energy check = max relative |scipy f(x) - m360's reported energy|",
        ["ERP", "unknowns", "samples", "E0", "E*", "E* converged", "build s", "export s",
         "assembly s", "energy check"],
        problem_rows,
    )  # fmt: skip
    h.print_table(
        f"time to first reach the same energy on that problem (solve only, build excluded), "
        f"median of {args.repeats}: scipy L-BFGS-B (scipy.sparse, wall time to the callback) "
        "vs m360 L-BFGS and m360 Newton (solve_seconds of a run capped at the iterations "
        "shown); ratio = scipy s / m360 s",
        ["ERP", "target", "energy", "scipy its", "scipy s", "IQR", "L-BFGS its", "L-BFGS s",
         "IQR", "Newton its", "Newton s", "IQR", "scipy/L-BFGS", "scipy/Newton"],
        race_rows,
    )  # fmt: skip
    if args.json:
        h.write_json(args.json, json_rows, meta)


if __name__ == "__main__":
    main()
