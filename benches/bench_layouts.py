"""Tangent layouts with more redundancy: accuracy under content errors against network cost.

Table 1 (accuracy): on ``--scenes`` rooms per size, under two distortions — the affine one of
benches/bench_align.py (scale ×[0.5, 2], shift ±30 % of the median, a smooth ±10 % field, 1 %
noise) and content errors (``m360.synthetic.content_errors``) followed by the same affine one —
the median and worst AbsRel over the rooms and the median stitch seconds (alignment + blend, one
run per room) of each (layout, method) pair. Layouts (``LAYOUTS``, ``--layouts`` picks by
index): the paper's 20 faces at padding 0.3 / 0.5 / 0.7 / 1.0 (at the default tangent width,
so wider padding means larger pixels), the once-subdivided icosahedron (80 faces, the paper's
angular pixel size) at padding 0.2 / 0.3 with a 2x2 → 4x4 alignment schedule, and the 20 faces
at padding 0.7 / 1.0 widened to the paper's pixel size. Methods (``--methods``): the
defaults before issue 15 (least squares + Poisson), Cauchy loss + consensus blend (the default
blend), and Cauchy loss + the weighted-median blend.

Fairness: ``content_errors`` draws region sizes as fractions of a tile and a number of regions
per tile, so smaller tiles would get smaller errors and larger tiles larger ones. Every layout
here gets errors of one angular size and one density per solid angle instead: ``reference_area``
= the paper's tile area (346x400 at 2K) in the layout's own pixels ((fx / fx_paper)² of it), and
the blur (1 px per 2048 of ERP width in the paper's pixels) is scaled by fx / fx_paper. A third
distortion, "content, blur ∝ tile", models instead what a network with a fixed input size does:
it sees every tile at the same number of pixels, so its lost detail is a fixed fraction of the
tile (1 px per 2048 of ERP width on a 400-pixel tile, scaled by the tile's width): finer on the
80 smaller tiles, coarser on the wider padded ones (whose pixels are also larger). The
paper's layout at padding 0.3 passes no ``reference_area``: its errors are exactly those of
bench_align.py ``--robust`` and tests/test_robust.py.

Table 2 (network cost): per layout, tiles and their size, the mean and largest number of
tangents that see an ERP pixel's direction, and the time of the MiDaS-small-sized stand-in (the
random-weight CNN of benches/bench_estimate.py, 9 blocks, fixed 256x256 input, ONNX Runtime with
``--threads``) per tile, median of ``--repeats`` batches of 20 tiles, times the tiles: a network
with a fixed input costs the same per tile whatever the tile's size, so the cost is linear in the
number of tiles.

Run: ``.venv/bin/python benches/bench_layouts.py [--sizes 2048 4096] [--scenes 4]``.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import _harness as h
import m360
import m360.synthetic as syn
import onnx_graphs
from m360.geometry import sphere as sph

#: Alignment schedule of the 80-face layouts: nodes about as far apart, in angle, as the
#: default 4x3 → 8x7 on the paper's twice-as-wide tiles (8x7 on them costs 4-5x the time).
COARSE = {"align": [(2, 2), (4, 4)]}
#: Marks a 20-face layout whose tangents are widened to keep the paper's angular pixel size
#: (a wider padding at the default width has larger pixels: 1.6x at 0.7, 2x at 1.0).
PAPER_PIXELS = {"paper_pixels": True}
#: (label, subdivisions, padding, extra stitch keywords) of the layouts compared.
LAYOUTS = [
    ("20 faces, padding 0.3 (paper)", 0, 0.3, {}),
    ("20 faces, padding 0.5", 0, 0.5, {}),
    ("20 faces, padding 0.7", 0, 0.7, {}),
    ("20 faces, padding 1.0", 0, 1.0, {}),
    ("80 faces, padding 0.2, 2x2 → 4x4", 1, 0.2, COARSE),
    ("80 faces, padding 0.3, 2x2 → 4x4", 1, 0.3, COARSE),
    ("20 faces, padding 0.7, paper's pixels", 0, 0.7, PAPER_PIXELS),
    ("20 faces, padding 1.0, paper's pixels", 0, 1.0, PAPER_PIXELS),
]
#: (label, stitch keywords) of the methods compared.
METHODS = [
    ("before: least squares + poisson", {"loss": "squared", "blend": "poisson"}),
    ("cauchy + consensus", {}),
    ("cauchy + median", {"blend": "median"}),
]


def layout_of(
    width: int, subdivisions: int, padding: float, extra: dict | None = None
) -> m360.Layout:
    layout = m360.Layout.icosahedron(width, padding=padding, subdivisions=subdivisions)
    if extra and extra.get("paper_pixels"):
        paper = m360.Layout.icosahedron(width, padding=0.3)
        tangent_width = round(layout.tangent_shape[1] * paper.cameras[0].fx / layout.cameras[0].fx)
        layout = m360.Layout.icosahedron(width, padding=padding, tangent_width=tangent_width)
    return layout


def distorted_inputs(
    layout: m360.Layout, paper: m360.Layout, scene: Any, seed: int, width: int
) -> list[tuple[str, np.ndarray]]:
    """The affine and the content-error tangents of one room, errors at the paper's scale."""
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    ratio = layout.cameras[0].fx / paper.cameras[0].fx
    same = layout.key == paper.key
    h_, w_ = paper.tangent_shape
    reference = None if same else h_ * w_ * ratio**2
    wrong = syn.content_errors(
        exact, seed + 200, blur=ratio * width / 2048, reference_area=reference
    )
    cases = [("affine", exact), ("content errors", wrong)]
    if not same:  # the blur of a fixed-size network input: a fixed fraction of the tile
        tile_blur = layout.tangent_shape[1] / w_ * width / 2048
        cases.append(("content, blur ∝ tile", syn.content_errors(
            exact, seed + 200, blur=tile_blur, reference_area=reference)))  # fmt: skip
    return [
        (name, syn.distort(base, seed + 100, scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01))
        for name, base in cases
    ]


