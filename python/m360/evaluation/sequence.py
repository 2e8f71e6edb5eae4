"""Synthetic 360° video: a camera moving through a ray-cast room, with exact depth and motion.

:func:`walk` takes a room of :func:`m360.synthetic.room` and moves the camera along a
straight path through it (the camera stays at the origin of each frame's scene: the room,
its objects and its lights are translated the other way). Every frame has its exact radial
depth (:meth:`Sequence.render`) and the true camera motion (:attr:`Sequence.positions`); the
simulated network's output of a frame (:meth:`Sequence.tangents`) draws its per-tangent
affine ambiguity and content errors anew for every frame, as a real per-tile network's
errors change from frame to frame. :func:`flicker` measures how much a prediction flickers
against that truth (the video benchmark's first row).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence as SequenceOf
from dataclasses import dataclass
from typing import Any

import numpy as np

from m360._validate import as_array, integer, number
from m360.errors import InputError
from m360.geometry.layout import Layout
from m360.geometry.sphere import directions_to_lonlat, erp_directions, lonlat_to_erp_pixel

from . import synthetic

__all__ = ["Sequence", "SequenceEstimator", "flicker", "walk"]

#: The smallest distance (metres) kept between the moving camera and any wall or object.
CLEARANCE = 0.3


def _world_fixed(material: synthetic.Material, offset: np.ndarray) -> synthetic.Material:
    """Give the material with its texture fixed to the world when the scene moves by ``offset``.

    The renderer evaluates textures at the camera-relative hit point; a wave texture stays put
    when its phase takes the offset up. A checker cannot (its cells are not a phase), so it
    becomes the noise texture of the same waves: the room's look changes, not its geometry.
    """
    texture = "noise" if material.texture == "checker" else material.texture
    shift = -2 * np.pi * (material.waves @ offset) / material.period
    return dataclasses.replace(material, texture=texture, phase=material.phase + shift)


def _translated(scene: synthetic.Scene, position: np.ndarray) -> synthetic.Scene:
    """``scene`` seen from ``position`` (world): everything moved by ``-position``."""
    off = -np.asarray(position, dtype=np.float64)
    return synthetic.Scene(
        room_min=scene.room_min + off,
        room_max=scene.room_max + off,
        boxes=tuple(
            dataclasses.replace(b, center=b.center + off, material=_world_fixed(b.material, off))
            for b in scene.boxes
        ),
        spheres=tuple(
            dataclasses.replace(s, center=s.center + off, material=_world_fixed(s.material, off))
            for s in scene.spheres
        ),
        lights=tuple(dataclasses.replace(li, position=li.position + off) for li in scene.lights),
        room_materials=tuple(_world_fixed(m, off) for m in scene.room_materials),
        ambient=scene.ambient,
        shadows=scene.shadows,
    )


def _frame_seed(seed: int, index: int, what: str) -> int:
    """Give a seed per (sequence seed, frame, purpose): independent draws for every frame."""
    digest = hashlib.sha256(f"{seed}/{index}/{what}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


@dataclass(frozen=True)
class Sequence:
    """A camera path through a room: the frames' scenes, exact depth and the simulated network.

    Attributes
    ----------
    scene : m360.synthetic.Scene
        The room in world coordinates (the camera's start is the world origin), with its
        textures fixed to the world.
    positions : (T, 3) float64
        The camera's position at each frame (metres, world frame = m360 frame: x right, y down,
        z forward); ``positions[t] - positions[t - 1]`` is the true motion.
    fps : float
        Frames per second (times are ``index / fps``).
    erp_width : int
        Width of the rendered frames (height ``erp_width // 2``).
    seed : int
        Seed of the room, the path and every frame's network errors.
    """

    scene: synthetic.Scene
    positions: np.ndarray
    fps: float
    erp_width: int
    seed: int

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def _index(self, index: int) -> int:
        return integer(index, "frame index", low=0, high=len(self) - 1)

    def scene_at(self, index: int) -> synthetic.Scene:
        """Give the scene of frame ``index``, camera at the origin (for the ray casters)."""
        return _translated(self.scene, self.positions[self._index(index)])

    def render(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``: (H, W, 3) uint8 RGB and its exact (H, W) float32 radial depth."""
        return synthetic.render(self.scene_at(index), self.erp_width)

    def tangents(self, index: int, layout: Layout, *, errors: bool = True) -> np.ndarray:
        """Give the simulated network's output on frame ``index``: (N, h, w) float32 disparity.

        The exact perspective disparity of the layout's tangents with, when ``errors``,
        content errors (:func:`m360.synthetic.content_errors`, regions too near or too far)
        and a per-tangent affine ambiguity (:func:`m360.synthetic.distort`), both drawn anew
        for every frame from the sequence's seed and the frame index.
        """
        if not isinstance(layout, Layout):
            raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
        i = self._index(index)
        exact = synthetic.tangent_perspective_disparity(self.scene_at(i), layout.cameras)
        if not errors:
            return exact
        wrong = synthetic.content_errors(exact, _frame_seed(self.seed, i, "content"))
        return synthetic.distort(np.asarray(wrong), _frame_seed(self.seed, i, "affine"))


def walk(
    seed: int = 0,
    frames: int = 60,
    *,
    erp_width: int = 512,
    fps: float = 30.0,
    speed: float = 0.6,
) -> Sequence:
    """Make a synthetic 360° video: a straight camera path through ``m360.synthetic.room(seed)``.

    The path starts at the room's camera and runs at ``speed`` metres per second in a
    horizontal direction (drawn from the seed) in which every frame keeps at least
    :data:`CLEARANCE` from walls and objects; where no direction has room for the whole path
    at that speed, the speed is halved until one does.

    Parameters
    ----------
    seed : int
        Seed of the room, the direction and the network errors.
    frames : int
        Number of frames T (2 to 100,000).
    erp_width : int
        Width of the rendered frames (even, ≥ 8).
    fps : float
        Frames per second (> 0).
    speed : float
        Camera speed in metres per second (≥ 0).

    Returns
    -------
    Sequence
    """
    seed = integer(seed, "seed")
    count = integer(frames, "frames", low=2, high=100_000)
    fps = number(fps, "fps", low=0.0, high=1e4)
    speed = number(speed, "speed", low=0.0, high=100.0)
    if fps <= 0:
        raise InputError(f"fps must be > 0, got {fps}")
    width = integer(erp_width, "erp_width", low=8)
    if width % 2:
        raise InputError(f"erp_width must be even, got {width}")
    scene = synthetic.room(seed)
    rng = np.random.default_rng(_frame_seed(seed, -1, "path"))
    steps = np.arange(count, dtype=np.float64)[:, None] / fps
    angles = rng.uniform(0, 2 * np.pi) + np.linspace(0, 2 * np.pi, 12, endpoint=False)
    positions = np.zeros((count, 3))
    while speed > 1e-3:
        for angle in angles:
            direction = np.array([np.cos(angle), 0.0, np.sin(angle)])
            path = steps * speed * direction
            if all(_translated(scene, p).camera_clearance() >= CLEARANCE for p in path):
                positions = path
                break
        else:
            speed /= 2
            continue
        break
    world = _translated(scene, np.zeros(3))  # world-fixed textures (checkers become noise)
    return Sequence(world, positions, float(fps), width, seed)


class SequenceEstimator:
    """The simulated network of a :class:`Sequence`: each frame's :meth:`Sequence.tangents`.

    NOT a network. ``predict`` recognises which frame its RGB tangents come from (the nearest
    frame by a small thumbnail of every tangent, so decoded video frames with compression
    noise are recognised too) and returns that frame's simulated output. Made for one layout
    (``layout``); the outputs are computed on first use and kept. ``frames``: the frame
    indices it knows (default all); ``images``: their RGB frames when already rendered.
    """

    output_kind = "affine_disparity"

    def __init__(
        self,
        seq: Sequence,
        layout: Layout,
        frames: SequenceOf[int] | None = None,
        *,
        images: SequenceOf[np.ndarray] | None = None,
    ) -> None:
        from m360.geometry.layout import erp_to_tangents

        if not isinstance(seq, Sequence):
            raise InputError(f"seq must be an m360 Sequence, got {type(seq).__name__}")
        if not isinstance(layout, Layout):
            raise InputError(f"layout must be an m360.Layout, got {type(layout).__name__}")
        self.sequence = seq
        self.layout = layout
        self.frames = list(range(len(seq))) if frames is None else [int(f) for f in frames]
        self.name = f"simulated sequence (seed {seq.seed}, per-frame tangent errors)"
        self._cache: dict[int, np.ndarray] = {}
        if images is not None and len(images) != len(self.frames):
            raise InputError(f"images must hold {len(self.frames)} frames, got {len(images)}")
        thumbs = []
        for k, index in enumerate(self.frames):
            rgb = seq.render(index)[0] if images is None else np.asarray(images[k])
            thumbs.append(_thumbnail(erp_to_tangents(_resized(rgb, layout), layout)))
        self._thumbs = np.stack(thumbs)

    def frame_of(self, tangents: np.ndarray) -> int:
        """Find the index of the frame whose tangents these are (the nearest thumbnail)."""
        distance = np.abs(self._thumbs - _thumbnail(tangents)[None]).mean(axis=(1, 2, 3, 4))
        return self.frames[int(np.argmin(distance))]

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        """Return the simulated output (N, h, w) float32 of the frame these tangents show.

        Several frames' tangents one after the other (K·N of them, one network call for K
        frames) give each frame's output in turn: each group of N is recognised on its own,
        so the output does not depend on how frames are grouped into calls.
        """
        n = len(self.layout)
        shape = tuple(np.shape(tangents)[:3])
        if (
            len(shape) != 3
            or shape[0] % n
            or shape[0] == 0
            or shape[1:] != self.layout.tangent_shape
        ):
            expected = (n, *self.layout.tangent_shape)
            raise InputError(
                f"expected tangents of shape {expected} (or K frames': K·{n}), got "
                f"{np.shape(tangents)}"
            )
        array = np.asarray(tangents)
        outputs = []
        for start in range(0, shape[0], n):
            index = self.frame_of(array[start : start + n])
            if index not in self._cache:
                self._cache[index] = self.sequence.tangents(index, self.layout)
            outputs.append(self._cache[index])
        output: np.ndarray = np.concatenate(outputs) if len(outputs) > 1 else outputs[0].copy()
        return output


def _resized(rgb: np.ndarray, layout: Layout) -> np.ndarray:
    import cv2

    height, width = layout.erp_shape
    if rgb.shape[:2] == (height, width):
        return rgb
    resized: np.ndarray = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    return resized


def _thumbnail(tangents: np.ndarray) -> np.ndarray:
    """(N, 8, 8, 3) float32 block means of (N, h, w, 3) tangents (h, w cropped to 8·k)."""
    t = np.asarray(tangents, dtype=np.float32)
    n, h, w = t.shape[:3]
    t = t[:, : h - h % 8, : w - w % 8]
    blocks = t.reshape(n, 8, (h - h % 8) // 8, 8, (w - w % 8) // 8, -1)
    thumbs: np.ndarray = blocks.mean(axis=(2, 4))
    return thumbs


def flicker(
    predicted: SequenceOf[np.ndarray],
    true_depth: SequenceOf[np.ndarray],
    positions: Any,
    *,
    tolerance: float = 0.01,
) -> np.ndarray:
    """Measure the flicker of a predicted depth video against the truth, frame pair by pair.

    For each pair (t−1, t) and each pixel p of frame t that shows a point also seen by
    frame t−1 (the true depth at the point's pixel in t−1 agrees with its distance within
    ``tolerance``, at all four neighbouring pixels, so depth edges are left out), the point's
    pixel q in frame t−1 follows from the true camera motion. The predicted relative change
    ``D_t(p) / D_{t−1}(q) − 1`` (D_{t−1} interpolated bilinearly, wrapping in longitude)
    minus the true change ``d_t(p) / |X − c_{t−1}| − 1`` is the error; the pair's flicker is
    its median absolute value. A still prediction of a moving camera scores the true change;
    a correct one scores 0; a per-frame global scale error scores that error.

    Parameters
    ----------
    predicted : sequence of (H, W) float arrays
        Predicted radial depth per frame (any units, one for the whole video; NaN = none).
    true_depth : sequence of (H, W) float arrays
        Exact radial depth per frame, same shape.
    positions : (T, 3) array
        Camera position per frame (world, metres).
    tolerance : float
        Relative depth agreement for a point to count as seen in both frames.

    Returns
    -------
    np.ndarray
        (T − 1,) float64 median flicker of each consecutive pair (NaN where no point counts).
    """
    import cv2

    pos = as_array(positions, "positions").astype(np.float64)
    count = len(predicted)
    if len(true_depth) != count or pos.shape != (count, 3):
        raise InputError(
            f"predicted ({count} frames), true_depth ({len(true_depth)}) and positions "
            f"{pos.shape} must describe the same frames"
        )
    tolerance = number(tolerance, "tolerance", low=0.0, high=1.0)
    shapes = {np.shape(a) for a in (*predicted, *true_depth)}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise InputError(f"every map must have one (H, W) shape, got {sorted(shapes)}")
    height, width = next(iter(shapes))
    dirs = erp_directions(height, width)
    out = np.full(max(count - 1, 0), np.nan)
    for t in range(1, count):
        truth = np.asarray(true_depth[t], dtype=np.float64)
        before = np.asarray(true_depth[t - 1], dtype=np.float32)
        points = truth[..., None] * dirs + (pos[t] - pos[t - 1])  # in frame t-1's camera frame
        distance = np.linalg.norm(points, axis=-1)
        lon, lat = directions_to_lonlat(points / np.maximum(distance, 1e-12)[..., None])
        col, row = lonlat_to_erp_pixel(lon, lat, height, width)
        col = np.mod(col, width).astype(np.float32)
        row = np.clip(row, 0, height - 1).astype(np.float32)
        seen = np.ones((height, width), dtype=bool)
        for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
            c = np.mod(np.floor(col) + dc, width).astype(np.intp)
            r = np.clip(np.floor(row) + dr, 0, height - 1).astype(np.intp)
            seen &= np.abs(before[r, c] / distance - 1) <= tolerance
        previous = cv2.remap(
            np.asarray(predicted[t - 1], dtype=np.float32),
            col,
            row,
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        current = np.asarray(predicted[t], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            error = (current / previous - 1) - (truth / distance - 1)
        keep = seen & np.isfinite(error) & np.isfinite(truth)
        if keep.any():
            out[t - 1] = float(np.median(np.abs(error[keep])))
    return out
