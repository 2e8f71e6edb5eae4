"""``m360 view``: a page showing a result's point cloud, mesh or splats (``viser``, extra 3d).

The page is served on 127.0.0.1 only; the address is printed, and a browser is opened when the
machine has one (``open_browser``). Large clouds are subsampled for display (a regular stride
over the points, at most ``max_points``); the files on disk are never changed. The scene is in
m360's frame (x right, y down, z forward): the viewer is told that up is −y and starts at the
camera position (the origin) looking forward (+z), so the first view is the panorama's centre.

Gaussian splats (``--splats``) are drawn by viser's splat renderer, which stores covariances as
float16: the scene is scaled about the camera for display so that the median distance is
:data:`SPLAT_DISPLAY_DISTANCE` (a tiny or thin covariance would round to zero otherwise); the
view from the centre is the same.
"""

from __future__ import annotations

import os
import webbrowser
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._validate import integer, one_of
from ..errors import InputError

__all__ = ["DEFAULT_MAX_POINTS", "Scene3D", "load_scene", "serve"]

#: Most points sent to the browser (a regular subsample beyond that).
DEFAULT_MAX_POINTS = 2_000_000
#: Median distance of the splats as displayed (scene units; see the module docstring).
SPLAT_DISPLAY_DISTANCE = 50.0


@dataclass(frozen=True)
class Scene3D:
    """What the viewer shows: points (N, 3) in the m360 frame, colours, optional faces.

    Splats also have ``covariances`` (N, 3, 3) and ``opacity`` (N,) in [0, 1].
    """

    xyz: np.ndarray
    rgb: np.ndarray
    faces: np.ndarray | None
    source: str
    covariances: np.ndarray | None = None
    opacity: np.ndarray | None = None


def _depth_colours(xyz: np.ndarray) -> np.ndarray:
    from .files import colorize

    distance = np.linalg.norm(xyz, axis=1)
    with np.errstate(divide="ignore"):
        bgr = colorize((1.0 / distance)[None, :])[0]
    return np.ascontiguousarray(bgr[:, ::-1])


def load_scene(
    path: str | os.PathLike[str],
    *,
    mesh: bool = False,
    colour: str = "rgb",
    splats: bool = False,
) -> Scene3D:
    """Read what ``m360 view`` shows from a PLY/GLB file or an output stem.

    A stem shows its ``STEM.points.ply`` (colours of the panorama) when present, else the
    points of its depth map; with ``mesh`` its ``STEM.mesh.glb`` or the mesh of its depth map;
    with ``splats`` its ``STEM.splat.ply`` (or any 3D Gaussian Splatting ``.ply`` given) or the
    splats of its depth map. ``colour="depth"`` colours by distance (near warm, far cool)
    instead of the panorama.

    Raises
    ------
    ReadError
        A missing or unreadable file or stem.
    """
    from . import mesh as mesh_mod
    from .files import output_stem
    from .reading import load

    colour = one_of(colour, "colour", ("rgb", "depth"))
    p = Path(path)
    if splats:
        return _splat_scene(p, colour)
    if p.suffix.lower() in (".ply", ".glb") and p.is_file():
        files = [p]
    else:
        base = output_stem(p)
        tail = ".mesh.glb" if mesh else ".points.ply"
        candidate = base.with_name(base.name + tail)
        files = [candidate] if candidate.is_file() else []
        p = base
    if files:
        xyz, faces, rgb = _read_3d(files[0])
        source = str(files[0])
    else:
        saved = load(p)
        geometry: Any = mesh_mod.to_mesh(saved) if mesh else mesh_mod.to_points(saved)
        xyz = geometry.vertices if mesh else geometry.xyz
        faces = geometry.faces if mesh else None
        rgb = None
        source = f"{p} (depth)"
    if rgb is None or colour == "depth":
        rgb = _depth_colours(xyz)
    return Scene3D(np.ascontiguousarray(xyz, np.float32), rgb, faces, source)


def _splat_scene(path: Path, colour: str) -> Scene3D:
    from . import splat as splat_mod
    from .files import GEOMETRY_FILES, output_stem
    from .reading import load

    if path.suffix.lower() == ".ply" and path.is_file():
        chosen: Path | None = path
    else:
        base = output_stem(path)
        candidate = base.with_name(base.name + GEOMETRY_FILES["splat"][1])
        chosen = candidate if candidate.is_file() else None
        path = base
    if chosen is not None:
        splats = splat_mod.read_splats(chosen)
        source = str(chosen)
    else:
        splats = splat_mod.to_splats(load(path))
        source = f"{path} (depth)"
        colour = "depth"  # no panorama: colour by distance
    rgb = (
        _depth_colours(splats.xyz)
        if colour == "depth"
        else np.rint(splats.colours() * 255).astype(np.uint8)
    )
    opacity = 1.0 / (1.0 + np.exp(-splats.opacity.astype(np.float64)))
    return Scene3D(
        np.ascontiguousarray(splats.xyz, np.float32),
        rgb,
        None,
        source,
        covariances=splats.covariances().astype(np.float32),
        opacity=opacity.astype(np.float32),
    )


