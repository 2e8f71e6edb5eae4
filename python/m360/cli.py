"""Command line: ``m360 demo``, ``m360 run``, ``m360 models``.

``m360 run`` processes one image after another with :func:`m360.estimate.run_image` (the
per-image job that batch and Ray engines will call); folders, manifests, resume and workers come
with the batch module.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import cv2

from . import __version__, models, synthetic
from .errors import M360Error
from .estimate import OUTPUT_KINDS, SimulatedEstimator, estimate, run_image
from .eval import depth_metrics, format_metrics
from .geometry import Layout
from .io import save, save_npy, save_png
from .stitch import ALIGN_MODES, BLEND_MODES


def default_align() -> str:
    """The method's alignment (``"multiscale"``) when this build has it, else ``"none"``."""
    return "multiscale" if "multiscale" in ALIGN_MODES else "none"


def default_blend() -> str:
    """The method's blend (``"poisson"``) when this build has it, else ``"mean"``."""
    return "poisson" if "poisson" in BLEND_MODES else "mean"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``m360`` command; returns the exit code (0 ok, 1 failed, 2 usage)."""
    parser = argparse.ArgumentParser(prog="m360", description=__doc__)
    parser.add_argument("--version", action="version", version=f"m360 {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser(
        "demo",
        help="run m360.estimate on a synthetic panorama with a simulated network",
        description=(
            "Render a synthetic room with exact depth and run m360.estimate on it end to end "
            "with a SIMULATED network: each tangent gets its exact ray-cast perspective "
            "disparity with a random scale and shift and gaussian noise (what a perfect "
            "affine-invariant network would give). Write the outputs and print the paper's "
            "metrics against the true depth."
        ),
    )
    demo.add_argument("-o", "--output", type=Path, default=Path("out"), help="output folder")
    demo.add_argument("--width", type=int, default=2048, help="ERP width (height is half)")
    demo.add_argument("--seed", type=int, default=0, help="scene and distortion seed")
    demo.add_argument("--noise", type=float, default=0.01, help="relative noise of the network")
    _stitch_options(demo)

    run = commands.add_parser(
        "run",
        help="estimate the depth of panoramas",
        description=(
            "Estimate the depth of each equirectangular image (W == 2H) and write "
            "OUT/STEM.disparity.npy, OUT/STEM.depth.npy (float32, NaN = invalid), a colour "
            "preview OUT/STEM.preview.png and the sidecar OUT/STEM.json. The model is "
            "downloaded and verified on first use (see `m360 models`)."
        ),
    )
    run.add_argument("inputs", nargs="+", type=Path, help="panorama image files")
    run.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    run.add_argument(
        "--model",
        default=models.DEFAULT_MODEL,
        help=f"registry name or path to an .onnx file (default {models.DEFAULT_MODEL})",
    )
    run.add_argument("--threads", type=int, default=None, help="ONNX Runtime intra-op threads")
    run.add_argument(
        "--input-size",
        type=int,
        nargs=2,
        metavar=("H", "W"),
        default=None,
        help="network input size of a dynamic-size .onnx file (default: the model's)",
    )
    run.add_argument(
        "--output-kind",
        choices=OUTPUT_KINDS,
        default=None,
        help="what a .onnx file outputs (default: the registry's, or affine_disparity)",
    )
    run.add_argument(
        "--providers",
        default=None,
        help="ONNX Runtime providers, comma-separated (e.g. CUDAExecutionProvider,"
        "CPUExecutionProvider); default CPU",
    )
    _stitch_options(run)

    mod = commands.add_parser("models", help="list, fetch or locate depth models")
    mod_commands = mod.add_subparsers(dest="action")
    fetch = mod_commands.add_parser("fetch", help="download and verify models")
    fetch.add_argument("names", nargs="+", choices=models.names(), metavar="NAME")
    fetch.add_argument("--force", action="store_true", help="download again even if cached")
    where = mod_commands.add_parser("path", help="print where a model's file is (or goes)")
    where.add_argument("name", choices=models.names(), metavar="NAME")

    args = parser.parse_args(argv)
    try:
        if args.command == "demo":
            return _demo(args.output, args.width, args.seed, args.noise, args.align, args.blend)
        if args.command == "run":
            providers = args.providers.split(",") if args.providers else None
            return _run(args, providers)
        return _models_command(args)
    except M360Error as exc:
        print(f"m360: error: {exc}", file=sys.stderr)
        return 1


def _stitch_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--align",
        choices=ALIGN_MODES,
        default=default_align(),
        help=f"alignment (default {default_align()!r} in this build)",
    )
    parser.add_argument(
        "--blend",
        choices=BLEND_MODES,
        default=default_blend(),
        help=f"blending (default {default_blend()!r} in this build)",
    )


def _demo(out: Path, width: int, seed: int, noise: float, align: str, blend: str) -> int:
    t0 = time.perf_counter()
    layout = Layout.icosahedron(width)
    scene = synthetic.room(seed)
    rgb, gt_depth = synthetic.render(scene, width)
    network = SimulatedEstimator(scene, layout, seed=seed, noise=noise)
    print(f"m360 {__version__} demo: {width}x{width // 2} synthetic room (seed {seed}), {layout}")
    print(
        "  network: SIMULATED, not a trained model: exact tangent disparity with a random "
        f"scale/shift per tangent and {noise:g} relative noise"
    )
    print(f"  rendered in {time.perf_counter() - t0:.1f} s; align={align!r} blend={blend!r}")
    result = estimate(rgb, network, align=align, blend=blend)
    metrics = depth_metrics(result.disparity, gt_depth)
    stages = ", ".join(f"{k} {v:.3f}" for k, v in result.timings.items())
    print(f"  timings (s): {stages}")
    print(f"  vs true depth: {format_metrics(metrics)}")
    if align == "none":
        print(
            "  alignment is not in this build (align='none'): the per-tangent distortion stays; "
            "the multi-scale alignment removes it"
        )
    written = save(result, out / "demo", extra={"input": "synthetic.room", "seed": seed})
    written["rgb"] = save_png(out / "demo_rgb.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    written["gt_depth"] = save_npy(out / "demo_gt_depth.npy", gt_depth)
    print("  wrote " + ", ".join(str(p) for p in written.values()))
    return 0


def _run(args: argparse.Namespace, providers: list[str] | None) -> int:
    failures = 0
    for path in args.inputs:
        try:
            summary = run_image(
                path,
                args.output,
                model=args.model,
                align=args.align,
                blend=args.blend,
                threads=args.threads,
                providers=providers,
                input_size=tuple(args.input_size) if args.input_size else None,
                output_kind=args.output_kind,
            )
        except M360Error as exc:
            failures += 1
            print(f"m360: {path}: error: {exc}", file=sys.stderr)
            continue
        total = summary["timings"]["total"]
        print(f"{path} -> {summary['outputs']['sidecar']} ({total:.2f} s)")
    if failures:
        print(f"m360: {failures} of {len(args.inputs)} images failed", file=sys.stderr)
    return 1 if failures else 0


def _models_command(args: argparse.Namespace) -> int:
    if args.action == "fetch":
        for name in args.names:
            path = models.fetch(name, force=args.force)
            print(f"{name}: {path} (sha256 verified)")
        return 0
    if args.action == "path":
        entry = models.get(args.name)
        print(models.local_path(entry) or models.cache_dir() / entry.filename)
        return 0
    print(f"models cache: {models.cache_dir()}  (set M360_HOME to move it)")
    header = f"{'name':<24} {'size':>8}  {'cached':<6}  {'sha256':<10}  licence"
    print(header)
    print("-" * len(header))
    for row in models.list_models():
        size = "?" if row["size_mb"] is None else f"{row['size_mb']:.0f} MB"
        cached = "yes" if row["cached"] else "no"
        sha = row["sha256"][:8] if row["sha256"] else "UNKNOWN"
        print(f"{row['name']:<24} {size:>8}  {cached:<6}  {sha:<10}  {row['licence']}")
    print("fetch with `m360 models fetch NAME`; the default model is fetched on first `m360 run`")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
