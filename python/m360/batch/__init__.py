"""Many panoramas, nothing lost: :func:`run`, the engine behind ``m360 run``.

:mod:`~m360.batch.runner` collects the inputs, hands images to an engine (local processes, or
Ray: :mod:`~m360.batch._ray_engine`) and reports; :mod:`~m360.batch.image` is one image's work,
shared by both engines (claim, read, estimate, write, resume check).

The batch's guarantees are also the building blocks of other runs over many items
(``m360.video.run``): the per-output OS lock (:func:`claim`), the failed outcomes
(:func:`failure_outcome`, :func:`error_outcome`) and their ``failures.jsonl`` line
(:func:`append_failure`), the output folder's check (:func:`make_output_folder`), the Ray
resources of the engine options (:func:`ray_resources`), Ctrl-C handling
(:func:`keyboard_interrupt_once`, :class:`MainThreadInterrupts`) and the silent progress bar
(:class:`NoBar`).
"""

from __future__ import annotations

from ._interrupt import MainThreadInterrupts
from .image import ImageOutcome, Job, claim, error_outcome, failure_outcome, is_done
from .runner import (
    ENGINES,
    FAILURES_FILE,
    MANIFEST_SUFFIXES,
    STAGES,
    BatchReport,
    NoBar,
    append_failure,
    collect,
    fingerprint,
    keyboard_interrupt_once,
    make_output_folder,
    ray_resources,
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
    "MainThreadInterrupts",
    "NoBar",
    "append_failure",
    "claim",
    "collect",
    "error_outcome",
    "failure_outcome",
    "fingerprint",
    "is_done",
    "keyboard_interrupt_once",
    "make_output_folder",
    "ray_resources",
    "run",
]
