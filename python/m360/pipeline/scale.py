"""Metric scale from what the user knows: the camera height, sparse points, a coarse metric map.

A *scaler* turns a relative ERP disparity (up to a global scale, or scale and shift) into one in
1/metres. It is applied to the final disparity before depth is formed
(``m360.estimate(..., scale=...)`` or :func:`apply` on a result), and it reports how it found the
scale (:class:`ScaleFit`: method, value, residual …), which the sidecar records with
``units: "metres"``. A fit that cannot be trusted (no floor visible, too few usable points, the
points disagree) raises :class:`m360.ScaleError` and nothing is turned into metres.

Models: metric disparity ``= a · disparity`` (depth scale ``value = 1/a``), or with
``affine=True`` ``= a · disparity + b`` (networks whose output is affine-invariant disparity).

- :func:`camera_height`: the floor is a plane ``n · P = h`` in the lower hemisphere; it is found
  by RANSAC over the relative 3D points (planes within 30° of horizontal, inliers within 3 % of
  the plane's distance), refined by iteratively reweighted least squares (Cauchy weights), and
  ``value = height / h``.
- :func:`points`: directions and metric distances of sparse points (LiDAR, SfM); robust fit of
  ``a`` (median of log ratios, then Tukey IRLS) or of ``a, b`` (RANSAC on pairs, then Tukey IRLS).
- :func:`metric_map`: a low-resolution metric ERP depth map, fitted as points at its pixel centres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from .._validate import as_array, number
from ..errors import InputError, ScaleError
from ..stitching.depth import depth_of

__all__ = [
    "CameraHeight",
    "Points",
    "ScaleFit",
    "Scaler",
    "apply",
    "camera_height",
    "depth_of",
    "describe",
    "metric_map",
    "points",
]

#: Seed of the RANSAC draws: fits are deterministic.
_SEED = 360
#: Most samples a fit uses (RANSAC and IRLS cost is linear in it).
_MAX_SAMPLES = 40_000


@dataclass(frozen=True)
class ScaleFit:
    """How a scaler turned relative disparity into 1/metres.

    Attributes
    ----------
    method : str
        ``"camera_height"``, ``"points"`` or ``"metric_map"``.
    value : float
        Depth scale: metres per relative depth unit (``1 / disparity_scale``).
    disparity_scale, disparity_shift : float
        Metric disparity ``= disparity_scale · disparity + disparity_shift`` (shift 0 unless
        affine).
    residual : float
        Robust relative residual of the fit (camera height: RMS distance of the floor inliers
        to the plane / camera height; points: median relative distance error of the inliers).
    details : dict
        Method-specific numbers (inliers, floor tilt, points used …).
    """

    method: str
    value: float
    disparity_scale: float
    disparity_shift: float
    residual: float
    details: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (the sidecar's ``scale``)."""
        return {
            "method": self.method,
            "value": self.value,
            "disparity_scale": self.disparity_scale,
            "disparity_shift": self.disparity_shift,
            "residual": self.residual,
            **self.details,
        }


class Scaler(Protocol):
    """Anything with ``fit(disparity, *, affine) -> ScaleFit``."""

    def fit(self, disparity: np.ndarray, *, affine: bool = False) -> ScaleFit:
        """Fit the metric scale of an (H, W) relative spherical disparity map."""
        ...


def _check_disparity(disparity: Any) -> np.ndarray:
    array = as_array(disparity, "disparity")
    if array.ndim != 2 or array.shape[1] != 2 * array.shape[0] or array.dtype.kind != "f":
        raise InputError(f"disparity must be a float ERP map (H, W), W == 2H, got {array.shape}")
    return array.astype(np.float64)


