"""Tests of m360.synthetic (analytic ray casting) and of the numpy sphere oracle it uses."""

from __future__ import annotations

from dataclasses import dataclass

import m360.synthetic as syn
import numpy as np
import pytest
from m360.errors import InputError
from m360.geometry import sphere as sph


@dataclass
class Cam:
    rotation: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


def unit(v: list[float]) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def empty_room() -> syn.Scene:
    return syn.Scene(room_min=(-1.0, -2.0, -3.0), room_max=(4.0, 5.0, 6.0))


# ------------------------------------------------------------------ sphere oracle


def test_erp_directions_known_pixels() -> None:
    h, w = 4, 8
    d = sph.erp_directions(h, w)
    assert d.shape == (h, w, 3) and d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-15)
    # Row 0 centre has latitude 90 - 22.5 = 67.5 deg (looks up, -y); column 4 has lon 22.5 deg.
    lat, lon = np.deg2rad(67.5), np.deg2rad(22.5)
    expected = [np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)]
    np.testing.assert_allclose(d[0, 4], expected, atol=1e-15)
    # Column 0 centre is at lon -157.5 deg, bottom row at lat -67.5 deg (looks down, +y).
    lat, lon = np.deg2rad(-67.5), np.deg2rad(-157.5)
    expected = [np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)]
    np.testing.assert_allclose(d[3, 0], expected, atol=1e-15)


def test_lonlat_pixel_roundtrip() -> None:
    h, w = 6, 12
    lon, lat = sph.directions_to_lonlat(sph.erp_directions(h, w))
    col, row = sph.lonlat_to_erp_pixel(lon, lat, h, w)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    np.testing.assert_allclose(col, jj, atol=1e-12)
    np.testing.assert_allclose(row, ii, atol=1e-12)


def test_camera_pixel_directions_principal_point_and_norm() -> None:
    rot = syn.rotation_matrix(yaw=0.4, pitch=-0.3, roll=0.2)
    dirs, norm = sph.camera_pixel_directions(rot, 10.0, 20.0, 3.0, 2.0, 7, 5, return_ray_norm=True)
    assert dirs.shape == (5, 7, 3) and norm.shape == (5, 7)
    np.testing.assert_allclose(dirs[2, 3], rot[2], atol=1e-15)  # Rᵀ e_z
    assert norm[2, 3] == 1.0
    # Pixel (row 4, col 6): q = (0.3, 0.1, 1).
    assert norm[4, 6] == pytest.approx(np.sqrt(1.1))
    np.testing.assert_allclose(rot @ dirs[4, 6] * norm[4, 6], [0.3, 0.1, 1.0], atol=1e-14)
    with pytest.raises(InputError, match="fx and fy"):
        sph.camera_pixel_directions(rot, 0.0, 1.0, 0.0, 0.0, 4, 4)
    with pytest.raises(InputError, match="rotation"):
        sph.camera_pixel_directions(np.eye(2), 1.0, 1.0, 0.0, 0.0, 4, 4)


# ------------------------------------------------------------------ analytic depth


def test_empty_room_axis_and_diagonal_distances() -> None:
    scene = empty_room()
    dirs = np.array(
        [
            [1, 0, 0],
            [-1, 0, 0],
            [0, 1, 0],
            [0, -1, 0],
            [0, 0, 1],
            [0, 0, -1],
            unit([1, 1, 1]),
            unit([-1, 0, 1]),
            unit([0.5, -2, -1]),
        ],
        dtype=np.float64,
    )
    expected = [4, 1, 5, 2, 6, 3, 4 * np.sqrt(3), np.sqrt(2), np.sqrt(5.25)]
    np.testing.assert_allclose(scene.distance(dirs), expected, rtol=1e-14)


