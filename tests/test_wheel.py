"""The release wheel and the sdist, installed the way a user installs them (issue 12 §1).

``make wheel`` builds ``dist/m360-VERSION-cp310-abi3-manylinux_2_28_x86_64.whl`` (one stable-ABI
wheel for every CPython >= 3.10, linked by zig against glibc 2.28) and the sdist. This module runs
it (a no-op when dist/ is up to date: CI runs ``make wheel`` just before ``make test``), checks
the wheel's tags with auditwheel, installs the wheel into a fresh virtual environment of every
CPython >= 3.10 on the machine (the running one, and pyenv's) with no Rust toolchain on PATH, and
runs ``m360 demo`` and an API smoke test there, whose result must equal this process's (m360
built from source). Finally the sdist is built from nothing (``pip install m360-*.tar.gz``, with
the Rust toolchain) in one more environment. All installs share one pip cache and prefer binary
wheels. Several minutes: deselect with ``-m "not wheel"``.
"""

from __future__ import annotations

import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import m360
import numpy as np
import pytest

pytestmark = pytest.mark.wheel

ROOT = Path(__file__).resolve().parents[1]
DIST = ROOT / "dist"
BIN = "Scripts" if os.name == "nt" else "bin"
EXE = ".exe" if os.name == "nt" else ""
SMOKE_WIDTH = 256  # the API smoke test's panorama (W x W/2)
DEMO_WIDTH = 512  # `m360 demo --width`: the whole demo pipeline, kept short


def _version_of(name: str) -> tuple[int, int, int] | None:
    m = re.fullmatch(r"(\d+)\.(\d+)\.(\d+)", name)  # CPython releases only: no 3.13t, no -dev
    return (int(m[1]), int(m[2]), int(m[3])) if m else None


def interpreters() -> dict[str, str]:
    """One interpreter per CPython minor version >= 3.10: the running one, and pyenv's newest."""
    found = {f"{sys.version_info.major}.{sys.version_info.minor}": sys.executable}
    root = Path(os.environ.get("PYENV_ROOT") or Path.home() / ".pyenv") / "versions"
    candidates = sorted(
        ((v, d) for d in (root.iterdir() if root.is_dir() else ()) if (v := _version_of(d.name))),
        reverse=True,
    )
    for version, folder in candidates:
        exe = folder / BIN / "python"
        minor = f"{version[0]}.{version[1]}"
        if version >= (3, 10, 0) and minor not in found and exe.is_file():
            found[minor] = str(exe)
    return dict(sorted(found.items(), key=lambda kv: tuple(map(int, kv[0].split(".")))))


INTERPRETERS = interpreters()


# --- environments ------------------------------------------------------------------------------


def _rust_dir(entry: str) -> bool:
    return any((Path(entry) / f"{tool}{EXE}").exists() for tool in ("cargo", "rustc"))


def clean_env(venv: Path | None, *, rust: bool) -> dict[str, str]:
    """The environment a user's shell would give: the venv first on PATH, the test run's own venv
    and (unless `rust`) every folder holding cargo/rustc removed, no build variables."""
    drop = ("PYO3", "MATURIN", "PYTHON") + (() if rust else ("CARGO", "RUSTUP", "RUSTC"))
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(drop)
        and k not in {"VIRTUAL_ENV", "PIP_REQUIRE_VIRTUALENV", "PIP_NO_CACHE_DIR"}
    }
    own_bin = str(Path(sys.prefix) / BIN)
    entries = [e for e in env.get("PATH", "").split(os.pathsep) if e and e != own_bin]
    if not rust:
        entries = [e for e in entries if not _rust_dir(e)]
    if venv is not None:
        entries.insert(0, str(venv / BIN))
        env["VIRTUAL_ENV"] = str(venv)
    env["PATH"] = os.pathsep.join(entries)
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    env["M360_OFFLINE"] = "1"  # nothing here may need a download of a model
    return env


def run(
    cmd: list[Any], *, env: dict[str, str], cwd: Path | None = None, timeout: float = 900
) -> subprocess.CompletedProcess[str]:
    """Run `cmd`; on failure, fail the test with the tail of its output."""
    proc = subprocess.run(
        [str(c) for c in cmd],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    if proc.returncode != 0:
        out = (proc.stdout + proc.stderr)[-6000:]
        pytest.fail(f"exit {proc.returncode}: {' '.join(map(str, cmd))}\n{out}", pytrace=False)
    return proc


def pip_cache() -> str:
    """The one pip cache every install of this module shares (the running pip's)."""
    cache = os.environ.get("PIP_CACHE_DIR")
    if cache:
        return cache
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "cache", "dir"], capture_output=True, text=True, check=False
    )
    return proc.stdout.strip() or str(Path.home() / ".cache" / "pip")


def make_venv(python: str, where: Path, *, rust: bool) -> tuple[Path, dict[str, str]]:
    run([python, "-m", "venv", where], env=clean_env(None, rust=rust))
    env = clean_env(where, rust=rust)
    return where, env


