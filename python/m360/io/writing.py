"""Writing one result, never leaving a half-written set: :func:`save`.

Every file goes through :func:`m360.io.files.atomic_path`; the sidecar ``STEM.json`` is written
last, so a sidecar means the whole set is there (:func:`m360.io.results.load` refuses a stem
without one).
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._validate import flag
from ..errors import InputError
from . import mesh, normals, splat
from .files import (
    ERP_CONVENTION,
    FORMAT_SUFFIXES,
    GEOMETRY_FILES,
    GEOMETRY_FORMATS,
    NORMALS_FORMATS,
    QUANTITIES,
    SAVE_FORMATS,
    STEREO_FILES,
    STEREO_FORMATS,
    _check_map,
    check_formats,
    colorize,
    save_json,
    save_png,
    write_array,
)

if TYPE_CHECKING:
    from typing_extensions import Unpack

    from .stereo import StereoKeywords


def save(
    result: Any,
    stem: str | os.PathLike[str],
    *,
    formats: Sequence[str] | str = ("npy",),
    preview: bool = True,
    extra: Mapping[str, Any] | None = None,
    rgb: np.ndarray | None = None,
    confidence: bool = False,
    max_vertices: int | None = mesh.DEFAULT_MAX_VERTICES,
    **stereo_options: Unpack[StereoKeywords],
) -> dict[str, Path]:
    """Write an :class:`m360.EstimateResult` next to ``stem``, atomically, the sidecar last.

    Files: ``STEM.disparity.EXT`` and ``STEM.depth.EXT`` per format (``npy``, ``pfm``, ``exr``:
    float32, NaN = invalid; ``png16``: ``.png`` 16-bit, 0 = invalid, value = offset +
    (code − 1)·scale with offset/scale in the sidecar), ``STEM.preview.png`` (colour preview of
    the disparity) and last ``STEM.json``, the sidecar: quantities and units, ERP convention,
    model and its sha256, layout, options, timings, m360 version, the files (plus ``extra``,
    e.g. the input file and its sha256). Any earlier sidecar is removed first and the files of
    this call are removed again if it fails, so a sidecar always describes a complete set.

    Parameters
    ----------
    result : EstimateResult
        Or any object with ``disparity``/``depth`` (H, W) float arrays (``model``, ``units``,
        ``options``, ``timings``, ``layout`` are recorded when present).
    stem : path
        Output path without suffix, e.g. ``out/pano``; folders are created.
    formats : sequence of str
        Any of ``"npy"`` (default), ``"pfm"``, ``"exr"``, ``"png16"``, and the 3D formats
        (extra ``m360[3d]``) ``"ply"`` (``STEM.points.ply``: the point cloud, m360 frame) and
        ``"glb"`` (``STEM.mesh.glb``: the mesh of :func:`m360.to_mesh`, glTF frame, y up),
        ``"splat"`` (``STEM.splat.ply``: the 3D Gaussian splats of :func:`m360.to_splats`,
        m360 frame), and ``"normals"`` (``STEM.normals.exr`` float32 and ``STEM.normals.png``
        8-bit: :func:`m360.normals`, m360 frame); the sidecar's ``frame`` says which frame
        each 3D file is in.
    preview : bool
        Also write the colour preview PNG.
    extra : mapping, optional
        More JSON-serialisable fields for the sidecar.
    rgb : (H, W, 3) uint8, optional
        The panorama: colours of the 3D files.
    confidence : bool
        Also write ``result.confidence`` (the overlap disagreement left, in disparity units,
        lower = more consistent; NaN = unseen) as ``STEM.confidence.EXT`` in every format, and
        describe it in the sidecar.
    max_vertices : int or None
        The most vertices of each 3D file: a larger map is strided to fit
        (:func:`m360.mesh.stride_for`; default :data:`m360.mesh.DEFAULT_MAX_VERTICES`, None =
        every pixel). The sidecar's ``geometry`` records the stride and counts of each file.
        The 3D files are written a band of rows at a time (:func:`m360.mesh.write_points_ply`,
        :func:`m360.mesh.write_mesh_glb`).
    **stereo_options
        ``ipd``, ``pole_fade``, ``median_distance`` of the stereo formats ``stereo``
        (``STEM.stereo.jpg``) and ``stereo-png`` (``STEM.stereo.png``): the ODS pair of
        :func:`m360.stereo` top-bottom, left eye on top, with GPano stereo XMP; they need
        ``rgb``. The sidecar's ``stereo`` records the IPD, the depth's scale and the filled
        fraction.

    Returns
    -------
    dict
        Role (``disparity.npy``, ``depth.pfm`` …, ``preview``, ``sidecar``) → path written.
    """
    from .._core import __version__

    chosen = check_formats(formats)
    mesh.check_max_vertices(max_vertices)
    unknown = [k for k in stereo_options if k not in ("ipd", "pole_fade", "median_distance")]
    if unknown:
        raise TypeError(f"save() got unexpected keyword argument(s) {unknown}")
    stereo_formats = [f for f in chosen if f in STEREO_FORMATS]
    if stereo_formats:
        from .._keywords import checked
        from .stereo import StereoKeywords

        stereo_options = checked(stereo_options, StereoKeywords)  # type: ignore[assignment]
        if rgb is None:
            raise InputError(f"the formats {', '.join(stereo_formats)} need the panorama: rgb=")
    with np.errstate(over="ignore"):  # float64 beyond float32's range is ±inf, as in m360's maps
        arrays = {
            q: np.ascontiguousarray(_check_map(getattr(result, q, None), q), dtype=np.float32)
            for q in QUANTITIES
        }
    flag(confidence, "confidence")
    if confidence:
        with np.errstate(over="ignore"):
            arrays["confidence"] = np.ascontiguousarray(
                _check_map(getattr(result, "confidence", None), "confidence"), dtype=np.float32
            )
        if arrays["confidence"].shape != arrays["disparity"].shape:
            raise InputError(
                f"result.confidence {arrays['confidence'].shape} and result.disparity "
                f"{arrays['disparity'].shape} differ in shape"
            )
    if arrays["disparity"].shape != arrays["depth"].shape:
        raise InputError(
            f"result.disparity {arrays['disparity'].shape} and result.depth "
            f"{arrays['depth'].shape} differ in shape"
        )
    base = Path(stem)
    sidecar_path = base.with_name(base.name + ".json")
    written: dict[str, Path] = {}
    files: dict[str, Any] = {q: {} for q in arrays}
    png16: dict[str, Any] = {}
    with contextlib.suppress(FileNotFoundError):
        sidecar_path.unlink()  # the old set is incomplete from here on
    try:
        for fmt in [f for f in chosen if f in SAVE_FORMATS]:
            for quantity, values in arrays.items():
                path = base.with_name(f"{base.name}.{quantity}{FORMAT_SUFFIXES[fmt]}")
                params = write_array(path, values, fmt)
                if params:
                    png16[quantity] = params
                written[f"{quantity}.{fmt}"] = path
                files[quantity][fmt] = path.name
        if preview:
            written["preview"] = save_png(
                base.with_name(base.name + ".preview.png"), colorize(arrays["disparity"])
            )
            files["preview"] = written["preview"].name
        frames, geometry = _save_geometry(result, base, chosen, rgb, written, files, max_vertices)
        stereo_info = _save_stereo(
            result, base, stereo_formats, rgb, written, files, stereo_options
        )
        sidecar = _sidecar(result, arrays["disparity"], files, png16, __version__)
        if stereo_info:
            sidecar["stereo"] = stereo_info
        if frames:
            sidecar["frame"] = frames
            sidecar["geometry"] = geometry  # stride used and counts, per 3D file
        if extra:
            sidecar.update(extra)
        written["sidecar"] = save_json(sidecar_path, sidecar)
    except BaseException:
        for path in written.values():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        raise
    return written


def _save_geometry(
    result: Any,
    base: Path,
    chosen: Sequence[str],
    rgb: np.ndarray | None,
    written: dict[str, Path],
    files: dict[str, Any],
    max_vertices: int | None,
) -> tuple[dict[str, str], dict[str, Any]]:
    """Write the 3D formats among ``chosen`` (streamed) and the normals.

    Returns file name → frame and file name → stride, budget and counts, for the sidecar.
    """
    frames: dict[str, str] = {}
    geometry: dict[str, Any] = {}
    for fmt in [f for f in chosen if f in GEOMETRY_FORMATS]:
        kind, tail = GEOMETRY_FILES[fmt]
        path = base.with_name(base.name + tail)
        if fmt == "ply":
            info: dict[str, Any] = mesh.write_points_ply(
                path, result, rgb=rgb, max_vertices=max_vertices
            )
        elif fmt == "splat":
            info = splat.write_splat_ply(path, result, rgb=rgb, max_vertices=max_vertices)
        else:
            info = mesh.write_mesh_glb(path, result, rgb=rgb, max_vertices=max_vertices)
        written[f"{kind}.{fmt}"] = path
        files[kind] = {fmt: path.name}
        frames[path.name] = splat.FRAME if fmt == "splat" else mesh.FRAMES[fmt]
        geometry[path.name] = {**info, "max_vertices": max_vertices}
    if any(f in NORMALS_FORMATS for f in chosen):
        paths = normals.write_normals(base, result)
        files["normals"] = {}
        for fmt, path in paths.items():
            written[f"normals.{fmt}"] = path
            files["normals"][fmt] = path.name
            frames[path.name] = normals.NORMALS_FRAME
    return frames, geometry


def _save_stereo(
    result: Any,
    base: Path,
    formats: Sequence[str],
    rgb: np.ndarray | None,
    written: dict[str, Path],
    files: dict[str, Any],
    options: Mapping[str, Any],
) -> dict[str, Any] | None:
    """Write the stereo formats among ``formats`` (one warp for both); return the sidecar part."""
    if not formats:
        return None
    from .stereo import stereo, write_stereo

    pair = stereo(result, rgb, **{k: v for k, v in options.items() if v is not None})
    files["stereo"] = {}
    for fmt in formats:
        path = write_stereo(base.with_name(base.name + STEREO_FILES[fmt][1]), pair, fmt)
        written[f"stereo.{fmt}"] = path
        files["stereo"][fmt] = path.name
    return pair.describe()


def _sidecar(
    result: Any,
    disparity: np.ndarray,
    files: dict[str, Any],
    png16: dict[str, Any],
    version: str,
) -> dict[str, Any]:
    units = getattr(result, "units", "relative")
    layout = getattr(result, "layout", None)
    sidecar: dict[str, Any] = {
        "m360_version": version,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "files": files,
        "quantities": {
            "disparity": {
                "meaning": "spherical disparity 1/distance"
                + (" up to a global scale and shift" if units == "relative" else ""),
                "units": "relative" if units == "relative" else "1/metres",
                "dtype": "float32",
                "invalid": "NaN (png16: 0)",
            },
            "depth": {
                "meaning": "radial distance |P| = 1/disparity where disparity > 0",
                "units": units,
                "dtype": "float32",
                "invalid": "NaN (png16: 0)",
            },
        },
        "shape": list(disparity.shape),
        "erp_convention": ERP_CONVENTION,
        "model": getattr(result, "model", None),
        "layout": None
        if layout is None
        else {
            "name": layout.name,
            "erp_shape": list(layout.erp_shape),
            "cameras": len(layout),
            "tangent_shape": list(layout.tangent_shape),
            "padding": layout.padding,
            "key": layout.key,
        },
        "options": getattr(result, "options", {}),
        "timings_s": {k: round(float(v), 6) for k, v in getattr(result, "timings", {}).items()},
        # The truth: the share of pixels with a finite, positive disparity (a depth).
        "valid_fraction": _valid_fraction(disparity),
        "units": units,
    }
    if "confidence" in files:
        sidecar["quantities"]["confidence"] = {
            "meaning": "overlap disagreement left after blending (lower = more consistent)",
            "units": "disparity units",
            "dtype": "float32",
            "invalid": "NaN (png16: 0)",
        }
    if "normals" in files:
        sidecar["quantities"]["normals"] = {
            "meaning": "unit surface normal facing the camera, from 3D chords of the depth",
            "frame": normals.NORMALS_FRAME,
            "dtype": "float32 (exr), uint8 (png)",
            "invalid": "NaN (png: 0 0 0)",
        }
    report = getattr(getattr(result, "stitch", None), "report", None)
    if isinstance(report, Mapping) and "align_fallback" in report:
        sidecar["alignment"] = {"fallback": report["align_fallback"]}
    checks = getattr(result, "checks", None)
    if isinstance(checks, Mapping) and checks:
        # What the result was checked for before it was written (m360.EstimateResult.checks).
        sidecar["fallback"] = checks.get("fallback", "none")
        sidecar["checks"] = _jsonable(
            {k: v for k, v in checks.items() if k not in ("fallback", "valid_fraction")}
        )
    if png16:
        sidecar["png16"] = png16
    if getattr(result, "scale", None) is not None:
        sidecar["scale"] = result.scale
    return sidecar


def _valid_fraction(disparity: np.ndarray) -> float:
    """Share of the pixels whose disparity is finite and > 0 (they have a depth)."""
    with np.errstate(invalid="ignore"):
        return float((np.isfinite(disparity) & (disparity > 0)).mean())


def _jsonable(value: Any) -> Any:
    """``value`` with non-finite floats as None and tuples as lists (strict JSON)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
