"""What a network does on a scene whose depth is known: the guesses of ``m360 models check``.

A synthetic corridor (:mod:`m360.evaluation.synthetic`: textured walls, a checker floor, two
boxes, lights) is ray cast through a few pinhole cameras at the origin; the network runs on each
view and its output is rank-correlated with the true z-depth. Any depth network, however weak,
gets a corridor's strong perspective roughly right: its output grows with depth (a depth) or
falls with it (a disparity). The same views run under each named normalisation tell which one
the network was trained with (the right one gives the clearest depth). A panoramic network sees
the corridor as one ERP panorama (:func:`erp_views`), its output compared with the radial
distance.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..evaluation import synthetic
from ..geometry.sphere import camera_pixel_directions, erp_directions

__all__ = [
    "DEPTH_DIRECTION",
    "KindGuess",
    "best_normalisation",
    "erp_views",
    "guess_kind",
    "rank_correlation",
    "views",
]

#: |rank correlation| with depth below which the output is taken not to follow depth at all.
FOLLOWS_DEPTH = 0.3
#: |rank correlation| for a "high" and a "medium" confidence.
HIGH, MEDIUM = 0.6, 0.45
#: A metric output's median is within this factor of the true median depth.
METRIC_FACTOR = 3.0
#: The best normalisation must beat the next by this much rank correlation to be named. A weak
#: hint: brightness and normalisation are confounded (a dark scene under ImageNet's constants
#: looks like a normal one in [0, 1]), so only a clear lead counts.
NORMALIZE_MARGIN = 0.12
#: Whether a network's raw output of each kind grows (+1) or falls (−1) with depth.
DEPTH_DIRECTION: dict[str, int] = {
    "affine_disparity": -1,
    "disparity": -1,
    "affine_depth": 1,
    "metric_depth": 1,
    "distance": 1,
    "negated_affine_disparity": 1,
}
#: (yaw, pitch) in degrees of the probe views: down the corridor, a little to each side, and
#: more steeply down (the floor's regular depth gradient is what weak networks get right).
VIEW_ANGLES = ((0.0, -10.0), (15.0, -12.0), (-15.0, -12.0), (0.0, -18.0))


def _material(texture: str, albedo: tuple[float, float, float], period: float, seed: int) -> Any:
    rng = np.random.default_rng(seed)
    return synthetic.Material(
        albedo=np.array(albedo),
        texture=texture,
        period=period,
        waves=rng.normal(size=(3, 3)),
        phase=rng.uniform(0.0, 2 * np.pi, 3),
    )


@functools.cache
def corridor() -> synthetic.Scene:
    """A 3 m wide, 2.5 m high, 13 m long corridor around the camera (1.3 m above the floor)."""
    walls = (
        _material("stripes", (0.8, 0.7, 0.6), 0.6, 1),  # -x
        _material("stripes", (0.6, 0.7, 0.8), 0.6, 2),  # +x
        _material("plain", (0.9, 0.9, 0.9), 0.5, 0),  # ceiling (-y)
        _material("checker", (0.5, 0.4, 0.3), 0.5, 0),  # floor (+y)
        _material("noise", (0.7, 0.7, 0.7), 0.4, 3),  # behind (-z)
        _material("noise", (0.4, 0.5, 0.4), 0.4, 4),  # far end (+z)
    )
    boxes = (
        synthetic.Box(
            center=np.array([-0.9, 0.9, 3.0]),
            half_size=np.array([0.4, 0.4, 0.4]),
            material=_material("checker", (0.8, 0.3, 0.2), 0.2, 5),
        ),
        synthetic.Box(
            center=np.array([1.0, 0.7, 6.0]),
            half_size=np.array([0.3, 0.6, 0.4]),
            material=_material("noise", (0.2, 0.4, 0.8), 0.2, 6),
        ),
    )
    lights = (
        synthetic.Light(position=np.array([0.0, -1.0, 2.0]), intensity=3.0),
        synthetic.Light(position=np.array([0.0, -1.0, 8.0]), intensity=6.0),
    )
    return synthetic.Scene(
        room_min=np.array([-1.5, -1.2, -1.0]),
        room_max=np.array([1.5, 1.3, 12.0]),
        boxes=boxes,
        lights=lights,
        room_materials=walls,
        ambient=0.3,
    )


@functools.lru_cache(maxsize=4)
def views(shape: tuple[int, int]) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The probe views at ``shape`` (h, w): ((h, w, 3) uint8 RGB, (h, w) float32 z-depth) each.

    Pinhole cameras at the origin with a 70° horizontal field of view (an icosahedron tangent
    with m360's padding sees about as much).
    """
    h, w = shape
    f = w / 2 / np.tan(np.radians(35.0))
    scene = corridor()
    out = []
    for yaw, pitch in VIEW_ANGLES:
        rotation = synthetic.rotation_matrix(np.radians(yaw), np.radians(pitch)).T
        dirs, ray_norm = camera_pixel_directions(
            rotation, f, f, (w - 1) / 2, (h - 1) / 2, w, h, return_ray_norm=True
        )
        rgb = scene.shade(dirs)
        z = (scene.distance(dirs) / ray_norm).astype(np.float32)
        rgb.flags.writeable = False
        z.flags.writeable = False
        out.append((rgb, z))
    return tuple(out)


