"""``m360 view`` in a real browser: headless Chromium opens the page and shows the cloud."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import cv2
import m360
import m360.synthetic as syn
import m360.viewer as viewer
import numpy as np
import pytest
from browser import chromium, chromium_path, missing_browser, read_line

pytest.importorskip("viser")
pytest.importorskip("trimesh")

#: Saturated colours of the test panorama, in 12 bands of 30° of longitude.
BANDS = np.array(
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [0, 255, 255], [255, 0, 255]],
    np.uint8,
)
WATCHDOG_S = 180.0


def banded_output(stem, width: int = 512) -> None:
    scene = syn.Scene(room_min=np.array([-2.0, -1.3, -3.0]), room_max=np.array([3.0, 1.5, 2.0]))
    _, depth = syn.render(scene, width)
    rgb = np.ascontiguousarray(
        np.broadcast_to(BANDS[(np.arange(width) * 12 // width) % 6][None], (width // 2, width, 3))
    )

    class Result:
        disparity = (1.0 / depth).astype(np.float32)

    Result.depth = depth
    m360.save(Result(), stem, formats=("npy", "ply"), rgb=rgb)


def colour_shares(image: np.ndarray) -> np.ndarray:
    """Share of the screenshot's pixels within 60 (RGB distance) of each band colour."""
    diff = image[:, :, None, :].astype(np.int32) - BANDS[None, None].astype(np.int32)
    near = np.sqrt((diff**2).sum(-1)) < 60
    return near.reshape(-1, len(BANDS)).mean(axis=0)  # type: ignore[no-any-return]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_load_scene_and_subsample(tmp_path):
    banded_output(tmp_path / "pano", width=64)
    scene = viewer.load_scene(tmp_path / "pano")
    assert scene.xyz.shape == (64 * 32, 3) and scene.faces is None
    assert {tuple(c) for c in scene.rgb} == {tuple(c) for c in BANDS}  # the panorama's colours
    small = viewer.subsample(scene, 100)
    assert 50 < len(small.xyz) <= 100
    np.testing.assert_array_equal(small.xyz, scene.xyz[:: -(-len(scene.xyz) // 100)])
    by_depth = viewer.load_scene(tmp_path / "pano.depth.npy", colour="depth")
    assert len({tuple(c) for c in by_depth.rgb}) > 10
    meshed = viewer.load_scene(tmp_path / "pano", mesh=True)
    assert meshed.faces is not None and viewer.subsample(meshed, 10) is meshed
    with pytest.raises(m360.ReadError):
        viewer.load_scene(tmp_path / "nothing")


def test_view_in_headless_chromium(tmp_path):
    if chromium_path() is None:
        # .ci/run sets M360_REQUIRE_BROWSER where it found or installed a browser.
        if os.environ.get("M360_REQUIRE_BROWSER"):
            pytest.fail(f"{missing_browser()}, and M360_REQUIRE_BROWSER is set")
        pytest.skip(missing_browser())
    deadline = time.monotonic() + WATCHDOG_S
    banded_output(tmp_path / "pano")
    port = free_port()
    cmd = [sys.executable, "-c", "from m360.cli import main; raise SystemExit(main())"]
    server = subprocess.Popen(
        [*cmd, "view", str(tmp_path / "pano"), "--no-browser", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        line = read_line(server.stdout, lambda s: s.startswith("m360 view: http"), deadline)
        url = line.split()[2]
        assert url.startswith("http://127.0.0.1:")
        with chromium(tmp_path / "profile", deadline) as page:
            page.call("Page.navigate", deadline, url=url)
            page.wait_event("Page.loadEventFired", deadline)
            # Ready when the drawing area shows the cloud: poll screenshots until it does, under
            # the watchdog (WebGL in SwiftShader takes as long as it takes).
            while True:
                shot = page.screenshot(deadline)
                shares = colour_shares(shot)
                if shares.sum() > 0.2 and (shares > 0.01).sum() >= 2:
                    break
                if time.monotonic() > deadline:
                    break
            cv2.imwrite(str(tmp_path / "viewer.png"), shot[:, :, ::-1])
        assert shot.std() > 10, "the page is blank"
        # Looking forward from the camera over 75°: at least two of the bands' colours, and
        # they fill a good part of the drawing area.
        assert (shares > 0.01).sum() >= 2, f"colour shares {shares.round(3)}"
        assert shares.sum() > 0.2, f"colour shares {shares.round(3)}"
        # The frame: straight ahead (longitude 0) is band 6 (red), to its right band 7
        # (green), to its left band 5 (magenta), as the ERP convention says.
        columns = {}
        for k in (0, 1, 5):
            near = np.abs(shot.astype(int) - BANDS[k].astype(int)).sum(-1) < 100
            columns[k] = np.nonzero(near)[1].mean()
        assert columns[5] < columns[0] < columns[1], columns
        assert abs(columns[0] - shot.shape[1] / 2) < shot.shape[1] / 6
    finally:
        server.terminate()
        server.wait(timeout=30)
        assert server.stdout is not None
        server.stdout.close()


# ------------------------------------------------------------------------------------ splats

#: Correlation (grey levels, outside the page's panels) between the splats drawn by the viewer
#: and the panorama's own perspective view: measured 0.983 (room 3, 256 px) and 0.991 (512 px);
#: the view backwards correlates -0.09, and a wrong field of view (60° or 90° for 75°) 0.47 and
#: 0.62. The mean absolute difference (RGB levels) was 3.4 at 256 px and 2.5 at 512 px: the
#: colours are right too (while the splats fade in it is larger).
SPLAT_CORRELATION = 0.9
SPLAT_MEAN_DIFFERENCE = 10.0


def splat_output(stem, width: int = 512) -> np.ndarray:
    rgb, depth = syn.render(syn.room(3), width)

    class Result:
        disparity = (1.0 / depth).astype(np.float32)

    Result.depth = depth
    m360.save(Result(), stem, formats=("npy", "splat"), rgb=rgb)
    return rgb


def perspective_view(rgb: np.ndarray, height: int, width: int, vfov_deg: float) -> np.ndarray:
    """The panorama seen by a pinhole camera at the centre looking along +z (y down)."""
    f = (height / 2) / np.tan(np.radians(vfov_deg) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    lon = np.arctan2(u / f, 1.0)
    lat = np.arctan2(-v / f, np.hypot(u / f, 1.0))
    h, w = rgb.shape[:2]
    col = ((lon + np.pi) * w / (2 * np.pi) - 0.5).astype(np.float32)
    row = ((np.pi / 2 - lat) * h / np.pi - 0.5).astype(np.float32)
    return cv2.remap(rgb, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def scene_mask(shape: tuple[int, ...]) -> np.ndarray:
    """The drawing area without viser's panels: the notice at the top left, the control panel
    at the top right and the axes at the bottom left (CSS pixels of the 800-wide window)."""
    height, width = shape[:2]
    mask = np.ones((height, width), bool)
    mask[:200, :330] = False
    mask[:290, width - 350 :] = False
    mask[height - 90 :, :90] = False
    return mask


def grey_correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    ga = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)[mask].astype(np.float64)
    gb = cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)[mask].astype(np.float64)
    if ga.std() == 0 or gb.std() == 0:  # a blank page (not drawn yet)
        return 0.0
    return float(np.corrcoef(ga, gb)[0, 1])


def test_load_splat_scene(tmp_path):
    rgb = splat_output(tmp_path / "pano", width=64)
    scene = viewer.load_scene(tmp_path / "pano", splats=True)
    splats = m360.to_splats(m360.load(tmp_path / "pano"), rgb)
    assert scene.covariances is not None and scene.opacity is not None
    assert scene.covariances.shape == (len(splats), 3, 3)
    np.testing.assert_allclose(scene.opacity, 0.95, rtol=1e-5)
    np.testing.assert_array_equal(scene.rgb, rgb.reshape(-1, 3)[splats.pixels])
    assert scene.source.endswith("pano.splat.ply")
    # covariances are symmetric positive semi-definite with the thin axis along the normal
    np.testing.assert_allclose(scene.covariances, scene.covariances.transpose(0, 2, 1), atol=1e-9)
    thin = np.einsum("nij,nj->ni", scene.covariances, splats.normals)
    smallest = np.linalg.eigvalsh(scene.covariances.astype(np.float64))[:, 0]
    np.testing.assert_allclose(thin, splats.normals * smallest[:, None], atol=1e-6)
    # a subsample covers as much: each kept splat is widened by the stride
    small = viewer.subsample(scene, len(splats) // 4)
    step = -(-len(splats) // (len(splats) // 4))
    np.testing.assert_allclose(small.covariances, scene.covariances[::step] * step)
    # without a splat file: the splats of the depth map, coloured by distance
    (tmp_path / "pano.splat.ply").unlink()
    derived = viewer.load_scene(tmp_path / "pano", splats=True)
    assert derived.source.endswith("(depth)") and len(derived.xyz) == len(splats)
    with pytest.raises(m360.InputError):
        viewer.serve(tmp_path / "pano", mesh=True, splats=True, open_browser=False)


def test_view_splats_in_headless_chromium(tmp_path):
    if chromium_path() is None:
        if os.environ.get("M360_REQUIRE_BROWSER"):
            pytest.fail(f"{missing_browser()}, and M360_REQUIRE_BROWSER is set")
        pytest.skip(missing_browser())
    deadline = time.monotonic() + WATCHDOG_S
    rgb = splat_output(tmp_path / "pano", width=256)
    port = free_port()
    cmd = [sys.executable, "-c", "from m360.cli import main; raise SystemExit(main())"]
    server = subprocess.Popen(
        [*cmd, "view", str(tmp_path / "pano"), "--splats", "--no-browser", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        line = read_line(server.stdout, lambda s: s.startswith("m360 view: http"), deadline)
        assert "splats of" in line
        url = line.split()[2]
        with chromium(tmp_path / "profile", deadline) as page:
            page.call("Page.navigate", deadline, url=url)
            page.wait_event("Page.loadEventFired", deadline)
            # Ready when the drawing resembles the view (SwiftShader sorts and draws the
            # splats as slowly as it does), under the watchdog.
            while True:
                shot = page.screenshot(deadline)
                mask = scene_mask(shot.shape)
                # viser's camera: three.js's default vertical field of view, 75°
                ahead = perspective_view(rgb, shot.shape[0], shot.shape[1], 75.0)
                correlation = grey_correlation(shot, ahead, mask)
                difference = float(np.abs(shot.astype(np.int32) - ahead)[mask].mean())
                done = correlation > SPLAT_CORRELATION and difference < SPLAT_MEAN_DIFFERENCE
                if done or time.monotonic() > deadline:  # (the splats fade in)
                    break
            cv2.imwrite(str(tmp_path / "splats.png"), shot[:, :, ::-1])
        behind = perspective_view(np.roll(rgb, rgb.shape[1] // 2, axis=1), *shot.shape[:2], 75.0)
        control = grey_correlation(shot, behind, mask)
        assert correlation > SPLAT_CORRELATION, f"correlation {correlation:.3f}"
        assert difference < SPLAT_MEAN_DIFFERENCE, f"mean difference {difference:.1f}"
        assert control < 0.5, f"the view backwards correlates {control:.3f}"
    finally:
        server.terminate()
        server.wait(timeout=30)
        assert server.stdout is not None
        server.stdout.close()
