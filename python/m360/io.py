"""Writing results without ever leaving a half-written file behind."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError

__all__ = ["atomic_path", "colorize", "save_npy", "save_png"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary file lives in the target folder so the final rename is atomic (same file
    system); on any exception it is removed and ``path`` is left as it was.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates 0600; give the result the permissions a plain open() would.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npy(path: str | os.PathLike[str], array: np.ndarray) -> Path:
    """Write ``array`` as .npy atomically; returns the path."""
    target = Path(path)
    with atomic_path(target) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
    return target


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Write a uint8/uint16 image (H,W) or (H,W,3) BGR as PNG atomically; returns the path."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise InputError(
            f"cannot encode an image of shape {image.shape} and dtype {image.dtype} as PNG"
        )
    target = Path(path)
    with atomic_path(target) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return target


def colorize(disparity: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """A colour preview (H, W, 3) uint8 BGR of a disparity map: near warm, far cool, NaN black.

    Values are scaled between the given percentiles of the finite values (robust to outliers).
    """
    values = np.asarray(disparity, dtype=np.float32)
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros((*values.shape, 3), np.uint8)
    lo, hi = np.percentile(values[finite], percentiles)
    scaled = np.clip((values - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0)
    grey = np.where(finite, scaled * 255.0 + 0.5, 0.0).astype(np.uint8)
    preview = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
    preview[~finite] = 0
    return preview
