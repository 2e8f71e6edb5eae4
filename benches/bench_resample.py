"""Resampling speed and memory: ERP → 20 tangents and tangents → ERP at 2K / 4K / 8K.

Baselines, measured in the same run on the same inputs:
- ``cv2.remap`` with precomputed maps (float32 maps and OpenCV's fixed-point maps; the faster
  one is the baseline), the fastest known way to do the same sampling from Python, on as many
  threads as m360;
- ``py360convert.e2p`` called once per tangent (what most 360° code does);
- tangents → ERP (N, H, W), the output of ``tangents_to_erp``: per face, ``cv2.remap`` with
  precomputed maps over the ERP rows the face reaches, written in place into a stack that is
  NaN elsewhere (map entries outside the footprint fall on the NaN border); float and
  fixed-point maps, the faster is the baseline. Also, for scale, ``cv2.remap`` of the footprint
  pixels alone into one compact array (not the same output: 4 values per pixel, not 20);
- tangents → ERP mean: that compact ``cv2.remap``, then a ``np.bincount`` mean: the same work
  as ``stitch(align="none", blend="mean")``.

Memory: peak RSS of a fresh interpreter running one ``stitch(align="none", blend="mean")`` per size,
its own high-water mark (VmHWM on Linux, not inherited from this process), absolute and above its
baseline after importing numpy and m360 (``--no-rss`` skips it).

Run: ``.venv/bin/python benches/bench_resample.py [--sizes 2048 4096 8192] [--repeats 5]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import m360
from m360.geometry import clear_plan_cache, plan_for
from m360.geometry import sphere as sph

Row = tuple[int, str, str, h.Timing, "float | None"]


def panorama(width: int) -> np.ndarray:
    """A textured RGB panorama (content does not affect timing): a 1K render, upscaled."""
    rgb, _ = m360.synthetic.render(m360.synthetic.room(0), 1024)
    return cv2.resize(rgb, (width, width // 2), interpolation=cv2.INTER_LINEAR)


def tangent_maps(layout: m360.Layout) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (N*h, w) float32 of every tangent pixel into the ERP."""
    height, width = layout.erp_shape
    cols, rows = [], []
    for cam in layout.cameras:
        d = sph.camera_pixel_directions(
            cam.rotation, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height
        )
        col, row = sph.lonlat_to_erp_pixel(*sph.directions_to_lonlat(d), height, width)
        cols.append(col.astype(np.float32))
        rows.append(row.astype(np.float32))
    return np.concatenate(cols), np.concatenate(rows)


def footprints(layout: m360.Layout) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per face: the ERP flat indices it sees and its (x, y) positions there, as cv2 maps."""
    height, width = layout.erp_shape
    lat, lon = sph.erp_latitudes(height), sph.erp_longitudes(width)
    out = []
    for cam in layout.cameras:
        idx, xs, ys = [], [], []
        for r0 in range(0, height, 256):
            d = sph.lonlat_to_directions(lon[None, :], lat[r0 : r0 + 256, None])
            x, y, front = cam.project(d)
            inside = front & (x >= -0.5) & (x <= cam.width - 0.5)
            inside &= (y >= -0.5) & (y <= cam.height - 0.5)
            flat = np.flatnonzero(inside)
            idx.append(flat + r0 * width)
            xs.append(np.clip(x.ravel()[flat], 0, cam.width - 1).astype(np.float32))
            ys.append(np.clip(y.ravel()[flat], 0, cam.height - 1).astype(np.float32))
        out.append((np.concatenate(idx), _blocks(np.concatenate(xs)), _blocks(np.concatenate(ys))))
    return out


def row_maps(
    layout: m360.Layout, prints: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Per face: the ERP rows r0..r1 it reaches and cv2 maps (r1 - r0, W) of those rows, -1
    (outside the tile: the border) where the face does not see the pixel."""
    width = layout.erp_shape[1]
    out = []
    for idx, xs, ys in prints:
        rows = idx // width
        r0, r1 = int(rows.min()), int(rows.max()) + 1
        mx = np.full((r1 - r0, width), -1.0, np.float32)
        my = np.full((r1 - r0, width), -1.0, np.float32)
        mx.ravel()[idx - r0 * width] = xs.ravel()[: len(idx)]
        my.ravel()[idx - r0 * width] = ys.ravel()[: len(idx)]
        out.append((r0, r1, mx, my))
    return out


def _blocks(values: np.ndarray, width: int = 1024) -> np.ndarray:
    """A flat map as (rows, width), edge-padded: cv2.remap needs both sides < 32767."""
    pad = -len(values) % width
    return np.pad(values, (0, pad), mode="edge").reshape(-1, width)


