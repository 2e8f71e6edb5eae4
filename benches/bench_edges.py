"""The photo-guided edge refinement (``m360.stitching.refine_edges``, ``edges="photo"``): time
against the same filter written with numpy, and what it does to a smeared room.

Input per size: a rendered room (``m360.synthetic.room(0)``), its photo, and its true disparity
blurred by a gaussian of std W / 2048 pixels (the smear of a network that sees each tangent at
the 2K layout's size). ``core`` is ``refine_edges`` with its defaults; ``numpy`` is the same
filter vectorised over the pixels near jumps (below, ``numpy_refine``: the same samples,
weights, bins and blend, in float64), the baseline measured in the same run. Both give the
band AbsRel (a 4 px band around the true depth edges, as in ``bench_prior.py``), so the table
also shows that they compute the same thing.

Run: ``.venv/bin/python benches/bench_edges.py [--sizes 2048 4096 8192] [--repeats 5]``
(``--numpy-sizes`` limits the slow baseline, default 2048 4096).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import m360
import m360.synthetic as syn
from m360.stitching.edges import default_edge_radius

BINS, FULL_TAPS = 24, 3  # rust/m360-core/src/edges.rs


def numpy_refine(
    disparity: np.ndarray,
    rgb: np.ndarray,
    radius: int,
    colour_sigma: float = 15.0,
    transition: float = 0.05,
    jump: float = 0.05,
    chunk: int = 20000,
) -> np.ndarray:
    """The core's filter with numpy: whole-array passes, then the pixels near jumps in chunks."""
    h_, w = disparity.shape
    logd = np.log(np.where(disparity > 0, disparity, np.nan))
    gx = (np.roll(logd, -1, axis=1) - np.roll(logd, 1, axis=1)) * 0.5
    up, down = np.clip(np.arange(h_) - 1, 0, h_ - 1), np.clip(np.arange(h_) + 1, 0, h_ - 1)
    gy = (logd[down] - logd[up]) / np.maximum(down - up, 1)[:, None]
    flat = np.nan_to_num(np.exp(-(gx * gx + gy * gy) * (radius / transition) ** 2))
    step = math.ceil(radius / FULL_TAPS)
    reach = radius // step
    k = np.arange(-reach, reach + 1) * step
    dy, dx = (a.ravel() for a in np.meshgrid(k, k, indexing="ij"))
    space = np.exp(-(dy**2 + dx**2) / (2 * (radius / 2) ** 2))
    # The window's range: separable min / max over the sampled offsets, wrapping in longitude.
    lo_rows = np.min([np.roll(np.nan_to_num(logd, nan=np.inf), -s, axis=1) for s in k], axis=0)
    hi_rows = np.max([np.roll(np.nan_to_num(logd, nan=-np.inf), -s, axis=1) for s in k], axis=0)
    lo = np.full_like(logd, np.inf)
    hi = np.full_like(logd, -np.inf)
    for s in k:
        rows = np.arange(h_) + s
        ok = (rows >= 0) & (rows < h_)
        lo[ok] = np.minimum(lo[ok], lo_rows[rows[ok]])
        hi[ok] = np.maximum(hi[ok], hi_rows[rows[ok]])
    ys, xs = np.nonzero((hi - lo > jump) & np.isfinite(logd))
    out = disparity.astype(np.float32).copy()
    colour = rgb.astype(np.float64)
    cut = math.ceil(9 * colour_sigma**2)
    for start in range(0, len(ys), chunk):
        y, x = ys[start : start + chunk], xs[start : start + chunk]
        yy, xx = y[:, None] + dy[None], (x[:, None] + dx[None]) % w
        inside = (yy >= 0) & (yy < h_)
        yy = np.clip(yy, 0, h_ - 1)
        v = logd[yy, xx]
        d2 = ((colour[yy, xx] - colour[y, x][:, None]) ** 2).sum(-1)
        f = flat[yy, xx]
        wt = space[None] * np.exp(-d2 / (2 * colour_sigma**2)) * f
        wt[~inside | ~np.isfinite(v) | (f < 1e-3) | (d2 > cut)] = 0
        v = np.where(inside & np.isfinite(v), v, 0)
        lo_p, hi_p = lo[y, x][:, None], hi[y, x][:, None]
        b = np.minimum(((v - lo_p) * (BINS / (hi_p - lo_p))).astype(int).clip(0), BINS - 1)
        weight = np.zeros((len(y), BINS))
        rows = np.repeat(np.arange(len(y)), b.shape[1])
        np.add.at(weight, (rows, b.ravel()), wt.ravel())
        triple = weight.copy()
        triple[:, 1:] += weight[:, :-1]
        triple[:, :-1] += weight[:, 1:]
        best = triple.argmax(1)[:, None]
        sel = np.where(np.abs(b - best) <= 1, wt, 0)
        total = sel.sum(1)
        mode = (sel * v).sum(1) / np.where(total > 0, total, 1)
        keep = flat[y, x]
        refined = np.exp(keep * logd[y, x] + (1 - keep) * mode)
        out[y, x] = np.where(total > 0, refined, out[y, x])
    return out


def one_size(width: int, repeats: int, with_numpy: bool) -> list[Any]:
    """[width, radius, band smeared, band refined, core s, numpy s, speed-up, same]."""
    rgb, depth = syn.render(syn.room(0), width)
    smeared = cv2.GaussianBlur((1 / depth).astype(np.float32), (0, 0), width / 2048)
    band = m360.eval.edge_band(depth)
    radius = default_edge_radius(width)

    def band_error(d: np.ndarray) -> float:
        return float(m360.eval.depth_metrics(d, depth, valid=band)["abs_rel"])

    core = h.measure(lambda: m360.stitching.refine_edges(smeared, rgb), repeats=repeats)
    refined = m360.stitching.refine_edges(smeared, rgb)
    row: list[Any] = [width, radius, band_error(smeared), band_error(refined), core.median]
    if not with_numpy:
        return [*row, "", "", ""]
    base = h.measure(lambda: numpy_refine(smeared, rgb, radius), repeats=1, warmup=0)
    reference = numpy_refine(smeared, rgb, radius)
    same = float(np.isclose(reference, refined, rtol=1e-4, equal_nan=True).mean())
    return [*row, base.median, base.median / core.median, same]


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=5, sizes=[2048, 4096, 8192])
    parser.add_argument("--numpy-sizes", type=int, nargs="*", default=[2048, 4096])
    args = parser.parse_args()
    meta = h.metadata()
    print(f"m360 {m360.__version__} @ {meta.get('git_commit')}, threads {m360.get_num_threads()}")
    rows: list[list[Any]] = []
    for width in args.sizes:
        rows.append(one_size(width, args.repeats, width in args.numpy_sizes))
        print(f"  done {width}", flush=True)
    h.print_table(
        f"refine_edges on a smeared room: band AbsRel and seconds (core: median of "
        f"{args.repeats}; numpy: one run); same = share of pixels equal to 1e-4",
        ["ERP", "radius", "band smeared", "band refined", "core s", "numpy s", "speed-up", "same"],
        rows,
    )
    if args.json:
        h.write_json(args.json, rows, meta)


if __name__ == "__main__":
    main()
