"""m360: high-resolution 360° monocular depth estimation (360MonoDepth, CVPR 2022).

An equirectangular panorama is projected onto tangent images (icosahedron faces), a perspective
depth network predicts disparity on each, and the per-tangent disparities are aligned and blended
back into one seamless ERP disparity map. The heavy lifting runs in a Rust core (``m360._core``).

>>> import m360
>>> layout = m360.Layout.icosahedron(erp_width=2048)
>>> tangents = m360.erp_to_tangents(erp, layout)          # (20, 346, 400[, C])
>>> disp = m360.stitch(tangents, layout, align="none", blend="mean")
>>> opts = m360.StitchOptions(energy="paper", blend="frustum")  # validated, canonical
>>> model = m360.ModelOptions(input_size=(224, 224), mean=(0, 0, 0), std=(1, 1, 1))
>>> result = m360.estimate(erp_rgb, model="midas-v21-small")  # end to end, ONNX Runtime
>>> m360.save(result, "out/pano", formats=("npy", "exr"))      # m360.load("out/pano") reads it
>>> pair = m360.stereo(result, erp_rgb, ipd=0.064)              # VR: left/right eye panoramas
>>> report = m360.batch.run(["photos/"], "out/", workers=2)     # many images, resumable
"""

from __future__ import annotations

import sys as _sys

from . import batch, estimators, evaluation, geometry, io, pipeline, stitching, video
from ._core import __version__, get_num_threads, set_num_threads
from .errors import (
    AspectRatioError,
    InputError,
    M360Error,
    ModelError,
    ReadError,
    ScaleError,
    SolverError,
)
from .estimators import ModelOptions
from .estimators import registry as models
from .evaluation import metrics as eval
from .evaluation import synthetic
from .geometry import Layout, TangentCamera, clear_plan_cache, erp_to_tangents, tangents_to_erp
from .io import SavedResult, decode, load, mesh, save, splat, viewer
from .io.mesh import Mesh, PointCloud, to_mesh, to_points
from .io.normals import normals
from .io.splat import Splats, to_splats
from .io.stereo import StereoResult, stereo
from .pipeline import masks, memory, scale
from .pipeline.estimate import EstimateResult, estimate
from .stitching import align, blend, options, upsample
from .stitching.options import StitchOptions
from .stitching.stitch import StitchResult, stitch

#: The module names of the flat layout before the stage packages (docs/architecture.md, "Package
#: layout"), and where each module lives now. They stay importable under their old names
#: (``import m360.models``, ``from m360.align import SCHEDULES``): users' scripts use them.
_FLAT_NAMES = {
    "align": align,
    "blend": blend,
    "decode": decode,
    "eval": eval,
    "masks": masks,
    "memory": memory,
    "mesh": mesh,
    "models": models,
    "options": options,
    "plan_cache": geometry.plan_cache,
    "scale": scale,
    "synthetic": synthetic,
    "upsample": upsample,
    "viewer": viewer,
}
#: Flat modules whose name is now that of a function (``m360.stitch``, ``m360.estimate``): only
#: ``from m360.stitch import ...`` reaches the module (it holds names kept for old scripts).
_FLAT_MODULES_OF_FUNCTIONS = {"estimate": pipeline.estimate, "stitch": stitching.stitch}
for _name, _module in {**_FLAT_NAMES, **_FLAT_MODULES_OF_FUNCTIONS}.items():
    _sys.modules.setdefault(f"{__name__}.{_name}", _module)
del _name, _module

__all__ = [
    "AspectRatioError",
    "EstimateResult",
    "InputError",
    "Layout",
    "M360Error",
    "Mesh",
    "ModelError",
    "ModelOptions",
    "PointCloud",
    "ReadError",
    "SavedResult",
    "ScaleError",
    "SolverError",
    "Splats",
    "StereoResult",
    "StitchOptions",
    "StitchResult",
    "TangentCamera",
    "__version__",
    "align",
    "batch",
    "blend",
    "clear_plan_cache",
    "decode",
    "erp_to_tangents",
    "estimate",
    "estimators",
    "eval",
    "evaluation",
    "geometry",
    "get_num_threads",
    "io",
    "load",
    "masks",
    "memory",
    "mesh",
    "models",
    "normals",
    "options",
    "pipeline",
    "save",
    "scale",
    "set_num_threads",
    "splat",
    "stereo",
    "stitch",
    "stitching",
    "synthetic",
    "tangents_to_erp",
    "to_mesh",
    "to_points",
    "to_splats",
    "upsample",
    "video",
]
