"""The Ray engine (m360.batch.run(engine="ray"), `m360 run --engine ray`) on a local Ray of 2
CPUs started once for the module: outputs byte-identical to the local engine, bad inputs and a
worker killed mid-run, resume after SIGKILL of the driver, a local run and a Ray run sharing a
folder. The simulated multi-node cluster is in test_ray_cluster.py."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import batch_helpers
import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
import ray_helpers as h
from m360.cli import main

ray = pytest.importorskip("ray")

HERE = Path(__file__).resolve().parent
WATCHDOG_S = 300  # only ever reached when something hangs
GATED = {"align": "none", "blend": "frustum", "progress": False}


@pytest.fixture(scope="module")
def local_ray() -> Iterator[str]:
    """A local Ray of 2 CPUs whose workers can import the test helpers; yields its address."""
    with h.local_ray() as address:
        yield address


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> str:
    # Offset 3: a positive affine disparity even on the dark (clipped) photos, whose tangents
    # m360 would otherwise drop as "wrong sign" (docs/method.md, "Checking the network's output").
    return str(g.affine_of_mean(tmp_path_factory.mktemp("model") / "tiny.onnx", 1.0, 3.0))


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return h.make_photos(tmp_path_factory.mktemp("photos"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory, photos: Path, model: str) -> Path:
    """The local engine's outputs of the photos (the same model without its faults)."""
    out = tmp_path_factory.mktemp("reference")
    m360.batch.run([photos], out, model=h.Faulty(model, crash=False), **h.OPTIONS)
    return out


