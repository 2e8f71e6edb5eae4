"""The result checked before it is written: bounds, fallbacks, and the anchoring.

:func:`stitch_checked` stitches, puts an aligned result back on the tangents' own values
(:func:`_anchor`: one global scale and offset; metres for a metric network), measures it against
the bounds below and, while it fails them, stitches again with a coarser alignment, then with
none, recording every try (docs/method.md, "Checking the result", "Anchoring the alignment").
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from ..geometry import sphere
from ..geometry.layout import Layout
from ..stitching.options import StitchOptions
from ..stitching.prior import check_prior
from ..stitching.stitch import StitchResult, stitch

__all__ = ["stitch_checked"]

_log = logging.getLogger("m360")

#: Bounds of a stitched result that is trusted (docs/method.md, "Checking the result"): at most
#: this share of the covered pixels not finite beyond what the tangents leave uncovered, ...
RESULT_MAX_LOST = 0.02
#: ... at most this share of the finite pixels ≤ 0, ...
RESULT_MAX_NEGATIVE = 0.01
#: ... a dynamic range (99th over 1st percentile of the positive disparity) at most this times
#: the tangents' own (measured, anchored: real networks 0.20-0.68, exact synthetic tangents up
#: to 0.97; the paper's energy unanchored up to 30; docs/method.md), ...
RESULT_MAX_RANGE = 2.0
#: ... and the alignment's scales within this factor of their median.
RESULT_MAX_SCALE_SPREAD = 1e3
#: The checks and the anchoring read at most this many tangent pixels (a regular subsample).
_CHECK_SAMPLES = 1 << 16


def _fallbacks(opts: StitchOptions) -> list[tuple[str, StitchOptions]]:
    """List the options to try in turn: as asked, a coarser alignment, no alignment."""
    blend = opts.blend
    tries = [("none", opts)]
    if opts.align is not None:
        coarse = StitchOptions.from_dict(
            {"align": {"levels": [_core_first_level()]}, "blend": blend}
        )
        if coarse != opts:
            tries.append(("coarser alignment", coarse))
        tries.append(("no alignment", StitchOptions.from_dict({"align": None, "blend": blend})))
    return tries


def _core_first_level() -> list[int]:
    from .. import _core

    return [int(v) for v in _core.DEFAULTS["align"]["levels"][0]]


def _result_problems(
    details: StitchResult,
    perspective: np.ndarray,
    layout: Layout,
    mask: np.ndarray | None,
    anchor: tuple[float, float] | None,
    reference: np.ndarray | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Measure a stitched result (as ``anchor`` maps it) and list what is out of bounds.

    The dynamic range is compared with the tangents', or with ``reference``'s (the spherical
    disparity of a prior in metres, whose units an unanchored result is in).
    """
    disparity = details.disparity
    finite = np.isfinite(disparity)
    # Pixels some tangent contains that came out NaN, beyond the share of tangent pixels
    # without an estimate (masks, sanitised pixels): those may leave holes.
    covered = details.coverage > 0
    lost = float((covered & ~finite).sum() / max(int(covered.sum()), 1))
    stride = _stride(perspective)
    sample = _spherical_sample(perspective, layout, stride)
    valid = np.isfinite(sample)
    if mask is not None:
        valid &= mask[:, ::stride, ::stride]
    allowed = RESULT_MAX_LOST + 1.5 * float(1.0 - valid.mean())
    erp_sample = disparity.reshape(-1)[:: max(1, disparity.size // (1 << 20))]
    values = erp_sample[np.isfinite(erp_sample)]
    if anchor is not None:
        values = values * np.float32(anchor[0]) + np.float32(anchor[1])
    negative = float((values <= 0).mean()) if values.size else 1.0
    own = _dynamic_range(sample if reference is None else reference)
    dynamic = _dynamic_range(values) / own
    spread = 1.0
    for grid in details.grids:
        scales = np.abs(grid[..., 0])
        median = float(np.median(scales))
        if not np.all(np.isfinite(grid)) or median <= 0:
            spread = float("inf")
            break
        spread = max(
            spread, float(scales.max() / median), float(median / max(scales.min(), 1e-300))
        )
    measured = {
        "lost_fraction": round(lost, 6),
        "negative_fraction": round(negative, 6),
        "dynamic_range": round(dynamic, 4),
        "scale_spread": spread,
    }
    problems = []
    if lost > allowed:
        problems.append(f"{lost:.1%} of the covered pixels are not finite (> {allowed:.1%})")
    if negative > RESULT_MAX_NEGATIVE:
        problems.append(f"{negative:.1%} of the disparity is <= 0")
    if not dynamic <= RESULT_MAX_RANGE:
        whose = "the tangents'" if reference is None else "the prior's"
        problems.append(
            f"disparity range (99th/1st percentile) {dynamic:.3g} times {whose} "
            f"> {RESULT_MAX_RANGE:g}"
        )
    if not spread <= RESULT_MAX_SCALE_SPREAD:
        problems.append(f"alignment scales spread {spread:.3g}x > {RESULT_MAX_SCALE_SPREAD:g}x")
    return measured, problems


def _dynamic_range(values: np.ndarray) -> float:
    """99th over 1st percentile of the finite positive values (a regular subsample)."""
    flat = values.reshape(-1)
    flat = flat[:: max(1, flat.size // _CHECK_SAMPLES)]
    with np.errstate(invalid="ignore"):
        positive = flat[np.isfinite(flat) & (flat > 0)]
    if positive.size == 0:
        return float("nan")
    p1, p99 = np.percentile(positive, [1.0, 99.0])
    return float(p99 / p1) if p1 > 0 else float("inf")


def _stride(perspective: np.ndarray) -> int:
    """Row and column step that leaves about ``_CHECK_SAMPLES`` tangent pixels."""
    return max(1, int(np.ceil(np.sqrt(perspective.size / _CHECK_SAMPLES))))


def _ray_grid(layout: Layout, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel columns and rows ``[::stride, ::stride]`` of a tangent, as two 2D grids."""
    h, w = layout.tangent_shape
    cols = np.arange(0, w, stride, dtype=np.float64)
    rows = np.arange(0, h, stride, dtype=np.float64)
    grid_c, grid_r = np.meshgrid(cols, rows)
    return grid_c, grid_r


def _spherical_sample(perspective: np.ndarray, layout: Layout, stride: int) -> np.ndarray:
    """Give the tangents' spherical disparity (perspective / |q|) at ``[:, ::stride, ::stride]``.

    |q| is computed for the subsample only (the full ray-length stack is N·h·w floats).
    """
    grid_c, grid_r = _ray_grid(layout, stride)
    out = perspective[:, ::stride, ::stride].astype(np.float32)
    for k, cam in enumerate(layout.cameras):
        norm = np.sqrt(((grid_c - cam.cx) / cam.fx) ** 2 + ((grid_r - cam.cy) / cam.fy) ** 2 + 1)
        out[k] /= norm.astype(np.float32)
    return out


def _sample_at_tangent_pixels(erp: np.ndarray, layout: Layout, stride: int) -> np.ndarray:
    """Sample an (H, W) ERP map bilinearly at the tangent pixels ``[:, ::stride, ::stride]``.

    Per camera, the pixel's ray ``Rᵀ q`` to longitude and latitude (docs/conventions.md), then
    ``cv2.remap``: only the subsample is computed, where ``erp_to_tangents`` on a float map
    would build a second set of plan maps (about 130 MB at 2K) for one fit.
    """
    grid_c, grid_r = _ray_grid(layout, stride)
    height, width = erp.shape
    source = np.ascontiguousarray(erp, dtype=np.float32)
    out = np.empty((len(layout), *grid_c.shape), dtype=np.float32)
    for k, cam in enumerate(layout.cameras):
        q = np.stack(
            [(grid_c - cam.cx) / cam.fx, (grid_r - cam.cy) / cam.fy, np.ones_like(grid_c)],
            axis=-1,
        )
        world = q @ np.asarray(cam.rotation, dtype=np.float64)  # Rᵀ q, row vectors
        lon, lat = sphere.directions_to_lonlat(world)
        x, y = sphere.lonlat_to_erp_pixel(lon, lat, height, width)
        out[k] = cv2.remap(
            source,
            np.mod(x, width).astype(np.float32),  # wrap in longitude
            np.clip(y, 0.0, height - 1.0).astype(np.float32),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
    return out


def stitch_checked(
    perspective: np.ndarray,
    layout: Layout,
    mask: np.ndarray | None,
    opts: StitchOptions,
    *,
    prior: Mapping[str, Any] | None = None,
    anchor: bool = True,
) -> tuple[StitchResult, dict[str, Any]]:
    """Stitch, check the result, and fall back (coarser alignment, then none) while it fails.

    ``prior`` holds the prior's keywords of :func:`m360.stitch` (``prior``, ``prior_kind``,
    ``prior_confidence``), given to every try that aligns (a prior acts through the alignment;
    the last fallback, no alignment, stitches without it and its try records ``"prior":
    "dropped"``). ``anchor`` False leaves an aligned result where the stitch put it (a prior in
    metres sets its scale) instead of anchoring it on the tangents' own values.
    """
    prior_args = dict(prior or {})
    reference = None
    if prior_args and not anchor:
        # The result is in the prior's units: its range is what the result's is measured by.
        reference, _, _ = check_prior(
            prior_args["prior"], prior_args["prior_kind"], prior_args.get("prior_confidence")
        )
    tries = _fallbacks(opts)
    report: list[dict[str, Any]] = []
    details: StitchResult | None = None
    taken = "none"
    for k, (name, candidate) in enumerate(tries):
        with_prior = prior_args if candidate.align is not None else {}
        details = stitch(
            perspective,
            layout,
            mask=mask,
            options=candidate,
            return_details=True,
            **with_prior,
        )
        anchored = None
        fit = None
        if candidate.align is not None and anchor:
            fit = _anchor(details.disparity, perspective, layout)
            if fit is not None:
                anchored = {"scale": fit[0], "offset": fit[1], "pixels": fit[2]}
        measured, problems = _result_problems(
            details,
            perspective,
            layout,
            mask,
            None if fit is None else fit[:2],
            reference if with_prior else None,
        )
        report.append(
            {
                "options": name if k else "as asked",
                "anchor": anchored,
                **measured,
                "problems": problems,
                **({"prior": "dropped"} if prior_args and not with_prior else {}),
            }
        )
        taken = name
        if not problems:
            break
        if k + 1 < len(tries):
            _log.warning(
                "the stitched result failed its checks (%s): falling back to %s",
                "; ".join(problems),
                tries[k + 1][0],
            )
        else:
            _log.warning(
                "the result failed its checks without alignment too: %s", "; ".join(problems)
            )
    if details is None:  # _fallbacks always gives at least the asked options
        raise RuntimeError("no stitch was tried")
    return details, {"result": report, "fallback": taken, "anchor": report[-1]["anchor"]}


def _anchor(
    disparity: np.ndarray, perspective: np.ndarray, layout: Layout
) -> tuple[float, float, int] | None:
    """Fit the global affine map that puts an aligned result back on the tangents' own values.

    The alignment fixes every tangent's scale and offset relative to the others but leaves one
    global scale and offset free (a gauge); its standardisation puts them somewhere, and the
    paper's energy drives them far off (docs/method.md, "Anchoring the alignment"). The fit is
    of the tangents' spherical disparity (perspective / |q|) against the result sampled at the
    same tangent pixels: least squares, reweighted three times with a Cauchy loss (scale 2.385
    times the median absolute residual), on about 2¹⁶ pixels (every k-th row and column). The map
    is applied after the upsampling (:func:`_from_network`), which therefore sees the same
    values as before the anchoring existed.

    Returns
    -------
    (scale, offset, pixels), or None when no usable fit exists (no common pixel, scale ≤ 0).
    """
    stride = _stride(perspective)
    x32 = _sample_at_tangent_pixels(disparity, layout, stride).reshape(-1)
    y32 = _spherical_sample(perspective, layout, stride).reshape(-1)
    good = np.isfinite(x32) & np.isfinite(y32)
    count = int(good.sum()) * stride * stride  # about how many tangent pixels took part
    if good.sum() < 2:
        return None
    x = x32[good].astype(np.float64)
    y = y32[good].astype(np.float64)
    weight = np.ones_like(x)
    scale = offset = float("nan")
    for _ in range(3):
        root = np.sqrt(weight)
        design = np.stack([x * root, root], axis=1)
        solution, *_ = np.linalg.lstsq(design, y * root, rcond=None)
        scale, offset = float(solution[0]), float(solution[1])
        residual = y - (scale * x + offset)
        width = 2.385 * float(np.median(np.abs(residual))) + 1e-12
        weight = 1.0 / (1.0 + (residual / width) ** 2)
    if not (np.isfinite(scale) and np.isfinite(offset) and scale > 0):
        return None
    return scale, offset, count
