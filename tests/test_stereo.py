"""m360.stereo (omnidirectional stereo) against ray-cast eyes, its file and its plumbing.

The oracle: on m360.synthetic rooms, each eye pixel's ray is cast from its own origin on the
viewing circle (radius ipd/2 faded towards the poles, tangent to the ray seen from above), with
Scene.shade/intersect(origins=...). The warp must match those eyes outside the pixels it filled
(PSNR, SSIM), far better than the centre view does; the filled pixels must be those the eyes see
and the centre cannot (the ray-cast hit point hidden from the centre).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import cv2
import m360
import numpy as np
import pytest
from m360.geometry.sphere import erp_latitudes, erp_longitudes, lonlat_to_directions
from m360.io import gpano

WIDTH = 512
SEED = 1


def fade(lat: np.ndarray, ipd: float, start_deg: float) -> np.ndarray:
    """The viewing circle's radius per latitude: ipd/2, then a half cosine to 0 at the poles."""
    a = np.abs(lat)
    start = np.radians(start_deg)
    t = np.clip((a - start) / max(np.pi / 2 - start, 1e-12), 0.0, 1.0)
    return np.where(a <= start, ipd / 2, ipd / 2 * 0.5 * (1 + np.cos(np.pi * t)))


def eye_rays(width: int, ipd: float, start_deg: float, sign: float) -> tuple[np.ndarray, ...]:
    height = width // 2
    lon = erp_longitudes(width)[None, :]
    lat = erp_latitudes(height)[:, None]
    dirs = lonlat_to_directions(lon, lat)
    east = np.stack([np.cos(lon), np.zeros_like(lon), -np.sin(lon)], axis=-1)
    origins = sign * fade(lat, ipd, start_deg)[..., None] * east
    return dirs, np.broadcast_to(origins, dirs.shape).copy()


