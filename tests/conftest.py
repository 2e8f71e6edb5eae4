"""Shared fixtures: layouts, synthetic scenes with exact depth, and hypothesis profiles."""

from __future__ import annotations

import functools
import os
import shutil
import tempfile
from collections.abc import Iterator
from datetime import timedelta

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from local_http import LocalServer
from m360.geometry import sphere as sph

# Profiles (``max_examples`` is the budget of a weight-1 fuzz test; test_fuzz.py scales it per
# test). "ci", the default: a few hundred examples over all fuzz tests, well under a minute.
# "slow": >= 10,000 in total. Select with HYPOTHESIS_PROFILE=slow (M360_HYPOTHESIS_PROFILE is
# also read) or ``pytest --hypothesis-profile=slow``. The deadline is per example and generous
# (the machine may be shared); a real hang is caught by test_fuzz.py's watchdog.
_FUZZ_DEADLINE = timedelta(seconds=20)
settings.register_profile(
    "ci", max_examples=30, deadline=_FUZZ_DEADLINE, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("fast", parent=settings.get_profile("ci"))
settings.register_profile(
    "slow",
    max_examples=1000,
    deadline=_FUZZ_DEADLINE,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(
    os.environ.get("HYPOTHESIS_PROFILE") or os.environ.get("M360_HYPOTHESIS_PROFILE") or "ci"
)


def pytest_configure(config: pytest.Config) -> None:
    # Plans built by the tests go to the disk plan cache (on by default) under M360_HOME: keep
    # them out of the user's cache folder unless M360_HOME was chosen explicitly.
    if not os.environ.get("M360_HOME"):
        home = tempfile.mkdtemp(prefix="m360-test-home-")
        os.environ["M360_HOME"] = home
        config.add_cleanup(lambda: shutil.rmtree(home, ignore_errors=True))
    config.addinivalue_line("markers", "fuzz: hypothesis fuzzing of the public API (test_fuzz.py)")


@functools.lru_cache(maxsize=8)
def layout(erp_width: int) -> m360.Layout:
    return m360.Layout.icosahedron(erp_width, padding="paper")  # the tests were written on it


@functools.lru_cache(maxsize=4)
def scene(seed: int) -> syn.Scene:
    return syn.room(seed)


@functools.lru_cache(maxsize=6)
def erp_depth(seed: int, erp_width: int) -> np.ndarray:
    """Exact radial depth (H, W) float64 of scene `seed`, by ray casting every ERP pixel centre."""
    h = erp_width // 2
    return scene(seed).distance(sph.erp_directions(h, erp_width))


@functools.lru_cache(maxsize=6)
def tangent_disparity(seed: int, erp_width: int) -> np.ndarray:
    """Exact perspective disparity (N, h, w) float32 of scene `seed`, by ray casting tangents."""
    return syn.tangent_perspective_disparity(scene(seed), layout(erp_width).cameras)


def smooth_field(d: np.ndarray) -> np.ndarray:
    """A smooth positive function of direction (..., 3) with structure at both poles."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return 2.0 + 0.6 * x + 0.4 * y + 0.3 * x * z - 0.2 * z + 0.25 * y * y


def tangent_directions(lay: m360.Layout) -> np.ndarray:
    """(N, h, w, 3) world directions of every tangent pixel centre (numpy oracle)."""
    return np.stack(
        [
            sph.camera_pixel_directions(c.rotation, c.fx, c.fy, c.cx, c.cy, c.width, c.height)
            for c in lay.cameras
        ]
    )


@pytest.fixture(params=[1, 2], ids=["1-thread", "2-threads"])
def threads(request: pytest.FixtureRequest):
    before = m360.get_num_threads()
    m360.set_num_threads(request.param)
    yield request.param
    m360.set_num_threads(before)


def as_perspective(spherical: np.ndarray, lay: m360.Layout) -> np.ndarray:
    """Tangent values whose spherical disparity is `spherical`: divide by cos(angle to axis)."""
    dirs = tangent_directions(lay)
    cosines = np.stack([dirs[k] @ cam.axis for k, cam in enumerate(lay.cameras)])
    return (spherical / cosines).astype(np.float32)


@pytest.fixture
def server() -> Iterator[LocalServer]:
    """A bounded HTTP server on 127.0.0.1 (see local_http.py), stopped after the test."""
    srv = LocalServer().start()
    try:
        yield srv
    finally:
        srv.stop()
