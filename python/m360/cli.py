"""Command line: ``m360 demo``, ``m360 run``, ``m360 eval``, ``m360 models``.

``m360 run`` is :func:`m360.batch.run` (folders, manifests, resume, workers, failures.jsonl);
exit codes: 0 every image succeeded (or was already done), 1 some failed, 2 usage errors (or
the model failed on the first image: the run stops there), 3 none failed but some were still
being written by another run into OUT (rerun to finish them), 130 interrupted (Ctrl-C; rerun
to finish). ``m360 video`` is :func:`m360.video.run` (every frame of a 360° video, resumable,
the same exit codes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from . import batch
from ._core import __version__
from ._keywords import add_flags, definition, from_args, plain_text
from .errors import InputError, M360Error, ModelError
from .estimators import ModelKeywords, ModelOptions, SimulatedEstimator
from .estimators import registry as models
from .evaluation import synthetic
from .evaluation.metrics import depth_metrics, format_metrics
from .geometry.layout import default_layout
from .io import (
    GEOMETRY_FORMATS,
    KNOWN_FORMATS,
    NORMALS_FORMATS,
    SAVE_FORMATS,
    STEREO_FORMATS,
    load,
    output_stem,
    read_array,
    save,
    save_npy,
    save_png,
)
from .io.mesh import DEFAULT_MAX_VERTICES, check_max_vertices
from .io.stereo import StereoKeywords
from .pipeline import masks as m360_masks
from .pipeline import scale as m360_scale
from .pipeline.estimate import estimate
from .pipeline.options import JobKeywords, PriorKeywords
from .pipeline.prior import PRIOR_MODEL_OPTIONS
from .stitching.edges import AUTO_PHOTO_SHRINK, edges_for
from .stitching.options import StitchKeywords, StitchOptions

#: Where ``m360 run`` can run images; the first is the default.
ENGINES = batch.ENGINES


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``m360`` command; return its exit code (the module docstring lists them)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage error (2) or --help/--version (0)
        return int(exc.code or 0)
    return _dispatch(args)


def build_parser() -> argparse.ArgumentParser:
    """Build the parser of every ``m360`` command (flags from the shared option lists)."""
    parser = argparse.ArgumentParser(prog="m360", description=plain_text(__doc__ or ""))
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
        help="estimate the depth of panoramas (files, folders, manifests)",
        description=(
            "Estimate the depth of each equirectangular image (W == 2H) and write, per image, "
            "OUT/STEM.disparity.EXT and OUT/STEM.depth.EXT per format (float32, NaN = invalid; "
            "png16: 0 = invalid, scale in the sidecar), a colour preview OUT/STEM.preview.png "
            "and last the sidecar OUT/STEM.json. INPUTS are image files, folders, or manifests "
            "(.txt: a path per line; .csv: input[,output]). A rerun skips images already done "
            "with the same input and options; failures go to OUT/failures.jsonl and the run "
            "goes on. Folder scans leave out m360's own outputs and depth maps (a single-"
            "channel 16-bit PNG or TIFF, a single-channel float EXR or TIFF); a file named "
            "here is always tried. The model is downloaded and verified on first use (see "
            "`m360 models`). Exit codes: 0 all done, 1 some failed, 2 usage error, 3 some "
            "images were still being written by another run (rerun), 130 interrupted."
        ),
    )
    run.add_argument("inputs", nargs="+", type=Path, help="images, folders or manifests")
    run.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    run.add_argument(
        "--model",
        default=models.DEFAULT_MODEL,
        help=f"registry name or path to an .onnx file (default {models.DEFAULT_MODEL})",
    )
    run.add_argument(
        "--formats",
        type=_formats,
        default=("npy",),
        help=f"comma-separated formats: arrays {', '.join(SAVE_FORMATS)} (default npy); 3D "
        f"{', '.join(GEOMETRY_FORMATS)} (ply: point cloud, glb: mesh, splat: Gaussian splats; "
        f"extra m360[3d]); {', '.join(NORMALS_FORMATS)} (surface normals, exr and png); VR "
        f"{', '.join(STEREO_FORMATS)} (the stereo 360 pair top-bottom, left eye on top, JPEG or "
        "PNG, GPano stereo XMP)",
    )
    run.add_argument("--no-preview", action="store_true", help="do not write the colour preview")
    run.add_argument(
        "--confidence",
        action="store_true",
        help="also write OUT/STEM.confidence.EXT (overlap disagreement left, lower = better)",
    )
    run.add_argument(
        "--max-vertices",
        type=_max_vertices,
        default=DEFAULT_MAX_VERTICES,
        metavar="N",
        help=f"most vertices (splats) of each 3D file (ply, glb, splat): larger images are "
        f"strided to fit (default {DEFAULT_MAX_VERTICES}; 'none': every pixel); the sidecar "
        "records the stride",
    )
    add_flags(
        run.add_argument_group("stereo outputs (--formats stereo, stereo-png)"), StereoKeywords
    )
    run.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes working at once (--engine ray: model actors, one network session each)",
    )
    again = run.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        dest="resume",
        action="store_true",
        default=True,
        help="skip images already done with the same input and options (default)",
    )
    again.add_argument("--overwrite", dest="resume", action="store_false", help="redo every image")
    run.add_argument("--recursive", action="store_true", help="also look in sub-folders")
    run.add_argument(
        "--fix-aspect",
        action="store_true",
        help="resize images that are not W == 2H to W x W/2 (default: they fail)",
    )
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument(
        "--engine",
        choices=ENGINES,
        default=ENGINES[0],
        help='where images run: local processes (default) or ray (pip install "m360[ray]"; '
        "the cluster in RAY_ADDRESS, else a local one)",
    )
    run.add_argument(
        "--gpus-per-model",
        type=float,
        default=None,
        help="--engine ray: GPUs per model actor (default 1 with a CUDA provider, else 0)",
    )
    run.add_argument(
        "--cpus-per-stitch",
        type=float,
        default=1.0,
        help="--engine ray: CPUs per align + blend task (default 1)",
    )
    run.add_argument(
        "--camera-height",
        type=float,
        default=None,
        metavar="METRES",
        help="metric depth: the camera is METRES above the floor (floor plane fit; images "
        "without a visible floor fail with ScaleError)",
    )
    run.add_argument(
        "--nadir",
        type=float,
        default=None,
        metavar="DEG",
        help="leave out the cap within DEG degrees of the bottom pole (tripod, operator): NaN "
        "there, and no part in alignment or blending",
    )
    run.add_argument(
        "--zenith",
        type=float,
        default=None,
        metavar="DEG",
        help="leave out the cap within DEG degrees of the top pole",
    )
    add_flags(run.add_argument_group("model (ONNX models given by name or path)"), ModelKeywords)
    add_flags(run.add_argument_group("job"), JobKeywords)
    add_flags(
        run.add_argument_group(
            "global prior (a panoramic model or an ERP map the alignment pulls the tangents' "
            "low frequencies toward; tangent models only)"
        ),
        PriorKeywords,
    )
    _stitch_options(run)
    _add_video_parser(commands)

    ev = commands.add_parser(
        "eval",
        help="the paper's depth metrics of a prediction against ground truth",
        description=(
            "Print AbsRel, RMSE, log10 and the delta accuracies of PRED against GT after a "
            "least-squares scale and shift of the disparity (docs/method.md, evaluation). PRED "
            "is an m360 output (its stem, sidecar or any of its files) or an array file (.npy, "
            ".pfm, .exr); GT is an array file of radial depth (or disparity with --gt-kind)."
        ),
    )
    ev.add_argument("pred", type=Path, help="m360 output or array file")
    ev.add_argument("gt", type=Path, help="ground-truth array file (.npy, .pfm, .exr)")
    ev.add_argument("--pred-kind", choices=("disparity", "depth"), default="disparity")
    ev.add_argument("--gt-kind", choices=("depth", "disparity"), default="depth")
    ev.add_argument(
        "--pole-cap", type=float, default=0.0, help="ignore this many degrees at each pole"
    )
    ev.add_argument(
        "--weighting", choices=("uniform", "solid_angle"), default="uniform", help="pixel weights"
    )
    ev.add_argument("--json", action="store_true", help="print the metrics as JSON")

    mod = commands.add_parser("models", help="list, fetch or locate depth models")
    mod_commands = mod.add_subparsers(dest="action")
    fetch = mod_commands.add_parser("fetch", help="download and verify models")
    fetch.add_argument("names", nargs="+", choices=models.names(), metavar="NAME")
    fetch.add_argument("--force", action="store_true", help="download again even if cached")
    where = mod_commands.add_parser("path", help="print where a model's file is (or goes)")
    where.add_argument("name", choices=models.names(), metavar="NAME")
    check = mod_commands.add_parser(
        "check",
        help="say what m360 will do with an .onnx file and which flags it needs (exit 2 if it "
        "cannot use it)",
        description=(
            "Load an .onnx file as `m360 run --model FILE` would (with the model flags given) "
            "and probe it: the input sizes it runs at, the normalisation its graph holds and "
            "the one its output suggests, its output's shape and values, and what the output "
            "looks like (a disparity, a metric depth, a depth up to scale and shift) on a "
            "synthetic corridor whose depth is known. Prints the flags `m360 run` needs. Exit "
            "code 0 when m360 can use the file (perhaps with those flags), 2 when it cannot."
        ),
    )
    check.add_argument("file", type=Path, help="the .onnx file")
    check.add_argument(
        "--width", type=int, default=models.CHECK_ERP_WIDTH, help="ERP width of the layout"
    )
    check.add_argument("--json", action="store_true", help="print the findings as JSON")
    add_flags(check.add_argument_group("model (as for m360 run)"), ModelKeywords)

    plans = commands.add_parser(
        "plans", help="show where built plans are kept on disk and their size, or clear them"
    )
    plans.add_argument("action", nargs="?", choices=("show", "clear"), default="show")
    plans.add_argument(
        "--stale", action="store_true", help="clear only files other m360 builds wrote"
    )

    view = commands.add_parser(
        "view",
        help="show a result's point cloud, mesh or splats in the browser (extra m360[3d])",
        description=(
            "Serve a local page (viser) on 127.0.0.1 showing the point cloud of an output "
            "(STEM.points.ply with the panorama's colours, else the depth map's points coloured "
            "by distance) or, with --mesh, its mesh, with --splats its Gaussian splats. Prints "
            "the address and opens it in the browser when there is one. Large clouds are "
            "subsampled for display only."
        ),
    )
    view.add_argument("path", type=Path, help="output stem (or one of its files), .ply or .glb")
    view.add_argument("--port", type=int, default=8080, help="port (the next free one if taken)")
    shown = view.add_mutually_exclusive_group()
    shown.add_argument("--mesh", action="store_true", help="show the mesh instead of the points")
    shown.add_argument(
        "--splats",
        action="store_true",
        help="show the Gaussian splats (STEM.splat.ply, else made from the depth map)",
    )
    view.add_argument("--colour", choices=("rgb", "depth"), default="rgb", help="point colours")
    view.add_argument("--max-points", type=int, default=2_000_000, help="most points displayed")
    view.add_argument("--no-browser", action="store_true", help="do not open a browser")

    return parser


def _dispatch(args: argparse.Namespace) -> int:
    try:
        if args.command == "demo":
            return _demo(args.output, args.width, args.seed, args.noise, _options(args))
        if args.command == "run":
            return _run(args)
        if args.command == "video":
            return _video(args)
        if args.command == "eval":
            return _eval(args)
        if args.command == "view":
            return _view(args)
        if args.command == "plans":
            return _plans_command(args.action, args.stale)
        return _models_command(args)
    except ModelError as exc:
        print(f"m360: error: {exc}", file=sys.stderr)
        return 1
    except InputError as exc:  # before any image ran: the command itself is wrong
        print(f"m360: error: {exc}", file=sys.stderr)
        return 2
    except M360Error as exc:
        print(f"m360: error: {exc}", file=sys.stderr)
        return 1


def _max_vertices(text: str) -> int | None:
    if text.strip().lower() == "none":
        return None
    try:
        return check_max_vertices(int(text))
    except (ValueError, InputError) as exc:
        raise argparse.ArgumentTypeError(
            f"--max-vertices must be an integer >= 64 or 'none', got {text!r}"
        ) from exc


def _formats(text: str) -> tuple[str, ...]:
    chosen = tuple(f.strip() for f in text.split(",") if f.strip())
    known = KNOWN_FORMATS
    unknown = [f for f in chosen if f not in known]
    if unknown or not chosen:
        raise argparse.ArgumentTypeError(
            f"unknown format(s) {', '.join(unknown) or '(none)'}; choose from {', '.join(known)}"
        )
    return chosen


def _stitch_options(parser: argparse.ArgumentParser) -> None:
    """Add the stitching flags: one per entry of the shared list (the core's defaults shown)."""
    add_flags(parser.add_argument_group("stitching (defaults are the core's)"), StitchKeywords)


def _options(args: argparse.Namespace) -> StitchOptions:
    """Build the :class:`m360.StitchOptions` the stitching flags describe (InputError: exit 2)."""
    return StitchOptions(**from_args(args, StitchKeywords))


def _demo(out: Path, width: int, seed: int, noise: float, options: StitchOptions) -> int:
    t0 = time.perf_counter()
    layout = default_layout(width)
    scene = synthetic.room(seed)
    rgb, gt_depth = synthetic.render(scene, width)
    network = SimulatedEstimator(scene, layout, seed=seed, noise=noise)
    print(f"m360 {__version__} demo: {width}x{width // 2} synthetic room (seed {seed}), {layout}")
    print(
        "  network: SIMULATED, not a trained model: exact tangent disparity with a random "
        f"scale/shift per tangent and {noise:g} relative noise"
    )
    align = options.align
    levels = "none" if align is None else ",".join(f"{c}x{r}" for c, r in align["levels"])
    print(f"  rendered in {time.perf_counter() - t0:.1f} s; align={levels} blend={options.method}")
    result = estimate(rgb, network, options=options)
    metrics = depth_metrics(result.disparity, gt_depth)
    stages = ", ".join(f"{k} {v:.3f}" for k, v in result.timings.items())
    print(f"  timings (s): {stages}")
    print(f"  vs true depth: {format_metrics(metrics)}")
    written = save(result, out / "demo", extra={"input": "synthetic.room", "seed": seed})
    written["rgb"] = save_png(out / "demo_rgb.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    written["gt_depth"] = save_npy(out / "demo_gt_depth.npy", gt_depth)
    print("  wrote " + ", ".join(str(p) for p in written.values()))
    return 0


def _view(args: argparse.Namespace) -> int:
    import threading

    from .io.viewer import serve

    server = serve(
        args.path,
        port=args.port,
        mesh=args.mesh,
        splats=args.splats,
        colour=args.colour,
        max_points=args.max_points,
        open_browser=not args.no_browser,
        announce=lambda line: print(line, flush=True),
    )
    try:
        threading.Event().wait()  # until Ctrl-C / SIGTERM
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


def _caps(nadir: float | None, zenith: float | None) -> list[m360_masks.Cap] | None:
    """Make the polar caps asked for by --nadir / --zenith (None: no mask)."""
    caps = [
        make(deg)
        for make, deg in ((m360_masks.nadir, nadir), (m360_masks.zenith, zenith))
        if deg is not None
    ]
    return caps or None


def _run(args: argparse.Namespace) -> int:
    def report_failure(outcome: batch.ImageOutcome) -> None:
        if outcome.status == "failed":
            _log(f"m360: {outcome.input}: {outcome.error}: {outcome.message}")

    report = batch.run(
        args.inputs,
        args.output,
        model=args.model,
        options=_options(args),
        formats=args.formats,
        preview=not args.no_preview,
        confidence=args.confidence,
        max_vertices=args.max_vertices,
        workers=args.workers,
        resume=args.resume,
        recursive=args.recursive,
        fix_aspect=args.fix_aspect,
        progress=not args.no_progress,
        on_outcome=report_failure,
        scale=None if args.camera_height is None else m360_scale.camera_height(args.camera_height),
        mask=_caps(args.nadir, args.zenith),
        engine=args.engine,
        gpus_per_model=args.gpus_per_model,
        cpus_per_stitch=args.cpus_per_stitch,
        model_options=ModelOptions(**from_args(args, ModelKeywords)),
        **from_args(args, JobKeywords),
        **from_args(args, PriorKeywords),
        **from_args(args, StereoKeywords),
    )
    print(report.summary(), file=sys.stderr)
    return report.exit_code


def _log(line: str) -> None:
    """Write a line on stderr without tearing the progress bar."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr)


def _eval(args: argparse.Namespace) -> int:
    pred = _read_map(args.pred, args.pred_kind, allow_output=True)
    gt = _read_map(args.gt, args.gt_kind, allow_output=False)
    if pred.shape != gt.shape:
        raise InputError(f"PRED is {pred.shape} but GT is {gt.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        gt_depth = gt if args.gt_kind == "depth" else np.where(gt > 0, 1.0 / gt, np.nan)
        disparity = (
            pred if args.pred_kind == "disparity" else np.where(pred > 0, 1.0 / pred, np.nan)
        )
    metrics = depth_metrics(
        disparity, gt_depth, pole_cap_deg=args.pole_cap, weighting=args.weighting
    )
    if args.json:
        print(json.dumps(metrics, indent=2))
    else:
        print(format_metrics(metrics))
    return 0


def _inverse(values: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(values > 0, 1.0 / values, np.nan)


def _read_map(path: Path, kind: str, *, allow_output: bool) -> np.ndarray:
    """Read an m360 output's ``kind`` map (when ``path`` names one with a sidecar) or an array."""
    stem = output_stem(path)
    if allow_output and stem.with_name(stem.name + ".json").is_file():
        values: np.ndarray = getattr(load(stem), kind)
        return values
    return read_array(path)


def _models_check(args: argparse.Namespace) -> int:
    try:
        info = models.check(args.file, erp_width=args.width, **from_args(args, ModelKeywords))
    except (ModelError, InputError) as exc:  # corrupt, not ONNX, not feedable, bad options
        print(f"m360: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # never a traceback from the command that diagnoses a file
        print(
            f"m360: error: cannot check {args.file}: {type(exc).__name__}: {exc} (unexpected; "
            "please report it)",
            file=sys.stderr,
        )
        return 2
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print("\n".join(_check_report(info)))
    if not info["usable"]:
        print(f"m360: error: {args.file}: {info['problem']}", file=sys.stderr)
        return 2
    return 0


def _flag_text(flags: dict[str, object], *, prior: bool = False) -> str:
    """``{"multiple_of": 32}`` → ``--multiple-of 32`` (each model option's own flag).

    ``prior``: the flags of a prior model (``--prior-kind`` for its output kind, and the
    ``--prior-...`` flags of ``prior_options``).
    """
    entries = definition(ModelKeywords)
    prior_entries = definition(PriorKeywords)["prior_options"].parts
    parts = []
    for key, value in flags.items():
        shown = " ".join(str(v) for v in value) if isinstance(value, list) else str(value)
        if prior and key == "output_kind":
            flag = "--prior-kind"
        elif prior and key in prior_entries:
            flag = prior_entries[key].flag_name(key)
        elif key in entries:
            flag = entries[key].flag_name(key)
        else:
            flag = f"--{key.replace('_', '-')}"
        parts.append(f"{flag} {shown}")
    return " ".join(parts)


def _auto_edges(tile_width: int, network_width: int) -> str:
    """Say what the default ``edges="auto"`` does for a network this wide on tiles this wide."""
    shrink = (
        f"the {tile_width}-px tangents are {tile_width / network_width:.1f}x the network's "
        f"{network_width}-px input; --edges auto refines from {AUTO_PHOTO_SHRINK:g}x"
    )
    if edges_for("auto", tile_width, network_width) == "photo":
        return f"refined along the photo by default ({shrink})"
    return f"as the network gives them by default ({shrink})"


def _check_report(info: dict[str, Any]) -> list[str]:
    """Write the lines `m360 models check` prints for :func:`m360.models.check`'s findings."""
    inp, norm = info["input"], info["normalization"]
    shape = ", ".join(str(d) for d in inp["shape"])
    size = "static size {}x{}".format(*inp["size"]) if inp["static"] else "dynamic size"
    registry = f"{info['registry']} (matched by sha256)" if info["registry"] else "not registered"
    nh, nw = info["network_size"]
    runs = info["network_size_runs"]
    panoramic = info.get("kind") == "panoramic"
    seen = (
        f"a {info['erp_width']}-px ERP (panoramic: the whole panorama at once)"
        if panoramic
        else f"the default layout (icosahedron of a {info['erp_width']}-px ERP, tangents "
        f"{info['tangent_shape'][0]}x{info['tangent_shape'][1]})"
    )
    lines = [
        f"file:          {info['path']} ({info['size_bytes']} bytes, sha256 {info['sha256']})",
        f"registry:      {registry}",
        f"input:         {inp['name']!r} ({shape}), {inp['layout']}, {size}",
        f"network size:  {nh}x{nw} for {seen}" + ("" if runs is None else f": FAILS ({runs})"),
    ]
    if runs is None:  # what the stitch can resolve (docs/your-own-model.md)
        where = "on the equator" if panoramic else "at a tile's centre, whatever the ERP width"
        lines.append(f"detail:        {info['degrees_per_pixel']:.2f}° per network pixel {where}")
        if not panoramic:
            lines.append(f"edges:         {_auto_edges(info['tangent_shape'][1], nw)}")
    target = "the photo (upsampled along its edges)" if panoramic else "the tangent"
    rule = info["size_rule"]
    if inp["static"]:
        lines.append(
            "sizes:         fixed: m360 resizes "
            + ("the panorama" if panoramic else "each tangent")
            + " to it"
        )
    elif rule is None:
        lines.append(f"sizes:         runs at none of the sizes tried near {nh}x{nw}")
    else:
        need = "any size" if rule == 1 else f"sizes that are multiples of {rule}"
        lines.append(f"sizes:         runs at {need} (probed near {nh}x{nw})")
    if info["working_size"] is not None and info["working_size"] != info["network_size"]:
        lines.append(
            "               with {}: {}x{}".format(
                _flag_text({"multiple_of": info["flags"].get("multiple_of")}), *info["working_size"]
            )
        )
    if norm["source"] == "graph":
        how = f"graph (m360 feeds RGB in [0, {norm['input_range']:g}])"
    else:
        how = "m360 feeds (rgb - mean) / std"
    lines += [
        f"normalisation: {how}: mean {tuple(norm['mean'])}, std {tuple(norm['std'])}",
        f"               {norm['detail']}",
    ]
    scores = info["normalize_scores"]
    if scores:
        listed = ", ".join(f"{k} {v:+.2f}" for k, v in scores.items())
        verdict = (
            f"{info['normalize_guess']} fits best"
            if info["normalize_guess"]
            else "no clear winner (a model card wins over this hint)"
        )
        lines.append(f"               on the probe scene: {verdict} (follows depth: {listed})")
    if info["output_shape"] is not None:
        oh, ow = info["output_shape"][1:]
        wh, ww = info["working_size"]
        sh, sw = info["output_scale"]
        if (sh, sw) == (1.0, 1.0):
            scale = "the input's size"
        elif sh == sw and (1 / sh).is_integer():
            scale = f"1/{int(1 / sh)} of the input's size: m360 resizes it to {target}"
        else:
            scale = f"another size than the input: m360 resizes it to {target}"
        lines.append(f"output:        {oh}x{ow} for a {wh}x{ww} input ({scale})")
    if info["output_range"] is not None:
        lo, mid, hi = info["output_range"]
        finite = "" if info["output_finite"] else " (some values NOT finite)"
        lines.append(
            f"               values {lo:.4g} … {hi:.4g}, median {mid:.4g} on the probe scene"
            + finite
        )
    kind = info["output_kind"]
    kind_from = {"user": "--output-kind", "registry": f"registry: {info['registry']}"}
    lines.append(
        "output kind:   "
        + (
            f"{kind} ({kind_from[info['output_kind_source']]})"
            if kind
            else "unknown: pass --output-kind (m360 run assumes affine_disparity)"
        )
    )
    guess = info["kind_guess"]
    if guess is not None:
        looks = guess["kind"] or "cannot tell"
        sure = f", sure: {guess['confidence']}" if guess["kind"] else ""
        lines.append(f"kind guess:    {looks}{sure} ({guess['reason']})")
        if kind and guess["kind"] and guess["kind"] != kind and guess["confidence"] != "low":
            lines.append(f"               warning: declared {kind}, the output looks like {looks}")
    flags = info["flags"]
    if not info["usable"]:
        lines.append(f"usable:        no: {info['problem']}")
    elif panoramic:
        options = ", ".join(f"{k}={v!r}" for k, v in info["options"].items())
        # Its kind first; its providers and threads are the main model's (prior_options takes
        # neither).
        prior_flags = {k: v for k, v in info["options"].items() if k == "output_kind"}
        prior_flags.update((k, v) for k, v in info["options"].items() if k in PRIOR_MODEL_OPTIONS)
        as_prior = f"--prior {info['path']} " + _flag_text(prior_flags, prior=True)
        lines += [
            "usable:        yes" + (", with the flags below" if flags else ""),
            f"use:           m360 run IN -o OUT --model {info['path']} "
            + _flag_text(info["options"]),
            f"as a prior:    m360 run IN -o OUT --model TANGENT_MODEL {as_prior.rstrip()}",
            f"python:        m360.ModelOptions({options})",
        ]
    elif not flags:
        lines.append("usable:        yes")
    else:
        options = ", ".join(f"{k}={v!r}" for k, v in info["options"].items())
        lines += [
            "usable:        yes, with the flags below",
            f"use:           m360 run IN -o OUT --model {info['path']} "
            + _flag_text(info["options"]),
            f"python:        m360.ModelOptions({options})",
        ]
    return lines


def _plans_command(action: str, stale_only: bool) -> int:
    from .geometry import plan_cache

    if action == "clear":
        freed = plan_cache.clear(stale_only=stale_only)
        print(f"plan cache: freed {freed / 1e6:.1f} MB in {plan_cache.directory()}")
        return 0
    use = plan_cache.usage()
    state = "on" if plan_cache.enabled() else f"off ({plan_cache.ENV_SWITCH}=0)"
    print(f"plan cache: {use.path}  ({state}; set M360_HOME to move it)")
    print(f"{use.files} files, {use.bytes / 1e6:.1f} MB ({use.stale_files} of other m360 builds)")
    print("clear with `m360 plans clear` (`--stale`: only other builds' files)")
    return 0


def _models_command(args: argparse.Namespace) -> int:
    if args.action == "check":
        return _models_check(args)
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


# --------------------------------------------------------------------------------------------
# m360 video


def _frame_bound(text: str) -> int | float:
    """``--start``/``--end``: a frame index (``120``) or seconds (``4.5s``)."""
    try:
        return float(text[:-1]) if text.endswith("s") else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a frame index (120) or seconds (4.5s), got {text!r}"
        ) from None


def _add_video_parser(commands: Any) -> None:
    from .video import TEMPORAL_MODES

    video = commands.add_parser(
        "video",
        help="estimate the depth of every frame of a 360° video (resumable, no flicker)",
        description=(
            "Estimate the depth of every frame of a 360-degree video file (MP4, MOV, MKV, "
            'WebM ...: pip install "m360[video]") or of a folder of frames, and write per '
            "frame OUT/000123.disparity.EXT, OUT/000123.depth.EXT per format, the small state "
            "the next frame starts from (OUT/000123.temporal.npy) and last the sidecar "
            "OUT/000123.json (frame index and time). --temporal smooth (default) keeps each "
            "frame consistent with the one before where the image did not change, and starts "
            "afresh at scene cuts. Ctrl-C and rerun: goes on where it stopped (same bytes). "
            "Failed frames go to OUT/failures.jsonl and the run goes on. Exit codes: 0 all "
            "done, 1 some frames failed, 2 usage error, 3 another run is writing OUT, 130 "
            "interrupted."
        ),
    )
    video.add_argument("video", type=Path, help="video file or folder of frames")
    video.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    video.add_argument(
        "--model",
        default=models.DEFAULT_MODEL,
        help=f"registry name or path to an .onnx file (default {models.DEFAULT_MODEL})",
    )
    video.add_argument("--every", type=int, default=1, metavar="N", help="every N-th frame")
    video.add_argument(
        "--start", type=_frame_bound, default=None, help="first frame: index (120) or time (4.5s)"
    )
    video.add_argument(
        "--end",
        type=_frame_bound,
        default=None,
        help="first frame no longer taken: index or time (4.5s)",
    )
    video.add_argument(
        "--fps", type=float, default=None, help="frame rate of a folder of frames (gives times)"
    )
    video.add_argument(
        "--temporal",
        choices=TEMPORAL_MODES,
        default=TEMPORAL_MODES[0],
        help="smooth: consistent with the previous frame (default); none: frames as stills",
    )
    video.add_argument(
        "--formats",
        type=_formats,
        default=("npy",),
        help=f"comma-separated array formats: {', '.join(SAVE_FORMATS)} (default npy)",
    )
    video.add_argument(
        "--preview", action="store_true", help="also write each frame's colour preview PNG"
    )
    video.add_argument(
        "--preview-video",
        action="store_true",
        help="write OUT/preview.mp4, the disparity in colour with one scale for the whole run",
    )
    video.add_argument(
        "--engine",
        choices=ENGINES,
        default=ENGINES[0],
        help="where frames run: in this process, in order (default), or ray: chunks of frames "
        'on a Ray cluster (pip install "m360[ray]"; the cluster in RAY_ADDRESS, else a local one)',
    )
    video.add_argument(
        "--workers", type=int, default=1, help="--engine ray: chunk workers running at once"
    )
    video.add_argument(
        "--chunk",
        type=int,
        default=None,
        metavar="N",
        help="frames per chunk (--engine ray: default 32; with the local engine, run the same "
        "chunks here)",
    )
    video.add_argument(
        "--overlap",
        type=int,
        default=None,
        metavar="N",
        help="warm-up frames a chunk starts early, its gauge fitted on them (default 4)",
    )
    video.add_argument(
        "--gpus-per-model",
        type=float,
        default=None,
        help="--engine ray: GPUs per chunk worker (default 1 with a CUDA provider, else 0)",
    )
    video.add_argument(
        "--cpus-per-stitch",
        type=float,
        default=1.0,
        help="--engine ray: CPUs per chunk worker (default 1)",
    )
    video.add_argument(
        "--frame-batch",
        type=int,
        default=1,
        metavar="K",
        help="local engine: frames whose tangents go to the network in one call, then finished "
        "in order (the same outputs; default 1: on CPU a larger call gains nothing)",
    )
    video.add_argument("--confidence", action="store_true", help="also write confidence maps")
    video.add_argument("--overwrite", dest="resume", action="store_false", help="redo every frame")
    video.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_flags(video.add_argument_group("model (ONNX models given by name or path)"), ModelKeywords)
    add_flags(video.add_argument_group("job"), JobKeywords)
    _stitch_options(video)


def _video(args: argparse.Namespace) -> int:
    from . import video

    def report_failure(outcome: batch.ImageOutcome) -> None:
        if outcome.status == "failed":
            _log(f"m360: frame {outcome.stem}: {outcome.error}: {outcome.message}")

    report = video.run(
        args.video,
        args.output,
        model=args.model,
        options=_options(args),
        temporal=args.temporal,
        every=args.every,
        start=args.start,
        end=args.end,
        fps=args.fps,
        formats=args.formats,
        preview=args.preview,
        preview_video=args.preview_video,
        confidence=args.confidence,
        resume=args.resume,
        progress=not args.no_progress,
        on_outcome=report_failure,
        engine=args.engine,
        workers=args.workers,
        chunk=args.chunk,
        overlap=args.overlap,
        gpus_per_model=args.gpus_per_model,
        cpus_per_stitch=args.cpus_per_stitch,
        frame_batch=args.frame_batch,
        model_options=ModelOptions(**from_args(args, ModelKeywords)),
        **from_args(args, JobKeywords),
    )
    print(report.summary(), file=sys.stderr)
    return report.exit_code


if __name__ == "__main__":
    raise SystemExit(main())
