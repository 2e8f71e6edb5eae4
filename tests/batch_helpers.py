"""Estimators for batch tests; importable by spawned worker processes (tests/ is on sys.path)."""

from __future__ import annotations

import os

import numpy as np


class CrashOnBlack:
    """Returns mean RGB + 1 as affine disparity, but kills its process on an all-black image
    (what a segfault or the OOM killer does to a worker)."""

    output_kind = "affine_disparity"
    name = "crash-on-black"

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        if tangents.max() == 0:
            os._exit(3)
        return tangents.astype(np.float32).mean(axis=-1) / 255.0 + 1.0


class Gated:
    """Affine disparity of the mean RGB, one image at a time under the test's control.

    With a ``folder`` holding two FIFOs, each ``predict`` first writes one byte to
    ``folder/started`` and then takes one byte from ``folder/tokens``, blocking until the test
    writes one. When the test has read N + k start bytes after writing N tokens to a run with k
    workers, every worker is blocked in ``predict`` and exactly N images are complete: a worker
    starts an image only after finishing its previous one. ``folder=None``: no gate. The name
    does not depend on the folder, so a gated run and an ungated rerun share their fingerprint.
    """

    output_kind = "affine_disparity"
    name = "gated"

    def __init__(self, folder: str | None) -> None:
        self.folder = folder

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        if self.folder is not None:
            started = os.open(os.path.join(self.folder, "started"), os.O_WRONLY)
            try:
                os.write(started, b"s")
            finally:
                os.close(started)
            tokens = os.open(os.path.join(self.folder, "tokens"), os.O_RDONLY)
            try:
                os.read(tokens, 1)  # Ctrl-C here raises KeyboardInterrupt
            finally:
                os.close(tokens)
        return tangents.astype(np.float32).mean(axis=-1) / 255.0 + 1.0


def make_gate(folder: str) -> tuple[int, int]:
    """Create the FIFOs of :class:`Gated` in ``folder``; returns (started, tokens) descriptors.

    Both are opened read-write, so neither the test nor a worker ever blocks in ``open`` and
    the pipes keep their bytes while no worker has them open.
    """
    os.mkfifo(os.path.join(folder, "started"))
    os.mkfifo(os.path.join(folder, "tokens"))
    return (
        os.open(os.path.join(folder, "started"), os.O_RDWR),
        os.open(os.path.join(folder, "tokens"), os.O_RDWR),
    )