def test_empty_room_render_hits_lie_on_walls() -> None:
    scene = empty_room()
    rgb, depth = syn.render(scene, 64)
    assert rgb.shape == (32, 64, 3) and rgb.dtype == np.uint8
    assert depth.shape == (32, 64) and depth.dtype == np.float32
    p = depth.astype(np.float64)[..., None] * sph.erp_directions(32, 64)
    # A point on the boundary of the box: max over axes of p_i / bound_i equals exactly 1.
    rel = np.maximum(p / scene.room_max, p / scene.room_min).max(axis=-1)
    np.testing.assert_allclose(rel, 1.0, atol=1e-6)


def test_sphere_straight_ahead_and_off_axis() -> None:
    scene = syn.Scene(
        room_min=(-10, -10, -10),
        room_max=(10, 10, 10),
        spheres=(syn.Sphere(center=(0, 0, 5), radius=1.0),),
    )
    assert scene.distance(np.array([0.0, 0.0, 1.0])) == pytest.approx(4.0, rel=1e-14)
    alpha = 0.15  # sin(alpha) < 1/5: hits the sphere
    d = np.array([np.sin(alpha), 0.0, np.cos(alpha)])
    expected = 5 * np.cos(alpha) - np.sqrt(1 - 25 * np.sin(alpha) ** 2)
    assert scene.distance(d) == pytest.approx(expected, rel=1e-13)
    miss = np.array([np.sin(0.25), 0.0, np.cos(0.25)])  # sin > 1/5: passes by, hits the +z wall
    assert scene.distance(miss) == pytest.approx(10 / np.cos(0.25), rel=1e-13)
    hit = scene.intersect(d)
    np.testing.assert_allclose(hit.normal, (hit.point - [0, 0, 5]) / 1.0, atol=1e-12)
    assert int(hit.object_id) == 6


def test_boxes_slab_and_nearest_object_wins() -> None:
    rot = syn.rotation_matrix(pitch=0.5)
    half_t = 0.02
    slab = syn.Box(center=(0, 0, 2), half_size=(1, half_t, 1), rotation=rot)
    box = syn.Box(center=(0.0, 0.0, 4.0), half_size=(1.0, 1.0, 0.5))
    ball = syn.Sphere(center=(3.0, 0.0, 0.0), radius=0.5)
    scene = syn.Scene(room_min=(-9, -9, -9), room_max=(9, 9, 9), boxes=(box, slab), spheres=(ball,))
    n = rot[1]  # the slab's thin axis in world coordinates
    t_slab = (n @ [0, 0, 2] - half_t * np.sign(n[2])) / n[2]
    assert 1.5 < t_slab < 2.0
    dirs = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0]])
    np.testing.assert_allclose(scene.distance(dirs), [t_slab, 2.5, 9.0], rtol=1e-13)
    scene_no_slab = syn.Scene(room_min=(-9, -9, -9), room_max=(9, 9, 9), boxes=(box,))
    assert scene_no_slab.distance(np.array([0, 0, 1.0])) == pytest.approx(3.5, rel=1e-14)
    hit = scene.intersect(dirs)
    np.testing.assert_allclose(hit.normal[0], -n * np.sign(n[2]), atol=1e-12)
    assert hit.object_id.tolist() == [7, 8, 4]


def test_distance_rejects_non_unit_directions() -> None:
    with pytest.raises(InputError, match="unit"):
        empty_room().distance(np.array([0.0, 0.0, 2.0]))
    with pytest.raises(InputError, match=r"\(\.\.\., 3\)"):
        empty_room().distance(np.zeros((4, 2)))


def test_scene_must_enclose_camera() -> None:
    with pytest.raises(InputError, match="strictly inside"):
        syn.Scene(room_min=(0.5, -1, -1), room_max=(2, 1, 1))


# ------------------------------------------------------------------ generator


def test_room_is_deterministic() -> None:
    rgb_a, depth_a = syn.render(syn.room(3), 64)
    rgb_b, depth_b = syn.render(syn.room(3), 64)
    np.testing.assert_array_equal(rgb_a, rgb_b)
    np.testing.assert_array_equal(depth_a, depth_b)
    rgb_c, depth_c = syn.render(syn.room(4), 64)
    assert not np.array_equal(depth_a, depth_c)
    assert not np.array_equal(rgb_a, rgb_c)


