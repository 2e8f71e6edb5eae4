"""Big panoramas: first and warm call, peak memory per stage, and the memory estimate, 2K-16K.

Each configuration runs in a fresh interpreter (so the first call really builds its plan and the
peak is its own): ``m360.estimate`` on a panorama of the given width, first call, then
``--repeats`` warm calls (median). The network is replaced by held-out-style tangents: the
exact disparity of a synthetic room ray-cast for a 1024-wide layout, distorted per tangent as a
network errs (``m360.synthetic.distort``: scale, shift, smooth field, noise) and resized to the
layout's tangent size, so the times are "beyond the network" (the network stage is that resize).

Peak memory per stage: a thread samples the process's resident memory (VmRSS) every 5 ms during
the first call; each sample is given to the stage (``EstimateResult.timings`` order: load,
project, network, convert, align, blend, upsample) running at that time. ``peak`` is the
process's high-water mark (VmHWM) at the end, above the baseline after the imports and the
input image; ``estimate`` is :func:`m360.memory.estimate_memory` for the same call.

Tables:
1. per ERP width and blend (``--blends``, default m360.estimate's default and frustum), with
   the default working width (the input's up to 8192, 4096 above): first call, warm call
   (median), first / warm, peak and estimated memory, per-stage peaks;
2. with ``--mp72``: a 72 MP photo (11904 x 5952) with ``working_width`` 2048, 4096 and native
   (``--no-native`` leaves native out: it needs about 12 GB with the Poisson blend).

3. with ``--plan-cache N``: the disk plan cache, N rounds per size (default blend), each
   configuration in a fresh interpreter with its own ``M360_HOME``: the first call with the
   cache off (``M360_PLAN_CACHE=0``), cold (empty cache: builds and writes the plan), and with
   the warm disk cache the cold run left (loads it); medians of the first and warm calls. Then
   ``Layout.prepare()`` alone the same three ways (build, build + write, load) and the files'
   sizes.

4. with ``--outputs IMAGE`` (alone: tables 1-3 are skipped): one real image through the whole
   run with a real network (``--model``, default the real data's fastdepth_224.onnx, see
   tests/real_data.py; metric depth, RGB in [0, 1]) and the outputs ``--formats`` (default
   npy,png16,ply,glb): the peak above the stage's start of reading, the estimate, and
   ``m360.save`` of each format alone and of npy with the preview, in one fresh interpreter;
   then ``m360.batch.run`` of all of it in another, its peak against the whole-run estimate
   (:func:`m360.memory.estimate_memory` with the formats and the file's header). Works on older
   m360 trees (the whole-run estimate then shows "-").

Every child has its own ``M360_HOME`` (a temporary folder), so tables 1-2 measure cold plans
whatever the user's cache holds.

Run: ``.venv/bin/python benches/bench_bigpano.py [--sizes 2048 4096 8192] [--repeats 3]
[--mp72] [--plan-cache 3]``, or ``... --outputs PHOTO`` (e.g. the real data's 12K street photo,
tests/real_data.py).
Sizes above 8K need ``free -g`` headroom: run them alone.
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import _harness as h
import m360
import real_data

DEFAULT_BLEND = m360._core.DEFAULTS["blend"]["method"]  # what blend=None selects
STAGES = ("load", "project", "network", "convert", "align", "blend", "upsample")
MP72 = 11904
PLAN_KINDS = ("tangent", "erp", "tap", "overlaps")  # file name prefixes (tap weights: older m360)


def _status(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    return 0


class HeldOut:
    """Distorted exact tangents of a 1024-wide layout, resized to whatever layout asks."""

    output_kind = "affine_disparity"

    def __init__(self, tangents: np.ndarray) -> None:
        self.tangents = tangents

    def predict(self, tiles: np.ndarray) -> np.ndarray:
        th, tw = tiles.shape[1:3]
        return np.stack(
            [cv2.resize(t, (tw, th), interpolation=cv2.INTER_LINEAR) for t in self.tangents]
        )


def _padding() -> float | None:
    """The layout padding ``--padding`` asked for (None: the default layout's)."""
    value = os.environ.get("M360_BENCH_PADDING")
    return float(value) if value else None


def _default_layout(width: int) -> m360.Layout:
    """The layout ``m360.estimate`` uses (an older m360 without ``default_layout``: the
    paper's)."""
    try:
        from m360.geometry import default_layout
    except ImportError:
        return m360.Layout.icosahedron(width)
    return default_layout(width, _padding())


def child(data: Path, width: int, blend: str, working: str, repeats: int) -> dict[str, Any]:
    """One configuration in this (fresh) process; returns its figures."""
    rgb = cv2.resize(np.load(data / "rgb.npy"), (width, width // 2), interpolation=cv2.INTER_LINEAR)
    est = HeldOut(np.load(data / "tangents.npy"))
    ww: int | str | None = (
        None if working == "default" else ("native" if working == "native" else int(working))
    )
    # Without working_width for "default", so the same figures can be taken of an older m360
    # (PYTHONPATH pointing at its package) as a baseline.
    kwargs: dict[str, Any] = {} if working == "default" else {"working_width": ww}
    if _padding() is not None:
        kwargs["padding"] = _padding()
    try:
        memory = importlib.import_module("m360.memory")
        work = memory.working_width_for(ww, width)
        predicted: float = memory.estimate_memory(width, work, blend, **layout_kwarg(memory, work))
    except ImportError:
        work, predicted = width, float("nan")
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # reset the high-water mark: the peak of the call alone
    baseline = _status("VmRSS")
    samples: list[tuple[float, int]] = []
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            samples.append((time.perf_counter(), _status("VmRSS")))
            time.sleep(0.005)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    res = m360.estimate(rgb, est, blend=blend, **kwargs)
    first = time.perf_counter() - t0
    done.set()
    sampler.join()
    hwm = _status("VmHWM")
    try:  # where the first call's plan came from (an m360 without a disk plan cache: nothing)
        from m360.geometry import plan_for

        stats = plan_for(_default_layout(work)).cache_stats()
    except AttributeError:
        stats = {}
    stage_peak = {}
    start = t0
    for stage in STAGES:
        end = start + res.timings.get(stage, 0.0)
        inside = [rss for t, rss in samples if start <= t < end]
        stage_peak[stage] = (max(inside) - baseline) / 2**30 if inside else None
        start = end
    warm = []
    for _ in range(repeats):
        t1 = time.perf_counter()
        r = m360.estimate(rgb, est, blend=blend, **kwargs)
        warm.append((time.perf_counter() - t1, r.timings["network"]))
    return {
        "width": width, "blend": blend, "working": working, "work_width": work,
        "first": first, "first_network": res.timings["network"],
        "warm": statistics.median(w for w, _ in warm),
        "warm_network": statistics.median(n for _, n in warm),
        "peak_gb": (hwm - baseline) / 2**30, "estimate_gb": predicted / 2**30,
        "stage_peak_gb": stage_peak, "timings_first": res.timings, "stats": stats,
    }  # fmt: skip


def child_prepare(width: int) -> dict[str, Any]:
    """``Layout.prepare()`` alone in this (fresh) process: its time, the plan's cache counts
    and the plan files' sizes by kind."""
    from m360 import plan_cache
    from m360.geometry import plan_for

    layout = _default_layout(width)
    t0 = time.perf_counter()
    layout.prepare()
    seconds = time.perf_counter() - t0
    folder = plan_cache.directory()
    files = {p.name.split("-")[0]: p.stat().st_size for p in folder.glob("*.m360plan")}
    return {"width": width, "prepare": seconds, "stats": plan_for(layout).cache_stats(),
            "files": files}  # fmt: skip


def run_child(
    data: Path,
    width: int,
    blend: str,
    working: str,
    repeats: int,
    home: Path | None = None,
    cache: bool = True,
    prepare_only: bool = False,
) -> dict[str, Any]:
    """One configuration in a fresh interpreter, with plans under ``home`` (default: a new
    empty folder), the disk plan cache on or off."""
    cmd = [sys.executable, __file__, "--child", str(data), str(width), blend, working,
           str(repeats)] + (["prepare"] if prepare_only else [])  # fmt: skip
    with tempfile.TemporaryDirectory() as fresh:
        env = {**os.environ, "M360_HOME": str(home or fresh),
               "M360_PLAN_CACHE": "1" if cache else "0"}  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{width} {blend} {working} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def inputs(data: Path) -> None:
    """The photo (a 2048-wide render, resized per size) and the held-out tangents."""
    import m360.synthetic as syn

    scene = syn.room(0)
    rgb, _ = syn.render(scene, 2048)
    np.save(data / "rgb.npy", rgb)
    layout = _default_layout(1024)
    exact = syn.tangent_perspective_disparity(scene, layout.cameras)
    np.save(data / "tangents.npy", syn.distort(exact, 100, field=0.1, noise=0.01))


def layout_kwarg(memory: Any, work: int) -> dict[str, Any]:
    """``layout=`` for ``estimate_memory`` with ``--padding`` when understood (older m360: not)."""
    import inspect

    if _padding() is None or "layout" not in inspect.signature(memory.estimate_memory).parameters:
        return {}
    return {"layout": _default_layout(work)}


def fmt_gb(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


_REAL_MODEL = real_data.MODELS / "fastdepth_224.onnx"
_REAL_OPTIONS = {"output_kind": "metric_depth", "mean": (0, 0, 0), "std": (1, 1, 1)}


def outputs_child(image: Path, model: str, formats: list[str], whole: bool) -> dict[str, Any]:
    """Table 4 in this (fresh) process: peaks per stage, or (``whole``) of one batch run."""
    out = Path(tempfile.mkdtemp())
    figures: dict[str, Any] = {}

    def start() -> tuple[int, float]:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # reset the high-water mark
        return _status("VmRSS"), time.perf_counter()

    def stop(name: str, began: tuple[int, float]) -> None:
        figures[name] = {
            "gb": (_status("VmHWM") - began[0]) / 2**30,
            "s": time.perf_counter() - began[1],
        }

    try:
        if whole:
            from m360.estimators import load_estimator

            estimator = load_estimator(model, **_REAL_OPTIONS)  # type: ignore[arg-type]
            began = start()
            report = m360.batch.run(image, out / "run", model=estimator, formats=formats,
                                    progress=False)  # fmt: skip
            assert report.exit_code == 0, report.failed
            stop("run", began)
            figures["base_gb"] = began[0] / 2**30
            try:
                from m360.io.decode import image_header
                from m360.memory import estimate_memory, working_width_for

                data = image.read_bytes()
                header = image_header(data)
                work = working_width_for(None, header.width)
                figures["estimate_gb"] = estimate_memory(
                    header.width, work, DEFAULT_BLEND, _default_layout(work), formats=formats,
                    preview=True, header=header, file_bytes=len(data),
                ) / 2**30  # fmt: skip
            except (ImportError, TypeError, AttributeError):  # an older m360
                figures["estimate_gb"] = None
            return figures
        from m360.io.decode import load_image

        began = start()
        rgb = load_image(image)
        stop("read", began)
        began = start()
        result = m360.estimate(rgb, model, **_REAL_OPTIONS)  # type: ignore[arg-type]
        stop("estimate", began)
        for fmt in formats:
            began = start()
            m360.save(result, out / "x", formats=[fmt], preview=False, rgb=rgb)
            stop(fmt, began)
        began = start()
        m360.save(result, out / "x", formats=["npy"], preview=True, rgb=rgb)
        stop("npy+preview", began)
        return figures
    finally:
        shutil.rmtree(out, ignore_errors=True)


def outputs_table(image: Path, model: str, formats: list[str]) -> None:
    """Table 4: per-stage peaks and the whole run against its estimate."""
    rows = {}
    for whole in (False, True):
        cmd = [sys.executable, __file__, "--outputs-child", str(image), model, ",".join(formats),
               "whole" if whole else "stages"]  # fmt: skip
        with tempfile.TemporaryDirectory() as home:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600,
                                  env={**os.environ, "M360_HOME": home})  # fmt: skip
        if proc.returncode != 0:
            raise RuntimeError(proc.stderr[-3000:])
        rows.update(json.loads(proc.stdout.strip().splitlines()[-1]))
    print(f"m360 {m360.__file__}: {image.name}, formats {','.join(formats)}")
    print(f"{'stage':>12} {'peak above start GiB':>21} {'seconds':>8}")
    for name, fig in rows.items():
        if isinstance(fig, dict):
            print(f"{name:>12} {fig['gb']:21.2f} {fig['s']:8.1f}")
    print(f"whole run above {rows['base_gb']:.2f} GiB: measured {rows['run']['gb']:.2f} GiB, "
          f"estimated {fmt_gb(rows['estimate_gb'])} GiB")  # fmt: skip


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--outputs-child":
        image, model, formats, mode = sys.argv[2:6]
        print(json.dumps(outputs_child(Path(image), model, formats.split(","), mode == "whole")))
        return
    if "--outputs" in sys.argv:
        import argparse

        parser = argparse.ArgumentParser(description="table 4 of " + __doc__.splitlines()[0])
        parser.add_argument("--outputs", type=Path, required=True, metavar="IMAGE")
        parser.add_argument("--model", default=str(_REAL_MODEL))
        parser.add_argument("--formats", default="npy,png16,ply,glb")
        args = parser.parse_args()
        outputs_table(args.outputs, args.model, args.formats.split(","))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        data, width, blend, working, repeats = sys.argv[2:7]
        if sys.argv[7:] == ["prepare"]:
            out = child_prepare(int(width))
        else:
            out = child(Path(data), int(width), blend, working, int(repeats))
        print(json.dumps(out))
        return
    parser = h.bench_argparser(__doc__.splitlines()[0])
    parser.set_defaults(repeats=3)
    parser.add_argument("--blends", nargs="+", default=[DEFAULT_BLEND, "frustum"])
    parser.add_argument("--mp72", action="store_true", help="72 MP with working widths")
    parser.add_argument("--no-native", action="store_true", help="72 MP: leave native out")
    parser.add_argument(
        "--data", type=Path, default=None, help="keep the inputs here (reused when present)"
    )
    parser.add_argument(
        "--plan-cache", type=int, default=0, metavar="N",
        help="N rounds of first calls with the disk plan cache off, cold and warm",
    )  # fmt: skip
    parser.add_argument("--no-default", action="store_true", help="skip table 1")
    parser.add_argument(
        "--padding", type=float, default=None, help="layout padding (default: m360's default)"
    )
    args = parser.parse_args()
    if args.padding is not None:
        os.environ["M360_BENCH_PADDING"] = str(args.padding)  # the children inherit it
    meta = h.metadata()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data or Path(tmp)
        data.mkdir(parents=True, exist_ok=True)
        if not (data / "tangents.npy").exists():
            inputs(data)
        for width in [] if args.no_default else args.sizes:
            for blend in args.blends:
                rows.append(run_child(data, width, blend, "default", args.repeats))
                print(f"  done {width} {blend}", file=sys.stderr)
        mp_rows = []
        if args.mp72:
            workings = ["2048", "4096"] + ([] if args.no_native else ["native"])
            for working in workings:
                mp_rows.append(run_child(data, MP72, DEFAULT_BLEND, working, args.repeats))
                print(f"  done 72 MP {working}", file=sys.stderr)
        cache_rows, prepare_rows, cache_raw = [], [], []
        for width in args.sizes if args.plan_cache else []:
            calls: dict[str, list[dict[str, Any]]] = {"off": [], "cold": [], "disk": []}
            preps: dict[str, list[dict[str, Any]]] = {"off": [], "cold": [], "disk": []}
            for r in range(args.plan_cache):
                for kind, runs in (("estimate", calls), ("prepare", preps)):
                    home = Path(tmp) / f"home-{kind}-{width}-{r}"
                    common = (data, width, DEFAULT_BLEND, "default", args.repeats)
                    only = kind == "prepare"
                    runs["off"].append(run_child(*common, cache=False, prepare_only=only))
                    runs["cold"].append(run_child(*common, home=home, prepare_only=only))
                    runs["disk"].append(run_child(*common, home=home, prepare_only=only))
                    assert runs["disk"][-1].get("stats", {}).get("built", 0) == 0
                    shutil.rmtree(home, ignore_errors=True)
                print(f"  done plan cache {width} round {r + 1}", file=sys.stderr)
            cache_raw.append({"width": width, "plan_cache": calls, "prepare": preps})
            med = statistics.median
            warm = med(c["warm"] for c in calls["off"] + calls["cold"] + calls["disk"])
            cache_rows.append(
                [
                    f"{width}x{width // 2}",
                    warm,
                    *(med(c["first"] for c in calls[m]) for m in calls),
                    *(f"{med(c['first'] for c in calls[m]) / warm:.2f}" for m in calls),
                ]
            )
            files = preps["cold"][0]["files"]
            prepare_rows.append([f"{width}x{width // 2}",
                                 *(med(p["prepare"] for p in preps[m]) for m in preps),
                                 *(f"{files.get(k, 0) / 1e6:.1f}" for k in PLAN_KINDS),
                                 f"{sum(files.values()) / 1e6:.1f}"])  # fmt: skip

    def table(title: str, rs: list[dict[str, Any]]) -> None:
        h.print_table(
            title,
            ["ERP", "blend", "working", "first s", "warm s", "warm - net s", "first/warm",
             "peak GB", "estimate GB", "est/peak",
             *(f"{s} GB" for s in STAGES if s != "load")],
            [
                [f"{r['width']}x{r['width'] // 2}", r["blend"], r["work_width"], r["first"],
                 r["warm"], r["warm"] - r["warm_network"], f"{r['first'] / r['warm']:.2f}",
                 r["peak_gb"], r["estimate_gb"], f"{r['estimate_gb'] / r['peak_gb']:.2f}",
                 *(fmt_gb(r["stage_peak_gb"][s]) for s in STAGES if s != "load")]
                for r in rs
            ],
        )  # fmt: skip

    if rows:
        table(
            f"m360.estimate, held-out tangents, first call and median of {args.repeats} warm "
            "calls; memory above the baseline (imports + input); per-stage = peak RSS while it ran",
            rows,
        )
    if mp_rows:
        table("72 MP (11904x5952), default blend, by working width", mp_rows)
    if cache_rows:
        h.print_table(
            f"Disk plan cache: first call (median of {args.plan_cache} fresh interpreters) with "
            f"the cache off, cold (build + write) and warm on disk (load); warm = median of all "
            f"warm calls; default blend",
            ["ERP", "warm s", "first off s", "first cold s", "first disk s",
             "off/warm", "cold/warm", "disk/warm"],
            cache_rows,
        )  # fmt: skip
        h.print_table(
            "Layout.prepare() alone (the maps estimate needs): build (cache off), build + "
            "write (cold), load (warm disk); plan file sizes in MB",
            ["ERP", "build s", "build+write s", "load s", *(f"{k} MB" for k in PLAN_KINDS),
             "total MB"],
            prepare_rows,
        )  # fmt: skip
    print(f"\n{meta['cpu_model']}, {meta['cpu_count']} cores, commit {meta['git_commit']}")
    if args.json:
        h.write_json(args.json, [*rows, *mp_rows, *cache_raw], meta)


if __name__ == "__main__":
    main()