@functools.lru_cache(maxsize=4)
def erp_views(shape: tuple[int, int]) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The probe panorama at ``shape`` (h, w): one ((h, w, 3) uint8 RGB, (h, w) distance) pair.

    The corridor seen from the origin as an ERP (docs/conventions.md), with the true radial
    distance |P| of each pixel: what a panoramic network is probed on.
    """
    h, w = shape
    dirs = erp_directions(h, w)
    scene = corridor()
    rgb = scene.shade(dirs)
    distance = scene.distance(dirs).astype(np.float32)
    rgb.flags.writeable = False
    distance.flags.writeable = False
    return ((rgb, distance),)


def best_normalisation(scores: dict[str, float], direction: int = 0) -> str | None:
    """Name the normalisation under which the output follows depth most clearly, if one does.

    ``scores`` holds the output's rank correlation with depth per named normalisation. With a
    declared output kind, ``direction`` is its :data:`DEPTH_DIRECTION`: only correlations of
    that sign count, because an output that runs the other way is a broken input, however
    strongly it correlates. With 0 (no kind declared) either sign counts. The winner must follow
    depth (:data:`FOLLOWS_DEPTH`) and lead the next by :data:`NORMALIZE_MARGIN`; else None.
    """
    strength = {k: (direction * v if direction else abs(v)) for k, v in scores.items()}
    ranked = sorted(strength, key=lambda k: -strength[k])
    if len(ranked) < 2:
        return None
    best, second = strength[ranked[0]], strength[ranked[1]]
    if best >= FOLLOWS_DEPTH and best - second >= NORMALIZE_MARGIN:
        return ranked[0]
    return None


def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of two arrays over their finite pairs (0.0 if undefined)."""
    x, y = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return 0.0
    rx, ry = _ranks(x[ok]), _ranks(y[ok])
    rx -= rx.mean()
    ry -= ry.mean()
    denom = float(np.sqrt((rx * rx).sum() * (ry * ry).sum()))
    return float((rx * ry).sum() / denom) if denom > 0 else 0.0


def _ranks(values: np.ndarray) -> np.ndarray:
    """Ranks from 0, ties sharing their mean rank (a flat output has no correlation)."""
    order = np.argsort(values, kind="mergesort")
    ordered = values[order]
    first = np.r_[True, ordered[1:] != ordered[:-1]]
    group = np.cumsum(first) - 1
    starts = np.flatnonzero(first)
    ends = np.r_[starts[1:], values.size]
    ranks = np.empty(values.size, dtype=np.float64)
    ranks[order] = ((starts + ends - 1) / 2.0)[group]
    return ranks