@pytest.mark.parametrize("seed", range(8))
def test_room_layout_and_camera_clearance(seed: int) -> None:
    scene = syn.room(seed)
    size = scene.room_max - scene.room_min
    assert 3 <= size[0] <= 9 and 3 <= size[2] <= 9 and 2.4 <= size[1] <= 4
    centre = (scene.room_min + scene.room_max) / 2
    assert np.hypot(centre[0], centre[2]) > 0.2  # camera is off-centre
    assert 1.0 <= scene.room_max[1] <= 1.8  # camera height above the floor (y down)
    assert len(scene.spheres) >= 1
    assert any(b.half_size.min() < 0.03 for b in scene.boxes)  # at least one slab
    assert sum(b.half_size.min() >= 0.1 for b in scene.boxes) >= 1  # furniture
    assert scene.camera_clearance() >= 0.3
    _, depth = syn.render(scene, 256)
    assert np.all(np.isfinite(depth))
    assert depth.min() >= 0.3
    assert depth.max() <= np.linalg.norm(np.maximum(-scene.room_min, scene.room_max)) + 1e-5


def test_room_objects_visible_and_rgb_not_flat() -> None:
    scene = syn.room(0)
    rgb, depth = syn.render(scene, 128)
    assert rgb.reshape(-1, 3).std(axis=0).min() > 20
    ids = scene.intersect(sph.erp_directions(64, 128)).object_id
    assert len(np.unique(ids)) >= 8  # walls plus several objects are seen
    # Distances in the image agree with the Hit record.
    np.testing.assert_allclose(depth, scene.distance(sph.erp_directions(64, 128)), rtol=1e-6)


@pytest.mark.parametrize("width", [7, 9, 0, -2, 6, 10.0, True])
def test_render_rejects_bad_width(width: object) -> None:
    with pytest.raises(InputError, match="even integer >= 8"):
        syn.render(empty_room(), width)  # type: ignore[arg-type]


# ------------------------------------------------------------------ tangents


def test_tangent_disparity_fronto_parallel_wall() -> None:
    scene = syn.Scene(room_min=(-10, -10, -10), room_max=(10, 10, 2))
    cam = Cam(np.eye(3), 50.0, 50.0, 31.5, 23.5, 64, 48)
    disp = syn.tangent_perspective_disparity(scene, [cam])
    assert disp.shape == (1, 48, 64) and disp.dtype == np.float32
    np.testing.assert_allclose(disp, 0.5, rtol=1e-6)  # every pixel sees the wall z = 2
    dist = syn.tangent_distance(scene, [cam])[0]
    x = (np.arange(64) - 31.5) / 50
    y = (np.arange(48) - 23.5) / 50
    np.testing.assert_allclose(dist, 2 * np.sqrt(1 + x[None] ** 2 + y[:, None] ** 2), rtol=1e-6)


def test_tangent_disparity_is_inverse_camera_z() -> None:
    scene = syn.room(2)
    cams = [
        Cam(syn.rotation_matrix(yaw=a, pitch=p), 40.0, 40.0, 19.5, 14.5, 40, 30)
        for a, p in [(0.0, 0.0), (1.3, 0.4), (-2.5, -0.9)]
    ]
    disp = syn.tangent_perspective_disparity(scene, cams)
    dist = syn.tangent_distance(scene, cams)
    assert disp.shape == dist.shape == (3, 30, 40)
    for k, cam in enumerate(cams):
        dirs, ray_norm = sph.camera_pixel_directions(
            cam.rotation,
            cam.fx,
            cam.fy,
            cam.cx,
            cam.cy,
            cam.width,
            cam.height,
            return_ray_norm=True,
        )
        np.testing.assert_allclose(disp[k], ray_norm / dist[k], rtol=1e-6)
        points = dist[k].astype(np.float64)[..., None] * dirs
        z_cam = points @ cam.rotation[2]
        np.testing.assert_allclose(disp[k], 1.0 / z_cam, rtol=1e-6)