def bench_size(size: int, repeats: int, e2p_repeats: int) -> list[Row]:
    """Every timing of one ERP width: (width, operation, implementation, timing, baseline s)."""
    out: list[Row] = []
    layout = m360.Layout.icosahedron(size, padding=0.3)
    rgb = panorama(size)

    def build_plan(which: str) -> None:
        clear_plan_cache()
        plan_for(layout).prepare(which)

    for which, label in (("tangents", "ERP->tangent taps"), ("erp", "tangent->ERP taps")):
        t = h.measure(lambda: build_plan(which), repeats=repeats)  # noqa: B023
        out.append((size, "plan build", f"m360 {label}", t, None))
    plan_for(layout).prepare("all")

    # ERP -> 20 tangents.
    mx, my = tangent_maps(layout)
    fixed = cv2.convertMaps(mx, my, cv2.CV_16SC2)
    lin, wrap = cv2.INTER_LINEAR, cv2.BORDER_WRAP
    t_f32 = h.measure(lambda: cv2.remap(rgb, mx, my, lin, borderMode=wrap), repeats=repeats)
    t_fix = h.measure(lambda: cv2.remap(rgb, *fixed, lin, borderMode=wrap), repeats=repeats)
    base = min(t_f32.median, t_fix.median)
    t_m360 = h.measure(lambda: m360.erp_to_tangents(rgb, layout), repeats=repeats)
    op = "ERP->tangents u8x3"
    out += [
        (size, op, "m360", t_m360, base),
        (size, op, "cv2.remap float maps", t_f32, base),
        (size, op, "cv2.remap fixed maps", t_fix, base),
    ]
    try:
        import py360convert
    except ImportError:
        py360convert = None
    if py360convert is not None:
        cam = layout.cameras[0]
        fov = (
            float(np.degrees(2 * np.arctan(cam.width / 2 / cam.fx))),
            float(np.degrees(2 * np.arctan(cam.height / 2 / cam.fy))),
        )
        centres = [np.degrees(sph.directions_to_lonlat(c.axis)) for c in layout.cameras]

        def e2p_all() -> None:
            for lon, lat in centres:
                py360convert.e2p(rgb, fov, float(lon), float(lat), (cam.height, cam.width))

        reps = max(1, min(e2p_repeats, repeats))
        t = h.measure(e2p_all, repeats=reps, warmup=0)
        out.append((size, op, "py360convert.e2p x20", t, base))

    # Tangents -> ERP.
    tiles = m360.erp_to_tangents(rgb[..., 1].astype(np.float32), layout)
    prints = footprints(layout)
    n_pixels = layout.erp_shape[0] * layout.erp_shape[1]
    flat_idx = np.concatenate([i for i, _, _ in prints])

    def cv2_footprints() -> np.ndarray:
        return np.concatenate(
            [cv2.remap(tiles[k], x, y, lin).ravel()[: len(i)] for k, (i, x, y) in enumerate(prints)]
        )

    def cv2_mean() -> np.ndarray:
        s = np.bincount(flat_idx, weights=cv2_footprints(), minlength=n_pixels)
        c = np.bincount(flat_idx, minlength=n_pixels)
        return (s / c).reshape(layout.erp_shape)

    def cv2_stack(maps: list) -> np.ndarray:
        out = np.empty((len(maps), *layout.erp_shape), np.float32)
        for k, (r0, r1, m1, m2) in enumerate(maps):
            out[k, :r0] = np.nan
            out[k, r1:] = np.nan
            dst = out[k, r0:r1]
            cv2.remap(tiles[k], m1, m2, lin, dst=dst, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=float("nan"))  # fmt: skip
        return out

    def measure_stack(maps: list) -> h.Timing:
        return h.measure(lambda: cv2_stack(maps), repeats=repeats)

    # One set of maps alive at a time (8K float maps take gigabytes).
    t_stack_fix = measure_stack(
        [
            (r0, r1, *cv2.convertMaps(x, y, cv2.CV_16SC2))
            for r0, r1, x, y in row_maps(layout, prints)
        ]
    )
    boxes = row_maps(layout, prints)
    t_stack_f32 = measure_stack(boxes)
    # The baseline must produce what tangents_to_erp produces: checked once, not timed.
    want = m360.tangents_to_erp(tiles, layout)
    got = cv2_stack(boxes)
    # cv2's bilinear reads its NaN border at the outermost half pixel of a tile, where m360
    # clamps: it may lose those pixels, nothing else.
    lost = np.isnan(got) & ~np.isnan(want)
    assert not (~np.isnan(got) & np.isnan(want)).any(), "cv2 stack: pixels outside a footprint"
    assert lost.sum() < 0.01 * (~np.isnan(want)).sum(), "cv2 stack: footprints differ"
    assert np.nanmax(np.abs(got - want)) < 1e-3 * np.nanmax(np.abs(want)), "cv2 stack: values"
    del boxes, got, want
    stack_base = min(t_stack_fix.median, t_stack_f32.median)
    t_fp = h.measure(cv2_footprints, repeats=repeats)
    t_mean = h.measure(cv2_mean, repeats=repeats)
    t_stitch = h.measure(
        lambda: m360.stitch(tiles, layout, align="none", blend="mean"), repeats=repeats
    )
    t_maps = h.measure(lambda: m360.tangents_to_erp(tiles, layout), repeats=repeats)
    out += [
        (size, "tangents->ERP mean", "m360 stitch(none, mean)", t_stitch, t_mean.median),
        (size, "tangents->ERP mean", "cv2 footprints + bincount", t_mean, t_mean.median),
        (size, "tangents->ERP (N,H,W)", "m360 tangents_to_erp", t_maps, stack_base),
        (size, "tangents->ERP (N,H,W)", "cv2.remap float maps", t_stack_f32, stack_base),
        (size, "tangents->ERP (N,H,W)", "cv2.remap fixed maps", t_stack_fix, stack_base),
        (size, "tangents->ERP compact", "cv2.remap footprints only", t_fp, stack_base),
    ]
    clear_plan_cache()
    return out


