"""m360.normals and the normals files against the analytic normals of ray-cast scenes.

The oracle is m360.synthetic's ray caster: ``Scene.intersect`` returns each ray's distance and
the unit normal of the surface it hits (facing the camera), from the boxes', the room's and the
spheres' own geometry, with no finite differences. The ERP rays are built here in float64 from
the formulas of docs/conventions.md.
"""

from __future__ import annotations

import functools
import json

import cv2
import m360
import m360.synthetic as syn
import numpy as np
import pytest

ROOM_MIN = np.array([-2.1, -1.3, -3.2])
ROOM_MAX = np.array([2.9, 1.55, 1.8])


def erp_directions(width: int) -> np.ndarray:
    """(H, W, 3) float64 unit rays of the ERP pixel centres (docs/conventions.md)."""
    return erp_directions_rows(width, 0, width // 2)


def erp_directions_rows(width: int, start: int, stop: int) -> np.ndarray:
    """The rays of rows start…stop − 1."""
    height = width // 2
    lat = np.pi / 2 - np.pi * (np.arange(start, min(stop, height)) + 0.5) / height
    lon = 2 * np.pi * (np.arange(width) + 0.5) / width - np.pi
    lon_g, lat_g = np.meshgrid(lon, lat)
    return np.stack(
        [np.cos(lat_g) * np.sin(lon_g), -np.sin(lat_g), np.cos(lat_g) * np.cos(lon_g)], axis=-1
    )


def cast(scene: syn.Scene, width: int) -> syn.Hit:
    return scene.intersect(erp_directions(width))


@functools.cache
def room_hit(seed: int, width: int) -> syn.Hit:
    return cast(syn.room(seed), width)


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.clip((a.astype(np.float64) * b).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))  # type: ignore[no-any-return]


def depth_of(hit: syn.Hit) -> np.ndarray:
    return hit.distance.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_planes_and_boxes_match_the_analytic_normals(seed):
    scene = syn.room(seed)
    hit = cast(scene, 512)
    normals = m360.normals(depth_of(hit))
    assert normals.shape == (256, 512, 3) and normals.dtype == np.float32
    valid = np.isfinite(normals).all(-1)
    assert valid.mean() > 0.99  # only one-pixel slivers between depth jumps have none
    error = angles_deg(normals, hit.normal)
    planes = hit.object_id < 6 + len(scene.boxes)  # room faces, then boxes, then spheres
    assert planes.sum() > 0.8 * planes.size
    # The bar is a median of 2°; on a plane two chords from a pixel lie in the plane,
    # so the error is float rounding except at creases (box edges, room corners).
    assert np.median(error[planes & valid]) < 0.05
    assert np.quantile(error[planes & valid], 0.95) < 2.0
    # unit length, facing the camera
    np.testing.assert_allclose(np.linalg.norm(normals[valid], axis=-1), 1.0, atol=1e-5)
    assert ((normals[valid] * hit.point[valid]).sum(-1) < 0).all()


def test_curved_surfaces_converge_at_first_order():
    # One-sided chords on a sphere give the normal half a pixel away: the error halves when
    # the resolution doubles (measured 0.83°, 0.42°, 0.21° at 512, 1K, 2K for seed 7).
    scene = syn.room(7)
    errors = []
    for width in (256, 512):
        hit = room_hit(7, width)
        error = angles_deg(m360.normals(depth_of(hit)), hit.normal)
        spheres = (hit.object_id >= 6 + len(scene.boxes)) & np.isfinite(error)
        assert spheres.sum() > 1000 * width // 512
        errors.append(np.median(error[spheres]))
    assert errors[1] < 1.0
    assert 0.4 < errors[1] / errors[0] < 0.6, errors


def test_frame_of_the_empty_room():
    hit = cast(syn.Scene(room_min=ROOM_MIN, room_max=ROOM_MAX), 256)
    n = m360.normals(depth_of(hit))
    np.testing.assert_allclose(n[64, 128], [0, 0, -1], atol=1e-4)  # wall ahead (+z) faces back
    np.testing.assert_allclose(n[64, 192], [-1, 0, 0], atol=1e-4)  # wall to the right (+x)
    np.testing.assert_allclose(n[0, :], np.tile([0, 1, 0], (256, 1)), atol=1e-4)  # ceiling
    np.testing.assert_allclose(n[-1, :], np.tile([0, -1, 0], (256, 1)), atol=1e-4)  # floor