def accuracy_table(
    sizes: list[int], scenes: int, layouts: list[int], methods: list[int]
) -> tuple[list[list], list[list]]:
    rows, per_scene = [], []
    for width in sizes:
        paper = layout_of(width, 0, 0.3)
        results: dict[tuple[str, str, str], tuple[list[float], list[float]]] = {}
        for seed in range(scenes):
            scene = syn.room(seed)
            depth = scene.distance(sph.erp_directions(width // 2, width))
            for lname, sub, pad, extra in (LAYOUTS[k] for k in layouts):
                layout = layout_of(width, sub, pad, extra)
                for distortion, tiles in distorted_inputs(layout, paper, scene, seed, width):
                    for mname, method_kwargs in (METHODS[k] for k in methods):
                        kwargs = {**extra, **method_kwargs}
                        kwargs.pop("paper_pixels", None)
                        start = time.perf_counter()
                        out = m360.stitch(tiles, layout, **kwargs)
                        seconds = time.perf_counter() - start
                        err = m360.eval.depth_metrics(out, depth)["abs_rel"]
                        acc = results.setdefault((distortion, lname, mname), ([], []))
                        acc[0].append(err)
                        acc[1].append(seconds)
                        per_scene.append([width, seed, distortion, lname, mname, err])
            print(f"  done {width} room {seed}", flush=True)
        for (distortion, lname, mname), (errs, times) in results.items():
            rows.append([width, distortion, lname, mname, statistics.median(errs), max(errs),
                         statistics.median(times)])  # fmt: skip
    return rows, per_scene


def coverage(layout: m360.Layout) -> tuple[float, int]:
    """Area-weighted mean and largest number of tangent images that hold an ERP pixel."""
    height, width = layout.erp_shape
    d = sph.erp_directions(height, width)
    count = np.zeros((height, width), np.int32)
    for cam in layout.cameras:
        x, y, front = cam.project(d)
        inside = (x >= -0.5) & (x <= cam.width - 0.5) & (y >= -0.5) & (y <= cam.height - 0.5)
        count += front & inside
    area = np.cos(sph.erp_latitudes(height))[:, None] * np.ones((1, width))
    return float((count * area).sum() / area.sum()), int(count.max())


def network_table(width: int, repeats: int, threads: int) -> list[list]:
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        model = onnx_graphs.conv_net(Path(tmp) / "stand_in.onnx", size=256, width=32, layers=9)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        session = ort.InferenceSession(str(model), opts, providers=["CPUExecutionProvider"])
        name = session.get_inputs()[0].name
        batch = np.random.default_rng(0).standard_normal((1, 3, 256, 256)).astype(np.float32)
        session.run(None, {name: batch})  # warm-up

        def twenty() -> None:
            for _ in range(20):
                session.run(None, {name: batch})

        per_tile = h.measure(twenty, repeats=repeats).median / 20
    rows = []
    for lname, sub, pad, extra in LAYOUTS:
        layout = layout_of(width, sub, pad, extra)
        mean_cover, max_cover = coverage(layout)
        th, tw = layout.tangent_shape
        rows.append([lname, len(layout), f"{tw}x{th}", mean_cover, max_cover,
                     1000 * per_tile, len(layout) * per_tile])  # fmt: skip
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(sizes=[2048], repeats=5)
    parser.add_argument("--scenes", type=int, default=4, help="rooms per size (4)")
    parser.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (2)")
    parser.add_argument("--no-accuracy", action="store_true", help="only the network table")
    parser.add_argument("--layouts", type=int, nargs="+", default=list(range(len(LAYOUTS))),
                        help="indices into LAYOUTS (all)")  # fmt: skip
    parser.add_argument("--methods", type=int, nargs="+", default=list(range(len(METHODS))),
                        help="indices into METHODS (all)")  # fmt: skip
    args = parser.parse_args()
    meta = h.metadata()
    net = network_table(2048, args.repeats, args.threads)
    h.print_table(
        f"network cost per layout at 2K: stand-in CNN at 256x256, {args.threads} threads, median "
        f"of {args.repeats} batches of 20 tiles",
        ["layout", "tiles", "tile", "mean cover", "max cover", "ms/tile", "network s"],
        net,
    )
    if args.no_accuracy:
        return
    rows, per_scene = accuracy_table(args.sizes, args.scenes, args.layouts, args.methods)
    h.print_table(
        f"median AbsRel (and worst room) over {args.scenes} rooms, median stitch seconds (one "
        "run per room)",
        ["ERP", "distortion", "layout", "method", "AbsRel", "worst", "stitch s"],
        rows,
    )
    h.print_table("per room", ["ERP", "room", "distortion", "layout", "method", "AbsRel"],
                  per_scene)  # fmt: skip
    if args.json:
        h.write_json(args.json, [{"network": net, "accuracy": rows, "per_scene": per_scene}], meta)
    print(f"\n{meta.get('cpu_model')}, commit {meta.get('git_commit')}")


if __name__ == "__main__":
    main()