def peak_rss(sizes: list[int]) -> list[list]:
    """Per size, a fresh interpreter imports numpy and m360 (its baseline), then runs one
    stitch(align='none', blend='mean'): [size, peak MB, peak - baseline MB, baseline MB,
    counter, wall s]."""
    code = (
        "lay = m360.Layout.icosahedron({w}, padding=0.3)\n"
        "tiles = np.ones((20, *lay.tangent_shape), np.float32)\n"
        "m360.stitch(tiles, lay, align='none', blend='mean')\n"
    )
    rows = []
    for size in sizes:
        t0 = time.perf_counter()
        rss = h.fresh_process_rss(code.format(w=size))
        wall = time.perf_counter() - t0
        rows.append([size, rss.peak_mb, rss.delta_mb, rss.baseline_mb, rss.source, wall])
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.add_argument("--e2p-repeats", type=int, default=2, help="repeats of py360convert (slow)")
    parser.add_argument("--no-rss", action="store_true", help="skip the peak-RSS subprocesses")
    args = parser.parse_args()
    # Same thread count for both: cv2's default pool need not match m360's.
    cv2.setNumThreads(m360.get_num_threads())
    meta = h.metadata()
    meta.update(m360_threads=m360.get_num_threads(), cv2_threads=cv2.getNumThreads())
    print(
        f"m360 {m360.__version__} @ {meta.get('git_commit')}, {meta.get('cpu_model')}, "
        f"{meta.get('cpu_count')} cpus, m360 threads {meta['m360_threads']}, "
        f"cv2 threads {meta['cv2_threads']}; median of {args.repeats} runs"
    )
    # Each RSS figure is the child's own VmHWM (not ru_maxrss, which a child inherits from this
    # process across fork + exec), with the baseline after imports read in the same child.
    rss = [] if args.no_rss else peak_rss(args.sizes)
    rows, json_rows = [], []
    for size in args.sizes:
        for width, op, impl, t, baseline in bench_size(size, args.repeats, args.e2p_repeats):
            ratio = t.median / baseline if baseline else float("nan")
            rows.append([width, op, impl, t.median, t.iqr, ratio])
            json_rows.append({"erp_width": width, "op": op, "impl": impl, "timing": t})
    h.print_table(
        "ratio = median / baseline in the same run (<= 1: m360 at least as fast)",
        ["ERP width", "operation", "implementation", "median s", "IQR s", "ratio"],
        rows,
    )
    if rss:
        json_rows += [
            {"erp_width": r[0], "op": "stitch peak RSS MB", "value": r[1],
             "peak_minus_baseline_mb": r[2], "baseline_mb": r[3], "counter": r[4]}
            for r in rss
        ]  # fmt: skip
        h.print_table(
            "peak RSS of a fresh interpreter running stitch(align='none', blend='mean') (plan "
            "build included); baseline = its peak after `import numpy, m360`, same process",
            ["ERP width", "peak MB", "peak - baseline MB", "baseline MB", "counter", "wall s"],
            rss,
        )
    if args.json:
        h.write_json(args.json, json_rows, meta)


if __name__ == "__main__":
    main()