def depth_at(z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The true depth of a view at an output's (h, w) (area-averaged)."""
    if z.shape == shape:
        return z
    return cv2.resize(z, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class KindGuess:
    """What a network's output looks like on the probe views.

    Attributes
    ----------
    kind : str or None
        ``"affine_disparity"``, ``"metric_depth"``, ``"affine_depth"``, or None (cannot tell).
    confidence : str
        ``"high"``, ``"medium"``, ``"low"`` or ``"none"``.
    correlation : float
        Mean rank correlation of the output with the true depth over the views (-1 … 1).
    median_ratio : float
        Median output / median true depth (NaN when not all outputs are finite and > 0).
    reason : str
        One line for reports.
    """

    kind: str | None
    confidence: str
    correlation: float
    median_ratio: float
    reason: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-able record."""
        ratio = self.median_ratio
        return {
            "kind": self.kind,
            "confidence": self.confidence,
            "correlation_with_depth": round(self.correlation, 3),
            "median_over_true_depth": None if not np.isfinite(ratio) else round(ratio, 3),
            "reason": self.reason,
        }


def guess_kind(
    outputs: list[np.ndarray], depths: list[np.ndarray], *, panoramic: bool = False
) -> KindGuess:
    """Guess what the ``outputs`` (one per view) are from the views' true z-``depths``.

    Grows with depth and reads like metres (all > 0, median within a factor 3 of the true
    median): ``metric_depth``; grows with depth otherwise: ``affine_depth``; falls with depth:
    ``affine_disparity``; neither (|rank correlation| < 0.3): None. With ``panoramic`` the
    depths are radial distances, and metres are ``distance``; an output falling with depth
    whose inverse reads like metres is ``disparity`` (1/metres).
    """
    pairs = [
        (np.asarray(o, np.float64), depth_at(z, np.shape(o)))
        for o, z in zip(outputs, depths, strict=True)
    ]
    finite = np.concatenate([np.isfinite(o).ravel() for o, _ in pairs])
    if finite.mean() < 0.5:
        return KindGuess(None, "none", 0.0, float("nan"), "the output is mostly not finite")
    rho = float(np.mean([rank_correlation(o, z) for o, z in pairs]))
    values = np.concatenate([o.ravel() for o, _ in pairs])
    values = values[np.isfinite(values)]
    truth = np.concatenate([z.ravel() for _, z in pairs])
    positive = bool(values.size and values.min() > 0)
    ratio = float(np.median(values) / np.median(truth)) if positive else float("nan")
    strength = abs(rho)
    confidence = "high" if strength >= HIGH else "medium" if strength >= MEDIUM else "low"
    if strength < FOLLOWS_DEPTH:
        return KindGuess(
            None,
            "none",
            rho,
            ratio,
            f"the output does not follow the scene's depth (rank correlation {rho:+.2f})",
        )
    if rho < 0:
        inverse = 1.0 / ratio / float(np.median(truth)) ** 2 if positive else float("nan")
        if panoramic and positive and 1 / METRIC_FACTOR <= inverse <= METRIC_FACTOR:
            return KindGuess(
                "disparity",
                confidence,
                rho,
                ratio,
                f"falls as distance grows (rank correlation {rho:+.2f}), positive, its inverse "
                f"about {inverse:.2f}x the true distance: 1/metres",
            )
        return KindGuess(
            "affine_disparity",
            confidence,
            rho,
            ratio,
            f"falls as depth grows (rank correlation {rho:+.2f}): a disparity",
        )
    if positive and 1 / METRIC_FACTOR <= ratio <= METRIC_FACTOR:
        return KindGuess(
            "distance" if panoramic else "metric_depth",
            confidence,
            rho,
            ratio,
            f"grows with depth (rank correlation {rho:+.2f}), positive, median {ratio:.2f}x the "
            "true depth: metres",
        )
    sign = "positive" if positive else "not all positive"
    scale = f", median {ratio:.2f}x the true depth" if positive else ""
    return KindGuess(
        "affine_depth",
        confidence,
        rho,
        ratio,
        f"grows with depth (rank correlation {rho:+.2f}) but is {sign}{scale}: a depth up to "
        "scale and shift",
    )