@pytest.fixture(scope="module")
def ten(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("ten")
    rgb, _ = m360.synthetic.render(m360.synthetic.room(5), 128)
    for k in range(10):
        assert cv2.imwrite(str(folder / f"p{k}.png"), np.roll(rgb, 5 * k, axis=1)[:, :, ::-1])
    return folder


def test_ray_equals_the_local_engine_records_the_bad_inputs_and_survives_a_killed_worker(
    local_ray: str, photos: Path, model: str, reference: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    faults = tmp_path / "faults"
    faults.mkdir()
    seen: list[str] = []
    report = m360.batch.run(
        [photos],
        out,
        model=h.Faulty(model, str(faults)),
        engine="ray",
        on_outcome=lambda o: seen.append(o.input),
        **h.OPTIONS,
    )
    assert report.exit_code == 1
    assert h.failures(out) == h.BAD
    assert len(report.done) == 36 and len(report.failed) == 4
    assert sorted(seen) == sorted(str(p) for p in photos.iterdir())  # each image once
    # The image that killed its worker once was redone.
    assert (faults / "crashed-once").exists()
    assert (out / "z_clipped_77.json").exists()
    assert h.assert_same_outputs(reference, out, skip=frozenset({"z_black"})) == 36
    h.assert_clean(out)
    stages = report.stage_seconds()
    assert all(stages[s] > 0 for s in ("read", "project", "network", "align", "blend", "write"))
    assert "36 done, 0 already done, 4 failed" in report.summary()

    # A rerun skips everything done and tries the failures again.
    again = m360.batch.run(
        [photos], out, model=h.Faulty(model, str(faults)), engine="ray", **h.OPTIONS
    )
    assert (len(again.done), len(again.skipped), len(again.failed)) == (0, 36, 4)
    assert again.exit_code == 1
    h.assert_clean(out)


def test_cli_engine_ray(
    local_ray: str, ten: Path, model: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    args = ["run", str(ten), "-o", str(out), "--model", model, "--input-size", "64", "96"]
    # --edges photo and --subdivisions 1: the Ray engine passes the photo, the option and the
    # layout as the local one does.
    fast = ["--align", "none", "--blend", "frustum", "--edges", "photo", "--no-progress"]
    fast += ["--subdivisions", "1"]
    # Two model actors of 1 CPU would leave the 2-CPU cluster no CPU for the other stages.
    code = main([*args, *fast, "-o", str(tmp_path / "none"), "--engine", "ray", "--workers", "2"])
    assert code == 2
    assert "the Ray cluster has 2 CPUs" in capsys.readouterr().err
    code = main([*args, *fast, "--engine", "ray", "--cpus-per-stitch", "1"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "10 done, 0 already done, 0 failed" in err
    local = tmp_path / "local"
    assert main([*args, *fast, "-o", str(local), "--threads", "1"]) == 0
    for file in local.glob("*.npy"):
        assert file.read_bytes() == (out / file.name).read_bytes()
    disparity = sorted(out.glob("*.disparity.npy"))[0]
    sidecar = json.loads(disparity.with_name(disparity.name.split(".")[0] + ".json").read_text())
    assert "80 cameras" in sidecar["options"]["layout"]
    assert main([*args, *fast, "--engine", "ray"]) == 0
    assert "0 done, 10 already done" in capsys.readouterr().err
    # Bad Ray options are usage errors, before any image runs.
    for bad in (["--gpus-per-model", "-1"], ["--cpus-per-stitch", "0"]):
        assert main([*args, "-o", str(tmp_path / "none"), "--engine", "ray", *bad]) == 2
        assert "must be a number" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path / "none"), "--cpus-per-stitch", "2"]) == 2
    assert "engine='ray' only" in capsys.readouterr().err


def test_import_m360_does_not_import_ray() -> None:
    code = "import sys, m360, m360.batch, m360.cli; assert 'ray' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=WATCHDOG_S)


class _Driver:
    """A Ray run in another process (a driver of the module's Ray) into ``tmp/out`` with the
    Gated estimator (its FIFOs ``started`` and ``tokens`` in ``tmp/gate``), whose JSON lines
    are read as they come (a watchdog fails the test if none comes). A context manager: on
    exit the driver is killed if still running and the FIFOs are closed."""

    def __init__(self, address: str, photos: Path, tmp: Path) -> None:
        gate = tmp / "gate"
        gate.mkdir()
        self.started, self.tokens = batch_helpers.make_gate(str(gate))
        self.out = out = tmp / "out"
        env = {**os.environ, "RAY_ADDRESS": address}
        job = [
            sys.executable,
            str(HERE / "ray_jobs.py"),
            "driver",
            str(photos),
            str(out),
            str(gate),
        ]
        self.proc = subprocess.Popen(job, env=env, stdout=subprocess.PIPE)
        assert self.proc.stdout is not None
        self.fd = self.proc.stdout.fileno()
        self.buffer = b""

    def line(self) -> dict[str, Any]:
        while True:
            while b"\n" not in self.buffer:
                ready, _, _ = select.select([self.fd], [], [], WATCHDOG_S)
                assert ready, "the Ray driver printed nothing for a long time"
                chunk = os.read(self.fd, 65536)
                assert chunk, f"the Ray driver ended early (exit {self.proc.wait()})"
                self.buffer += chunk
            line, _, self.buffer = self.buffer.partition(b"\n")
            if line.startswith(b"{"):  # Ray prints messages of its own to stdout too
                return dict(json.loads(line))

    def __enter__(self) -> _Driver:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(WATCHDOG_S)
        assert self.proc.stdout is not None
        self.proc.stdout.close()
        os.close(self.started)
        os.close(self.tokens)


def _read_byte(fd: int) -> None:
    ready, _, _ = select.select([fd], [], [], WATCHDOG_S)
    assert ready, "the network was never reached"
    assert os.read(fd, 1)


def test_rerun_after_sigkill_of_the_driver_does_only_the_rest(
    local_ray: str, ten: Path, tmp_path: Path
) -> None:
    with _Driver(local_ray, ten, tmp_path) as driver:
        os.write(driver.tokens, b"ttt")  # three images may pass the network, the fourth waits
        done = [driver.line() for _ in range(3)]
        assert [d["outcome"] for d in done] == ["done"] * 3
        driver.proc.send_signal(signal.SIGKILL)  # no image is being written: the fourth waits
        driver.proc.wait(WATCHDOG_S)
    out = driver.out
    finished = {p.name: p.stat().st_mtime_ns for p in out.glob("*.json")}
    assert sorted(finished) == sorted(f"{Path(d['input']).stem}.json" for d in done)
    report = m360.batch.run([ten], out, model=batch_helpers.Gated(None), engine="ray", **GATED)
    assert (len(report.done), len(report.skipped), report.exit_code) == (7, 3, 0)
    assert {
        p.name: p.stat().st_mtime_ns for p in out.glob("*.json") if p.name in finished
    } == finished
    assert len(list(out.glob("*.json"))) == 10
    h.assert_clean(out)


def test_a_local_run_and_a_ray_run_share_a_folder(
    local_ray: str, ten: Path, tmp_path: Path
) -> None:
    with _Driver(local_ray, ten, tmp_path) as driver:
        # The Ray run has claimed its first images and waits in the network on the first.
        _read_byte(driver.started)
        local = m360.batch.run([ten], driver.out, model=batch_helpers.Gated(None), **GATED)
        os.write(driver.tokens, b"t" * 10)
        lines = [driver.line() for _ in range(11)]
        assert driver.proc.wait(WATCHDOG_S) == 0
    out = driver.out
    counts = lines[-1]["report"]
    # The local run ended while the Ray run was still writing its images: exit 3, rerun.
    assert local.exit_code == m360.batch.runner.EXIT_BUSY == 3 and counts["exit_code"] == 0
    assert len(local.busy) >= 1 and len(local.done) >= 1
    assert counts["done"] == len(local.busy) and counts["skipped"] == len(local.done)
    assert len(list(out.glob("*.json"))) == 10
    assert not (out / "failures.jsonl").exists()
    h.assert_clean(out)


def test_ctrl_c_of_the_driver_stops_cleanly_and_a_rerun_finishes(
    local_ray: str, ten: Path, tmp_path: Path
) -> None:
    with _Driver(local_ray, ten, tmp_path) as driver:
        os.write(driver.tokens, b"tt")
        assert [driver.line()["outcome"] for _ in range(2)] == ["done", "done"]
        driver.proc.send_signal(signal.SIGINT)  # the third image waits in the network
        report = driver.line()["report"]
        assert driver.proc.wait(WATCHDOG_S) == 0
    out = driver.out
    assert (report["done"], report["exit_code"]) == (2, 130)
    h.assert_clean(out)  # no claim left, no partial file
    again = m360.batch.run([ten], out, model=batch_helpers.Gated(None), engine="ray", **GATED)
    assert (len(again.done), len(again.skipped), again.exit_code) == (8, 2, 0)
