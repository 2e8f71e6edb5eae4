"""Measuring m360: synthetic scenes with exact depth, and the paper's metrics against the truth.

:mod:`~m360.evaluation.synthetic` ray-casts rooms and their exact depth (the demo, the simulated
network, the tests); :mod:`~m360.evaluation.metrics` scores a prediction against ground truth.
"""

from __future__ import annotations

from . import metrics, sequence, synthetic
from .metrics import depth_metrics, edge_band, fit_scale_shift, format_metrics, seam_score

__all__ = [
    "depth_metrics",
    "edge_band",
    "fit_scale_shift",
    "format_metrics",
    "metrics",
    "seam_score",
    "sequence",
    "synthetic",
]
