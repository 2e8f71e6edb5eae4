"""Layouts and resampling against numpy oracles (analytic directions and ray casting)."""

from __future__ import annotations

import itertools

import m360
import numpy as np
import pytest
from conftest import erp_depth, layout, scene, smooth_field, tangent_directions
from m360.errors import InputError
from m360.geometry import sphere as sph

# ------------------------------------------------------------------------------------- layout


@pytest.mark.parametrize(
    ("erp_width", "size"), [(2048, (346, 400)), (4096, (693, 800)), (8192, (1386, 1600))]
)
def test_icosahedron_sizes(erp_width: int, size: tuple[int, int]) -> None:
    lay = m360.Layout.icosahedron(erp_width=erp_width, padding=0.3)
    assert lay.erp_shape == (erp_width // 2, erp_width)
    assert len(lay.cameras) == 20 and lay.tangent_shape == size
    for cam in lay.cameras:
        assert (cam.height, cam.width) == size
        assert cam.rotation.shape == (3, 3) and cam.rotation.dtype == np.float64
        np.testing.assert_allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(cam.rotation) == pytest.approx(1.0)


def face_vertices(cam: m360.TangentCamera) -> np.ndarray:
    """World directions of a camera's face triangle, from its gnomonic polygon."""
    assert cam.face is not None
    q = np.column_stack([cam.face, np.ones(3)])
    d = q @ cam.rotation  # Rᵀ q for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_faces_form_an_icosahedron_and_axes_hit_centroids() -> None:
    lay = layout(2048)
    verts = np.concatenate([face_vertices(c) for c in lay.cameras])
    unique = np.unique(np.round(verts, 9), axis=0)
    assert len(unique) == 12
    # Neighbouring icosahedron vertices are arctan(2) = 63.435° apart; every face edge is one.
    for cam in lay.cameras:
        v = face_vertices(cam)
        for a, b in itertools.combinations(range(3), 2):
            assert np.degrees(np.arccos(v[a] @ v[b])) == pytest.approx(63.4349, abs=1e-3)
        centroid = v.sum(axis=0) / np.linalg.norm(v.sum(axis=0))
        np.testing.assert_allclose(cam.axis, centroid, atol=1e-12)
        # No roll: the camera x axis is horizontal (no world-y component).
        assert abs(cam.rotation[0, 1]) < 1e-12


def test_face_triangles_lie_inside_their_images() -> None:
    for cam in layout(2048).cameras:
        x, y, front = cam.project(face_vertices(cam))
        assert front.all()
        assert (x > 0).all() and (x < cam.width - 1).all()
        assert (y > 0).all() and (y < cam.height - 1).all()


def test_every_direction_is_covered_two_to_five_times() -> None:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(100_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    covered = np.zeros(len(d), int)
    for cam in layout(2048).cameras:
        x, y, front = cam.project(d)
        inside = (
            front & (x >= -0.5) & (x <= cam.width - 0.5) & (y >= -0.5) & (y <= cam.height - 0.5)
        )
        covered += inside
    assert covered.min() >= 2 and covered.max() <= 5
    # The compiled footprints agree with this count on the ERP grid.
    lay = layout(512)
    counts = np.zeros(lay.erp_shape, int)
    grid = sph.erp_directions(*lay.erp_shape)
    for cam in lay.cameras:
        x, y, front = cam.project(grid)
        counts += (
            front & (x >= -0.5) & (x <= cam.width - 0.5) & (y >= -0.5) & (y <= cam.height - 0.5)
        )
    result = m360.stitch(
        np.ones((20, *lay.tangent_shape), np.float32), lay, "none", "mean", return_details=True
    )
    assert isinstance(result, m360.StitchResult)
    np.testing.assert_array_equal(result.coverage, counts)


def test_layout_equality_and_plan_reuse() -> None:
    a = m360.Layout.icosahedron(1024)
    b = m360.Layout.icosahedron(1024)
    assert a == b and hash(a) == hash(b) and a != m360.Layout.icosahedron(1024, padding=0.2)
    from m360.geometry import plan_for

    assert plan_for(a) is plan_for(b)


def test_custom_layout_from_cameras() -> None:
    base = layout(512)
    lay = m360.Layout.from_cameras(base.cameras[:3], base.erp_shape)
    tangents = m360.erp_to_tangents(np.ones(base.erp_shape, np.float32), lay)
    assert tangents.shape == (3, *base.tangent_shape)


# ---------------------------------------------------------------------------------- ERP → tangents


def test_erp_to_tangents_matches_ray_casting(threads: int) -> None:
    lay = layout(2048)
    depth = erp_depth(0, 2048).astype(np.float32)
    tangents = m360.erp_to_tangents(depth, lay)
    truth = scene(0).distance(tangent_directions(lay))
    rel = np.abs(tangents - truth) / truth
    # Away from depth edges (where bilinear mixes two surfaces) the error is tiny.
    smooth = _away_from_edges(truth)
    assert np.median(rel[smooth]) < 1e-3
    assert np.median(rel) < 1e-3


def _away_from_edges(d: np.ndarray, tol: float = 0.02) -> np.ndarray:
    padded = np.pad(d, ((0, 0), (2, 2), (2, 2)), mode="edge")
    h, w = d.shape[1:]
    lo, hi = d.copy(), d.copy()
    for dy in range(5):
        for dx in range(5):
            win = padded[:, dy : dy + h, dx : dx + w]
            lo, hi = np.minimum(lo, win), np.maximum(hi, win)
    return (hi - lo) < tol * d


def test_erp_to_tangents_smooth_field_everywhere_including_poles() -> None:
    lay = layout(1024)
    erp = smooth_field(sph.erp_directions(*lay.erp_shape)).astype(np.float32)
    tangents = m360.erp_to_tangents(erp, lay)
    want = smooth_field(tangent_directions(lay))
    err = np.abs(tangents - want)
    # Bilinear error of a smooth field ~ curvature * pixel²; the polar faces (0-4, 15-19) sample
    # across the pole rows and the longitude wrap.
    assert err.max() < 2e-3, err.reshape(20, -1).max(axis=1)


@pytest.mark.parametrize("channels", [None, 1, 2, 3, 4])
@pytest.mark.parametrize("content", ["render", "noise"])
def test_uint8_and_float_agree(channels: int | None, content: str) -> None:
    lay = layout(512)
    if content == "render":
        rgb, _ = m360.synthetic.render(scene(1), 512)
    else:
        # Full-range noise: neighbours differ by up to 255, the worst case for fixed point.
        rgb = np.random.default_rng(3).integers(0, 256, (256, 512, 3), dtype=np.uint8)
    img = (
        rgb[..., 0]
        if channels is None
        else np.concatenate([rgb, rgb[..., :1]], axis=2)[..., :channels]
    )
    out8 = m360.erp_to_tangents(img, lay)
    outf = m360.erp_to_tangents(img.astype(np.float32), lay)
    expected_shape = (20, *lay.tangent_shape) + (() if channels is None else (channels,))
    assert out8.shape == expected_shape and out8.dtype == np.uint8
    assert outf.shape == expected_shape and outf.dtype == np.float32
    # u8 rounds the same bilinear value, computed in fixed point: 2⁻¹⁵ fractions and (SIMD
    # path) two roundings to 1/128 of a grey level move it by less than 255·4·2⁻¹⁵.
    assert np.abs(out8.astype(np.float32) - outf).max() <= 0.5 + 0.04


def test_non_contiguous_and_read_only_inputs_work() -> None:
    lay = layout(512)
    rgb, _ = m360.synthetic.render(scene(1), 512)
    view = np.asfortranarray(rgb)
    ro = rgb.copy()
    ro.flags.writeable = False
    ref = m360.erp_to_tangents(rgb, lay)
    np.testing.assert_array_equal(m360.erp_to_tangents(view, lay), ref)
    np.testing.assert_array_equal(m360.erp_to_tangents(ro, lay), ref)
    np.testing.assert_array_equal(m360.erp_to_tangents(rgb[:, ::1, ::-1][..., ::-1], lay), ref)


def test_default_layout_is_the_icosahedron() -> None:
    erp = np.zeros((256, 512), np.uint8)
    assert m360.erp_to_tangents(erp).shape == (20, *layout(512).tangent_shape)


# ---------------------------------------------------------------------------------- tangents → ERP


def test_tangents_to_erp_per_face_maps() -> None:
    lay = layout(512)
    tangents = smooth_field(tangent_directions(lay)).astype(np.float32)
    maps = m360.tangents_to_erp(tangents, lay)
    assert maps.shape == (20, *lay.erp_shape) and maps.dtype == np.float32
    grid = sph.erp_directions(*lay.erp_shape)
    want = smooth_field(grid)
    for k, cam in enumerate(lay.cameras):
        x, y, front = cam.project(grid)
        seen = front & (x >= -0.5) & (x <= cam.width - 0.5) & (y >= -0.5) & (y <= cam.height - 0.5)
        np.testing.assert_array_equal(np.isfinite(maps[k]), seen)
        # Between pixel centres: bilinear error only. In the outer half-pixel ring the position
        # is clamped onto the border pixel centre: at most half a pixel's worth of gradient.
        interior = seen & (x >= 0) & (x <= cam.width - 1) & (y >= 0) & (y <= cam.height - 1)
        assert np.abs(maps[k][interior] - want[interior]).max() < 2e-3
        assert np.abs(maps[k][seen] - want[seen]).max() < 1.2e-2


# ------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("erp", "match"),
    [
        (np.zeros((256, 500), np.uint8), "W == 2H"),
        (np.zeros((256,), np.uint8), "dimensions|shape"),
        (np.zeros((256, 512, 5), np.uint8), "channels"),
        (np.zeros((256, 512), np.int32), "dtype"),
        (np.zeros((256, 512), bool), "dtype"),
        (np.full((256, 512), np.inf, np.float32), "infinite"),
        (np.zeros((16, 32), np.uint8), "erp_width"),
        ("not an image", "not a numeric array"),
    ],
)
def test_erp_to_tangents_rejects_bad_input(erp: object, match: str) -> None:
    with pytest.raises(InputError, match=match):
        m360.erp_to_tangents(erp)  # type: ignore[arg-type]


def test_erp_size_must_match_layout() -> None:
    with pytest.raises(InputError, match="erp_width=1024"):
        m360.erp_to_tangents(np.zeros((512, 1024), np.uint8), layout(512))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"erp_width": 2047}, "even"),
        ({"erp_width": 0}, "erp_width=0 is unusable: it must be even, at least 64"),
        ({"erp_width": 2048.0}, "integer"),
        ({"erp_width": 2048, "padding": -1.0}, "padding"),
        ({"erp_width": 2048, "padding": float("nan")}, "padding"),
        ({"erp_width": 2048, "tangent_width": 3}, "tangent_width"),
    ],
)
def test_layout_rejects_bad_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        m360.Layout.icosahedron(**kwargs)


