"""Layouts with more redundancy (the subdivided icosahedron), the weighted-median blend and the
angular scale of the simulated content errors."""

from __future__ import annotations

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from conftest import erp_depth, scene, tangent_disparity
from m360.errors import InputError
from m360.geometry import plan_for
from m360.geometry import sphere as sph
from scipy.spatial import ConvexHull

# ------------------------------------------------------------------ oracle: the icosahedron


def icosahedron_vertices() -> np.ndarray:
    """The 12 vertices with one at each pole (world y is down), the rings at latitude
    ±atan(1/2), the upper ring at longitudes 0, 72, ..., the lower one turned by 36°."""
    lat = np.arctan(0.5)
    upper = [sph.lonlat_to_directions(np.radians(72.0 * k), lat) for k in range(5)]
    lower = [sph.lonlat_to_directions(np.radians(36.0 + 72.0 * k), -lat) for k in range(5)]
    poles = [np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    return np.array([*poles, *upper, *lower], dtype=np.float64)


def subdivided_faces(n: int) -> np.ndarray:
    """(20·4ⁿ, 3, 3) spherical triangles: the convex hull's faces split n times at the
    normalised edge midpoints (independent of the core's face order and construction)."""
    vertices = icosahedron_vertices()
    faces = vertices[ConvexHull(vertices).simplices]
    for _ in range(n):
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]

        def mid(p: np.ndarray, q: np.ndarray) -> np.ndarray:
            m = p + q
            return m / np.linalg.norm(m, axis=-1, keepdims=True)

        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        faces = np.concatenate([np.stack(t, axis=1) for t in
                                ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])  # fmt: skip
    return faces


def fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - y * y)
    a = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(a), y, r * np.sin(a)], axis=-1)


def in_image(cam: m360.TangentCamera, d: np.ndarray) -> np.ndarray:
    x, y, front = cam.project(d)
    return front & (x >= -0.5) & (x <= cam.width - 0.5) & (y >= -0.5) & (y <= cam.height - 0.5)


# ------------------------------------------------------------------ the subdivided layout


def test_subdivisions_0_is_the_papers_layout() -> None:
    paper = m360.Layout.icosahedron(1024, padding="paper")
    assert m360.Layout.icosahedron(1024, padding=0.3, subdivisions=0) == paper
    assert len(paper) == 20 and paper.subdivisions == 0