def ray_cast_eye(scene, width, ipd, start_deg, sign):
    """(rgb, seen-from-centre mask) of one ODS eye by ray casting from the viewing circle."""
    dirs, origins = eye_rays(width, ipd, start_deg, sign)
    rgb = scene.shade(dirs, origins)
    hit = scene.intersect(dirs, origins)
    reach = np.linalg.norm(hit.point, axis=-1)
    towards = hit.point / reach[..., None]
    visible = scene.distance(towards) >= reach * (1 - 1e-6) - 1e-6
    return rgb, visible


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    err = (a.astype(np.float64) - b.astype(np.float64))[mask]
    return float(10 * np.log10(255.0**2 / max(np.mean(err**2), 1e-12)))


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Mean SSIM (Wang et al. 2004: 11-tap gaussian of sigma 1.5) of the grey images in mask."""
    x = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(np.float64)
    y = cv2.cvtColor(b, cv2.COLOR_RGB2GRAY).astype(np.float64)

    def blur(v: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(v, (11, 11), 1.5)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return float(s[mask].mean())


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    wrapped = np.concatenate([mask[:, -radius:], mask, mask[:, :radius]], axis=1)
    return cv2.dilate(wrapped.astype(np.uint8), kernel)[:, radius:-radius].astype(bool)


@pytest.fixture(scope="module")
def scene() -> m360.synthetic.Scene:
    return m360.synthetic.room(SEED)


@pytest.fixture(scope="module")
def centre(scene) -> tuple[np.ndarray, np.ndarray]:
    return m360.synthetic.render(scene, WIDTH)


@pytest.fixture(scope="module")
def eyes(scene) -> dict[float, tuple[np.ndarray, np.ndarray]]:
    """Ray-cast left (-1) and right (+1) eyes at ipd 0.064, fade from 60°."""
    return {s: ray_cast_eye(scene, WIDTH, 0.064, 60.0, s) for s in (-1.0, 1.0)}


def test_scene_rays_from_origins_match_the_centre_camera(scene):
    # Rays from the origin itself: the same as without origins; from a shifted origin, the hit
    # point lies on the ray and on the surface the centre sees in that point's direction.
    dirs = lonlat_to_directions(erp_longitudes(64)[None, :], erp_latitudes(32)[:, None])
    plain = scene.intersect(dirs)
    same = scene.intersect(dirs, np.zeros(3))
    np.testing.assert_allclose(plain.distance, same.distance, rtol=1e-12)
    np.testing.assert_array_equal(scene.shade(dirs), scene.shade(dirs, np.zeros(3)))
    origin = np.array([0.05, -0.02, 0.03])
    moved = scene.intersect(dirs, origin)
    np.testing.assert_allclose(moved.point, origin + moved.distance[..., None] * dirs, atol=1e-9)
    np.testing.assert_allclose(scene.distance(dirs, origin), moved.distance)
    with pytest.raises(m360.InputError, match="inside the room"):
        scene.intersect(dirs, np.array([1e3, 0.0, 0.0]))


def test_true_depth_matches_ray_cast_eyes(scene, centre, eyes):
    rgb, depth = centre
    pair = m360.stereo(depth, rgb, ipd=0.064)
    for eye, holes, sign in (
        (pair.left, pair.left_holes, -1.0),
        (pair.right, pair.right_holes, 1.0),
    ):
        truth, _ = eyes[sign]
        keep = ~dilate(holes, 1)
        warped = psnr(eye, truth, keep)  # measured 38.7 and 39.4 dB
        unwarped = psnr(rgb, truth, keep)  # the centre view as the eye: 29.2 and 29.4 dB
        assert warped > 35.0 and warped > unwarped + 6.0, (warped, unwarped)
        # measured 0.980 and 0.981 against 0.865 and 0.867
        assert ssim(eye, truth, keep) > 0.97 > 0.9 > ssim(rgb, truth, keep)


def test_holes_are_what_the_centre_cannot_see(scene, centre):
    # A wide IPD (0.2 m) opens disocclusions several pixels wide at 512 x 256.
    rgb, depth = centre
    pair = m360.stereo(depth, rgb, ipd=0.2)
    for eye, holes, sign in (
        (pair.left, pair.left_holes, -1.0),
        (pair.right, pair.right_holes, 1.0),
    ):
        truth, visible = ray_cast_eye(scene, WIDTH, 0.2, 60.0, sign)
        hidden = ~visible
        assert hidden.sum() > 200
        # Nearly every hidden pixel is filled (or next to a filled one), and nearly every
        # filled pixel is hidden (or next to a hidden one): measured 0.97 both ways.
        assert dilate(holes, 1)[hidden].mean() > 0.93
        assert dilate(hidden, 1)[holes].mean() > 0.93
        # Filled from the background: closer to the truth there than the centre view.
        assert psnr(eye, truth, holes) > psnr(rgb, truth, holes) + 3.0
        keep = ~dilate(holes, 1)
        assert psnr(eye, truth, keep) > psnr(rgb, truth, keep) + 10.0  # 37.1 against 24.5 dB


def test_estimated_depth_matches_ray_cast_eyes(scene, centre, eyes):
    rgb, depth = centre
    layout = m360.geometry.default_layout(WIDTH)
    # Per-tangent affine ambiguity and 5 % noise: m360's depth is 1.2 % off (median).
    estimator = m360.estimators.SimulatedEstimator(scene, layout, seed=SEED, noise=0.05)
    camera_height = float(scene.room_max[1])  # the floor is at y = room_max[1]
    result = m360.estimate(rgb, estimator, scale=m360.scale.camera_height(camera_height))
    assert result.units == "metres"
    pair = m360.stereo(result, rgb, ipd=0.064)
    exact = m360.stereo(depth, rgb, ipd=0.064)
    wrong = m360.stereo(depth * 0.25, rgb, ipd=0.064)  # a 4x wrong scale: 4x the parallax
    for eye, holes, sign, true_eye, wrong_eye in (
        (pair.left, pair.left_holes, -1.0, exact.left, wrong.left),
        (pair.right, pair.right_holes, 1.0, exact.right, wrong.right),
    ):
        truth, _ = eyes[sign]
        keep = ~dilate(holes, 1)
        warped = psnr(eye, truth, keep)  # measured 38.5 and 38.9 dB
        assert warped > psnr(rgb, truth, keep) + 6.0  # 29.1 and 29.4 dB
        assert warped > psnr(true_eye, truth, keep) - 1.5  # 38.6 and 39.3 dB
        assert warped > psnr(wrong_eye, truth, keep) + 6.0  # about 25 dB
        assert ssim(eye, truth, keep) > 0.97  # 0.980


def test_zero_ipd_gives_the_input_back(centre):
    rgb, depth = centre
    broken = depth.copy()
    broken[::7, ::5] = np.nan  # NaN depth: drawn at infinity, still the input's colour
    broken[3, :40] = -1.0
    pair = m360.stereo(broken, rgb, ipd=0.0)
    np.testing.assert_array_equal(pair.left, rgb)
    np.testing.assert_array_equal(pair.right, rgb)
    assert pair.filled_fraction == 0.0


def test_seam_and_poles_are_continuous(centre, eyes):
    rgb, depth = centre
    pair = m360.stereo(depth, rgb, ipd=0.064)
    # Turning the panorama by half a turn turns the eyes by as much: nothing depends on where
    # the 0/360° seam is.
    half = WIDTH // 2
    turned = m360.stereo(np.roll(depth, half, axis=1), np.roll(rgb, half, axis=1), ipd=0.064)
    for a, b in ((pair.left, turned.left), (pair.right, turned.right)):
        differ = np.abs(np.roll(a, half, axis=1).astype(int) - b.astype(int)) > 1
        assert differ.mean() < 1e-3
    # Near the seam and the poles the eyes match the ray-cast ones as well as anywhere.
    for eye, holes, sign in (
        (pair.left, pair.left_holes, -1.0),
        (pair.right, pair.right_holes, 1.0),
    ):
        truth, _ = eyes[sign]
        keep = ~dilate(holes, 1)
        seam = np.zeros_like(keep)
        seam[:, :8] = seam[:, -8:] = True
        poles = np.zeros_like(keep)
        poles[:8] = poles[-8:] = True
        overall = psnr(eye, truth, keep)
        assert psnr(eye, truth, keep & seam) > overall - 3.0
        assert psnr(eye, truth, keep & poles) > overall - 3.0
    # At the poles the IPD has faded out: the pole rows are the input's, in both eyes, and
    # each pole row is one ring round the pole (its first and last pixels meet).
    for eye in (pair.left, pair.right):
        for rows in (slice(0, 2), slice(-2, None)):
            assert np.abs(eye[rows].astype(int) - rgb[rows].astype(int)).max() <= 2


def test_threads_do_not_change_the_result(centre):
    rgb, depth = centre
    before = m360.get_num_threads()
    try:
        m360.set_num_threads(1)
        one = m360.stereo(depth, rgb, ipd=0.1)
        m360.set_num_threads(3)
        three = m360.stereo(depth, rgb, ipd=0.1)
    finally:
        m360.set_num_threads(before)
    np.testing.assert_array_equal(one.left, three.left)
    np.testing.assert_array_equal(one.right, three.right)
    np.testing.assert_array_equal(one.holes, three.holes)


def test_relative_depth_is_scaled_with_a_warning(centre):
    rgb, depth = centre
    relative = SimpleNamespace(depth=depth * 0.37, units="relative")
    with pytest.warns(UserWarning, match="median distance is 2.5 m"):
        pair = m360.stereo(relative, rgb)
    median = float(np.median(depth * 0.37))
    assert pair.depth_scale == pytest.approx(2.5 / median)
    assert "assumed" in (pair.assumption or "")
    # median_distance= states the scale: no warning, and the same eyes as the metric depth.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stated = m360.stereo(relative, rgb, median_distance=float(np.median(depth)))
    metric = m360.stereo(depth, rgb)
    assert (stated.left != metric.left).mean() < 1e-3
    assert metric.depth_scale == 1.0 and metric.assumption is None


def test_bad_input_is_refused(centre):
    rgb, depth = centre
    with pytest.raises(m360.InputError, match="ipd"):
        m360.stereo(depth, rgb, ipd=-0.1)
    with pytest.raises(m360.InputError, match="pole_fade"):
        m360.stereo(depth, rgb, pole_fade=95)
    with pytest.raises(m360.InputError, match="rgb"):
        m360.stereo(depth, rgb[:, :-2])
    with pytest.raises(m360.InputError, match="W == 2H"):
        m360.stereo(depth[:, :-2], rgb)
    with pytest.raises(m360.InputError, match="median_distance"):
        m360.stereo(depth, rgb, median_distance=0)
    with pytest.raises(m360.InputError, match="need the panorama"):
        m360.save(SimpleNamespace(depth=depth, disparity=1 / depth), "/tmp/x", formats="stereo")


def read_xmp_with_pillow(path: Path) -> dict[str, str]:
    """GPano fields as Pillow's own XMP reader (defusedxml) finds them: an independent path."""
    PIL = pytest.importorskip("PIL.Image")
    pytest.importorskip("defusedxml")
    with PIL.open(path) as image:
        xmp = image.getxmp()
    description = xmp["xmpmeta"]["RDF"]["Description"]
    return {k: v for k, v in description.items() if isinstance(v, str)}


