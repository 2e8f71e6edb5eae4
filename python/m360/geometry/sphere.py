"""Numpy oracle of m360's sphere and camera conventions (docs/conventions.md).

Plain, vectorised numpy: used by the tests (as an independent reference for the Rust core) and by
:mod:`m360.synthetic`. World frame: x right, y down, z forward (OpenCV style, right-handed).

ERP image (H, W), W == 2H. Pixel (row i, column j) centre:
longitude ``lon = 2π (j + 0.5) / W - π``, latitude ``lat = π/2 - π (i + 0.5) / H``, and direction
``d = (cos lat · sin lon, -sin lat, cos lat · cos lon)``.
"""

from __future__ import annotations

from typing import Literal, overload

import numpy as np

from m360.errors import InputError

__all__ = [
    "camera_pixel_directions",
    "directions_to_lonlat",
    "erp_directions",
    "erp_latitudes",
    "erp_longitudes",
    "lonlat_to_directions",
    "lonlat_to_erp_pixel",
]


def _check_size(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def erp_latitudes(height: int) -> np.ndarray:
    """Latitude of each ERP row centre.

    Parameters
    ----------
    height : int
        Number of rows H (≥ 1).

    Returns
    -------
    np.ndarray
        (H,) float64, radians: ``π/2 - π (i + 0.5) / H`` (positive = up, row 0 at the top).
    """
    h = _check_size("height", height)
    return np.pi / 2 - np.pi * (np.arange(h, dtype=np.float64) + 0.5) / h


def erp_longitudes(width: int) -> np.ndarray:
    """Longitude of each ERP column centre: (W,) float64 radians, ``2π (j + 0.5) / W - π``."""
    w = _check_size("width", width)
    return 2 * np.pi * (np.arange(w, dtype=np.float64) + 0.5) / w - np.pi


def lonlat_to_directions(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Return the unit directions of (longitude, latitude) pairs.

    Parameters
    ----------
    lon, lat : array_like
        Broadcastable float arrays, radians.

    Returns
    -------
    np.ndarray
        (..., 3) float64 unit vectors ``(cos lat · sin lon, -sin lat, cos lat · cos lon)``.
    """
    lon = np.asarray(lon, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    lon, lat = np.broadcast_arrays(lon, lat)
    c = np.cos(lat)
    return np.stack([c * np.sin(lon), -np.sin(lat), c * np.cos(lon)], axis=-1)


def erp_directions(height: int, width: int) -> np.ndarray:
    """Return the viewing directions of every ERP pixel centre.

    Parameters
    ----------
    height, width : int
        ERP size (H, W). Any positive sizes are accepted (W == 2H is the usual ERP shape but is not
        required here).

    Returns
    -------
    np.ndarray
        (H, W, 3) float64 unit vectors in the world frame (x right, y down, z forward); the image
        centre looks along +z and row 0 looks up (-y).
    """
    lat = erp_latitudes(height)
    lon = erp_longitudes(width)
    return lonlat_to_directions(lon[None, :], lat[:, None])


def directions_to_lonlat(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Longitude and latitude of directions (inverse of :func:`lonlat_to_directions`).

    Parameters
    ----------
    d : array_like
        (..., 3) float directions; need not be unit length (must be non-zero).

    Returns
    -------
    lon, lat : np.ndarray
        (...) float64 radians; lon in (-π, π] (``atan2(x, z)``), lat in [-π/2, π/2]
        (``atan2(-y, hypot(x, z))``).
    """
    d = np.asarray(d, dtype=np.float64)
    if d.ndim < 1 or d.shape[-1] != 3:
        raise InputError(f"directions must have shape (..., 3), got {d.shape}")
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    lon = np.arctan2(x, z)
    lat = np.arctan2(-y, np.hypot(x, z))
    return lon, lat


def lonlat_to_erp_pixel(
    lon: np.ndarray, lat: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous ERP pixel coordinates of (longitude, latitude).

    Parameters
    ----------
    lon, lat : array_like
        Broadcastable float arrays, radians.
    height, width : int
        ERP size (H, W).

    Returns
    -------
    col, row : np.ndarray
        float64, ``col = (lon + π) W / (2π) - 0.5`` and ``row = (π/2 - lat) H / π - 0.5``, so
        integer values are pixel centres (no wrapping is applied to col).
    """
    h = _check_size("height", height)
    w = _check_size("width", width)
    lon = np.asarray(lon, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    col = (lon + np.pi) * w / (2 * np.pi) - 0.5
    row = (np.pi / 2 - lat) * h / np.pi - 0.5
    return col, row


@overload
def camera_pixel_directions(
    rotation: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    *,
    return_ray_norm: Literal[False] = ...,
) -> np.ndarray: ...


@overload
def camera_pixel_directions(
    rotation: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    *,
    return_ray_norm: Literal[True],
) -> tuple[np.ndarray, np.ndarray]: ...


def camera_pixel_directions(
    rotation: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    *,
    return_ray_norm: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """World directions of a pinhole tangent camera's pixel centres.

    Pixel (row r, column c) has its centre at (x = c, y = r); its camera-frame ray is
    ``q = ((c - cx)/fx, (r - cy)/fy, 1)`` and its world direction is ``Rᵀ q / |q|``.

    Parameters
    ----------
    rotation : array_like
        (3, 3) float rotation R, world → camera.
    fx, fy, cx, cy : float
        Intrinsics in pixels (fx, fy > 0).
    width, height : int
        Image size in pixels.
    return_ray_norm : bool
        Also return ``|q|`` (the perspective disparity 1/z equals ``|q| / distance``).

    Returns
    -------
    directions : np.ndarray
        (height, width, 3) float64 unit world directions.
    ray_norm : np.ndarray
        (height, width) float64 ``|q|`` ≥ 1, only when ``return_ray_norm`` is true.
    """
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise InputError(f"rotation must be a finite (3, 3) array, got shape {r.shape}")
    if not (np.isfinite(fx) and np.isfinite(fy) and fx > 0 and fy > 0):
        raise InputError(f"fx and fy must be finite and > 0, got fx={fx!r}, fy={fy!r}")
    if not (np.isfinite(cx) and np.isfinite(cy)):
        raise InputError(f"cx and cy must be finite, got cx={cx!r}, cy={cy!r}")
    w = _check_size("width", width)
    h = _check_size("height", height)
    qx = (np.arange(w, dtype=np.float64) - cx) / fx
    qy = (np.arange(h, dtype=np.float64) - cy) / fy
    q = np.empty((h, w, 3), dtype=np.float64)
    q[..., 0] = qx[None, :]
    q[..., 1] = qy[:, None]
    q[..., 2] = 1.0
    norm = np.linalg.norm(q, axis=-1)
    dirs = (q / norm[..., None]) @ r  # row-vector form of Rᵀ q
    if return_ray_norm:
        return dirs, norm
    return dirs  # type: ignore[no-any-return]  # numpy stubs: Any
