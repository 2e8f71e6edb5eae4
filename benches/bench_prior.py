"""The global prior (issue 24): accuracy and cost of ``m360.stitch(..., prior=...)``.

Tangents on the default layout (20 faces, the default padding) as in ``bench_align.py
--robust``: ray cast exactly, then either affine errors only
(``distort``: scale ×[0.5, 2], shift ±30 %, a ±10 % smooth field, 1 % noise) or content errors
first (``content_errors``: 1-3 regions per tangent of 3-17 % of the tile, ±10-30 %, blur of 1 px
per 2048 of ERP width) and then the same affine errors. The prior is
``m360.synthetic.panoramic_prior`` of the same room (512 x 1024, blur 1.5 px, ±3 % smooth error,
0-2 regional errors of 1-5 % of the sphere at ±10-30 %, its own affine ambiguity), given as
``prior_kind="affine_disparity"``; "wrong prior" is the same with one regional error of 30 % on a
cap of 20 % of the sphere (and no others). Two references bound the affine-error case: the same
prior without its smooth error (``field=0``) and with a ±5 % one. A prior as poor as the
tangents (a ±10 % smooth error) checks that a worse panoramic network than the simulated one
does little harm, and the wrong prior with the affine-error tangents that a regional error does
not pass for a poor prior: the fusion weighs the prior's quality (docs/method.md, "The prior's
own quality").

Tables (medians over ``--scenes`` rooms, ``m360.synthetic.room(seed)`` for seeds from
``--first-room``, 0 by default; the defaults were tuned on rooms 0-3, so ``--first-room 4`` asks
rooms they never saw):

1. AbsRel per size and case: content errors without / with the prior, affine errors without /
   with it, content errors with the wrong prior; the goals of issue 24 beside them; the
   content-error case with the prior made sharp along the photo (``refine_edges``); and milder
   affine errors (a ±3 % field instead of ±10 %) without / with the prior, where the tangents
   agree well enough to correct the prior's own smooth error (``tangent_share``).
2. Detail at ``--detail-size`` (4096): AbsRel in a band of 4 px around the depth edges of the
   truth (a jump of more than 5 % between neighbours, dilated by 4 px), for the stitch with the
   prior and for the prior alone brought to that size by ``m360.stitching.guided_upsample``
   (guided by the rendered photo), and for the stitch made sharp along the photo's edges by
   ``m360.stitching.refine_edges`` with its time: what ``m360.estimate`` does by default
   (``edges="auto"``) for a network that sees its tile 4 or more times smaller, as the bench's
   tangents model at 4K (a network at about 200 px on the 800 px tiles). All
   are scale/shift-fitted to the truth by ``depth_metrics``. Then the stitch with the prior of
   the same content errors unblurred (a network at least as fine as its tile), and from a
   simulated network that sees each tile at 256 or 518 px (MiDaS small's input, Depth
   Anything's), blurred by half the tile's shrink factor, on the default layout and on the 80
   tangents of ``subdivisions=1``: the detail is the network's angular resolution
   (docs/method.md, "Where the detail comes from").
3. With ``--stress``, per size: the content- and affine-error tangents with no prior, the
   bench's prior, the wrong one, those with a ±5 % and a ±10 % smooth error, and the bench's
   prior broken as :data:`STRESS` says (a lower third 30 % too far, a ramp to 15 % at the
   0/360° seam, a ±20 % tilt between floor and ceiling), and the share of prior samples the
   tangents' consensus outvoted (docs/method.md, "Outvoted by the consensus") and the share of
   the prior's gap at the sphere's largest scales that moved it ("The sphere's largest
   scales").
4. Stitch seconds with and without the prior per ``--time-sizes`` (default 2048 8192), median
   of ``--repeats`` interleaved runs on one room, their ratio, and the median of the ratios of
   each pair of neighbouring runs (less moved by a shared machine's slow drifts). At 8K the
   ratio also depends on how glibc reuses large blocks between calls (docs/method.md, "Global
   prior": 1.18x by default, 1.09x with ``MALLOC_MMAP_THRESHOLD_=4294967296``).

Run: ``.venv/bin/python benches/bench_prior.py [--sizes 2048 4096] [--scenes 4] [--first-room 0]``.
Options of the prior term can be tried with ``--prior-weight`` / ``--prior-scale-deg``.
"""

