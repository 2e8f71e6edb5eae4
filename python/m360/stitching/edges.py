"""Sharp depth edges along the photo's: :func:`refine_edges`.

A depth network that sees each tangent below the tangent's resolution returns its depth edges
smeared over a few pixels (a 4K ERP gives 800-pixel tangents to a network of 384 or 518
pixels). The photo at full resolution still has them sharp. :func:`refine_edges` is a
confidence-weighted mode filter (after the weighted mode filter of Min, Lu & Do, TIP 2012):
near disparity jumps only, each pixel takes the most weighted log disparity of its window,
counting samples that look like it in the photo (RGB distance) and that are not themselves
inside a smeared transition (small disparity gradient), so each side of an edge takes the value
of its own flat side and the edge falls where the photo puts it. Smooth surfaces (a window
whose disparity spans less than ``jump``) are left exactly as they are, and so are NaN pixels.

It runs in the core (``_core.refine_edges``, ``rust/m360-core/src/edges.rs``), in parallel
over bands of rows; windows wrap in longitude (docs/conventions.md). What it gains and costs
on simulated rooms is in docs/method.md ("Sharp edges along the photo").
"""

from __future__ import annotations

import numpy as np

from .. import _core
from .._validate import as_array
from ..errors import InputError
from .upsample import rgb_u8

__all__ = ["AUTO_PHOTO_SHRINK", "EDGE_MODES", "default_edge_radius", "edges_for", "refine_edges"]

#: ``edges=`` choices of :func:`m360.estimate`: ``auto`` (default) is ``photo`` for a tangent
#: network that sees its tile :data:`AUTO_PHOTO_SHRINK` or more times smaller, else
#: ``network``; ``network`` keeps the edges as the network gave them; ``photo`` makes them sharp
#: along the photo's by :func:`refine_edges`.
EDGE_MODES = ("auto", "network", "photo")

#: The tile's width over the network input's from which ``edges="auto"`` refines along the
#: photo. The shared real networks, fed right, on the twelve 1K photos against the same network
#: at 512 px (benches/bench_edges_real.py, --jump 0.01): a network smear of 2 px made the band
#: around its edges 1.03-1.11x worse, 3 px 1.00-1.01x (5 of 12 photos nearer), 4 px 0.99x (6
#: and 8 of 12), 6 px 0.98-0.99x (10 and 12 of 12). On the synthetic rooms the same refinement
#: took the band at 4K from 0.189 to 0.064 (docs/method.md, "Sharp edges along the photo").
AUTO_PHOTO_SHRINK = 4.0


def edges_for(mode: str, tile_width: int | None, network_width: int | None) -> str:
    """Resolve an ``edges`` mode to ``"network"`` or ``"photo"``.

    ``auto`` is ``photo`` when a tangent network's input (``network_width``) is at most
    1/:data:`AUTO_PHOTO_SHRINK` of its tile (``tile_width``): its edges are smeared over four
    tile pixels or more. Unknown sizes (a simulated or panoramic network) give ``network``.
    """
    if mode != "auto":
        return mode
    if not tile_width or not network_width:
        return "network"
    return "photo" if tile_width >= AUTO_PHOTO_SHRINK * network_width else "network"


#: The default window radius in pixels per pixel of ERP width: 10 px at 4096 (0.9°), a little
#: more than twice the smear of a network seeing each tangent at the 2K layout's size.
RADIUS_PER_WIDTH = 10 / 4096


def default_edge_radius(width: int) -> int:
    """Return the default window radius of :func:`refine_edges` for an ERP ``width`` wide."""
    return max(2, round(width * RADIUS_PER_WIDTH))


def _photo_u8(photo: np.ndarray) -> np.ndarray:
    if photo.dtype != np.uint8 and photo.dtype.kind != "f":
        raise InputError(f"photo must be uint8 RGB or float RGB in [0, 1], got {photo.dtype}")
    if photo.dtype.kind == "f" and not np.isfinite(photo).all():
        raise InputError("photo has NaN or infinite values")
    return rgb_u8(photo)


def refine_edges(
    disparity: np.ndarray,
    photo: np.ndarray,
    *,
    radius: int | None = None,
    colour_sigma: float = 15.0,
    transition: float = 0.05,
    jump: float = 0.05,
) -> np.ndarray:
    """Make the depth edges of an ERP disparity map sharp along the edges of its photo.

    Parameters
    ----------
    disparity : (H, W) float array, W == 2H
        Disparity (or any positive map whose jumps are depth edges); NaN or ≤ 0 = invalid,
        kept as it is and never used.
    photo : (H, W, 3) uint8 RGB, or float RGB in [0, 1]
        The photo at the same resolution.
    radius : int, optional
        Window radius in pixels (1-256); it should exceed the edges' smear by a few pixels.
        Default :func:`default_edge_radius`: 10 at a width of 4096, in proportion elsewhere.
        Above 3 the window is sampled every ``ceil(radius / 3)`` pixels (at most 7 × 7).
    colour_sigma : float
        How alike two pixels must look to vote for each other: the std of the colour weight in
        0-255 RGB levels (cut at three stds).
    transition : float
        A sample whose log disparity changes by about this much over ``radius`` counts as
        inside a smeared edge and weighs little (weight exp(−(|∇log d|·radius/transition)²)).
    jump : float
        Windows whose log disparity spans at most this are left as they are.

    Returns
    -------
    (H, W) float32
        The refined disparity.
    """
    disp = as_array(disparity, "disparity")
    img = as_array(photo, "photo")
    if disp.ndim != 2 or disp.shape[1] != 2 * disp.shape[0] or disp.shape[0] < 1:
        raise InputError(f"disparity must be an ERP map (H, 2H), got shape {disp.shape}")
    if disp.dtype.kind != "f":
        raise InputError(f"disparity must be a float array, got dtype {disp.dtype}")
    if img.shape != (*disp.shape, 3):
        raise InputError(
            f"photo must be RGB of the disparity's size {(*disp.shape, 3)}, got {img.shape}"
        )
    if radius is None:
        radius = default_edge_radius(disp.shape[1])
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)):
        raise InputError(f"radius must be an integer number of pixels, got {radius!r}")
    if radius < 1:
        raise InputError(f"radius must be at least 1 pixel, got {radius}")
    p = np.ascontiguousarray(disp, np.float32)
    refined: np.ndarray = _core.refine_edges(
        p, _photo_u8(img), int(radius), float(colour_sigma), float(transition), float(jump)
    )
    return refined