def test_tangents_to_erp_rejects_bad_tiles() -> None:
    lay = layout(512)
    h, w = lay.tangent_shape
    with pytest.raises(InputError, match="expected"):
        m360.tangents_to_erp(np.zeros((19, h, w), np.float32), lay)
    with pytest.raises(InputError, match="expected"):
        m360.tangents_to_erp(np.zeros((20, h + 1, w), np.float32), lay)
    with pytest.raises(InputError, match="float"):
        m360.tangents_to_erp(np.zeros((20, h, w), np.int16), lay)
    with pytest.raises(InputError, match="Layout"):
        m360.tangents_to_erp(np.zeros((20, h, w), np.float32), "icosahedron")  # type: ignore[arg-type]


def test_compiled_core_checks_shapes_itself() -> None:
    """A validation slip in Python still gives InputError from the core, never a panic."""
    from m360 import _core
    from m360.geometry import plan_for

    plan = plan_for(layout(512))
    with pytest.raises(InputError, match="shape"):
        plan.blend(np.zeros((20, 3, 3), np.float32), {"method": "mean"})
    with pytest.raises(InputError, match="shape"):
        plan.erp_to_tangents(np.zeros((10, 20, 3), np.uint8))
    with pytest.raises(InputError, match="contiguous"):
        plan.tangents_to_erp(np.zeros((20, *layout(512).tangent_shape, 2), np.float32)[..., 0])
    with pytest.raises(InputError, match="rotation"):
        _core.Plan((256, 512), np.ones((1, 3, 3)), np.ones((1, 4)), (10, 10))
    with pytest.raises(InputError, match="threads"):
        m360.set_num_threads(0)


def test_plan_cache_is_safe_under_many_threads() -> None:
    """Threads asking for plans of several layouts at once while the cache is cleared: every
    call gets a working plan of its own layout, and a cached layout has one plan."""
    import threading

    from m360.geometry import plan_for

    layouts = [m360.Layout.icosahedron(w) for w in (64, 96, 128, 160, 192, 224)]
    errors: list[BaseException] = []
    start = threading.Barrier(8)

    def work(k: int) -> None:
        try:
            start.wait()
            for i in range(40):
                lay = layouts[(k + i) % len(layouts)]
                plan = plan_for(lay)
                assert plan.coverage().shape == lay.erp_shape
                if k == 0 and i % 10 == 0:
                    m360.clear_plan_cache()
        except BaseException as exc:  # reported below, in the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    lay = layouts[0]
    assert plan_for(lay) is plan_for(lay)