def test_tangent_cameras_validated() -> None:
    with pytest.raises(InputError, match="non-empty"):
        syn.tangent_distance(empty_room(), [])
    with pytest.raises(InputError, match="share one"):
        syn.tangent_distance(
            empty_room(),
            [Cam(np.eye(3), 5, 5, 2, 2, 5, 5), Cam(np.eye(3), 5, 5, 2, 2, 6, 5)],
        )


# ------------------------------------------------------------------ distort


def tiles_fixture(n: int = 4, h: int = 40, w: int = 48) -> np.ndarray:
    rng = np.random.default_rng(11)
    return rng.uniform(0.2, 2.0, size=(n, h, w)).astype(np.float32)


def test_distort_identity() -> None:
    tangents = tiles_fixture()
    out = syn.distort(tangents, 5, scale=(1.0, 1.0), shift=0.0)
    assert out.dtype == np.float32 and out.shape == tangents.shape
    np.testing.assert_array_equal(out, tangents)


def test_distort_is_exact_affine_per_tile() -> None:
    tangents = tiles_fixture(n=6)
    tangents[2, 3:7, 5:9] = np.nan
    out = syn.distort(tangents, 123)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(tangents))
    np.testing.assert_array_equal(out, syn.distort(tangents, 123))
    assert not np.array_equal(out, syn.distort(tangents, 124))
    scales = []
    for k in range(tangents.shape[0]):
        ok = np.isfinite(tangents[k])
        x = tangents[k][ok].astype(np.float64)
        y = out[k][ok].astype(np.float64)
        a = np.stack([x, np.ones_like(x)], axis=1)
        (s, o), *_ = np.linalg.lstsq(a, y, rcond=None)
        np.testing.assert_allclose(s * x + o, y, rtol=1e-6, atol=1e-6)
        assert 0.5 <= s <= 2.0
        assert abs(o) <= 0.3 * np.median(x) + 1e-6
        scales.append(s)
    assert np.ptp(scales) > 0.1  # tangents get independent maps


def test_distort_field_is_bounded_and_smooth() -> None:
    tangents = np.full((3, 64, 64), 2.0, dtype=np.float32)
    out = syn.distort(tangents, 7, scale=(1.0, 1.0), shift=0.0, field=0.2)
    ratio = out / tangents - 1.0
    assert np.abs(ratio).max() <= 0.2 + 1e-6
    assert ratio.std(axis=(1, 2)).min() > 0.005
    # Wavelength >= 1/1.5 tile: neighbour differences stay below 0.2 * 2π * 1.5 * √2 / 64.
    assert np.abs(np.diff(ratio, axis=1)).max() < 0.042
    assert np.abs(np.diff(ratio, axis=2)).max() < 0.042


def test_distort_noise_level() -> None:
    tangents = np.full((2, 100, 100), 2.0, dtype=np.float32)
    out = syn.distort(tangents, 9, scale=(1.0, 1.0), shift=0.0, noise=0.01)
    rel = (out.astype(np.float64) - 2.0) / 2.0
    assert rel.std() == pytest.approx(0.01, rel=0.05)
    assert abs(rel.mean()) < 0.001


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"scale": (0.0, 1.0)}, "scale"),
        ({"scale": (2.0, 1.0)}, "scale"),
        ({"scale": 1.0}, "scale"),
        ({"shift": -0.1}, "shift"),
        ({"field": 1.0}, "field"),
        ({"noise": -1.0}, "noise"),
    ],
)
def test_distort_rejects_bad_options(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(InputError, match=match):
        syn.distort(tiles_fixture(), 0, **kwargs)  # type: ignore[arg-type]


def test_distort_rejects_bad_tiles() -> None:
    with pytest.raises(InputError, match=r"\(N, h, w\)"):
        syn.distort(np.ones((4, 4), dtype=np.float32), 0)
    with pytest.raises(InputError, match="float"):
        syn.distort(np.ones((1, 4, 4), dtype=np.int32), 0)