@pytest.mark.parametrize(("n", "padding"), [(1, 0.15), (1, 0.3), (2, 0.075)])
def test_subdivided_cameras_look_at_the_sub_face_centroids(n: int, padding: float) -> None:
    lay = m360.Layout.icosahedron(2048, padding=padding, subdivisions=n)
    paper = m360.Layout.icosahedron(2048, padding="paper")
    faces = subdivided_faces(n)
    assert len(lay) == len(faces) == 20 * 4**n
    centroids = faces.sum(axis=1)
    centroids /= np.linalg.norm(centroids, axis=-1, keepdims=True)
    axes = np.stack([cam.axis for cam in lay.cameras])
    # One camera per sub-face centroid, one-to-one.
    nearest = np.argmax(axes @ centroids.T, axis=1)
    assert sorted(nearest) == list(range(len(faces)))
    np.testing.assert_allclose(axes, centroids[nearest], atol=1e-12)
    for cam, k in zip(lay.cameras, nearest, strict=True):
        # No roll: image x is horizontal; square pixels of the paper's angular size.
        assert abs(cam.rotation[0, 1]) < 1e-12 and cam.rotation[1, 1] > 0
        assert cam.fx == pytest.approx(paper.cameras[0].fx, rel=1e-12) and cam.fx == cam.fy
        # The whole sub-face is in the image, and the core's polygon is that sub-face.
        assert in_image(cam, faces[k]).all()
        assert cam.face is not None
        x, y, _ = cam.project(faces[k])
        gnomonic = np.stack([(x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy], axis=-1)
        got = {tuple(np.round(p, 9)) for p in cam.face}
        assert got == {tuple(np.round(p, 9)) for p in gnomonic}


def test_subdivided_layout_covers_every_direction_and_round_trips_rays() -> None:
    lay = m360.Layout.icosahedron(512, padding=0.0, subdivisions=1)
    faces = subdivided_faces(1)
    d = fibonacci_directions(20_000)
    # Each direction lies in some spherical sub-triangle (the oracle's), and the camera of that
    # sub-face holds it even with no padding.
    seen = np.zeros(len(d), bool)
    for cam in lay.cameras:
        seen |= in_image(cam, d)
    assert seen.all()
    # Every direction is in some spherical sub-triangle of the oracle (the sub-faces tile the
    # sphere), and then in the image of that sub-face's camera.
    normals = np.cross(faces, np.roll(faces, -1, axis=1))  # (F, 3, 3): edge planes
    side = np.einsum("fkc,nc->nfk", normals, d)
    same = (side >= -1e-12).all(axis=2) | (side <= 1e-12).all(axis=2)
    front = d @ faces.sum(axis=1).T > 0  # the sign test alone also takes the antipode
    owner = np.argmax(same & front, axis=1)
    assert (same & front).any(axis=1).all()
    axes = np.stack([cam.axis for cam in lay.cameras])
    centroids = faces.sum(axis=1)
    camera_of = np.argmax(centroids @ axes.T, axis=1)
    for f in np.unique(owner):
        assert in_image(lay.cameras[camera_of[f]], d[owner == f]).all()
    # Analytic ray-cast round trip: pixel -> direction -> pixel.
    for cam in lay.cameras[::7]:
        rays = sph.camera_pixel_directions(
            cam.rotation, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height
        )
        x, y, front = cam.project(rays)
        cols, rows = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        assert front.all()
        np.testing.assert_allclose(x, cols, atol=1e-9)
        np.testing.assert_allclose(y, rows, atol=1e-9)


def test_subdivided_layout_refuses_what_the_taps_cannot_hold() -> None:
    assert m360._core.LIMITS["max_subdivisions"] == 2
    with pytest.raises(InputError, match="subdivisions"):
        m360.Layout.icosahedron(512, subdivisions=3)
    with pytest.raises(InputError, match="tangents see one direction"):
        m360.Layout.icosahedron(512, padding=0.5, subdivisions=1)
    with pytest.raises(InputError):
        m360.Layout.icosahedron(512, subdivisions=-1)
    # The largest allowed padding at n = 1 stays within the taps' 16 faces per pixel.
    lay = m360.Layout.icosahedron(512, padding=0.3, subdivisions=1)
    assert int(plan_for(lay).coverage().max()) <= 16
    assert "subdivisions=1" in repr(lay)


def test_exact_tangents_through_the_subdivided_layout_stay_at_the_resampling_floor() -> None:
    width = 1024
    lay = m360.Layout.icosahedron(width, padding=0.2, subdivisions=1)
    exact = syn.tangent_perspective_disparity(scene(0), lay.cameras)
    out = m360.stitch(exact, lay, align=[(2, 2), (4, 4)])
    assert m360.eval.depth_metrics(out, erp_depth(0, width))["abs_rel"] <= 0.003


def test_multiscale_alignment_scales_its_grids_to_the_subdivided_tiles() -> None:
    """align="multiscale" on a subdivided layout: the energy's grids with 2^n times fewer nodes
    per side (at least 2), so the nodes are as far apart in angle as on the 20 faces; the same
    bytes as the grids given explicitly. Grids given, or options built without the layout, are
    kept as they are."""
    assert m360.stitching.options.multiscale_levels("normalized", 0) == [(4, 3), (8, 7)]
    assert m360.stitching.options.multiscale_levels("normalized", 1) == [(2, 2), (4, 4)]
    assert m360.stitching.options.multiscale_levels("paper", 1) == [(2, 2), (4, 4), (8, 7)]
    assert m360.stitching.options.multiscale_levels("normalized", 2) == [(2, 2), (2, 2)]
    lay = m360.Layout.icosahedron(512, subdivisions=1)
    tiles = syn.distort(
        syn.tangent_perspective_disparity(scene(0), lay.cameras), 1, scale=(0.5, 2.0), shift=0.3
    )
    default = m360.stitch(tiles, lay, return_details=True)
    assert default.options is not None
    assert default.options.align is not None
    assert default.options.align["levels"] == [(2, 2), (4, 4)]
    explicit = m360.stitch(tiles, lay, align=[(2, 2), (4, 4)])
    np.testing.assert_array_equal(default.disparity, explicit)
    given = m360.stitch(tiles, lay, align=[(4, 3), (8, 7)], return_details=True)
    assert given.options is not None and given.options.align is not None
    assert given.options.align["levels"] == [(4, 3), (8, 7)]
    paper = m360.stitch(tiles, lay, energy="paper", return_details=True)
    assert paper.options is not None and paper.options.align is not None
    assert paper.options.align["levels"] == [(2, 2), (4, 4), (8, 7)]
    built = m360.StitchOptions()  # no layout in sight: the energy's own schedule
    assert built.align is not None and built.align["levels"] == [(4, 3), (8, 7)]


@pytest.mark.parametrize(("padding", "n"), [(None, 0), ("paper", 0), (0.3, 1), (0.2, 1)])
def test_network_pixel_degrees_is_the_angle_rays_through_the_tile_centre_span(
    padding: float | str | None, n: int
) -> None:
    """The angle between the rays that land half a network pixel either side of a tile's
    centre, found by bisection through TangentCamera.project, on every camera of the layout;
    and the same network sees finer on the smaller tiles."""
    lay = m360.Layout.icosahedron(1024, padding=padding, subdivisions=n)
    for network_width in (64, 256, 518):
        half = 0.5 * lay.tangent_shape[1] / network_width  # tile pixels
        for cam in lay.cameras[:: max(1, len(lay.cameras) // 5)]:
            lo, hi = 0.0, 1.0
            for _ in range(60):  # the angle off the axis that lands `half` px right of it
                mid = 0.5 * (lo + hi)
                x, _, _ = cam.project(cam.rotation.T @ np.array([np.sin(mid), 0.0, np.cos(mid)]))
                lo, hi = (mid, hi) if float(x) - cam.cx < half else (lo, mid)
            expected = np.degrees(2 * lo)
            assert lay.network_pixel_degrees(network_width) == pytest.approx(expected, abs=1e-9)
    default = m360.Layout.icosahedron(1024).network_pixel_degrees(384)
    assert lay.network_pixel_degrees(384) <= default
    with pytest.raises(InputError, match="network_width"):
        lay.network_pixel_degrees(0)


# ------------------------------------------------------------------ weighted median blend


def weighted_median_oracle(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per pixel of (N, H, W) samples (NaN = unseen): the smallest value whose cumulative weight
    reaches half the total where >= 3 are valid (equal weights if they sum to 0), else the
    weighted mean (the plain mean if the weights sum to 0)."""
    valid = np.isfinite(values)
    count = valid.sum(axis=0)
    w = np.where(valid, weights, 0.0).astype(np.float32)
    v = np.where(valid, values, 0.0)
    wsum = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(wsum > 0, (w * v).sum(axis=0) / wsum, v.sum(axis=0) / count)
    order = np.argsort(np.where(valid, values, np.inf), axis=0, kind="stable")
    sorted_v = np.take_along_axis(values, order, axis=0)
    equal = wsum <= 0
    sorted_w = np.take_along_axis(np.where(equal, valid.astype(np.float32), w), order, axis=0)
    cumulative = np.cumsum(sorted_w, axis=0, dtype=np.float32)
    half = cumulative[-1] / np.float32(2)
    first = np.argmax(cumulative >= half, axis=0)
    median = np.take_along_axis(sorted_v, first[None], axis=0)[0]
    return np.where(count >= 3, median, mean).astype(np.float32)


def test_median_blend_matches_a_numpy_weighted_median() -> None:
    width = 128
    lay = m360.Layout.icosahedron(width, padding=0.7)
    plan = plan_for(lay)
    exact = syn.tangent_perspective_disparity(scene(0), lay.cameras)
    tiles = syn.content_errors(exact, 3, amplitude=(0.3, 0.6))
    tiles = syn.distort(tiles, 4, scale=(0.8, 1.25), shift=0.1, noise=0.02)
    spherical = plan.spherical_disparity(tiles)
    values = plan.tangents_to_erp(spherical, "depth_edges")  # as the blends read disparity
    weights = plan.tangents_to_erp(plan.blend_weights("frustum"))
    expected = weighted_median_oracle(values, weights)
    got = plan.blend(spherical, {"method": "median"})[0]
    assert (np.isfinite(values).sum(axis=0) >= 3).mean() > 0.9  # the median is what is tested
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=2e-6, equal_nan=True)
    # Through stitch, unaligned: the same numbers.
    np.testing.assert_allclose(m360.stitch(tiles, lay, align="none", blend="median"), got)


def test_median_blend_ignores_one_wild_tangent_where_three_see_a_pixel() -> None:
    width = 256
    lay = m360.Layout.icosahedron(width, padding=0.7)
    exact = syn.tangent_perspective_disparity(scene(1), lay.cameras)
    wild = exact.copy()
    wild[3] *= 5.0
    out = m360.stitch(wild, lay, align="none", blend="median")
    frustum = m360.stitch(wild, lay, align="none", blend="frustum")
    plan = plan_for(lay)
    others = plan.tangents_to_erp(plan.spherical_disparity(exact), "depth_edges")
    seen = np.isfinite(others)
    others[3] = np.nan
    # Where tangent 3 and two or more others see a pixel (and its weight is not the majority),
    # the median is one of the others' values, never the wild one.
    weights = np.where(seen, plan.tangents_to_erp(plan.blend_weights("frustum")), 0.0)
    minority = weights[3] < 0.5 * weights.sum(axis=0)
    three = (seen.sum(axis=0) >= 3) & seen[3] & minority
    assert three.mean() > 0.02
    with np.errstate(invalid="ignore"):
        lo, hi = np.nanmin(others, axis=0), np.nanmax(others, axis=0)
    assert ((out[three] >= lo[three] * (1 - 1e-6)) & (out[three] <= hi[three] * (1 + 1e-6))).all()
    # The weighted mean is pulled far off there.
    assert np.median(frustum[three] / hi[three]) > 1.3


# ------------------------------------------------------------------ content errors' scale


def test_content_errors_reference_area_keeps_angular_size_and_density() -> None:
    exact = tangent_disparity(0, 512)  # (20, 87, 100)
    _, h, w = exact.shape
    # Tiles 4x smaller than the reference: 4 regions per reference tile -> exactly 1 per tile,
    # of 5 % of the reference area = 20 % of the tile (less where the ellipse leaves the tile).
    _, errors = syn.content_errors(exact, 1, regions=(4, 4), size=(0.05, 0.05),
                                   reference_area=4 * h * w, return_regions=True)  # fmt: skip
    covered = (np.abs(errors) > 0).mean(axis=(1, 2))
    assert covered.max() <= 0.2 + 0.01 and covered.max() >= 0.15
    assert (covered > 0).all()
    # Expected 1/4 region per tile: about a quarter of the tiles have one, seeded.
    _, sparse = syn.content_errors(exact, 2, regions=(1, 1), reference_area=4 * h * w,
                                   return_regions=True)  # fmt: skip
    hit = (np.abs(sparse) > 0).any(axis=(1, 2))
    assert 1 <= hit.sum() <= 12
    again = syn.content_errors(exact, 2, regions=(1, 1), reference_area=4 * h * w)
    assert isinstance(again, np.ndarray)
    np.testing.assert_array_equal(np.isnan(again), np.isnan(exact))
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError):
            syn.content_errors(exact, 1, reference_area=bad)


# ------------------------------------------------------------------ the goal, with more overlap


def fair_content_errors(lay: m360.Layout, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Affine-only and content-error tangents of room ``seed`` for ``lay``, the errors of the
    paper layout's angular size, density per solid angle and blur (benches/bench_layouts.py)."""
    width = lay.erp_shape[1]
    paper = m360.Layout.icosahedron(width, padding="paper")
    exact = syn.tangent_perspective_disparity(scene(seed), lay.cameras)
    ratio = lay.cameras[0].fx / paper.cameras[0].fx
    h, w = paper.tangent_shape
    wrong = syn.content_errors(exact, seed + 200, blur=ratio * width / 2048,
                               reference_area=h * w * ratio**2)  # fmt: skip
    affine = dict(scale=(0.5, 2.0), shift=0.3, field=0.1, noise=0.01)
    return (syn.distort(exact, seed + 100, **affine),  # type: ignore[arg-type]
            syn.distort(wrong, seed + 100, **affine))  # type: ignore[arg-type]  # fmt: skip


def test_the_default_layout_meets_the_content_error_goal_on_every_scene() -> None:
    """The default layout (padding 0.7) with the default stitch against the paper's layout
    with least squares + Poisson (the defaults before): better on every room, under content
    errors and under the affine distortion alone, and ≤ 0.025 median under content errors."""
    width = 1024
    paper = m360.Layout.icosahedron(width, padding="paper")
    wide = m360.geometry.default_layout(width)
    assert wide.padding == 0.7
    before = {"loss": "squared", "blend": "poisson"}
    ours = []
    for seed in (0, 1, 2):
        depth = erp_depth(seed, width)

        def err(disparity: np.ndarray, depth: np.ndarray = depth) -> float:
            return float(m360.eval.depth_metrics(disparity, depth)["abs_rel"])

        affine, wrong = fair_content_errors(wide, seed)
        paper_affine = syn.distort(tangent_disparity(seed, width), seed + 100, scale=(0.5, 2.0),
                                   shift=0.3, field=0.1, noise=0.01)  # fmt: skip
        paper_wrong = syn.content_errors(tangent_disparity(seed, width), seed + 200,
                                         blur=width / 2048)  # fmt: skip
        paper_wrong = syn.distort(paper_wrong, seed + 100, scale=(0.5, 2.0), shift=0.3,
                                  field=0.1, noise=0.01)  # fmt: skip
        new = err(m360.stitch(wrong, wide))
        old = err(m360.stitch(paper_wrong, paper, **before))  # type: ignore[arg-type]
        print(f"seed {seed}: content errors, padding 0.7 {new:.4f}, before {old:.4f}")
        assert new < old
        new_affine = err(m360.stitch(affine, wide))
        old_affine = err(m360.stitch(paper_affine, paper, **before))  # type: ignore[arg-type]
        assert new_affine < old_affine
        ours.append(new)
    # Measured 0.0204-0.0275, median 0.0222 (0.0359-0.0408 before).
    assert float(np.median(ours)) <= 0.025
