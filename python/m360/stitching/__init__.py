"""Per-tangent disparity in, one seamless ERP disparity out: options, alignment, blending.

:mod:`~m360.stitching.options` holds every stitching option (:class:`StitchOptions`);
:mod:`~m360.stitching.align` and :mod:`~m360.stitching.blend` say what each option means;
:mod:`~m360.stitching.stitch` runs them (:func:`m360.stitch`); :mod:`~m360.stitching.prior`
checks a global prior map; :mod:`~m360.stitching.upsample` brings a working-resolution result to
the photo's, and :mod:`~m360.stitching.edges` makes smeared depth edges sharp along its edges;
:mod:`~m360.stitching.depth` turns disparity into depth.
"""

from __future__ import annotations

from . import align, blend, depth, edges, options, prior, upsample
from .depth import depth_of
from .edges import refine_edges
from .options import StitchOptions
from .stitch import StitchResult
from .upsample import guided_upsample

__all__ = [
    "StitchOptions",
    "StitchResult",
    "align",
    "blend",
    "depth",
    "depth_of",
    "edges",
    "guided_upsample",
    "options",
    "prior",
    "refine_edges",
    "upsample",
]