def test_seam_is_continuous_and_rotation_equivariant():
    scene = syn.room(3)
    width = 512
    depth = depth_of(cast(scene, width))
    n = m360.normals(depth).astype(np.float64)
    # Turning the panorama by half a turn (a rotation by π about y) moves the seam into the
    # middle: the normals must be the rotated, rolled normals wherever they are finite.
    turned = m360.normals(np.roll(depth, width // 2, axis=1)).astype(np.float64)
    expected = np.roll(n * np.array([-1.0, 1.0, -1.0]), width // 2, axis=1)
    both = np.isfinite(expected).all(-1) & np.isfinite(turned).all(-1)
    assert both.mean() > 0.99
    assert np.nanmax(angles_deg(turned[both], expected[both])) < 0.1  # float32 rounding
    # Across the seam the step between columns W-1 and 0 is like any step between columns.
    steps = angles_deg(n, np.roll(n, -1, axis=1))
    seam, inside = steps[:, -1], steps[:, :-1]
    assert np.nanmedian(seam) <= np.nanmedian(inside) + 0.01
    hit = cast(scene, width)
    for col in (0, width - 1):
        ok = np.isfinite(n[:, col]).all(-1) & (hit.object_id[:, col] < 6 + len(scene.boxes))
        assert np.median(angles_deg(n[ok, col], hit.normal[ok, col])) < 0.05


def test_poles_use_the_neighbour_across_the_pole():
    # A tilted slab over the camera and a tilted ramp under it: the first and last rows see
    # planes that are not perpendicular to the pole axis, so a normal there is only right if
    # the latitude chord crosses the pole to the opposite meridian.
    tilt = syn.rotation_matrix(pitch=0.35, roll=-0.2)
    scene = syn.Scene(
        room_min=ROOM_MIN,
        room_max=ROOM_MAX,
        boxes=(
            syn.Box(center=[0.1, -1.0, 0.0], half_size=[1.5, 0.02, 1.5], rotation=tilt),
            syn.Box(center=[0.0, 1.2, 0.1], half_size=[1.4, 0.02, 1.4], rotation=tilt.T),
        ),
    )
    hit = cast(scene, 512)
    assert set(np.unique(hit.object_id[[0, -1]])) == {6, 7}
    n = m360.normals(depth_of(hit))
    for row in (0, 1, 2, -3, -2, -1):
        error = angles_deg(n[row], hit.normal[row])
        # float32 rounding of the short longitude chords near the pole: ≤ 0.1° at 512
        assert np.isfinite(error).all() and error.max() < 0.2, (row, np.nanmax(error))
    # The splats' grid with a stride that does not divide H: the grid column nearest the
    # opposite meridian is off by a fraction of a column, which the chord takes into account
    # (without: 0.3° and 0.5° at strides 3 and 5).
    for stride in (3, 5):
        splats = m360.to_splats(depth_of(hit), stride=stride, max_depth_ratio=float("inf"))
        rows, cols = np.divmod(splats.pixels, 512)
        poles = (rows == rows.min()) | (rows == rows.max())
        error = angles_deg(splats.normals[poles], hit.normal[rows[poles], cols[poles]])
        assert error.max() < 0.1, (stride, error.max())


def test_nan_and_depth_jumps():
    scene = syn.room(0)
    hit = cast(scene, 256)
    depth = depth_of(hit)
    holes = depth.copy()
    holes[40:60, 100:140] = np.nan  # a masked block
    holes[90, 30] = np.nan  # one pixel
    holes[:, 200] = np.nan  # a full column
    n = m360.normals(holes)
    assert np.isnan(n[~np.isfinite(holes)]).all()
    # The pixels next to a hole take the chord on their other side: still exact on a plane.
    ring = np.zeros(holes.shape, bool)
    ring[39, 100:140] = ring[60, 100:140] = ring[40:60, 99] = ring[40:60, 140] = True
    ring[:, 199] = ring[:, 201] = True
    planes = hit.object_id < 6 + len(scene.boxes)
    ok = ring & planes & np.isfinite(n).all(-1)
    assert ok.sum() > 0.8 * (ring & planes).sum()
    assert np.median(angles_deg(n[ok], hit.normal[ok])) < 0.05
    # An isolated pixel has no chord at all.
    lone = np.full_like(depth, np.nan)
    lone[100, 50:53] = 2.0
    lone[99:102, 51] = 2.0
    n_lone = m360.normals(lone)
    assert np.isfinite(n_lone[100, 51]).all() and np.isnan(n_lone[100, 50]).all()
    # Occlusion edges: the pixels on either side take the chord on their own surface.
    edges = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        for shift in (1, -1):
            other = np.roll(depth, shift, axis)
            edges |= np.maximum(depth, other) > 1.3 * np.minimum(depth, other)
    edges &= planes
    assert edges.sum() > 200
    assert np.nanmedian(angles_deg(m360.normals(depth), hit.normal)[edges]) < 0.05
    # A one-pixel sliver of wall between two posts in front of it: both longitude chords
    # cross a depth jump, so it has no normal; with every chord allowed it gets a bent one.
    posts = depth.copy()
    posts[100:120, 60:64] *= 0.5
    posts[100:120, 65:69] *= 0.5
    assert np.isnan(m360.normals(posts)[100:120, 64]).all()
    bent = m360.normals(posts, max_depth_ratio=float("inf"))[100:120, 64]
    assert (angles_deg(bent, hit.normal[100:120, 64]) > 20).all()


def test_sources_and_bad_input(tmp_path):
    hit = cast(syn.room(1), 128)
    depth = depth_of(hit)
    n = m360.normals(depth)

    class Result:
        pass

    result = Result()
    result.depth = depth
    result.disparity = (1 / depth).astype(np.float32)
    np.testing.assert_array_equal(m360.normals(result), n)
    from_disparity = m360.normals(result.disparity, quantity="disparity")
    assert np.nanmax(angles_deg(from_disparity, n)) < 0.05
    m360.save(result, tmp_path / "pano", formats=("npy",))
    np.testing.assert_array_equal(m360.normals(tmp_path / "pano"), n)
    for bad in (depth[:, :100], depth[..., None], depth.astype(np.int32)):
        with pytest.raises(m360.InputError):
            m360.normals(bad)
    for ratio in (1.0, 0.5, float("nan"), "2"):
        with pytest.raises(m360.InputError):
            m360.normals(depth, max_depth_ratio=ratio)


def test_save_writes_exr_and_png_with_the_frame(tmp_path):
    hit = cast(syn.room(2), 256)
    depth = depth_of(hit)
    depth[10:20, 10:20] = np.nan

    class Result:
        pass

    result = Result()
    result.depth = depth
    result.disparity = (1 / depth).astype(np.float32)
    written = m360.save(result, tmp_path / "pano", formats=("npy", "normals"))
    expected = m360.normals(depth)
    exr = m360.decode.read_exr(written["normals.exr"])  # R, G, B = x, y, z
    np.testing.assert_array_equal(exr, expected)  # bit-exact, NaN where none
    png = cv2.imread(str(written["normals.png"]), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
    assert png.dtype == np.uint8
    finite = np.isfinite(expected).all(-1)
    decoded = png.astype(np.float64) / 255 * 2 - 1
    assert np.abs(decoded[finite] - expected[finite]).max() <= 1 / 255 + 1e-6
    assert (png[~finite] == 0).all()
    meta = json.loads((tmp_path / "pano.json").read_text())
    assert meta["files"]["normals"] == {"exr": "pano.normals.exr", "png": "pano.normals.png"}
    for name in ("pano.normals.exr", "pano.normals.png"):
        assert "y down" in meta["frame"][name] and "facing the camera" in meta["frame"][name]
    assert "normals" in meta["quantities"]
    assert m360.io.output_stem(tmp_path / "pano.normals.png") == tmp_path / "pano"
    # m360.load still reads the arrays of a set with normals
    np.testing.assert_array_equal(m360.load(tmp_path / "pano").depth, depth)
    # a killed writer's temporaries of these files are cleaned up
    stale = tmp_path / ".pano.normals.exr.abcdefgh.tmp"
    stale.write_bytes(b"x")
    assert stale in m360.io.remove_stale_temporaries(tmp_path / "pano")


def test_pole_rows_keep_their_digits_at_4k():
    # Two tilted planes, one over and one under the camera, depth r = 1.5 / |n · d| exactly.
    # Next to the poles one column is 4e-7 rad at 4K: neighbouring float32 depths differ by
    # about their rounding, so a one-column chord gave 1.0° median (3.4° max) on the first row;
    # the chord reaches over enough columns there (MIN_CHORD_ANGLE).
    width = 4096
    height = width // 2
    normal = np.array([0.2, -0.95, 0.24]) / np.linalg.norm([0.2, -0.95, 0.24])
    rays = np.empty((height, width, 3))
    for start in range(0, height, 256):  # in bands: 200 MB of float64 rays at a time
        rays[start : start + 256] = erp_directions_rows(width, start, start + 256)
    side = rays @ normal
    depth = (1.5 / np.abs(side)).astype(np.float32)
    n = m360.normals(depth)
    truth = np.where((side > 0)[..., None], -normal, normal)
    for row in (0, 1, 2, 3, height - 2, height - 1):
        error = angles_deg(n[row], truth[row])
        assert error.max() < 0.1, (row, error.max())


@pytest.mark.parametrize("seed", range(6))
def test_random_maps_never_fail(seed):
    # Noise, holes, zeros, negatives, infinities and tiny maps: unit normals facing the camera
    # where the depth is valid and a neighbour on each axis is usable, NaN elsewhere.
    rng = np.random.default_rng(seed)
    height = int(rng.integers(2, 40))
    depth = rng.lognormal(0.0, 0.5 * seed, (height, 2 * height)).astype(np.float32)
    bad = rng.random(depth.shape) < 0.2
    depth[bad] = rng.choice(np.array([np.nan, 0.0, -1.0, np.inf], np.float32), bad.sum())
    n = m360.normals(depth, max_depth_ratio=float(rng.choice([1.05, 2.0, np.inf])))
    assert n.shape == (*depth.shape, 3) and n.dtype == np.float32
    valid = np.isfinite(n).all(-1)
    assert (np.isnan(n) == ~valid[..., None]).all()  # a normal is whole or NaN
    assert not valid[~(np.isfinite(depth) & (depth > 0))].any()
    np.testing.assert_allclose(np.linalg.norm(n[valid], axis=-1), 1.0, atol=1e-5)
    rays = erp_directions(2 * height)
    assert ((n[valid] * rays[valid]).sum(-1) <= 1e-6).all()
    splats = m360.to_splats(depth, max_depth_ratio=np.inf) if valid.any() else None
    if splats is not None:
        assert np.isfinite(splats.scales).all() and np.isfinite(splats.rotations).all()