def test_save_writes_top_bottom_files_with_gpano_stereo_xmp(tmp_path, centre):
    rgb, depth = centre
    result = SimpleNamespace(depth=depth, disparity=1 / depth, units="metres")
    written = m360.save(
        result, tmp_path / "pano", formats=("npy", "stereo", "stereo-png"), rgb=rgb, ipd=0.07
    )
    jpg, png = tmp_path / "pano.stereo.jpg", tmp_path / "pano.stereo.png"
    assert written["stereo.stereo"] == jpg and written["stereo.stereo-png"] == png
    pair = m360.stereo(depth, rgb, ipd=0.07)
    image = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
    assert image.shape == (WIDTH, WIDTH, 3)  # two W x W/2 eyes, top-bottom
    np.testing.assert_array_equal(image[: WIDTH // 2], pair.left)  # left eye on top
    np.testing.assert_array_equal(image[WIDTH // 2 :], pair.right)
    lossy = cv2.cvtColor(cv2.imread(str(jpg)), cv2.COLOR_BGR2RGB)
    assert psnr(lossy, image, np.ones(image.shape[:2], bool)) > 30
    for path in (jpg, png):
        fields = read_xmp_with_pillow(path)
        assert fields["StereoMode"] == "top-bottom"
        assert fields["ProjectionType"] == "equirectangular"
        assert fields["UsePanoramaViewer"] == "True"
        assert (fields["FullPanoWidthPixels"], fields["FullPanoHeightPixels"]) == (
            str(WIDTH),
            str(WIDTH // 2),
        )
        assert fields["CroppedAreaImageHeightPixels"] == str(WIDTH // 2)
        # m360 itself refuses a stereo file as input, naming why.
        with pytest.raises(m360.ReadError, match="StereoMode"):
            gpano.read_gpano(path.read_bytes(), path.name)
    meta = json.loads((tmp_path / "pano.json").read_text())
    assert meta["files"]["stereo"] == {"stereo": jpg.name, "stereo-png": png.name}
    assert meta["stereo"]["ipd_m"] == 0.07
    assert meta["stereo"]["layout"] == "top-bottom, left eye on top"
    assert 0 < meta["stereo"]["filled_fraction"]["left"] < 0.2
    assert m360.io.output_stem(jpg) == tmp_path / "pano"


def test_memory_estimate_covers_stereo():
    without = m360.memory.estimate_memory(2048, formats=("npy",))
    with_stereo = m360.memory.estimate_memory(2048, formats=("npy", "stereo"))
    assert with_stereo > without


@pytest.fixture()
def isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("M360_OFFLINE", "1")


def test_cli_run_writes_stereo_and_reruns_on_a_new_ipd(tmp_path, centre, isolated_cache, capsys):
    import onnx_graphs as g
    from m360.cli import main

    rgb, _ = centre
    small = cv2.resize(rgb, (256, 128), interpolation=cv2.INTER_AREA)
    panorama = tmp_path / "room.png"
    cv2.imwrite(str(panorama), cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    out = tmp_path / "out"
    base = ["run", str(panorama), "-o", str(out), "--model", str(model), "--formats", "npy,stereo"]
    fast = ["--align", "none", "--blend", "mean", "--input-size", "64", "96", "--no-progress"]
    with pytest.warns(UserWarning, match="relative depth"):
        code = main([*base, *fast, "--ipd", "0.1", "--pole-fade", "70"])
    assert code == 0, capsys.readouterr().err
    meta = json.loads((out / "room.json").read_text())
    assert meta["stereo"]["ipd_m"] == 0.1 and meta["stereo"]["pole_fade_deg"] == 70.0
    assert meta["batch"]["fingerprint"]["stereo"]["ipd"] == 0.1
    first = (out / "room.stereo.jpg").read_bytes()
    # The same options: skipped; another IPD: redone.
    assert main([*base, *fast, "--ipd", "0.1", "--pole-fade", "70"]) == 0
    assert (out / "room.stereo.jpg").read_bytes() == first
    with pytest.warns(UserWarning, match="relative depth"):
        assert main([*base, *fast, "--ipd", "0.2", "--pole-fade", "70"]) == 0
    assert json.loads((out / "room.json").read_text())["stereo"]["ipd_m"] == 0.2
    assert main([*base, *fast, "--ipd", "-1"]) == 2


@pytest.mark.parametrize("engine", ["local", "ray"])
def test_batch_engines_write_the_same_stereo(tmp_path, centre, isolated_cache, engine):
    if engine == "ray":
        ray = pytest.importorskip("ray")
    import onnx_graphs as g

    rgb, _ = centre
    folder = tmp_path / "in"
    folder.mkdir()
    small = cv2.resize(rgb, (256, 128), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(folder / "room.png"), cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
    model = g.affine_of_mean(tmp_path / "m.onnx", 1.0, 0.1)
    options = {
        "formats": ("npy", "stereo-png"),
        "align": "none",
        "blend": "mean",
        "input_size": (64, 96),
        "progress": False,
        "median_distance": 2.0,
        "ipd": 0.08,
    }
    if engine == "ray":
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        report = m360.batch.run(
            [folder], tmp_path / engine, model=str(model), engine=engine, **options
        )
    finally:
        if engine == "ray":
            ray.shutdown()
    assert report.exit_code == 0
    saved = m360.load(tmp_path / engine / "room")
    expected = m360.stereo(saved, small, ipd=0.08, median_distance=2.0)
    image = cv2.cvtColor(cv2.imread(str(tmp_path / engine / "room.stereo.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(image, expected.top_bottom())
