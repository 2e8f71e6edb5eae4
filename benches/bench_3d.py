"""3D outputs: m360.to_points, m360.to_mesh and the GLB/PLY writers at 2K, 4K and 8K.

Per ERP width, in a fresh subprocess each (so peak RSS belongs to the one operation): seconds
(median of --repeat runs; also the process's CPU seconds, all threads, less noisy on a shared
machine), peak RSS (ru_maxrss of the subprocess) and its growth over the input
alone (0 when the operation stays below the peak of importing m360), and the file size for the
writers. Compared in the same run with

- trimesh's exporters writing the same mesh/points (``trimesh_glb`` times the export of the
  mesh built by to_mesh, ``trimesh_ply`` of the points; m360 streams numpy arrays instead);

- the streaming writers :func:`m360.mesh.write_mesh_glb` / :func:`m360.mesh.write_points_ply`
  (what ``m360.save`` uses: byte-identical files, a band of rows in memory), at every pixel and,
  ``stream_glb_budget``, with the default vertex budget (8K: every 2nd pixel);
- the numpy floor: the same points written out as plain numpy (directions from a lon/lat
  meshgrid, times depth, NaN dropped) — what any implementation must at least do;
- Open3D (with ``--open3d-python`` naming an interpreter that has open3d; it need not have
  m360): ``PointCloud.create_from_depth_image`` is pinhole-only, so it is timed on the same
  number of pixels read as a pinhole depth image (a cost reference), and
  ``o3d_from_numpy`` times building an ``o3d.geometry.PointCloud`` from the numpy points.

Stereo (``m360.stereo``, the ODS pair at IPD 64 mm): ``stereo`` times the warp of both eyes in
the Rust core, ``stereo_save`` the warp and the top-bottom JPEG with its XMP (what ``m360.save``
writes for ``formats=("stereo",)``; its file size), against ``numpy_warp``, a plain numpy
forward warp of both eyes written in this bench: each pixel's eye position (the same ODS
formula, no pole-fade iteration), rounded to the nearest pixel, z-buffered by sorting by depth,
holes filled with the nearest seen pixel on their left (no background test).

The depth map is a synthetic room rendered at 2K and resized (bilinear) to 4K/8K: timings do
not depend on the content beyond the share of cut triangles.

Normals and Gaussian splats (``SURFACE_OPS``): ``normals`` (m360.normals, the (H, W, 3)
array), ``normals_files`` (STEM.normals.exr + .png, file MB of both), ``to_splats`` and
``stream_splat`` (the splat PLY m360.save writes, default vertex budget) and
``splat_whole`` (every pixel), against ``normals_numpy``: np.gradient of the point
grid and a cross product, the plain numpy a user would write (no seam, pole or jump handling).

    .venv/bin/python benches/bench_3d.py [--widths 2048 4096 8192] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OPS = (
    "numpy_floor",
    "to_points",
    "to_mesh",
    "to_mesh+glb",
    "to_points+ply",
    "stream_glb",
    "stream_ply",
    "stream_glb_budget",
    "trimesh_glb",
    "trimesh_ply",
    "o3d_from_depth",
    "o3d_from_numpy",
    "numpy_warp",
    "stereo",
    "stereo_save",
)
#: Normals and Gaussian splats (m360.normals, m360.to_splats and their files), with the numpy
#: baseline a user would write for normals (central differences of the point grid, no seam,
#: pole or depth-jump handling).
SURFACE_OPS = (
    "normals_numpy",
    "normals",
    "normals_files",
    "to_splats",
    "stream_splat",
    "splat_whole",
)
OPS += SURFACE_OPS


def depth_map(width: int, cache: Path) -> Path:
    path = cache / f"depth_{width}.npy"
    if not path.exists():
        import cv2
        from m360 import synthetic

        base = cache / "depth_2048.npy"
        if not base.exists():
            rgb, depth = synthetic.render(synthetic.room(0), 2048)
            np.save(base, depth)
            np.save(cache / "rgb_2048.npy", rgb)
        depth = np.load(base)
        rgb = np.load(cache / "rgb_2048.npy")
        if width != 2048:
            depth = cv2.resize(depth, (width, width // 2), interpolation=cv2.INTER_LINEAR)
            rgb = cv2.resize(rgb, (width, width // 2), interpolation=cv2.INTER_LINEAR)
        np.save(path, depth)
        np.save(cache / f"rgb_{width}.npy", rgb)
    return path


def numpy_warp(rgb: np.ndarray, depth: np.ndarray, ipd: float = 0.064) -> list[np.ndarray]:
    """Both ODS eyes by a plain numpy forward warp (nearest pixel, z-buffer by sorting)."""
    h, w = depth.shape
    lat = (np.pi / 2 - np.pi * (np.arange(h) + 0.5) / h)[:, None]
    lon = (2 * np.pi * (np.arange(w) + 0.5) / w - np.pi)[None, :]
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 1e9)
    rho = d * np.cos(lat)
    r = ipd / 2
    ok = (rho > r).ravel()
    order = np.argsort(-d.ravel()[ok], kind="stable")  # far first: the nearest is written last
    src = np.flatnonzero(ok)[order]
    eyes = []
    for sign in (-1.0, 1.0):
        with np.errstate(invalid="ignore"):
            eye_lon = lon - np.arcsin(sign * r / rho)
            eye_lat = np.arctan2(d * np.sin(lat), np.sqrt(np.maximum(rho**2 - r * r, 0)))
            # (NaN where rho <= r: those pixels are not in src)
            col = np.rint((eye_lon + np.pi) * w / (2 * np.pi) - 0.5).astype(np.int64) % w
            row = np.rint((np.pi / 2 - eye_lat) * h / np.pi - 0.5).astype(np.int64)
        row = np.clip(row, 0, h - 1)
        target = (row * w + col).ravel()[src]
        out = np.zeros((h * w, 3), np.uint8)
        seen = np.zeros(h * w, bool)
        out[target] = rgb.reshape(-1, 3)[src]
        seen[target] = True
        # holes: the nearest seen pixel on the left in the row (a streak)
        index = np.where(seen.reshape(h, w), np.arange(w)[None, :], -1)
        index = np.maximum.accumulate(index, axis=1)
        index = np.where(index < 0, np.arange(w)[None, :], index)
        rows = np.arange(h)[:, None] * w
        eyes.append(out[(rows + index).ravel()].reshape(h, w, 3))
    return eyes


def numpy_floor(depth: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    lat = np.pi / 2 - np.pi * (np.arange(h, dtype=np.float32) + 0.5) / h
    lon = 2 * np.pi * (np.arange(w, dtype=np.float32) + 0.5) / w - np.pi
    lon_g, lat_g = np.meshgrid(lon, lat)
    c = np.cos(lat_g)
    xyz = np.stack([c * np.sin(lon_g), -np.sin(lat_g), c * np.cos(lon_g)], -1) * depth[..., None]
    return xyz[np.isfinite(depth)]


def normals_numpy(depth: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    lat = np.pi / 2 - np.pi * (np.arange(h, dtype=np.float32) + 0.5) / h
    lon = 2 * np.pi * (np.arange(w, dtype=np.float32) + 0.5) / w - np.pi
    c = np.cos(lat)[:, None]
    xyz = np.stack(
        [c * np.sin(lon), np.broadcast_to(-np.sin(lat)[:, None], (h, w)), c * np.cos(lon)], -1
    )
    xyz *= depth[..., None]
    d_row, d_col = np.gradient(xyz, axis=(0, 1))
    n = np.cross(d_col, d_row)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n  # type: ignore[no-any-return]


def surface_op(op: str, depth: np.ndarray, k: int, out_dir: str) -> int:
    """Run one normals/splat operation; returns the size of the file(s) it wrote (bytes)."""
    import m360
    from m360.io import normals, splat

    rgb = np.full((*depth.shape, 3), 128, np.uint8)
    if op == "normals_numpy":
        with np.errstate(invalid="ignore", divide="ignore"):
            normals_numpy(depth)
    elif op == "normals":
        m360.normals(depth)
    elif op == "normals_files":
        paths = normals.write_normals(Path(out_dir) / f"n{k}", depth)
        size = sum(p.stat().st_size for p in paths.values())
        for p in paths.values():
            p.unlink()
        return size
    elif op == "to_splats":
        m360.to_splats(depth, rgb)  # the default vertex budget (8K: every 2nd pixel)
    elif op in ("stream_splat", "splat_whole"):
        # what m360.save writes: the default budget, or every pixel
        budget = {"max_vertices": None} if op == "splat_whole" else {}
        target = Path(out_dir) / f"g{k}.splat.ply"
        splat.write_splat_ply(target, depth, rgb=rgb, **budget)
        size = target.stat().st_size
        target.unlink()
        return size
    return 0


def child(op: str, path: str, repeat: int, out_dir: str) -> dict[str, float]:
    if not op.startswith("o3d"):
        import m360
        from m360 import mesh
    depth = np.load(path)
    rgb = np.load(Path(path).with_name(Path(path).name.replace("depth_", "rgb_")))
    rss_input = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times = []
    cpu = []
    size = 0
    for k in range(repeat):
        c0 = time.process_time()
        t0 = time.perf_counter()
        if op in SURFACE_OPS:
            size = surface_op(op, depth, k, out_dir)
        elif op == "numpy_floor":
            numpy_floor(depth)
        elif op == "numpy_warp":
            numpy_warp(rgb, depth)
        elif op == "stereo":
            m360.stereo(depth, rgb, ipd=0.064)
        elif op == "stereo_save":
            from m360.io.stereo import write_stereo

            target = Path(out_dir) / f"st{k}.stereo.jpg"
            write_stereo(target, m360.stereo(depth, rgb, ipd=0.064))
            size = target.stat().st_size
            target.unlink()
        elif op == "to_points":
            m360.to_points(depth, max_vertices=None)
        elif op == "to_mesh":
            m360.to_mesh(depth, max_vertices=None)
        elif op == "to_mesh+glb":
            target = Path(out_dir) / f"m{k}.glb"
            mesh.write_glb(target, m360.to_mesh(depth, max_vertices=None))
            size = target.stat().st_size
            target.unlink()
        elif op == "to_points+ply":
            target = Path(out_dir) / f"p{k}.ply"
            mesh.write_ply(target, m360.to_points(depth, max_vertices=None))
            size = target.stat().st_size
            target.unlink()
        elif op.startswith("stream_"):
            # the streaming writers m360.save uses: the same bytes, a band of rows at a time
            # (stream_glb_budget: with the default vertex budget, as m360.save writes it)
            target = Path(out_dir) / f"s{k}.{op[7:10]}"
            budget = {} if op == "stream_glb_budget" else {"max_vertices": None}
            if op == "stream_ply":
                mesh.write_points_ply(target, depth, **budget)
            else:
                mesh.write_mesh_glb(target, depth, **budget)
            size = target.stat().st_size
            target.unlink()
        elif op in ("trimesh_glb", "trimesh_ply"):
            # the same files through trimesh's exporters (what m360 used first)
            import trimesh

            whole = {"max_vertices": None}
            geometry = (
                m360.to_mesh(depth, **whole)
                if op == "trimesh_glb"
                else m360.to_points(depth, **whole)
            )
            t0 = time.perf_counter()
            if op == "trimesh_glb":
                data = trimesh.Trimesh(
                    geometry.vertices, geometry.faces, process=False, validate=False
                ).export(file_type="glb")
            else:
                data = trimesh.PointCloud(geometry.xyz).export(file_type="ply")
            target = Path(out_dir) / f"t{k}.{op[-3:]}"
            target.write_bytes(data)  # to disk, as m360's writers do
            size = target.stat().st_size
            target.unlink()
            del data
        elif op == "o3d_from_depth":
            # Open3D's depth-to-points is pinhole only: the same number of pixels read as a
            # pinhole depth image (a cost reference, not the ERP geometry).
            import open3d as o3d

            h, w = depth.shape
            image = o3d.geometry.Image(np.nan_to_num(depth, nan=0.0))
            intr = o3d.camera.PinholeCameraIntrinsic(w, h, w / 2, w / 2, w / 2, h / 2)
            t0 = time.perf_counter()
            o3d.geometry.PointCloud.create_from_depth_image(
                image, intr, depth_scale=1.0, depth_trunc=1e9
            )
        elif op == "o3d_from_numpy":
            import open3d as o3d

            pts = numpy_floor(depth).astype(np.float64)
            t0 = time.perf_counter()
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "seconds": float(np.median(times)),
        "cpu_seconds": float(np.median(cpu)),
        "peak_rss_mb": peak / 1024,
        "growth_mb": (peak - rss_input) / 1024,
        "file_mb": size / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[2048, 4096, 8192])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--open3d-python", default=None, help="python with open3d installed")
    parser.add_argument("--ops", nargs="+", choices=OPS, default=list(OPS))
    parser.add_argument(
        "--trimesh-max-width",
        type=int,
        default=4096,
        help="skip trimesh's exporters beyond this width (its GLB export of an 8K mesh peaks "
        "above 7 GB)",
    )
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        op, path, repeat, out_dir = args.child
        print(json.dumps(child(op, path, int(repeat), out_dir)))
        return
    import m360

    print(f"m360 {m360.__version__}, {os.cpu_count()} CPUs (machine shared: timings noisy)")
    print(
        f"{'width':>6} {'operation':<14} {'seconds':>8} {'CPU s':>7} {'peak RSS MB':>11} "
        f"{'growth MB':>9} {'file MB':>8}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp)
        for width in args.widths:
            path = depth_map(width, cache)
            for op in args.ops:
                if op.startswith("trimesh") and width > args.trimesh_max_width:
                    print(f"{width:>6} {op:<14} skipped (--trimesh-max-width)")
                    continue
                python = sys.executable
                if op.startswith("o3d"):
                    if args.open3d_python is None:
                        continue
                    python = args.open3d_python
                cmd = [python, __file__, "--child", op, str(path), str(args.repeat), tmp]
                run = subprocess.run(cmd, capture_output=True, text=True, check=False)
                if run.returncode != 0:
                    why = (run.stderr.strip().splitlines() or [f"exit {run.returncode}"])[-1]
                    print(f"{width:>6} {op:<14} failed: {why}")
                    continue
                r = json.loads(run.stdout.strip().splitlines()[-1])
                print(
                    f"{width:>6} {op:<14} {r['seconds']:>8.3f} {r['cpu_seconds']:>7.2f} "
                    f"{r['peak_rss_mb']:>11.0f} "
                    f"{r['growth_mb']:>9.0f} {r['file_mb']:>8.1f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