def pip_install(venv: Path, env: dict[str, str], *what: str | Path) -> float:
    """Install into `venv` with its own pip; return the seconds it took."""
    t0 = time.perf_counter()
    pip = [venv / BIN / "python", "-m", "pip", "install", "--prefer-binary"]
    run([*pip, "--cache-dir", pip_cache(), *what], env=env)
    return time.perf_counter() - t0


# --- the wheel ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dist() -> dict[str, Path]:
    """dist/'s wheel and sdist of this version, built by `make wheel` unless up to date."""
    if shutil.which("make") is None:
        pytest.skip("`make` is not on PATH: run `make wheel` to build dist/")
    cmd = ["make", "-s", "wheel"]
    if sys.prefix != sys.base_prefix:  # run by a venv's pytest: build with that venv's tools
        cmd += [f"VENV={sys.prefix}", f"PYTHON={sys.executable}"]
    run(cmd, env=clean_env(None, rust=True), cwd=ROOT, timeout=1800)
    version = m360.__version__
    wheels = sorted(DIST.glob(f"m360-{version}-*.whl"))
    sdists = sorted(DIST.glob(f"m360-{version}.tar.gz"))
    assert len(wheels) == 1, f"expected one wheel of m360 {version} in dist/, found {wheels}"
    assert len(sdists) == 1, f"expected the sdist m360-{version}.tar.gz in dist/, found {sdists}"
    return {"wheel": wheels[0], "sdist": sdists[0]}


