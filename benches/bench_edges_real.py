"""Does ``edges="photo"`` help on real photos? ``refine_edges`` against a real network's edges.

There is no true depth for the real panoramas, so the reference is a real network's own
stitched disparity with the network run at a large input (``--reference-size``, larger than
the tiles: its edges are as sharp as that network makes them). It is smeared as a network
that sees each tile ``k`` times smaller would smear it (log disparity shrunk by area by ``k``,
then brought back bilinearly), and ``m360.stitching.refine_edges`` (the defaults of
``edges="photo"``) makes the smeared map sharp along the real photo. Printed per smear: the
median over the photos of the log-disparity AbsRel (|exp(log d − log ref) − 1|) in a 4 px band
(at 4096, in proportion) around the reference's jumps (``m360.eval.edge_band``: over 5 % in
disparity between neighbours) and over the whole map, smeared and refined, and on how many
photos the refined map is nearer the reference. The shared networks are weak and smooth: on
most 1K photos their maps have no jump of 5 % between neighbours, so ``--jump 0.01`` asks about
the edges they do have. With ``--radius-factor C ...`` each smear is
also refined with the window's radius at C·k pixels instead of the default (10 at 4096, in
proportion: 2-3 px at 1K), to ask whether a window as wide as the smear recovers it.

The synthetic rooms of ``bench_edges.py`` and ``bench_prior.py`` (their colour edges are
exactly their depth edges) say 3× better in the band; this is the check on real colour
statistics and a real network's depth (docs/method.md, "Sharp edges along the photo").

Needs the real data (tests/real_data.py: ``shared/real`` beside the checkout or
``M360_REAL_DATA``). Run: ``.venv/bin/python benches/bench_edges_real.py [--network pydnet]
[--reference-size 512] [--smear 3 6] [--radius-factor 1 2]`` (about two minutes for the twelve
1K photos).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import _harness as h
import m360
import real_data
from m360.estimators import load_estimator

#: The shared networks with the options their files need (the README beside them; the same as
#: tests/test_real.py): both take RGB in [0, 1] (``normalize="unit"``). Until stop 51 this said
#: "none", the raw 0-255 values: FastDepth then gave one and the same map for every tile, and the
#: real-photo verdicts of stops 36-50 measured that (docs/method.md, "Sharp edges along the
#: photo").
NETWORKS: dict[str, tuple[str, dict[str, Any]]] = {
    "pydnet": (
        "mobile_pydnet_dynamic.onnx",
        {
            "normalize": "unit",
            "multiple_of": 64,
            "output_kind": "negated_affine_disparity",
        },
    ),
    "fastdepth": (
        "fastdepth_dynamic.onnx",
        {"normalize": "unit", "multiple_of": 32, "output_kind": "affine_depth"},
    ),
}
#: Default relative disparity jump between neighbours that marks a reference edge (``--jump``).
JUMP = 0.05


def load_rgb(path: Path) -> np.ndarray:
    """The photo as RGB uint8."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SystemExit(f"cannot read {path}")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def smear(log_ref: np.ndarray, k: float) -> np.ndarray:
    """``log_ref`` as a network seeing the tiles ``k`` times smaller would give it."""
    hgt, wid = log_ref.shape
    small = cv2.resize(log_ref, (round(wid / k), round(hgt / k)), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (wid, hgt), interpolation=cv2.INTER_LINEAR)


def abs_rel(log_map: np.ndarray, log_ref: np.ndarray, where: np.ndarray) -> float:
    return float(np.mean(np.abs(np.expm1(log_map[where] - log_ref[where]))))


def window_radius(factor: float | None, k: float) -> int | None:
    """The refinement's window radius for ``--radius-factor`` ``factor`` at smear ``k``."""
    return None if factor is None else max(1, round(factor * k))


def one_photo(
    path: Path,
    network: str,
    size: int,
    smears: list[float],
    factors: list[float | None],
    jump: float = JUMP,
) -> list[list[list[float]]]:
    """Per smear and radius factor (None: the default radius): band and whole-map AbsRel of the
    smeared and the refined map."""
    file, options = NETWORKS[network]
    estimator = load_estimator(real_data.MODELS / file, input_size=size, **options)
    rgb = load_rgb(path)
    ref = m360.estimate(rgb, model=estimator).disparity
    valid = np.isfinite(ref) & (ref > 0)
    log_ref = np.log(np.where(valid, ref, np.nanmedian(ref[valid]))).astype(np.float32)
    # The band of bench_prior.py: 4 px at 4096, in proportion (at least 1).
    radius = max(1, round(4 * ref.shape[1] / 4096))
    band = m360.eval.edge_band(np.exp(-log_ref), band=radius, jump=jump) & valid
    out = []
    for k in smears:
        log_smeared = smear(log_ref, k)
        per_factor = []
        for factor in factors:
            radius = window_radius(factor, k)
            refined = m360.stitching.refine_edges(np.exp(log_smeared), rgb, radius=radius)
            log_refined = np.log(np.maximum(refined, np.finfo(np.float32).tiny))
            per_factor.append(
                [
                    abs_rel(log_smeared, log_ref, band),
                    abs_rel(log_refined, log_ref, band),
                    abs_rel(log_smeared, log_ref, valid),
                    abs_rel(log_refined, log_ref, valid),
                ]
            )
        out.append(per_factor)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--network", choices=sorted(NETWORKS), default="pydnet")
    parser.add_argument("--reference-size", type=int, default=512, help="network input, px")
    parser.add_argument("--smear", type=float, nargs="+", default=[3.0, 6.0], metavar="K")
    parser.add_argument(
        "--radius-factor",
        type=float,
        nargs="*",
        default=[],
        metavar="C",
        help="also refine with a window of radius C·k px",
    )
    parser.add_argument(
        "--jump", type=float, default=JUMP, help="reference edge: relative jump between neighbours"
    )
    parser.add_argument("--photos", type=Path, nargs="*", help="default: the twelve 1K photos")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH")
    args = parser.parse_args()
    if not real_data.PANOS.is_dir():
        raise SystemExit(real_data.MISSING)
    photos = args.photos or sorted(real_data.PANOS.glob("*_1k.tonemapped.png"))
    meta = h.metadata()
    print(f"m360 {m360.__version__} @ {meta.get('git_commit')}, {args.network}")
    factors: list[float | None] = [None, *args.radius_factor]
    per_photo = []
    for path in photos:
        per_photo.append(
            one_photo(path, args.network, args.reference_size, args.smear, factors, args.jump)
        )
        print(f"  done {path.name}", flush=True)
    # photo × smear × radius factor × (band smeared, band refined, whole smeared, whole refined)
    errors = np.array(per_photo)
    rows = []
    for i, k in enumerate(args.smear):
        for j, factor in enumerate(factors):
            med = np.median(errors[:, i, j], axis=0)
            nearer = int(np.sum(errors[:, i, j, 1] < errors[:, i, j, 0]))
            radius = "default" if factor is None else f"{factor:g}·k = {window_radius(factor, k)}"
            rows.append(
                [k, radius, *med.round(4), f"{med[1] / med[0]:.2f}x", f"{nearer}/{len(photos)}"]
            )
    h.print_table(
        f"refine_edges on {len(photos)} real photos, {args.network} at "
        f"{args.reference_size} px as the reference: medians of the log-disparity AbsRel",
        [
            "smear k",
            "radius px",
            "band smeared",
            "band refined",
            "whole smeared",
            "whole refined",
            "band ratio",
            "refined nearer",
        ],
        rows,
    )
    if args.json:
        h.write_json(args.json, rows, meta)


if __name__ == "__main__":
    main()