from __future__ import annotations

import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as h
import m360
import m360.synthetic as syn
from m360.geometry import sphere as sph
from m360.stitching.edges import edges_for

#: The goals of issue 24 per case (None: no goal, a reference).
GOALS = {
    "content errors, no prior": "(~0.022)",
    "content errors, with prior": "<= 0.012",
    "affine errors, no prior": "(~0.011)",
    "affine errors, with prior": "<= 0.009",
    "content errors, wrong prior": "<= no prior + 0.002",
    "milder affine errors (±3 % field), no prior": "-",
    "milder affine errors (±3 % field), with prior": "(below both)",
    # What bounds "affine errors, with prior": the prior's own smooth error, which tangents that
    # disagree by ±10 % cannot correct (docs/method.md, "What bounds the affine-error case").
    "affine errors, prior without its smooth error": "(reference)",
    "affine errors, prior with a ±5 % smooth error": "(reference)",
    # A prior as poor as the tangents, and one with a regional error where the tangents agree
    # well enough to be fused with it (docs/method.md, "The prior's own quality").
    "affine errors, prior with a ±10 % smooth error": "(about no prior)",
    "affine errors, wrong prior": "(reference)",
}
#: The content-error case with the prior, then ``refine_edges`` (``edges="photo"``).
SHARP = "content errors, with prior, edges='photo'"
GOALS[SHARP] = "(<= 0.012)"


#: The tangents' affine errors (``syn.distort``), after any content errors.
AFFINE: dict[str, Any] = {"scale": (0.5, 2.0), "shift": 0.3, "field": 0.1, "noise": 0.01}


#: The content-error tangents' blur in tangent pixels per pixel of ERP width (1 px at 2K).
BLUR_PER_WIDTH = 1 / 2048


def tangents(scene: syn.Scene, layout: m360.Layout, width: int, seed: int) -> dict[str, Any]:
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    wrong = syn.content_errors(exact, seed + 200, blur=width * BLUR_PER_WIDTH)
    return {
        "affine": syn.distort(exact, seed + 100, **AFFINE),
        "content": syn.distort(wrong, seed + 100, **AFFINE),
        "milder": syn.distort(exact, seed + 100, **{**AFFINE, "field": 0.03}),
    }


#: The simulated priors by name: keyword arguments of ``syn.panoramic_prior`` beyond its defaults.
PRIORS: dict[str, dict[str, Any]] = {
    "good": {},
    "wrong": {"regions": (1, 1), "region_share": (0.2, 0.2), "region_amplitude": (0.3, 0.3)},
    "no smooth error": {"field": 0.0},
    "±5 % smooth error": {"field": 0.05},
    "±10 % smooth error": {"field": 0.10},
}


def prior_of(scene: syn.Scene, seed: int, name: str = "good") -> np.ndarray:
    """The simulated prior ``name`` (:data:`PRIORS`) of room ``seed``."""
    return np.asarray(syn.panoramic_prior(scene, seed + 300, **PRIORS[name]))


def _latitudes(prior: np.ndarray) -> np.ndarray:
    """Row-centre latitudes of an (H, 2H) map in degrees, as a column."""
    h = prior.shape[0]
    return (90.0 - (np.arange(h) + 0.5) * 180.0 / h)[:, None]


#: Priors broken in ways :data:`PRIORS` are not (``--stress``): the bench's prior times a
#: factor per pixel. docs/method.md, "Outvoted by the consensus".
STRESS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "the lower third 30 % too far (lat < -30°)": lambda p: 1.0 - 0.3 * (_latitudes(p) < -30.0),
    "a ramp around the sphere, 15 % at the seam": lambda p: (
        1.0 + 0.15 * (np.arange(p.shape[1]) + 0.5)[None, :] / p.shape[1]
    ),
    "a tilt: ±20 % · sin(latitude)": lambda p: 1.0 + 0.2 * np.sin(np.radians(_latitudes(p))),
}


