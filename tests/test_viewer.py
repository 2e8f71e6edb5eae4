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
