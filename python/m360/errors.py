"""Exception hierarchy of m360.

Every error m360 raises on purpose is a subclass of :class:`M360Error`, so a batch script can catch
``m360.M360Error`` and go on with the next image. The compiled core raises the same classes (the
bindings import them from here), so there is one hierarchy whichever layer finds the problem.
"""

from __future__ import annotations

__all__ = [
    "AspectRatioError",
    "InputError",
    "M360Error",
    "ModelError",
    "ReadError",
    "ScaleError",
    "SolverError",
]


class M360Error(Exception):
    """Base class of every error raised by m360."""


class InputError(M360Error, ValueError):
    """An argument is unusable: wrong shape, dtype, size, NaN where not allowed, bad option."""


class ReadError(InputError):
    """A file cannot be read: missing, empty, truncated, corrupt, or of an unsupported kind."""


class AspectRatioError(InputError):
    """An equirectangular image is not W == 2H (``m360 run --fix-aspect`` resizes it)."""


class ModelError(M360Error):
    """A depth model is missing, corrupt, fails its hash check or produces unusable output."""


class SolverError(M360Error):
    """A numerical solve failed (non-finite energy, singular system) on otherwise valid input."""


class ScaleError(M360Error):
    """A metric scale cannot be found (no floor visible, too few usable points, a bad fit)."""
