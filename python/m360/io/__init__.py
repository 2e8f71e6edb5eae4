"""Files in and out: panoramas decoded, results saved and loaded, point clouds and meshes.

:mod:`~m360.io.decode` reads input panoramas; :mod:`~m360.io.files` writes one file atomically
in each array format; :mod:`~m360.io.writing` saves a whole result (:func:`save`, sidecar last)
and :mod:`~m360.io.reading` loads it back (:func:`load`); :mod:`~m360.io.mesh` makes point
clouds and meshes and their PLY/GLB files, :mod:`~m360.io.normals` surface normals,
:mod:`~m360.io.splat` 3D Gaussian splats and :mod:`~m360.io.stereo` the stereo (ODS) pair for
VR; :mod:`~m360.io.viewer` shows them in a browser.
"""

from __future__ import annotations

from . import decode, files, mesh, normals, reading, splat, stereo, writing
from .decode import (
    IMAGE_SUFFIXES,
    decode_image,
    fix_aspect_ratio,
    load_image,
    read_image,
    read_input_bytes,
)
from .files import (
    ERP_CONVENTION,
    FORMAT_SUFFIXES,
    GEOMETRY_FILES,
    GEOMETRY_FORMATS,
    KNOWN_FORMATS,
    NORMALS_FILES,
    NORMALS_FORMATS,
    QUANTITIES,
    SAVE_FORMATS,
    STEREO_FILES,
    STEREO_FORMATS,
    atomic_path,
    check_formats,
    colorize,
    output_stem,
    read_array,
    remove_stale_temporaries,
    save_json,
    save_npy,
    save_png,
    write_array,
)
from .reading import SavedResult, listed_files, load, read_map, read_sidecar
from .writing import save

__all__ = [
    "ERP_CONVENTION",
    "FORMAT_SUFFIXES",
    "GEOMETRY_FILES",
    "GEOMETRY_FORMATS",
    "IMAGE_SUFFIXES",
    "KNOWN_FORMATS",
    "NORMALS_FILES",
    "NORMALS_FORMATS",
    "QUANTITIES",
    "SAVE_FORMATS",
    "STEREO_FILES",
    "STEREO_FORMATS",
    "SavedResult",
    "atomic_path",
    "check_formats",
    "colorize",
    "decode",
    "decode_image",
    "files",
    "fix_aspect_ratio",
    "listed_files",
    "load",
    "load_image",
    "mesh",
    "normals",
    "output_stem",
    "read_array",
    "read_image",
    "read_input_bytes",
    "read_map",
    "read_sidecar",
    "reading",
    "remove_stale_temporaries",
    "save",
    "save_json",
    "save_npy",
    "save_png",
    "splat",
    "stereo",
    "write_array",
    "writing",
]