def _read_3d(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    from ..errors import ReadError
    from .decode import read_bytes
    from .mesh import _trimesh

    trimesh = _trimesh()
    data = read_bytes(path, "3D file")
    import io as _bytes_io

    try:
        loaded = trimesh.load(
            _bytes_io.BytesIO(data), file_type=path.suffix[1:].lower(), process=False
        )
    except Exception as exc:  # trimesh raises many kinds for corrupt files
        raise ReadError(f"cannot read {path}: {exc}") from exc
    if hasattr(loaded, "geometry"):  # a glTF scene
        loaded = loaded.dump(concatenate=True)
    xyz = np.asarray(loaded.vertices, np.float32)
    if path.suffix.lower() == ".glb":
        xyz = xyz * np.array([1.0, -1.0, -1.0], np.float32)  # glTF frame → m360 frame
    faces = getattr(loaded, "faces", None)
    colours = None
    visual = getattr(loaded, "visual", None)
    vertex_colors = getattr(visual, "vertex_colors", None)
    if vertex_colors is None:
        vertex_colors = getattr(loaded, "colors", None)
    if vertex_colors is not None and len(vertex_colors) == len(xyz):
        colours = np.ascontiguousarray(np.asarray(vertex_colors)[:, :3], np.uint8)
    return xyz, None if faces is None or len(faces) == 0 else np.asarray(faces), colours


def subsample(scene: Scene3D, max_points: int) -> Scene3D:
    """At most ``max_points`` points for display (a regular stride; meshes are shown whole).

    Splats kept are widened by sqrt(stride) so that they still cover the surface.
    """
    n = scene.xyz.shape[0]
    if scene.faces is not None or n <= max_points:
        return scene
    step = -(-n // max_points)
    covariances = None if scene.covariances is None else scene.covariances[::step] * step
    opacity = None if scene.opacity is None else scene.opacity[::step]
    return Scene3D(scene.xyz[::step], scene.rgb[::step], None, scene.source, covariances, opacity)


def serve(
    path: str | os.PathLike[str],
    *,
    port: int = 8080,
    mesh: bool = False,
    splats: bool = False,
    colour: str = "rgb",
    max_points: int = DEFAULT_MAX_POINTS,
    open_browser: bool = True,
    point_size: float | None = None,
    announce: Callable[[str], None] = print,
) -> Any:
    """Serve a result's point cloud or mesh on http://127.0.0.1:PORT; returns the viser server.

    Parameters
    ----------
    path : path
        An output stem (or any of its files) or a ``.ply`` / ``.glb`` file.
    port : int
        Port to serve on (the next free one if taken; 0 is not special to viser).
    mesh : bool
        Show the mesh instead of the points.
    splats : bool
        Show the Gaussian splats instead of the points (not with ``mesh``).
    colour : {"rgb", "depth"}
        Colours of the panorama (when the file has them) or by distance.
    max_points : int
        Most points sent to the browser.
    open_browser : bool
        Open the page in the default browser when there is one.
    point_size : float, optional
        Point size in scene units (default: 1.5 times the spacing of the points at the median
        distance, so the cloud looks closed from the camera).
    announce : callable
        Receives the line with the address (default: print).

    Returns
    -------
    viser.ViserServer
        Call ``.stop()`` to end it.
    """
    try:
        import viser
    except ImportError as exc:
        raise InputError("m360 view needs the optional extra: pip install 'm360[3d]'") from exc
    limit = integer(max_points, "max_points", low=1)
    if mesh and splats:
        raise InputError("show the mesh or the splats, not both")
    shown = subsample(load_scene(path, mesh=mesh, colour=colour, splats=splats), limit)
    server = viser.ViserServer(
        host="127.0.0.1", port=integer(port, "port", high=65535), verbose=False
    )
    server.scene.set_up_direction("-y")
    server.initial_camera.position = (0.0, 0.0, 0.0)
    server.initial_camera.look_at = (0.0, 0.0, 1.0)
    server.initial_camera.up = (0.0, -1.0, 0.0)
    scale = float(np.median(np.linalg.norm(shown.xyz, axis=1))) if len(shown.xyz) else 1.0
    if shown.covariances is not None and shown.opacity is not None:
        factor = SPLAT_DISPLAY_DISTANCE / scale if scale > 0 else 1.0
        server.initial_camera.far = 1000.0 * SPLAT_DISPLAY_DISTANCE
        server.scene.add_gaussian_splats(
            "/m360/splats",
            centers=shown.xyz * np.float32(factor),
            covariances=shown.covariances * np.float32(factor * factor),
            rgbs=shown.rgb.astype(np.float32) / 255.0,
            opacities=shown.opacity[:, None],
        )
    elif shown.faces is None:
        server.scene.add_point_cloud(
            "/m360/points",
            points=shown.xyz,
            colors=shown.rgb,
            point_size=point_size or 1.5 * scale * float(np.sqrt(4 * np.pi / len(shown.xyz))),
            precision="float32",
            point_shading="flat",
        )
    else:
        import trimesh

        tm = trimesh.Trimesh(
            shown.xyz, shown.faces, vertex_colors=shown.rgb, process=False, validate=False
        )
        server.scene.add_mesh_trimesh("/m360/mesh", tm)
    url = f"http://127.0.0.1:{server.get_port()}"
    what = (
        f"{len(shown.faces)} triangles"
        if shown.faces is not None
        else f"{len(shown.xyz)} {'points' if shown.covariances is None else 'splats'}"
    )
    announce(f"m360 view: {url} ({what} of {shown.source}); Ctrl-C to stop")
    if open_browser and _has_browser():
        webbrowser.open(url)
    return server


def _has_browser() -> bool:
    try:
        webbrowser.get()
    except webbrowser.Error:
        return False
    return True