def stress(sizes: list[int], rooms: range, tuning: dict[str, Any]) -> list[list]:
    """AbsRel per size, tangent case and prior (none, four of :data:`PRIORS`, :data:`STRESS`)."""
    rows = []
    for width in sizes:
        layout = m360.Layout.icosahedron(width)
        errs: dict[tuple[str, str], list[float]] = {}
        for seed in rooms:
            scene = syn.room(seed)
            depth = scene.distance(sph.erp_directions(width // 2, width))
            tiles = tangents(scene, layout, width, seed)
            good = prior_of(scene, seed)
            priors = {"no prior": None, "the bench's prior": good}
            for name in ("wrong", "±5 % smooth error", "±10 % smooth error"):
                priors[f"the {name} prior"] = prior_of(scene, seed, name)
            priors.update({name: (good * f(good)).astype(np.float32) for name, f in STRESS.items()})
            for case in ("content", "affine"):
                for name, prior in priors.items():
                    kw = tuning if prior is not None else {}
                    res = m360.stitch(tiles[case], layout, prior=prior, return_details=True, **kw)
                    fit = res.report.get("prior") or {}
                    errs.setdefault((case, name), []).append(
                        m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
                    )
                    for key in ("consensus_outvoted", "low_order_share"):
                        errs.setdefault((case, f"{name} {key}"), []).append(
                            fit.get(key, float("nan"))
                        )
        for (case, name), values in errs.items():
            if not name.endswith(("consensus_outvoted", "low_order_share")):
                voted, bent = (
                    statistics.median(errs[(case, f"{name} {key}")])
                    for key in ("consensus_outvoted", "low_order_share")
                )
                rows.append([width, f"{case} errors", name, statistics.median(values), voted, bent])
        print(f"  stressed {width}", flush=True)
    return rows


def accuracy(sizes: list[int], rooms: range, tuning: dict[str, Any]) -> list[list]:
    rows = []
    for width in sizes:
        layout = m360.Layout.icosahedron(width)
        errs: dict[str, list[float]] = {}
        outvoted: dict[str, list[float]] = {}
        shares: dict[str, list[float]] = {}
        for seed in rooms:
            scene = syn.room(seed)
            depth = scene.distance(sph.erp_directions(width // 2, width))
            rgb = syn.render(scene, width)[0]  # for refine_edges
            tiles = tangents(scene, layout, width, seed)
            prior = {name: prior_of(scene, seed, name) for name in PRIORS}
            cases = {
                "content errors, no prior": (tiles["content"], None),
                "content errors, with prior": (tiles["content"], prior["good"]),
                "affine errors, no prior": (tiles["affine"], None),
                "affine errors, with prior": (tiles["affine"], prior["good"]),
                "content errors, wrong prior": (tiles["content"], prior["wrong"]),
                "affine errors, prior without its smooth error": (
                    tiles["affine"],
                    prior["no smooth error"],
                ),
                "affine errors, prior with a ±5 % smooth error": (
                    tiles["affine"],
                    prior["±5 % smooth error"],
                ),
                "affine errors, prior with a ±10 % smooth error": (
                    tiles["affine"],
                    prior["±10 % smooth error"],
                ),
                "affine errors, wrong prior": (tiles["affine"], prior["wrong"]),
                "milder affine errors (±3 % field), no prior": (tiles["milder"], None),
                "milder affine errors (±3 % field), with prior": (tiles["milder"], prior["good"]),
            }
            for name, (t, p) in cases.items():
                kw = tuning if p is not None else {}
                res = m360.stitch(t, layout, prior=p, return_details=True, **kw)
                errs.setdefault(name, []).append(
                    m360.eval.depth_metrics(res.disparity, depth)["abs_rel"]
                )
                if name == "content errors, with prior":
                    sharp = m360.stitching.refine_edges(res.disparity, rgb)
                    errs.setdefault(SHARP, []).append(
                        m360.eval.depth_metrics(sharp, depth)["abs_rel"]
                    )
                fit = res.report.get("prior")
                if fit is not None:
                    outvoted.setdefault(name, []).append(fit["outvoted"])
                    shares.setdefault(name, []).append(fit["tangent_share"])
        nan = [float("nan")]
        for name, values in errs.items():
            rows.append(
                [
                    width,
                    name,
                    statistics.median(values),
                    max(values),
                    statistics.median(outvoted.get(name, nan)),
                    statistics.median(shares.get(name, nan)),
                    GOALS[name],
                ]
            )
        print(f"  done {width}", flush=True)
    return rows


#: Simulated tangent networks by the input width they see a tile at, and the layouts they run
#: on (``subdivisions``): where the stitch's detail comes from (docs/method.md, "Where the
#: detail comes from").
NETWORK_INPUTS = (256, 518)
NETWORK_LAYOUTS = {"the default layout": 0, "subdivisions=1 (80 tangents)": 1}


def network_tangents(
    scene: syn.Scene, layout: m360.Layout, seed: int, network_input: int | None
) -> np.ndarray:
    """The content-error tangents of a network that sees each tile at ``network_input`` px.

    The tile shrunk to the network's input and its output brought back smear an edge by a
    gaussian of about half the shrink factor (area down, bilinear up), so the blur is
    ``tile width / (2 network_input)`` tangent pixels: the same network is sharper in angle on
    smaller tiles. ``None``: no blur (a network at least as fine as the tile). Errors have the
    default layout's angular size and density on every layout.
    """
    base = m360.Layout.icosahedron(layout.erp_shape[1])
    ratio = layout.cameras[0].fx / base.cameras[0].fx
    reference = (
        None if layout.key == base.key else base.tangent_shape[0] * base.tangent_shape[1] * ratio**2
    )
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    blur = 0.0 if network_input is None else layout.tangent_shape[1] / (2 * network_input)
    wrong = syn.content_errors(exact, seed + 200, blur=blur, reference_area=reference)
    return np.asarray(syn.distort(wrong, seed + 100, **AFFINE))


def detail(width: int, rooms: range, tuning: dict[str, Any]) -> list[list]:
    layout = m360.Layout.icosahedron(width)
    stitched, sharpened, unblurred, alone, seconds = [], [], [], [], []
    networks: dict[tuple[str, int], list[float]] = {}
    for seed in rooms:
        scene = syn.room(seed)
        rgb, depth = syn.render(scene, width)
        band = m360.eval.edge_band(depth)
        tiles = tangents(scene, layout, width, seed)["content"]
        prior = prior_of(scene, seed)
        res = m360.stitch(tiles, layout, prior=prior, **tuning)
        timed = h.measure(lambda r=res, p=rgb: m360.stitching.refine_edges(r, p), repeats=3)
        seconds.append(timed.median)
        sharp = m360.stitching.refine_edges(res, rgb)
        up = m360.stitching.guided_upsample(prior, rgb)
        sharp_tiles = network_tangents(scene, layout, seed, None)
        finest = m360.stitch(sharp_tiles, layout, prior=prior, **tuning)
        for values, d in ((stitched, res), (sharpened, sharp), (unblurred, finest), (alone, up)):
            values.append(m360.eval.depth_metrics(d, depth, valid=band)["abs_rel"])
        for name, subdivisions in NETWORK_LAYOUTS.items():
            lay = m360.Layout.icosahedron(width, subdivisions=subdivisions)
            for n in NETWORK_INPUTS:
                d = m360.stitch(network_tangents(scene, lay, seed, n), lay, prior=prior, **tuning)
                networks.setdefault((name, n), []).append(
                    m360.eval.depth_metrics(d, depth, valid=band)["abs_rel"]
                )
    s, e, u, a = (statistics.median(v) for v in (stitched, sharpened, unblurred, alone))
    # The network the tangents model (network_tangents' blur, tile / (2 input), equal to
    # tangents' width · BLUR_PER_WIDTH) and what m360.estimate's default edges="auto" does for it.
    tile = layout.tangent_shape[1]
    modelled = round(tile / (2 * width * BLUR_PER_WIDTH))
    default = edges_for("auto", tile, modelled)
    rows = [
        [width, "stitch alone (m360.stitch: no photo)", s, a, a / s, "", "(>= 2x)"],
        [
            width,
            f"stitch + refine_edges (edges='auto' gives {default!r}: a {modelled} px network)",
            e,
            a,
            a / e,
            statistics.median(seconds),
            ">= 2x",
        ],
    ]
    rows.append(
        [
            width,
            "stitch, tangents not blurred (a network as fine as its tile)",
            u,
            a,
            a / u,
            "",
            "(>= 2x)",
        ]
    )
    for (name, n), values in networks.items():
        m = statistics.median(values)
        rows.append([width, f"stitch, a {n} px network, {name}", m, a, a / m, "", "(>= 2x)"])
    return rows


def timing(sizes: list[int], repeats: int, tuning: dict[str, Any]) -> list[list]:
    rows = []
    scene = syn.room(0)
    prior = prior_of(scene, 0)
    for width in sizes:
        layout = m360.Layout.icosahedron(width)
        tiles = tangents(scene, layout, width, 0)["content"]
        m360.stitch(tiles, layout)  # plan built, caches warm

        def plain(t: np.ndarray = tiles, lay: m360.Layout = layout) -> None:
            m360.stitch(t, lay)

        def with_prior(t: np.ndarray = tiles, lay: m360.Layout = layout) -> None:
            m360.stitch(t, lay, prior=prior, **tuning)

        # Interleaved, so drifts of a shared machine hit both alike.
        a, b = [], []
        for _ in range(repeats):
            a.append(h.measure(plain, repeats=1, warmup=0).median)
            b.append(h.measure(with_prior, repeats=1, warmup=0).median)
        ta, tb = statistics.median(a), statistics.median(b)
        pairs = statistics.median(y / x for x, y in zip(a, b, strict=True))
        rows.append([width, ta, tb, tb / ta, pairs, "<= 1.2x"])
        print(f"  timed {width}", flush=True)
    return rows


def main() -> None:
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=3, sizes=[2048])
    parser.add_argument("--scenes", type=int, default=4, help="rooms per size (4)")
    parser.add_argument(
        "--first-room",
        type=int,
        default=0,
        help="seed of the first room (0; rooms the tuning never saw: 4)",
    )
    parser.add_argument("--detail-size", type=int, default=4096, help="ERP width of table 2")
    parser.add_argument("--time-sizes", type=int, nargs="*", default=[2048, 8192])
    parser.add_argument("--prior-weight", type=float, default=None)
    parser.add_argument("--prior-scale-deg", type=float, default=None)
    parser.add_argument("--skip", nargs="*", default=[], choices=["accuracy", "detail", "time"])
    parser.add_argument(
        "--stress", action="store_true", help="also the priors broken otherwise (STRESS), per size"
    )
    args = parser.parse_args()
    tuning = {
        k: v
        for k, v in (("prior_weight", args.prior_weight), ("prior_scale_deg", args.prior_scale_deg))
        if v is not None
    }
    rooms = range(args.first_room, args.first_room + args.scenes)
    meta = h.metadata()
    print(f"m360 {m360.__version__} @ {meta.get('git_commit')}, threads {m360.get_num_threads()}")
    out: dict[str, Any] = {"tuning": tuning}
    if "accuracy" not in args.skip:
        rows = accuracy(args.sizes, rooms, tuning)
        h.print_table(
            f"AbsRel, median (and worst) over rooms {rooms.start}-{rooms.stop - 1}; outvoted = "
            "median share of the prior's pull its robust weights removed; fused = median share "
            "of the tangents' low-frequency disagreement that moved the prior (tangent_share)",
            ["ERP", "case", "AbsRel", "worst", "outvoted", "fused", "goal"],
            rows,
        )
        out["accuracy"] = rows
    if "detail" not in args.skip:
        rows = detail(args.detail_size, rooms, tuning)
        h.print_table(
            "AbsRel in a 4 px band around depth edges: stitch with the prior vs the prior alone "
            "(guided upsampling); refine s = median seconds of refine_edges",
            ["ERP", "result", "with prior", "prior alone", "ratio", "refine s", "goal"],
            rows,
        )
        out["detail"] = rows
    if args.stress:
        rows = stress(args.sizes, rooms, tuning)
        h.print_table(
            f"AbsRel, median over rooms {rooms.start}-{rooms.stop - 1}, with priors broken "
            "otherwise; outvoted = median share of prior samples the tangents' consensus "
            "outvoted; bent = median share of the prior's gap at the sphere's largest scales "
            "that moved it (low_order_share)",
            ["ERP", "tangents", "prior", "AbsRel", "outvoted", "bent"],
            rows,
        )
        out["stress"] = rows
    if "time" not in args.skip and args.time_sizes:
        rows = timing(args.time_sizes, args.repeats, tuning)
        h.print_table(
            f"stitch seconds without / with the prior, median of {args.repeats}",
            ["ERP", "no prior s", "prior s", "ratio", "pair ratio", "goal"],
            rows,
        )
        out["time"] = rows
    if args.json:
        h.write_json(args.json, [out], meta)


if __name__ == "__main__":
    main()