@pytest.fixture(scope="module")
def sdist_build(
    dist: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[dict[str, Any]]:
    """`pip install m360-VERSION.tar.gz` into a fresh venv, started in the background.

    The source build takes most of this module's time: the first test asks for it so that it
    overlaps the wheel installs; test_sdist_builds_from_nothing waits for it. It needs the Rust
    toolchain. CARGO_TARGET_DIR is target/ of this checkout, where `make install` built the
    extension: the crates.io dependencies compiled there are reused (the same lock file, features
    and profile), which saves 3-4 min on 2 cores. m360's own crates are always compiled from the
    sdist's unpacked sources: their path is part of their identity, so a missing file fails the
    build."""
    env = clean_env(None, rust=True)
    if shutil.which("cargo", path=env["PATH"]) is None:
        yield {"skip": "no cargo on PATH: building the sdist needs the Rust toolchain"}
        return
    folder = tmp_path_factory.mktemp("sdist")
    venv, env = make_venv(sys.executable, folder / "venv", rust=True)
    env["CARGO_TARGET_DIR"] = str(ROOT / "target")
    pip = [venv / BIN / "python", "-m", "pip", "install", "--prefer-binary"]
    cmd = [*pip, "--cache-dir", pip_cache(), dist["sdist"]]
    log = (folder / "pip.log").open("w")
    proc = subprocess.Popen(
        [str(c) for c in cmd], env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    build = {"venv": venv, "env": env, "proc": proc, "log": folder / "pip.log", "cmd": cmd}
    build["t0"] = time.perf_counter()
    try:
        yield build
    finally:
        if proc.poll() is None:  # the module failed or was interrupted before waiting for it
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
        log.close()


def test_wheel_tags_and_contents(dist: dict[str, Path], sdist_build: dict[str, Any]) -> None:
    wheel = dist["wheel"]
    version = m360.__version__
    _name, _ver, python_tag, abi_tag, platform_tag = wheel.stem.split("-")
    assert (python_tag, abi_tag) == ("cp310", "abi3"), wheel.name
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        meta = zf.read(f"m360-{version}.dist-info/WHEEL").decode()
        entry_points = zf.read(f"m360-{version}.dist-info/entry_points.txt").decode()
    assert f"Tag: cp310-abi3-{platform_tag}" in meta
    assert "m360=m360.cli:main" in entry_points.replace(" ", "")
    extensions = [n for n in names if n.startswith("m360/_core")]
    assert sorted(extensions) in (
        ["m360/_core.abi3.so", "m360/_core.pyi"],
        ["m360/_core.pyd", "m360/_core.pyi"],
    ), extensions
    assert {"m360/__init__.py", "m360/py.typed", "m360/cli.py"} <= names
    assert not any(n.startswith(("tests/", "rust/", "target/", "python/")) for n in names)
    if sys.platform != "linux":
        return
    assert platform_tag == f"manylinux_2_28_{platform.machine()}", wheel.name
    # auditwheel: the glibc symbols the extension needs must be allowed by the tag it carries.
    audit = run([sys.executable, "-m", "auditwheel", "show", wheel], env=clean_env(None, rust=True))
    print(audit.stdout)
    text = " ".join(audit.stdout.split())
    m = re.search(r'constrains the platform tag to "manylinux_(\d+)_(\d+)_\w+"', text)
    assert m, text
    needed = (int(m[1]), int(m[2]))
    assert needed <= (2, 28), f"the extension needs glibc {needed}, the wheel claims 2.28: {text}"
    assert f'consistent with the following platform tag: "manylinux_{m[1]}_{m[2]}_' in text


# --- the smoke test, in this process (source build) and in each venv (wheel) -------------------

SMOKE = '''
"""m360.estimate on a small synthetic panorama; the network's tiles come from the test."""
import sys

import numpy as np

import m360


class Replay:
    output_kind = "affine_disparity"

    def __init__(self, tiles):
        self.tiles = tiles

    def predict(self, tiles):
        assert tiles.shape[:3] == self.tiles.shape, (tiles.shape, self.tiles.shape)
        return self.tiles


def smoke(inputs):
    data = np.load(inputs)
    rgb = data["rgb"]
    res = m360.estimate(rgb, Replay(data["tiles"]))
    disparity = np.asarray(res.disparity)
    assert disparity.shape == rgb.shape[:2], disparity.shape
    assert disparity.dtype == np.float32, disparity.dtype
    assert np.isfinite(disparity).all() and (disparity > 0).all()
    return disparity


if __name__ == "__main__":
    np.save(sys.argv[2], smoke(sys.argv[1]))
    print(m360.__version__, m360.__file__, m360._core.__file__)
'''


@pytest.fixture(scope="module")
def smoke(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path | np.ndarray]:
    """The smoke script, its inputs and the result of this process's m360 (the source build)."""
    from m360.estimators import SimulatedEstimator

    folder = tmp_path_factory.mktemp("smoke")
    layout = m360.Layout.icosahedron(SMOKE_WIDTH)
    scene = m360.synthetic.room(0)
    rgb, _ = m360.synthetic.render(scene, SMOKE_WIDTH)
    tiles = SimulatedEstimator(scene, layout, seed=0, noise=0.01).predict(
        m360.erp_to_tangents(rgb, layout)
    )
    np.savez(folder / "inputs.npz", rgb=rgb, tiles=tiles)
    (folder / "smoke.py").write_text(SMOKE)
    namespace: dict = {}
    exec(compile(SMOKE, "smoke.py", "exec"), namespace)
    reference = namespace["smoke"](folder / "inputs.npz")
    return {"script": folder / "smoke.py", "inputs": folder / "inputs.npz", "reference": reference}


def check_installed(venv: Path, env: dict[str, str], smoke: dict, tmp: Path) -> None:
    """`m360 demo` and the API smoke test in `venv`, whose m360 must be its own."""
    python = venv / BIN / "python"
    out = tmp / "demo"
    demo = run([venv / BIN / "m360", "demo", "--width", DEMO_WIDTH, "-o", out], env=env, cwd=tmp)
    assert "vs true depth" in demo.stdout, demo.stdout
    assert (out / "demo.json").is_file() and (out / "demo.disparity.npy").is_file()
    result = tmp / "disparity.npy"
    proc = run([python, smoke["script"], smoke["inputs"], result], env=env, cwd=tmp)
    _version, module, core = proc.stdout.split()
    assert Path(module).resolve().is_relative_to(venv.resolve()), module
    assert Path(core).resolve().is_relative_to(venv.resolve()), core
    got = np.load(result)
    np.testing.assert_array_equal(got, smoke["reference"])


@pytest.mark.skipif(not INTERPRETERS, reason="no CPython >= 3.10 found (running one nor pyenv's)")
@pytest.mark.parametrize("minor", list(INTERPRETERS))
def test_wheel_installs_and_runs_without_rust(
    minor: str, dist: dict[str, Path], smoke: dict, tmp_path: Path
) -> None:
    python = INTERPRETERS[minor]
    venv, env = make_venv(python, tmp_path / "venv", rust=False)
    for tool in ("cargo", "rustc"):
        assert shutil.which(tool, path=env["PATH"]) is None, f"{tool} is on the venv's PATH"
    seconds = pip_install(venv, env, dist["wheel"])
    print(f"CPython {minor}: wheel installed in {seconds:.1f} s")
    version = run([venv / BIN / "python", "--version"], env=env).stdout.split()[1]
    assert version.startswith(f"{minor}."), (minor, version)
    no_rust = "import shutil, sys; sys.exit(shutil.which('cargo') or shutil.which('rustc'))"
    run([venv / BIN / "python", "-c", no_rust], env=env)
    check_installed(venv, env, smoke, tmp_path)


def test_sdist_builds_from_nothing(
    sdist_build: dict[str, Any], smoke: dict, tmp_path: Path
) -> None:
    """The sdist builds with pip in a fresh venv (see sdist_build), and that m360 runs too."""
    if "skip" in sdist_build:
        pytest.skip(sdist_build["skip"])
    proc = sdist_build["proc"]
    proc.wait(timeout=1800)
    seconds = time.perf_counter() - sdist_build["t0"]
    if proc.returncode != 0:
        out = sdist_build["log"].read_text()[-6000:]
        cmd = " ".join(map(str, sdist_build["cmd"]))
        pytest.fail(f"exit {proc.returncode}: {cmd}\n{out}", pytrace=False)
    print(f"sdist built and installed in {seconds:.1f} s (overlapping the wheel tests)")
    check_installed(sdist_build["venv"], sdist_build["env"], smoke, tmp_path)
