"""How much memory :func:`m360.estimate` needs, estimated before anything large is allocated.

A request that cannot fit fails early with an :class:`~m360.errors.InputError` that states the
estimate and what is available, instead of ending in an out-of-memory kill. The estimate is a
linear model of the peak resident memory per working-resolution ERP pixel (projection, plan
maps, alignment, blend) plus, with a working width below the input's, per full-resolution pixel
(the upsampled disparity, depth and confidence, the grey guide). The plan's ERP taps grow with
the number of tangents that see a pixel (3.8 on average with the paper's padding 0.3, 5.2 with
the default 0.7), so the per-pixel part is a fixed part plus a part per tap. The coefficients
were fitted (least squares of the relative error) to the peaks measured by
``benches/bench_bigpano.py`` at 2K, 4K and 8K, paddings 0.3 and 0.7, the consensus, frustum and
Poisson blends: from 1 % below to 7 % above each (docs/architecture.md, memory).

With the outputs (``formats``, ``preview``, ``confidence``) or the input's header given,
:func:`estimate_memory` estimates a whole image's run instead: decoding (the file's bytes, the
decoder's array and, for 16-bit and float inputs, their wider intermediate), then the estimate
with the decoded panorama held, and writing each requested output on top of what the estimate
reached (its result and plan stay, and the allocator keeps what it freed); the formats are
written one after another, so the largest counts. The per-pixel costs of
decoding and writing were measured at 12K (benches/bench_bigpano.py ``--outputs``).

A global prior adds a part per pixel of its map and a part per working pixel, measured (peak
RSS of ``m360.estimate`` at 2K and 4K with a 512 x 1024 prior map, with and without it: +51 MB
and +118 MB); a prior model's input and output are counted on top. A panoramic model alone
(:func:`estimate_panoramic_memory`) needs its network's arrays, the upsampling's planes at the
network's size and the full-resolution outputs, counted from the arrays m360 allocates. The
networks' own activations, held by ONNX Runtime, are not counted for any model.

``M360_MEMORY_LIMIT`` (bytes, or with a K/M/G suffix) replaces the available memory the check
compares against; ``M360_MEMORY_LIMIT=0`` turns the check off.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from ..geometry.layout import Layout
    from ..io.decode import ImageHeader

__all__ = [
    "available_memory",
    "check_memory",
    "check_working_width",
    "estimate_memory",
    "estimate_panoramic_memory",
    "taps_per_pixel",
    "working_width_for",
]

#: Widest input processed at its own resolution by default; wider inputs run at
#: :data:`DEFAULT_WORKING_WIDTH` and are upsampled along the photo's edges.
NATIVE_WIDTH_LIMIT = 8192
#: Working width of inputs wider than :data:`NATIVE_WIDTH_LIMIT`.
DEFAULT_WORKING_WIDTH = 4096

#: Peak bytes per working-resolution ERP pixel besides the plan's taps, per blend (the Poisson
#: blend's system and multigrid hierarchy dominate; the row blends need the rest of the plan
#: and the tangent stacks only).
_BYTES_PER_PIXEL = {"poisson": 152.0, "other": 78.0}
#: Peak bytes per ERP tap (one tangent seeing one working-resolution pixel): the tap itself;
#: fitted 8.4 over 2K-8K and paddings 0.3 and 0.7.
_BYTES_PER_TAP = 8.4
#: Taps per pixel the coefficients above were measured at (the paper's layout).
_REFERENCE_TAPS = 3.76
#: Peak bytes per full-resolution pixel when upsampling (outputs, grey guide).
_BYTES_PER_FULL_PIXEL = 14.0
#: Fixed part (interpreter-independent buffers, thread stacks, small maps): fitted 30 MiB.
_FIXED_BYTES = 32 * 2**20

#: The decoded panorama, (H, W, 3) uint8.
_RGB_BYTES_PER_PIXEL = 3.0
#: Peak bytes per full-resolution pixel of writing each output (beyond the result and the
#: panorama held), measured at 12K: npy streams into the file; pfm's and exr's encoders hold
#: the encoded map (and a copy); png16 holds its uint16 codes and the encoded PNG; the preview
#: the finite values (for the percentiles), then the colour image and its PNG.
#: ``normals`` holds its three float32 planes and 8-bit codes (13 bytes) and the encoders'
#: buffers (measured 19.7 at 4K, 17.4 at 8K: benches/bench_3d.py normals_files).
_OUTPUT_BYTES_PER_PIXEL = {
    "npy": 1.0,
    "pfm": 8.5,
    "exr": 8.5,
    "png16": 4.2,
    "preview": 5.0,
    "normals": 20.0,
}
#: The stereo pair (:func:`m360.stereo`, written once for both stereo formats): the two eyes
#: and their hole masks (8), the eye positions of the warp (8, one eye at a time), the scaled
#: depth of a relative result (4), then the top-bottom image, its BGR copy and the encoded file
#: with its XMP (about 6 + 6 + 4). Measured 18.6 at 8K beyond the input (benches/bench_3d.py,
#: stereo_save: 624 MB); the margin covers the allocator.
_STEREO_BYTES_PER_PIXEL = 24.0
#: The streamed 3D writers: a band's temporaries (about a million vertices; the splats' a
#: quarter million pixels, measured 114 MB at 4K and 141 MB at 8K) ...
_GEOMETRY_BAND_BYTES = {"ply": 64 * 2**20, "glb": 96 * 2**20, "splat": 160 * 2**20}
#: ... and, for the mesh, per strided grid vertex: the per-quad flags, the used mask and the
#: renumbering (int32).
_MESH_BYTES_PER_VERTEX = 9.0

#: Bytes per prior-map pixel: measured about 55 for a map (its checked and fitted copies, the
#: stitch's conversion and sampling), plus a model's float32 input and output (16).
_PRIOR_BYTES_PER_PIXEL = 64.0
#: Bytes per working-resolution ERP pixel a prior adds (the confidence combined with the
#: prior's disagreement): measured 10.7 between 2K and 4K with a 512 x 1024 prior.
_PRIOR_BYTES_PER_WORKING_PIXEL = 11.0
#: Bytes per network pixel of a panoramic model: input (12), output and disparity (8), the
#: guided upsampling's planes of that resolution (7 float32 planes and their sums in f64: 84).
_PANORAMIC_BYTES_PER_NETWORK_PIXEL = 104.0

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def working_width_for(working_width: int | str | None, width: int) -> int:
    """Return the ERP width the pipeline runs at for an input ``width`` pixels wide.

    ``None``: the input's width up to :data:`NATIVE_WIDTH_LIMIT`, above it
    :data:`DEFAULT_WORKING_WIDTH`; ``"native"``: the input's width; an even integer: that width
    (at most the input's; the input's own width if larger).
    """
    check_working_width(working_width)
    if working_width is None:
        return width if width <= NATIVE_WIDTH_LIMIT else DEFAULT_WORKING_WIDTH
    if working_width == "native":
        return width
    return min(int(working_width), width)


def check_working_width(working_width: int | str | None) -> None:
    """Check a ``working_width`` whatever the input's width.

    Raises :class:`m360.InputError` unless it is None, "native" or an even integer >= 64.
    """
    if working_width is None or working_width == "native":
        return
    if isinstance(working_width, bool) or not isinstance(working_width, int):
        raise InputError(
            f"working_width must be None, 'native' or an even integer, got {working_width!r}"
        )
    if working_width < 64 or working_width % 2:
        raise InputError(f"working_width must be an even integer >= 64, got {working_width}")


def estimate_memory(
    width: int,
    working_width: int | None = None,
    blend: str = "poisson",
    layout: Layout | None = None,
    *,
    formats: Sequence[str] | None = None,
    preview: bool = False,
    confidence: bool = False,
    max_vertices: int | str | None = "default",
    header: ImageHeader | None = None,
    file_bytes: int = 0,
    prior_pixels: int = 0,
) -> int:
    """Peak bytes :func:`m360.estimate` (or, with outputs or a header, a whole run) adds.

    Parameters
    ----------
    width : int
        Input ERP width (height width / 2).
    working_width : int, optional
        Width the pipeline runs at (default: ``width``).
    blend : str
        The blend method (``"poisson"`` needs the most).
    layout : Layout, optional
        The tangent layout (default: :func:`m360.geometry.default_layout`); the more tangents
        see each pixel, the larger the plan.
    formats : sequence of str, optional
        The formats written (as for :func:`m360.save`): estimate a whole run, writing included.
    preview, confidence : bool
        Whether the preview and the confidence maps are written too.
    max_vertices : int or None
        The 3D files' vertex budget (:func:`m360.save`; default its default).
    header : ImageHeader, optional
        The input file's header (:func:`m360.io.decode.image_header`): estimate a whole run,
        decoding included (its width is the decoded width; ``width`` is the panorama's, after
        any aspect fix).
    file_bytes : int
        The input file's size (held while it is decoded).
    prior_pixels : int
        Pixels of the global prior's map (a prior model's: its network input); 0: no prior.

    Returns
    -------
    int
        Bytes beyond what the process holds before the call: for :func:`m360.estimate` alone
        its input image is held before it; for a whole run nothing of the image is.
    """
    work = width if working_width is None else working_width
    if layout is None:  # taps per pixel hardly depend on the width: counted at 2048
        from ..geometry.layout import default_layout

        layout = default_layout(2048)
    taps = taps_per_pixel(layout)
    per_pixel = _BYTES_PER_PIXEL["poisson" if blend == "poisson" else "other"]
    per_pixel += _BYTES_PER_TAP * (taps - _REFERENCE_TAPS)
    working_pixels = work * (work // 2)
    total = _FIXED_BYTES + per_pixel * working_pixels
    if prior_pixels:
        total += _PRIOR_BYTES_PER_PIXEL * prior_pixels
        total += _PRIOR_BYTES_PER_WORKING_PIXEL * working_pixels
    if work != width:
        total += _BYTES_PER_FULL_PIXEL * width * (width // 2)
    if formats is None and header is None:
        return int(total)
    pixels = width * (width // 2)
    rgb = _RGB_BYTES_PER_PIXEL * pixels
    decoding = float(file_bytes) + (rgb if header is None else _decoding_bytes(header))
    # What the estimate reached stays resident while writing (measured at 4K and 12K: its
    # result, its plan kept for the next image, and freed memory the allocator keeps).
    writing = _writing_bytes(width, formats or (), preview, confidence, max_vertices)
    return int(max(decoding, rgb + total + writing))


def estimate_panoramic_memory(width: int, network_shape: tuple[int, int]) -> int:
    """Peak bytes :func:`m360.estimate` adds with a panoramic model (its activations apart).

    Parameters
    ----------
    width : int
        Input ERP width (height width / 2): the outputs' size.
    network_shape : (int, int)
        The network's input (height, width).

    Returns
    -------
    int
        Bytes beyond the input image.
    """
    network_pixels = int(network_shape[0]) * int(network_shape[1])
    full = width * (width // 2)
    return int(
        _FIXED_BYTES
        + _PANORAMIC_BYTES_PER_NETWORK_PIXEL * network_pixels
        + _BYTES_PER_FULL_PIXEL * full
    )


def _decoding_bytes(header: ImageHeader) -> float:
    """Peak bytes of decoding a file with ``header`` into 8-bit RGB (file bytes apart)."""
    pixels = header.width * header.height
    decoded = float(header.decoded_bytes)
    out = _RGB_BYTES_PER_PIXEL * pixels
    if header.sample_bytes == 4:
        # Float: the decoder's two arrays (EXR: the channels as read and stacked; OpenCV: its
        # own and the result), then a float32 working copy for the white point. Measured at 8K
        # (HDR, float and half EXR): within 0 to +17 %.
        return 2 * decoded + 4.0 * min(header.channels, 3) * pixels + out
    # 8 and 16 bits: OpenCV's decoders peak at twice their array (measured at 8K and 12K: JPEG,
    # 16-bit PNG); the 8-bit RGB copy comes after (16 bits, grey) or is the array itself.
    return max(2 * decoded, decoded + out)


def _writing_bytes(
    width: int,
    formats: Sequence[str],
    preview: bool,
    confidence: bool,
    max_vertices: int | str | None,
) -> float:
    """Peak bytes of :func:`m360.save` beyond the result and panorama it is given."""
    from ..io import mesh

    budget = mesh.DEFAULT_MAX_VERTICES if max_vertices == "default" else max_vertices
    height = width // 2
    pixels = width * height
    peaks = [0.0]
    for fmt in formats:
        if fmt in _OUTPUT_BYTES_PER_PIXEL:
            peaks.append(_OUTPUT_BYTES_PER_PIXEL[fmt] * pixels)
        elif fmt in ("ply", "splat"):
            peaks.append(_GEOMETRY_BAND_BYTES[fmt])
        elif fmt == "glb":
            step = mesh.stride_for(height, width, 1, budget if budget is None else int(budget), 2)
            grid = -(-height // step) * -(-width // step)
            peaks.append(_GEOMETRY_BAND_BYTES["glb"] + _MESH_BYTES_PER_VERTEX * grid)
    if any(fmt in ("stereo", "stereo-png") for fmt in formats):
        peaks.append(_STEREO_BYTES_PER_PIXEL * pixels)
    if preview:
        peaks.append(_OUTPUT_BYTES_PER_PIXEL["preview"] * pixels)
    del confidence  # written one quantity at a time: one more file, not a larger peak
    return max(peaks)


def taps_per_pixel(layout: Layout) -> float:
    """Return the mean number of tangents that see an ERP pixel of ``layout``.

    That is what its plan's ERP taps hold per pixel, counted on a 128x64 grid of ERP pixel
    centres (within 0.3 % of the plan's own count at 2K): a few milliseconds, no plan.
    """
    return _taps_per_pixel(layout)


@functools.lru_cache(maxsize=16)
def _taps_per_pixel(layout: Layout) -> float:
    from ..geometry import sphere

    directions = sphere.erp_directions(64, 128).reshape(-1, 3)
    seen = np.zeros(len(directions), np.int32)
    for cam in layout.cameras:
        u, v, ahead = cam.project(directions)
        with np.errstate(invalid="ignore"):  # behind the camera u, v are ±inf or NaN
            seen += ahead & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return float(seen.mean())


def _parse_bytes(text: str) -> int:
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]?)i?B?\s*", text, re.IGNORECASE)
    if match is None:
        raise InputError(
            f"M360_MEMORY_LIMIT={text!r} is not a size (bytes, or a number with K/M/G/T)"
        )
    return int(float(match.group(1)) * _UNITS[match.group(2).upper()])


def available_memory() -> int | None:
    """Return the bytes a new allocation may use.

    ``M360_MEMORY_LIMIT`` if set (0: no limit, None), else the kernel's ``MemAvailable``
    (Linux), else None (unknown: no check).
    """
    limit = os.environ.get("M360_MEMORY_LIMIT")
    if limit:
        value = _parse_bytes(limit)
        return value if value > 0 else None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def check_memory(needed: int, what: str, *, hint: str | None = None) -> None:
    """Raise :class:`InputError` if ``needed`` bytes exceed :func:`available_memory`.

    ``hint`` replaces the advice the message ends with (default: a smaller working width or
    a row blend).
    """
    available = available_memory()
    if available is not None and needed > available:
        advice = hint or (
            "use a smaller working_width (e.g. working_width=4096, upsampled along the "
            "photo's edges) or a row blend (blend='frustum')"
        )
        raise InputError(
            f"{what} needs about {needed / 2**30:.1f} GiB of memory but only "
            f"{available / 2**30:.1f} GiB is available; {advice}"
        )
