"""Many panoramas, nothing lost: :func:`run`, the engine behind ``m360 run``.

:mod:`~m360.batch.runner` collects the inputs, hands images to an engine (local processes, or
Ray: :mod:`~m360.batch._ray_engine`) and reports; :mod:`~m360.batch.image` is one image's work,
shared by both engines (claim, read, estimate, write, resume check).
"""

from __future__ import annotations

from .image import ImageOutcome, Job, is_done
from .runner import (
    ENGINES,
    FAILURES_FILE,
    MANIFEST_SUFFIXES,
    STAGES,
    BatchReport,
    collect,
    fingerprint,
    run,
)

__all__ = [
    "ENGINES",
    "FAILURES_FILE",
    "MANIFEST_SUFFIXES",
    "STAGES",
    "BatchReport",
    "ImageOutcome",
    "Job",
    "collect",
    "fingerprint",
    "is_done",
    "run",
]
