"""Measure the default max_depth_ratio of m360.to_mesh on synthetic rooms.

For every grid triangle of m360.to_mesh(exact depth, max_depth_ratio=inf) the depth ratio
max/min of its three vertices is compared with an oracle from the scene itself: each edge is
sampled at 8 intermediate rays, ray cast, and the triangle spans an occlusion edge when two
consecutive samples along an edge differ by more than 3 % (a continuous surface changes by well
under 1 % per eighth of a pixel). Prints, per resolution, the ratio quantiles of the triangles on
continuous surfaces and the smallest ratio of the triangles across an occlusion edge.

    .venv/bin/python benches/measure_depth_ratio.py [--widths 1024 2048] [--seeds 8]
"""

from __future__ import annotations

import argparse

import m360
import numpy as np
from m360 import synthetic

SUBSTEPS = 8
JUMP = 1.03


def spans_jump(scene: synthetic.Scene, ends: np.ndarray) -> np.ndarray:
    """(T, 3 vertices, 3) unit directions -> (T,) True where an edge crosses a depth jump."""
    out = np.zeros(ends.shape[0], bool)
    t = np.linspace(0.0, 1.0, SUBSTEPS + 1)[None, :, None]
    for k in range(3):
        p, q = ends[:, k], ends[:, (k + 1) % 3]
        rays = p[:, None] * (1 - t) + q[:, None] * t
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        dist = scene.distance(rays)
        step = dist[:, 1:] / dist[:, :-1]
        out |= (np.maximum(step, 1 / step) > JUMP).any(axis=1)
    return out


def measure(width: int, seeds: int) -> None:
    cont, jumps = [], []
    for seed in range(seeds):
        scene = synthetic.room(seed)
        _, depth = synthetic.render(scene, width)
        mesh = m360.to_mesh(depth, max_depth_ratio=np.inf, poles=False)
        r = np.linalg.norm(mesh.vertices, axis=1)
        tri_r = r[mesh.faces]
        ratio = tri_r.max(1) / tri_r.min(1)
        suspect = ratio > 1.01  # below this no edge can hide a 3 % jump between its samples
        dirs = mesh.vertices[mesh.faces[suspect]].astype(np.float64)
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        jump = spans_jump(scene, dirs)
        cont.append(np.concatenate([ratio[~suspect], ratio[suspect][~jump]]))
        jumps.append(ratio[suspect][jump])
    c, j = np.concatenate(cont), np.concatenate(jumps)
    q = np.quantile(c, [0.99, 0.999, 0.9999, 1.0])
    print(
        f"W={width}: continuous triangles {c.size}: ratio q99 {q[0]:.4f} q99.9 {q[1]:.4f} "
        f"q99.99 {q[2]:.4f} max {q[3]:.4f}; occlusion triangles {j.size}: ratio min "
        f"{j.min():.4f} q1 {np.quantile(j, 0.01):.4f} median {np.median(j):.4f}"
    )
    for cut in (1.05, 1.1, 1.15, 1.2, 1.3):
        print(
            f"  cut {cut}: drops {np.mean(c > cut) * 100:.4f} % of continuous, keeps "
            f"{np.mean(j <= cut) * 100:.2f} % of occlusion triangles"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[1024, 2048])
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args()
    for width in args.widths:
        measure(width, args.seeds)


if __name__ == "__main__":
    main()
