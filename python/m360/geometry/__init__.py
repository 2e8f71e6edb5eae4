"""Where pixels go: tangent layouts, their sampling plans (in memory and on disk), resampling.

:mod:`~m360.geometry.layout` builds the tangent cameras (the icosahedron layout of the paper, or
any user-given cameras), compiles each layout's plan once and resamples between the ERP image and
its tangents; :mod:`~m360.geometry.plan_cache` keeps built plans under ``$M360_HOME/plans``.
"""

from __future__ import annotations

from . import plan_cache
from .layout import (
    DEFAULT_PADDING,
    PAPER_PADDING,
    Layout,
    TangentCamera,
    check_tangents,
    clear_plan_cache,
    default_layout,
    erp_to_tangents,
    pixel_degrees,
    plan_for,
    tangents_to_erp,
)

__all__ = [
    "DEFAULT_PADDING",
    "PAPER_PADDING",
    "Layout",
    "TangentCamera",
    "check_tangents",
    "clear_plan_cache",
    "default_layout",
    "erp_to_tangents",
    "pixel_degrees",
    "plan_cache",
    "plan_for",
    "tangents_to_erp",
]