def _directions(height: int, width: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    lat = np.pi / 2 - np.pi * (rows + 0.5) / height
    lon = 2 * np.pi * (cols + 0.5) / width - np.pi
    c = np.cos(lat)
    return np.stack([c * np.sin(lon), -np.sin(lat), c * np.cos(lon)], axis=-1)


# ------------------------------------------------------------------------------ camera height


@dataclass(frozen=True)
class CameraHeight:
    """Scaler: the floor lies ``height`` metres below the camera (see :func:`camera_height`)."""

    height: float
    max_tilt_deg: float = 30.0
    inlier_tolerance: float = 0.03
    min_floor_fraction: float = 0.05

    def fit(self, disparity: np.ndarray, *, affine: bool = False) -> ScaleFit:
        """Fit the floor plane and return the scale (and the disparity shift when affine).

        With ``affine`` the floor also fixes the shift: on a plane ``n · P = h`` the true
        disparity is ``(n · d) / h``, so the relative disparity of the floor pixels is a line
        ``α (n · d) + o`` in ``n · d``; the plane is refitted after removing ``o`` (until ``o``
        settles, at most 10 rounds).
        """
        disp = _check_disparity(disparity)
        height, width = disp.shape
        # Lower hemisphere, sampled by area (cos latitude) so the pole rows do not dominate.
        rng = np.random.default_rng(_SEED)
        rows = np.arange(height // 2, height)
        lat = np.pi / 2 - np.pi * (rows + 0.5) / height
        per_row = np.maximum(1, np.rint(np.cos(lat) * width).astype(np.int64))
        weights = per_row / per_row.sum()
        n = min(_MAX_SAMPLES, int(per_row.sum()))
        r = rng.choice(rows, size=n, p=weights)
        c = rng.integers(0, width, size=n)
        d = disp[r, c]
        ok = np.isfinite(d)
        if (ok & (d > 0)).sum() < 100:
            raise ScaleError(
                f"camera_height: only {int((ok & (d > 0)).sum())} valid depths below the "
                "horizon; no floor to fit"
            )
        dirs = _directions(height, width, r[ok], c[ok])
        d = d[ok]
        shift = 0.0
        for _round in range(10 if affine else 1):
            previous = shift
            shifted = d - shift
            pos = shifted > 0
            pts = dirs[pos] / shifted[pos][:, None]
            normal, offset, inliers = self._ransac(pts, rng)
            if inliers.mean() < self.min_floor_fraction:
                raise ScaleError(
                    "camera_height: no floor visible: the best plane within "
                    f"{self.max_tilt_deg:g}° of horizontal below the camera holds "
                    f"{inliers.mean() * 100:.1f} % of the lower hemisphere (at least "
                    f"{self.min_floor_fraction * 100:g} % needed)"
                )
            normal, offset, inliers, rms = self._refine(pts, normal, offset)
            if affine:
                # floor pixels: disparity = alpha (n . d) + o, robustly (Tukey IRLS)
                x = dirs[pos][inliers] @ normal
                y = d[pos][inliers]
                design = np.stack([x, np.ones_like(x)], axis=1)
                coef = np.linalg.lstsq(design, y, rcond=None)[0]
                for _ in range(5):
                    w = _tukey(y - design @ coef)
                    lhs = design.T @ (w[:, None] * design)
                    if abs(np.linalg.det(lhs)) < 1e-300:
                        break
                    coef = np.linalg.solve(lhs, design.T @ (w * y))
                shift = float(coef[1])
                if abs(shift - previous) < 1e-4 * float(np.median(np.abs(d))):
                    break
        if affine:
            shifted = d - shift
            pos = shifted > 0
            pts = dirs[pos] / shifted[pos][:, None]
            normal, offset, inliers, rms = self._refine(pts, normal, offset)
        value = self.height / offset
        tilt = float(np.degrees(np.arccos(np.clip(normal[1], -1, 1))))
        return ScaleFit(
            method="camera_height",
            value=float(value),
            disparity_scale=float(1.0 / value),
            disparity_shift=float(-shift / value),
            residual=float(rms),
            details={
                "camera_height_m": self.height,
                "affine": bool(affine),
                "floor_normal": [float(v) for v in normal],
                "floor_tilt_deg": tilt,
                "floor_fraction": float(inliers.mean()),
                "samples": int(pts.shape[0]),
            },
        )

    def _ransac(
        self, pts: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, float, np.ndarray]:
        trials = 400
        pick = rng.integers(0, pts.shape[0], size=(trials, 3))
        p0, p1, p2 = pts[pick[:, 0]], pts[pick[:, 1]], pts[pick[:, 2]]
        normals = np.cross(p1 - p0, p2 - p0)
        length = np.linalg.norm(normals, axis=1)
        good = length > 1e-12
        normals[good] /= length[good, None]
        offsets = np.einsum("ij,ij->i", normals, p0)
        flip = offsets < 0
        normals[flip] *= -1
        offsets[flip] *= -1
        # The floor: below the camera (+y is down), nearly horizontal.
        good &= (normals[:, 1] > np.cos(np.radians(self.max_tilt_deg))) & (offsets > 0)
        if not good.any():
            raise ScaleError("camera_height: no horizontal plane below the camera was found")
        normals, offsets = normals[good], offsets[good]
        # Inlier counts of all candidates at once, in chunks to bound memory.
        counts = np.zeros(normals.shape[0], np.int64)
        for s in range(0, pts.shape[0], 8192):
            dist = pts[s : s + 8192] @ normals.T - offsets[None, :]
            counts += (np.abs(dist) < self.inlier_tolerance * offsets[None, :]).sum(axis=0)
        best = int(np.argmax(counts))
        normal, offset = normals[best], float(offsets[best])
        inliers = np.abs(pts @ normal - offset) < self.inlier_tolerance * offset
        return normal, offset, inliers

    def _refine(
        self, pts: np.ndarray, normal: np.ndarray, offset: float
    ) -> tuple[np.ndarray, float, np.ndarray, float]:
        for _ in range(10):
            res = (pts @ normal - offset) / offset
            near = np.abs(res) < 3 * self.inlier_tolerance
            sigma = self.inlier_tolerance / 2
            w = near / (1.0 + (res / sigma) ** 2)  # Cauchy weights
            centroid = (w[:, None] * pts).sum(0) / w.sum()
            centred = pts - centroid
            cov = (w[:, None] * centred).T @ centred
            normal_new = np.linalg.eigh(cov)[1][:, 0]
            if normal_new[1] < 0:
                normal_new = -normal_new
            normal, offset = normal_new, float(centroid @ normal_new)
        res = (pts @ normal - offset) / offset
        inliers = np.abs(res) < self.inlier_tolerance
        rms = float(np.sqrt(np.mean(res[inliers] ** 2))) if inliers.any() else float("inf")
        return normal, offset, inliers, rms


def camera_height(height: float, *, max_tilt_deg: float = 30.0) -> CameraHeight:
    """Scaler from the camera's height above the floor, in metres.

    The floor plane is fitted robustly in the lower hemisphere (RANSAC among planes within
    ``max_tilt_deg`` of horizontal, then IRLS); the depth scale is ``height`` over the plane's
    relative distance.

    Parameters
    ----------
    height : float
        Camera height above the floor, metres (> 0).
    max_tilt_deg : float
        How far from horizontal the floor may be tilted (camera not level), degrees.

    Returns
    -------
    CameraHeight

    Raises
    ------
    InputError
        ``height`` ≤ 0 or not finite.
    """
    if isinstance(height, bool) or not isinstance(height, (int, float, np.integer, np.floating)):
        raise InputError(f"camera height must be a number of metres, got {height!r}")
    if not np.isfinite(height) or height <= 0:
        raise InputError(f"camera height must be > 0 metres, got {height!r}")
    tilt = number(max_tilt_deg, "max_tilt_deg", low=0.0, high=89.0)
    return CameraHeight(height=float(height), max_tilt_deg=tilt)


# ------------------------------------------------------------------------------ points


def _sample(disp: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Bilinear ERP sample of ``disp`` along unit directions (longitude wraps)."""
    height, width = disp.shape
    lon = np.arctan2(dirs[:, 0], dirs[:, 2])
    lat = np.arctan2(-dirs[:, 1], np.hypot(dirs[:, 0], dirs[:, 2]))
    col = (lon + np.pi) * width / (2 * np.pi) - 0.5
    row = np.clip((np.pi / 2 - lat) * height / np.pi - 0.5, 0, height - 1)
    c0 = np.floor(col).astype(np.int64)
    r0 = np.minimum(np.floor(row).astype(np.int64), height - 2)
    fc, fr = col - c0, row - r0
    c0, c1 = c0 % width, (c0 + 1) % width
    top = disp[r0, c0] * (1 - fc) + disp[r0, c1] * fc
    bottom = disp[r0 + 1, c0] * (1 - fc) + disp[r0 + 1, c1] * fc
    return top * (1 - fr) + bottom * fr  # type: ignore[no-any-return]


def _tukey(res: np.ndarray) -> np.ndarray:
    mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
    c = 4.685 * max(mad, 1e-4)
    u = res / c
    return np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)


def _fit_points(
    rel: np.ndarray, inv_dist: np.ndarray, affine: bool, method: str
) -> tuple[float, float, float, dict[str, Any]]:
    """Fit inv_dist ≈ a·rel (+ b): returns a, b, residual, details."""
    n = rel.size
    need = 5 if affine else 3
    if n < need:
        raise ScaleError(
            f"{method}: {n} usable points (valid depth at their directions); "
            f"at least {need} are needed{' for scale and shift' if affine else ''}"
        )
    if not affine:
        log_ratio = np.log(inv_dist) - np.log(rel)
        est = float(np.median(log_ratio))
        for _ in range(10):
            w = _tukey(log_ratio - est)
            if w.sum() == 0:
                break
            est = float((w * log_ratio).sum() / w.sum())
        a, b = float(np.exp(est)), 0.0
    else:
        rng = np.random.default_rng(_SEED)
        pick = rng.integers(0, n, size=(min(500, n * n), 2))
        pick = pick[pick[:, 0] != pick[:, 1]]
        x0, x1 = rel[pick[:, 0]], rel[pick[:, 1]]
        y0, y1 = inv_dist[pick[:, 0]], inv_dist[pick[:, 1]]
        with np.errstate(divide="ignore", invalid="ignore"):
            a_c = (y1 - y0) / (x1 - x0)
        b_c = y0 - a_c * x0
        ok = np.isfinite(a_c) & (a_c > 0)
        if not ok.any():
            raise ScaleError(f"{method}: the points give no positive disparity scale")
        a_c, b_c = a_c[ok], b_c[ok]
        rel_err = np.abs((a_c[:, None] * rel[None, :] + b_c[:, None]) / inv_dist[None, :] - 1)
        best = int(np.argmax((rel_err < 0.1).sum(axis=1)))
        a, b = float(a_c[best]), float(b_c[best])
        for _ in range(10):
            res = (a * rel + b) / inv_dist - 1
            w = _tukey(res) / inv_dist**2  # residuals relative to each point's disparity
            if (w > 0).sum() < 2:
                break
            design = np.stack([rel, np.ones_like(rel)], axis=1)
            lhs = design.T @ (w[:, None] * design)
            if abs(np.linalg.det(lhs)) < 1e-300:
                break
            a, b = (float(v) for v in np.linalg.solve(lhs, design.T @ (w * inv_dist)))
        if not a > 0:
            raise ScaleError(f"{method}: the fitted disparity scale is {a:g}, not positive")
    pred = a * rel + b
    with np.errstate(divide="ignore", invalid="ignore"):
        dist_err = np.abs(inv_dist / pred - 1)  # relative error of the distances
    inliers = np.isfinite(dist_err) & (dist_err < 0.15)
    if inliers.mean() < 0.5:
        raise ScaleError(
            f"{method}: the points disagree with the depth map: only {inliers.sum()} of {n} "
            "within 15 % after the fit"
        )
    residual = float(np.median(dist_err[inliers]))
    return a, b, residual, {"points_used": n, "inliers": int(inliers.sum())}


def _check_points(directions: Any, distances: Any) -> tuple[np.ndarray, np.ndarray]:
    dirs = as_array(directions, "directions").astype(np.float64)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise InputError(f"directions must have shape (N, 3), got {dirs.shape}")
    if distances is None:
        dist = np.linalg.norm(dirs, axis=1)
    else:
        dist = as_array(distances, "distances").astype(np.float64)
        if dist.shape != (dirs.shape[0],):
            raise InputError(
                f"distances must have shape ({dirs.shape[0]},) like directions, got {dist.shape}"
            )
    if not (np.isfinite(dirs).all() and np.isfinite(dist).all()):
        raise InputError("directions and distances must be finite")
    norms = np.linalg.norm(dirs, axis=1)
    if (norms == 0).any():
        raise InputError(f"{int((norms == 0).sum())} directions are zero vectors")
    if (dist <= 0).any():
        raise InputError(
            f"{int((dist <= 0).sum())} points are behind the camera or at it (distance <= 0); "
            "distances are radial metres > 0"
        )
    return dirs / norms[:, None], dist


@dataclass(frozen=True)
class Points:
    """Scaler from sparse metric points (see :func:`points`)."""

    directions: np.ndarray = field(repr=False)
    distances: np.ndarray = field(repr=False)
    affine: bool | None = None
    method: str = "points"

    def fit(self, disparity: np.ndarray, *, affine: bool = False) -> ScaleFit:
        """Fit scale (and shift when affine) of the disparity to the points."""
        disp = _check_disparity(disparity)
        use_affine = affine if self.affine is None else self.affine
        rel = _sample(disp, self.directions)
        ok = np.isfinite(rel) & (rel > 0)
        a, b, residual, details = _fit_points(
            rel[ok], 1.0 / self.distances[ok], use_affine, self.method
        )
        return ScaleFit(
            method=self.method,
            value=1.0 / a,
            disparity_scale=a,
            disparity_shift=b,
            residual=residual,
            details={"affine": bool(use_affine), "points_given": int(ok.size), **details},
        )


def points(directions: Any, distances: Any = None, *, affine: bool | None = None) -> Points:
    """Scaler from sparse points of known distance (LiDAR, SfM, measured spots).

    Parameters
    ----------
    directions : (N, 3) array
        Directions of the points in the m360 frame (x right, y down, z forward; need not be unit),
        or the points themselves (N, 3) in metres when ``distances`` is None.
    distances : (N,) array, optional
        Radial distances in metres (> 0).
    affine : bool, optional
        Fit scale and shift in disparity (True) or scale only (False); default: shift when the
        network's output is affine (``m360.estimate`` passes that).

    Returns
    -------
    Points

    Raises
    ------
    InputError
        Mismatched shapes, zero directions, non-finite values, points behind the camera.
    """
    dirs, dist = _check_points(directions, distances)
    return Points(dirs, dist, affine=None if affine is None else bool(affine))


def metric_map(depth: Any, *, affine: bool | None = None) -> Points:
    """Scaler from a low-resolution metric ERP depth map (radial metres, NaN = unknown).

    Each finite pixel centre is a point of known distance (:func:`points`); at most 40,000 of
    them are used (a regular subsample).

    Parameters
    ----------
    depth : (h, 2h) float array
        Metric radial depth on the ERP grid (any size W == 2H).
    affine : bool, optional
        As for :func:`points`.

    Returns
    -------
    Points
    """
    array = as_array(depth, "depth")
    if array.ndim != 2 or array.shape[1] != 2 * array.shape[0] or array.dtype.kind != "f":
        raise InputError(f"depth must be a float ERP map (h, w), w == 2h, got {array.shape}")
    valid = np.isfinite(array) & (array > 0)
    if (np.isfinite(array) & (array <= 0)).any():
        raise InputError("the metric map has depths <= 0 (use NaN for unknown)")
    rows, cols = np.nonzero(valid)
    step = max(1, rows.size // _MAX_SAMPLES)
    rows, cols = rows[::step], cols[::step]
    if rows.size == 0:
        raise ScaleError("metric_map: the map has no finite depth")
    dirs = _directions(array.shape[0], array.shape[1], rows, cols)
    return Points(dirs, array[rows, cols].astype(np.float64), affine=affine, method="metric_map")


# ------------------------------------------------------------------------------ apply


def apply(result: Any, scaler: Scaler, *, affine: bool | None = None) -> Any:
    """Return a copy of ``result`` in metres: disparity in 1/m, depth in m, ``scale`` recorded.

    Parameters
    ----------
    result : EstimateResult
        A relative result of :func:`m360.estimate`.
    scaler : Scaler
        :func:`camera_height`, :func:`points`, :func:`metric_map` or any object with ``fit``.
    affine : bool, optional
        Fit a disparity shift too; default: when the model's output is affine disparity.

    Returns
    -------
    EstimateResult
        With ``units == "metres"`` and ``scale`` (:meth:`ScaleFit.as_dict`).

    Raises
    ------
    ScaleError
        The fit failed; ``result`` is left as it was.
    """
    if getattr(result, "units", "relative") != "relative":
        raise InputError(f"the result is already in {result.units}; scale applies to relative")
    if affine is None:
        affine = (getattr(result, "model", None) or {}).get("output_kind") == "affine_disparity"
    disparity, fit = scale_disparity(result.disparity, scaler, affine=bool(affine))
    return dataclasses.replace(
        result, disparity=disparity, depth=depth_of(disparity), units="metres", scale=fit.as_dict()
    )


def scale_disparity(
    disparity: np.ndarray, scaler: Any, *, affine: bool
) -> tuple[np.ndarray, ScaleFit]:
    """Fit ``scaler`` on a relative disparity map and return it in 1/metres with the fit."""
    if not callable(getattr(scaler, "fit", None)):
        raise InputError(
            f"scale must be a scaler (m360.scale.camera_height(...), points(...), metric_map(...)),"
            f" got {type(scaler).__name__}"
        )
    fit = scaler.fit(disparity, affine=affine)
    if not isinstance(fit, ScaleFit) or not (np.isfinite(fit.value) and fit.value > 0):
        raise ScaleError(f"the scaler returned an unusable fit: {fit!r}")
    metric = (fit.disparity_scale * disparity.astype(np.float64) + fit.disparity_shift).astype(
        np.float32
    )
    return metric, fit


def describe(scaler: Any) -> dict[str, Any]:
    """Describe a scaler as JSON (its kind and parameters; arrays by sha256)."""
    import hashlib

    if not dataclasses.is_dataclass(scaler) or isinstance(scaler, type):
        return {"kind": type(scaler).__name__, "repr": repr(scaler)}
    out: dict[str, Any] = {"kind": type(scaler).__name__}
    for f in dataclasses.fields(scaler):
        value = getattr(scaler, f.name)
        if isinstance(value, np.ndarray):
            out[f.name] = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()
        else:
            out[f.name] = value
    return out
