"""The end-to-end job, image in, depth out: :func:`m360.estimate` and what it takes.

:mod:`~m360.pipeline.estimate` projects, runs the estimator and stitches;
:mod:`~m360.pipeline.masks` says which pixels take part, :mod:`~m360.pipeline.scale` gives the
result a metric scale, :mod:`~m360.pipeline.memory` refuses a job the machine cannot hold.
"""

from __future__ import annotations

from . import masks, memory, scale
from .estimate import EstimateResult

__all__ = ["EstimateResult", "masks", "memory", "scale"]
