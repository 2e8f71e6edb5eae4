"""Batch runs (m360.batch, `m360 run`): bad files, resume, SIGKILL, Ctrl-C, concurrent runs,
manifests, worker crashes. Panoramas are 1024x512, the model a tiny ONNX graph."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import json
import os
import select
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import batch_helpers
import cv2
import m360
import numpy as np
import onnx_graphs as g
import pytest
import real_data
from m360.cli import main

FAST = ["--align", "none", "--blend", "frustum", "--threads", "1", "--input-size", "64", "96"]


@pytest.fixture(autouse=True)
def isolated_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))


@pytest.fixture(scope="module")
def base_rgb() -> np.ndarray:
    rgb, _ = m360.synthetic.render(m360.synthetic.room(3), 256)
    return cv2.resize(rgb, (1024, 512), interpolation=cv2.INTER_LINEAR)


def _panoramas(folder: Path, base: np.ndarray, count: int) -> list[Path]:
    """`count` different 1024x512 panoramas (the room turned about the vertical axis)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(count):
        image = np.roll(base, 37 * k, axis=1)[:, :, ::-1]
        path = folder / f"pano_{k:02d}.{'jpg' if k % 2 else 'png'}"
        assert cv2.imwrite(str(path), image)
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Positive on any photo (3 + the mean of its normalised input): a negative affine disparity
    # is refused as the wrong kind (docs/method.md, "Checking the network's output").
    return g.affine_of_mean(tmp_path_factory.mktemp("model") / "tiny.onnx", 1.0, 3.0)


@pytest.fixture(scope="module")
def photos(tmp_path_factory: pytest.TempPathFactory, base_rgb: np.ndarray) -> Path:
    """15 good panoramas, a grey PNG and a 16-bit PNG (also good), a truncated JPEG, a zero-byte
    file and a 3:2 image."""
    folder = tmp_path_factory.mktemp("photos")
    _panoramas(folder, base_rgb, 15)
    cv2.imwrite(str(folder / "grey.png"), cv2.cvtColor(base_rgb, cv2.COLOR_RGB2GRAY))
    cv2.imwrite(str(folder / "deep.png"), base_rgb[:, :, ::-1].astype(np.uint16) * 257)
    _, jpeg = cv2.imencode(".jpg", base_rgb)
    (folder / "truncated.jpg").write_bytes(jpeg.tobytes()[: len(jpeg) // 2])
    (folder / "zero.jpg").write_bytes(b"")
    cv2.imwrite(str(folder / "three_two.png"), base_rgb[:, :768])
    return folder


def _failures(out: Path) -> dict[str, str]:
    lines = (out / "failures.jsonl").read_text().splitlines()
    return {Path(r["input"]).name: r["error"] for r in map(json.loads, lines)}


def _sidecar_mtimes(out: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(out.rglob("*.json"))}


def _assert_clean(out: Path, shape: tuple[int, int] = (512, 1024)) -> None:
    """No temporary or lock files; every sidecar's set loads."""
    leftovers = [p.name for p in out.rglob(".*")]
    assert not leftovers, leftovers
    for sidecar in out.rglob("*.json"):
        result = m360.load(sidecar)
        assert result.disparity.shape == shape


def test_a_batch_with_bad_files_records_them_and_goes_on(
    photos: Path, model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    code = main(["run", str(photos), "-o", str(out), "--model", str(model), *FAST])
    err = capsys.readouterr().err
    assert code == 1, err
    assert _failures(out) == {
        "truncated.jpg": "ReadError",
        "zero.jpg": "ReadError",
        "three_two.png": "AspectRatioError",
    }
    assert "17 done, 0 already done, 3 failed" in err
    assert "three_two.png: AspectRatioError" in err and "is 512x768 (HxW)" in err
    done = sorted(p.stem for p in out.glob("*.json"))
    assert len(done) == 17 and {"grey", "deep"} <= set(done)
    _assert_clean(out)
    meta = m360.load(out / "pano_03").metadata
    assert meta["input"]["path"] == str(photos / "pano_03.jpg")
    assert (
        meta["input"]["sha256"] == hashlib.sha256((photos / "pano_03.jpg").read_bytes()).hexdigest()
    )
    assert meta["options"]["blend"] == {"method": "frustum"}
    assert meta["model"]["name"] == "tiny.onnx"

    # A rerun skips everything done (nothing is rewritten) and retries the failures.
    before = _sidecar_mtimes(out)
    code = main(["run", str(photos), "-o", str(out), "--model", str(model), *FAST])
    err = capsys.readouterr().err
    assert code == 1 and "0 done, 17 already done, 3 failed" in err
    assert _sidecar_mtimes(out) == before
    # Other options are other results: they are redone; --overwrite redoes the same options.
    main(["run", str(photos / "pano_00.png"), "-o", str(out), "--model", str(model),
          *FAST[:2], "--blend", "mean", *FAST[4:]])  # fmt: skip
    assert _sidecar_mtimes(out)["pano_00.json"] > before["pano_00.json"]
    code = main(
        ["run", str(photos / "pano_01.jpg"), "-o", str(out), "--model", str(model), *FAST,
         "--overwrite"]
    )  # fmt: skip
    assert code == 0 and _sidecar_mtimes(out)["pano_01.json"] > before["pano_01.json"]
    # --fix-aspect makes the 3:2 image a panorama.
    code = main(
        ["run", str(photos / "three_two.png"), "-o", str(out), "--model", str(model), *FAST,
         "--fix-aspect"]
    )  # fmt: skip
    assert code == 0 and m360.load(out / "three_two").metadata["input"]["aspect_fixed"]


def test_two_workers_give_the_same_results_as_one(
    photos: Path, model: Path, tmp_path: Path
) -> None:
    inputs = sorted(photos.glob("pano_0[0-5].*"))
    options = {"model": str(model), "align": "none", "blend": "frustum", "input_size": (64, 96)}
    one = m360.batch.run(inputs, tmp_path / "one", progress=False, **options)
    two = m360.batch.run(inputs, tmp_path / "two", progress=False, workers=2, **options)
    assert one.exit_code == two.exit_code == 0
    assert [o.stem for o in one.done] == [o.stem for o in two.done] == [p.stem for p in inputs]
    for path in inputs:
        a, b = m360.load(tmp_path / "one" / path.stem), m360.load(tmp_path / "two" / path.stem)
        np.testing.assert_array_equal(a.disparity, b.disparity)


def test_a_dead_worker_costs_only_its_image(tmp_path: Path, base_rgb: np.ndarray) -> None:
    inputs = _panoramas(tmp_path / "in", base_rgb[::2, ::2].copy(), 4)
    black = tmp_path / "in" / "black.png"
    cv2.imwrite(str(black), np.zeros((256, 512, 3), np.uint8))
    report = m360.batch.run(
        [*inputs[:2], black, *inputs[2:]], tmp_path / "out", model=batch_helpers.CrashOnBlack(),
        align="none", blend="mean", workers=2, progress=False,
    )  # fmt: skip
    assert [(o.stem, o.error) for o in report.failed] == [("black", "WorkerCrashed")]
    # An image in flight on the other worker when the pool broke is redone; if that worker had
    # already renamed its sidecar before it was killed, the redo finds it complete (skipped).
    finished = [*report.done, *report.skipped]
    assert sorted(o.stem for o in finished) == sorted(p.stem for p in inputs)
    assert all((tmp_path / "out" / f"{p.stem}.json").is_file() for p in inputs)
    assert report.exit_code == 1
    assert _failures(tmp_path / "out") == {"black.png": "WorkerCrashed"}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "m360.cli", *args]


def _env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "M360_HOME": str(tmp_path / "home"), "M360_NUM_THREADS": "1"}


# `m360 run` with the gated estimator of batch_helpers (the CLI takes no estimator object).
_GATED_RUN = """
import sys, m360, batch_helpers
if __name__ == "__main__":
    gate = sys.argv[3] or None
    report = m360.batch.run(sys.argv[1], sys.argv[2], model=batch_helpers.Gated(gate),
                            align="none", blend="mean", workers=int(sys.argv[4]), progress=False)
    print(report.summary(), file=sys.stderr)
    sys.exit(report.exit_code)
"""


_LINUX = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc and tgkill")


def _workers(pid: int) -> list[int]:
    """The pool's worker processes among the children of ``pid`` (Linux /proc)."""
    tasks = Path(f"/proc/{pid}/task")
    children = [int(c) for t in tasks.iterdir() for c in (t / "children").read_text().split()]
    # multiprocessing also starts a resource tracker: a worker runs spawn_main
    return [c for c in children if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]


def _signal_a_helper_thread(pid: int, signum: int) -> None:
    """Deliver ``signum`` to one thread of ``pid`` that is not its main thread (tgkill)."""
    helpers = sorted(int(t.name) for t in Path(f"/proc/{pid}/task").iterdir() if t.name != str(pid))
    assert helpers, f"process {pid} has no thread but its main thread"
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.tgkill(pid, helpers[0], signum) != 0:
        raise OSError(ctypes.get_errno(), f"tgkill({pid}, {helpers[0]}) failed")


def _read_exactly(fd: int, count: int, proc: subprocess.Popen[bytes]) -> None:
    """Read ``count`` bytes from the pipe ``fd``; fail (not hang) if the run ends or stalls."""
    got = 0
    while got < count:
        ready, _, _ = select.select([fd], [], [], 120)  # only a guard against a hung run
        assert ready, f"the run stalled after {got} of {count} image starts"
        got += len(os.read(fd, count - got))
        assert proc.poll() is None, "the run ended before it could be stopped"


@pytest.mark.parametrize(
    ("how", "workers"),
    [
        ("SIGKILL", 1),
        ("SIGINT", 1),
        ("SIGINT", 2),
        ("SIGINT to the parent only", 2),
        pytest.param("SIGINT to a helper thread", 1, marks=_LINUX),
        pytest.param("SIGINT to a helper thread of each process", 2, marks=_LINUX),
    ],
)
def test_a_killed_run_resumes_without_losing_or_redoing_anything(
    how: str, workers: int, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    """Stop a run with exactly 3 images done and one image in progress per worker (blocked in
    the network on a FIFO the test controls), then rerun: the rest completes, no file is
    truncated or duplicated, finished images are not redone.

    SIGKILL: no clean-up at all. SIGINT: Ctrl-C, to the whole process group as a terminal sends
    it. "SIGINT to the parent only" (``kill -INT PID``): the parent must stop its workers itself;
    it used to wait for their images, here forever. "A helper thread": the kernel may hand a
    process's SIGINT to any of its threads (rayon, BLAS, the pool's manager thread); one that
    is not the main thread used to leave the main thread blocked, here forever."""
    done_first = 3
    inputs = _panoramas(tmp_path / "in", base_rgb[::2, ::2].copy(), 12)
    out = tmp_path / "out"
    gate = tmp_path / "gate"
    gate.mkdir()
    started, tokens = batch_helpers.make_gate(str(gate))
    env = {**_env(tmp_path), "PYTHONPATH": str(Path(__file__).parent)}
    cmd = [sys.executable, "-c", _GATED_RUN, str(tmp_path / "in"), str(out)]
    proc = subprocess.Popen(
        [*cmd, str(gate), str(workers)], env=env, stderr=subprocess.PIPE, start_new_session=True
    )
    try:
        os.write(tokens, b"t" * done_first)
        # Each worker has started one more image, which waits for a token that never comes.
        _read_exactly(started, done_first + workers, proc)
        finished = _sidecar_mtimes(out)
        assert len(finished) == done_first
        if how == "SIGINT to the parent only":
            os.kill(proc.pid, signal.SIGINT)
        elif how.startswith("SIGINT to a helper thread"):
            targets = [proc.pid]
            if how.endswith("each process"):
                targets += _workers(proc.pid)
                assert len(targets) == 1 + workers
            for pid in targets:
                _signal_a_helper_thread(pid, signal.SIGINT)
        else:
            os.killpg(proc.pid, getattr(signal, how.split()[0]))
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # a failed test leaves no process behind
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    if how == "SIGKILL":
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == 130, err.decode()
        assert f"{done_first} done, 0 already done, 0 failed".encode() in err
        assert b"interrupted: rerun" in err and b"Traceback" not in err, err.decode()
        _assert_clean(out, (256, 512))  # Ctrl-C leaves no temporary or lock file behind
    assert _sidecar_mtimes(out) == finished  # nothing finished or started writing after
    for sidecar in finished:  # whatever was finished is complete and readable
        assert m360.load(out / sidecar).disparity.shape == (256, 512)

    rerun = subprocess.run([*cmd, "", "1"], env=env, capture_output=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr.decode()
    done_now = len(inputs) - done_first
    assert f"{done_now} done, {done_first} already done, 0 failed" in rerun.stderr.decode()
    after = _sidecar_mtimes(out)
    assert sorted(after) == sorted(f"{p.stem}.json" for p in inputs)
    assert {k: after[k] for k in finished} == finished  # not recomputed
    _assert_clean(out, (256, 512))  # stale temporaries and locks of the killed image are gone
    names = [p.name for p in out.iterdir()]
    assert len(names) == len(set(names)) == 4 * len(inputs)  # 2 arrays + preview + sidecar


_RUN_AND_REPORT = """
import json, sys, m360
report = m360.batch.run(sys.argv[1], sys.argv[2], model=sys.argv[3], align="none",
                        blend="poisson", progress=False, input_size=(64, 96))
print(json.dumps({s: [o.stem for o in getattr(report, s)] for s in ("done", "skipped", "busy",
                                                                    "failed")}))
"""


def test_two_concurrent_runs_do_every_image_exactly_once(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    inputs = _panoramas(tmp_path / "in", base_rgb, 10)
    out = tmp_path / "out"
    cmd = [sys.executable, "-c", _RUN_AND_REPORT, str(tmp_path / "in"), str(out), str(model)]
    procs = [subprocess.Popen(cmd, env=_env(tmp_path), stdout=subprocess.PIPE) for _ in range(2)]
    reports = [json.loads(p.communicate(timeout=300)[0]) for p in procs]
    assert all(p.returncode == 0 for p in procs)
    done = [set(r["done"]) for r in reports]
    assert not done[0] & done[1], "an image was processed by both runs"
    assert done[0] | done[1] == {p.stem for p in inputs}
    assert all(r["done"] for r in reports), "one run did everything: no concurrency was tested"
    _assert_clean(out)


def test_manifests_resolve_inside_out_and_refuse_escapes(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    a, b, c = _panoramas(tmp_path / "in", base_rgb[::2, ::2].copy(), 3)
    outside = tmp_path / "outside"
    outside.mkdir()
    out = tmp_path / "out"
    (out / "sub").mkdir(parents=True)
    (out / "link").symlink_to(outside)
    (tmp_path / "list.txt").write_text(f"# panoramas\n\nin/{a.name}\n{b}\n")
    (tmp_path / "list.csv").write_text(
        "input,output\n"
        f"in/{c.name},sub/third\n"
        f"in/{a.name},../escaped\n"
        f"in/{a.name},{outside / 'abs'}\n"
        f"in/{b.name},link/through\n"
        f"in/{b.name},pano_00\n"  # pano_00 already comes from list.txt
    )
    report = m360.batch.run(
        [tmp_path / "list.txt", tmp_path / "list.csv"], out, model=str(model), align="none",
        blend="mean", progress=False, input_size=(64, 96),
    )  # fmt: skip
    assert sorted(o.stem for o in report.done) == ["pano_00", "pano_01", "sub/third"]
    assert [(o.stem, o.error) for o in report.failed] == [
        ("../escaped", "InputError"),
        ((outside / "abs").as_posix(), "InputError"),
        ("link/through", "InputError"),
        ("pano_00", "InputError"),
    ]
    assert not list(outside.iterdir()) and not (tmp_path / "escaped.json").exists()
    assert (out / "sub" / "third.json").is_file()


def test_recursive_folders_keep_their_sub_paths(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    small = base_rgb[::2, ::2].copy()
    _panoramas(tmp_path / "in" / "x", small, 1)
    _panoramas(tmp_path / "in" / "y", small, 1)
    with pytest.raises(m360.InputError, match="no images found"):  # not without recursive
        m360.batch.run(tmp_path / "in", tmp_path / "flat", model=str(model), progress=False)
    report = m360.batch.run(
        tmp_path / "in", tmp_path / "out", model=str(model), progress=False, align="none",
        blend="mean", input_size=(64, 96), recursive=True,
    )  # fmt: skip
    assert sorted(o.stem for o in report.done) == ["x/pano_00", "y/pano_00"]


def test_usage_errors_exit_2_before_any_work(
    model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "empty").mkdir()
    base = ["run", "-o", str(tmp_path / "out"), "--model", str(model)]
    assert main([*base, str(tmp_path / "empty")]) == 2
    assert "no images found" in capsys.readouterr().err
    assert main([*base, str(tmp_path / "empty"), "--formats", "npy,tiff"]) == 2
    assert "unknown format(s) tiff" in capsys.readouterr().err
    assert main([*base, str(tmp_path / "empty"), "--workers", "0"]) == 2
    assert not (tmp_path / "out").exists()


def test_eval_prints_the_metrics_of_an_output(tmp_path: Path) -> None:
    gt = np.random.default_rng(1).uniform(1.0, 5.0, (32, 64)).astype(np.float32)
    np.save(tmp_path / "gt.npy", gt)
    result = type("R", (), {"disparity": 2.0 / gt + 0.5, "depth": gt / 2.0})()
    m360.save(result, tmp_path / "pred", formats="pfm")
    proc = subprocess.run(
        _cli("eval", str(tmp_path / "pred"), str(tmp_path / "gt.npy"), "--json"),
        capture_output=True, env=_env(tmp_path), timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr.decode()
    metrics = json.loads(proc.stdout)
    assert metrics["abs_rel"] < 1e-5 and metrics["delta1"] == 1.0


def test_a_claim_is_exclusive_and_leaves_nothing_behind(tmp_path: Path) -> None:
    stem = tmp_path / "sub" / "pano"
    with m360.batch.image.claim(stem) as first:
        with m360.batch.image.claim(stem) as second:  # another open file: as another process
            assert first and not second
        assert (tmp_path / "sub" / ".pano.lock").exists()
    assert not list((tmp_path / "sub").iterdir())
    with m360.batch.image.claim(stem) as again:
        assert again


@pytest.mark.parametrize("moment", ["locked", "unlinked"])
@pytest.mark.parametrize("handler", ["python", "m360"])
def test_ctrl_c_while_a_claim_is_taken_or_released_leaves_no_lock_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, moment: str, handler: str
) -> None:
    """A SIGINT delivered at the worst moment (the file is created and locked, not yet handed
    to the code that removes it; or removed, its descriptor not yet closed) is raised once the
    claim is safe, never lost and never leaving a ``.lock`` file behind. The signal is sent
    synchronously from inside the claim, so the moment is exact on every run."""
    stem = tmp_path / "pano"
    body_ran = False

    def ctrl_c_after(real: Any) -> Any:
        def wrapped(*args: Any) -> Any:
            result = real(*args)
            signal.raise_signal(signal.SIGINT)
            return result

        return wrapped

    if moment == "locked":
        monkeypatch.setattr(m360.batch.image, "_try_lock", ctrl_c_after(m360.batch.image._try_lock))
    else:
        monkeypatch.setattr(m360.batch.image.os, "unlink", ctrl_c_after(os.unlink))
    run_handler = (
        m360.batch._interrupt.MainThreadInterrupts(m360.batch.runner.keyboard_interrupt_once())
        if handler == "m360"
        else contextlib.nullcontext()
    )
    with pytest.raises(KeyboardInterrupt), run_handler:
        with m360.batch.image.claim(stem) as claimed:
            body_ran = claimed
            if moment == "unlinked":
                assert claimed
    monkeypatch.undo()
    assert body_ran == (moment == "unlinked")  # a held-back Ctrl-C stops before the work
    assert not list(tmp_path.iterdir())


def test_every_option_that_changes_an_output_byte_redoes_the_image(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    """A rerun into the same folder skips an image only when nothing that can change its outputs
    changed: each such option, varied alone, redoes it (input_size included: a run at 32x48
    must not be kept by a rerun at 48x64); threads, workers and progress do not."""
    (image,) = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 1)
    other_model = g.affine_of_mean(tmp_path / "other.onnx", 1.0, 0.2)
    out = tmp_path / "out"
    base = {
        "model": str(model),
        "align": "multiscale",
        "blend": "poisson",
        "input_size": (32, 48),
        "progress": False,
    }
    variants: list[dict[str, object]] = [
        {"model": str(other_model)},
        {"input_size": (48, 64)},
        {"output_kind": "distance"},
        {"formats": ("npy", "pfm")},
        {"preview": False},
        {"fix_aspect": True},
        {"edges": "photo"},
        {"align": "none"},
        {"align": [(3, 3)]},
        {"energy": "paper"},
        {"solver": "lbfgs"},
        {"iterations": 7},
        {"tolerance": 1e-5},
        {"sample_fraction": 0.02},
        {"pole_cap_deg": 5.0},
        {"smoothness": 2.0},
        {"scale_weight": 0.02},
        {"offsets": "spherical"},
        {"blend": "frustum"},
        {"blend_options": {"fidelity": "nn"}},
        {"blend_options": {"lam": 0.2}},
        {"blend_options": {"tolerance": 1e-5}},
        {"blend_options": {"iterations": 3000}},
        {"blend_options": {"solver": "fused"}},
    ]

    def status(**changes: object) -> str:
        report = m360.batch.run(image, out, **{**base, **changes})  # type: ignore[arg-type]
        assert report.exit_code == 0, report.outcomes
        (outcome,) = report.outcomes
        return outcome.status

    assert status() == "done"
    assert status() == "skipped"
    assert status(threads=1) == "skipped"  # results do not depend on the thread count
    for change in variants:
        assert status(**change) == "done", change
        assert status(**change) == "skipped", change
        assert status() == "done", change


def test_unusable_output_folders_are_usage_errors_and_unusable_outputs_fail_alone(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found by tests/test_fuzz_cli.py's kind of inputs: an OSError or ValueError must not
    escape (it was a traceback)."""
    (image,) = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 1)
    options = ["--model", str(model), "--align", "none", "--blend", "mean", "--no-progress"]
    with pytest.raises(m360.InputError, match="is not a valid path"):
        m360.batch.run(image, "out\x00x", model=str(model), progress=False)
    assert main(["run", str(image), "-o", str(image / "out"), *options]) == 2  # a file in the way
    assert f"cannot create the output folder {image / 'out'}" in capsys.readouterr().err
    out = tmp_path / "out"
    out.mkdir()
    (out / "taken").write_text("a file where a manifest wants a folder")
    (tmp_path / "list.csv").write_text(f"{image},taken/pano\n{image},fine/pano\n")
    assert main(["run", str(tmp_path / "list.csv"), "-o", str(out), *options]) == 1
    err = capsys.readouterr().err
    assert "InputError: cannot create the folder of output taken/pano" in err
    assert "1 done, 0 already done, 1 failed" in err and "Traceback" not in err
    assert _failures(out) == {image.name: "InputError"}


def test_ctrl_c_while_writing_leaves_no_partial_set(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C lands after the second image's arrays are in place, while its preview is being
    written: those arrays are removed again, the run reports 130, a rerun does the rest."""
    inputs = _panoramas(tmp_path / "in", base_rgb[::2, ::2].copy(), 3)
    out = tmp_path / "out"
    real_save_png = m360.io.save_png
    calls = []

    def interrupted_on_the_second(path: Path, image: np.ndarray) -> Path:
        calls.append(path)
        if len(calls) == 2:
            assert sorted(p.name for p in out.glob("pano_01.*")) == [
                "pano_01.depth.npy",
                "pano_01.disparity.npy",
            ]  # the arrays are written: this is the worst moment
            raise KeyboardInterrupt
        return real_save_png(path, image)

    monkeypatch.setattr(m360.io.writing, "save_png", interrupted_on_the_second)
    options = {"model": str(model), "align": "none", "blend": "mean", "progress": False}
    report = m360.batch.run(tmp_path / "in", out, input_size=(64, 96), **options)
    assert report.interrupted and report.exit_code == 130
    assert [o.stem for o in report.done] == ["pano_00"] and len(calls) == 2
    assert sorted(p.name for p in out.iterdir()) == [
        "pano_00.depth.npy",
        "pano_00.disparity.npy",
        "pano_00.json",
        "pano_00.preview.png",
    ]  # nothing of pano_01 (nor its lock), pano_02 not started
    monkeypatch.setattr(m360.io.writing, "save_png", real_save_png)
    again = m360.batch.run(tmp_path / "in", out, input_size=(64, 96), **options)
    assert [o.stem for o in again.done] == ["pano_01", "pano_02"]
    assert [o.stem for o in again.skipped] == ["pano_00"] and again.exit_code == 0
    _assert_clean(out, (256, 512))
    assert len(inputs) == 3


def _one_image_run(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> tuple[Path, Path, list[str]]:
    """One 256x512 panorama, its output folder, and `m360 run` arguments (fast: no alignment)."""
    (path,) = _panoramas(tmp_path / "in", base_rgb[::2, ::2].copy(), 1)
    out = tmp_path / "out"
    args = ["run", str(path), "-o", str(out), "--model", str(model), "--formats", "npy"]
    args += ["--align", "none", "--blend", "mean", "--input-size", "32", "48"]
    return path, out, args


def test_padding_in_batches(model: Path, tmp_path: Path, base_rgb: np.ndarray) -> None:
    """--padding gives every image the layout m360.estimate(padding=) makes. The default is 0.7:
    the paper's 0.3 is another result (redone), the default given explicitly the same (kept),
    and an image an older m360 wrote under its default (0.3, no padding in the fingerprint) is
    redone. A padding the core refuses is a usage error."""
    path, out, args = _one_image_run(model, tmp_path, base_rgb)
    assert main([*args, "--padding", "0.3"]) == 0
    saved = m360.load(out / path.stem)
    assert "padding=0.3" in saved.metadata["options"]["layout"]
    rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    kwargs: dict[str, Any] = {"align": "none", "blend": "mean", "input_size": (32, 48)}
    paper = m360.estimate(rgb, str(model), padding=0.3, **kwargs)
    np.testing.assert_array_equal(saved.disparity, paper.disparity)
    default = m360.estimate(rgb, str(model), **kwargs)
    assert default.layout.padding == m360.geometry.DEFAULT_PADDING == 0.7
    assert not np.array_equal(paper.disparity, default.disparity, equal_nan=True)
    with pytest.raises(m360.InputError, match="layout or padding"):
        m360.estimate(rgb, str(model), layout=m360.Layout.icosahedron(512), padding=0.7)
    assert main(args) == 0  # the default layout: another result, redone
    np.testing.assert_array_equal(m360.load(out / path.stem).disparity, default.disparity)
    again = {"model": str(model), "formats": ("npy",), "progress": False, **kwargs}
    assert len(m360.batch.run(path, out, padding=0.7, **again).skipped) == 1
    sidecar = out / f"{path.stem}.json"
    meta = json.loads(sidecar.read_text())
    del meta["batch"]["fingerprint"]["padding"]  # as an older m360 wrote it
    sidecar.write_text(json.dumps(meta))
    assert len(m360.batch.run(path, out, **again).done) == 1
    assert main([*args, "--padding", "5"]) == 2  # beyond the core's limit: a usage error


def test_edges_in_batches(model: Path, tmp_path: Path, base_rgb: np.ndarray) -> None:
    """--edges auto is the default and in the fingerprint: an image an older m360 wrote under its
    default (network edges, no edges in the fingerprint) is redone, one written under auto kept.
    A network that sees its tile 4 or more times smaller gets its edges refined along the photo,
    as m360.estimate does."""
    path, out, args = _one_image_run(model, tmp_path, base_rgb)
    assert main(args) == 0
    sidecar = out / f"{path.stem}.json"
    meta = json.loads(sidecar.read_text())
    assert meta["batch"]["fingerprint"]["edges"] == "auto"
    kwargs: dict[str, Any] = {"align": "none", "blend": "mean", "input_size": (32, 48)}
    again = {"model": str(model), "formats": ("npy",), "progress": False, **kwargs}
    assert len(m360.batch.run(path, out, **again).skipped) == 1
    del meta["batch"]["fingerprint"]["edges"]  # as an older m360 wrote it
    sidecar.write_text(json.dumps(meta))
    assert len(m360.batch.run(path, out, **again).done) == 1
    assert "edges" not in m360.load(out / path.stem).metadata["options"]  # 48 px on 100: kept
    coarse = [*args[:-2], "16", "24", "--overwrite"]  # 24 px on the 100 px tiles
    assert main(coarse) == 0
    saved = m360.load(out / path.stem)
    assert saved.metadata["options"]["edges"] == "photo"
    rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    small = {**kwargs, "input_size": (16, 24)}
    np.testing.assert_array_equal(
        saved.disparity, m360.estimate(rgb, str(model), edges="photo", **small).disparity
    )


def test_subdivisions_in_batches(model: Path, tmp_path: Path, base_rgb: np.ndarray) -> None:
    """--subdivisions 1 gives every image the 80-tangent layout (padding 0.3 unless given) that
    m360.estimate(subdivisions=1) and Layout.icosahedron(W, subdivisions=1) make; it is another
    result than the default (redone both ways) and the same given again (kept). A padding too
    wide for the smaller tangents is refused before any image, naming both options."""
    path, out, args = _one_image_run(model, tmp_path, base_rgb)
    assert main([*args, "--subdivisions", "1"]) == 0
    saved = m360.load(out / path.stem)
    assert "80 cameras" in saved.metadata["options"]["layout"]
    assert "padding=0.3" in saved.metadata["options"]["layout"]
    rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    kwargs: dict[str, Any] = {"align": "none", "blend": "mean", "input_size": (32, 48)}
    finer = m360.estimate(rgb, str(model), subdivisions=1, **kwargs)
    assert len(finer.layout) == 80 and finer.layout.padding == 0.3
    np.testing.assert_array_equal(saved.disparity, finer.disparity)
    given = m360.Layout.icosahedron(512, subdivisions=1)
    np.testing.assert_array_equal(
        m360.estimate(rgb, str(model), layout=given, **kwargs).disparity, finer.disparity
    )
    with pytest.raises(m360.InputError, match="layout or padding and subdivisions"):
        m360.estimate(rgb, str(model), layout=given, subdivisions=1, **kwargs)
    with pytest.raises(m360.InputError, match=r"padding=0\.7 with subdivisions=1"):
        m360.estimate(rgb, str(model), subdivisions=1, padding=0.7, **kwargs)
    again = {"model": str(model), "formats": ("npy",), "progress": False, **kwargs}
    assert len(m360.batch.run(path, out, subdivisions=1, **again).skipped) == 1
    assert len(m360.batch.run(path, out, **again).done) == 1  # the 20 default tangents
    assert len(m360.batch.run(path, out, subdivisions=1, padding=0.2, **again).done) == 1
    assert "padding=0.2" in m360.load(out / path.stem).metadata["options"]["layout"]
    with pytest.raises(m360.InputError, match=r"padding=0\.7 with subdivisions=1"):
        m360.batch.run(path, out, subdivisions=1, padding=0.7, **again)
    assert main([*args, "--subdivisions", "1", "--padding", "0.7"]) == 2
    assert main([*args, "--subdivisions", "3"]) == 2  # beyond the core's limit


def test_a_prior_finer_than_the_tangent_network_gets_a_note(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    """A tangent network that sees each default tile at 36 px (6° per pixel) with a prior map
    of 80 columns (4.5° per pixel): the run says its edges will be no sharper than the prior's
    and what would be. It says nothing with 16 columns (22.5°), nor on the 80 smaller tiles,
    which the same network sees at 3°."""
    path, out, _ = _one_image_run(model, tmp_path, base_rgb)
    kw: dict[str, Any] = {"model": str(model), "input_size": (32, 48), "progress": False}
    layout = m360.geometry.default_layout(2048)
    net = m360.estimators.load_estimator(str(model), input_size=(32, 48))
    degrees = layout.network_pixel_degrees(net.network_size(layout.tangent_shape)[1])
    assert 5 < degrees < 7
    prior: dict[str, Any] = {"prior": np.ones((40, 80)), "prior_kind": "distance"}
    coarse = m360.batch.run(path, out, **prior, **kw)
    assert coarse.exit_code == 0
    (note,) = coarse.notes
    assert note.startswith(f"detail: the tangent network sees {degrees:.2f}° per pixel")
    assert "no finer than the prior's 4.50°" in note and "subdivisions=1" in note
    assert note in coarse.summary()
    smaller = m360.batch.run(path, out / "sub", subdivisions=1, **prior, **kw)
    assert smaller.exit_code == 0 and not smaller.notes
    blurry = {"prior": np.ones((8, 16)), "prior_kind": "distance"}
    assert not m360.batch.run(path, out / "blurry", **blurry, **kw).notes


def test_working_width_in_batches(model: Path, tmp_path: Path, base_rgb: np.ndarray) -> None:
    """--working-width runs the method at that width and writes the image's resolution; the
    result is m360.estimate's, and another working width is another result (redone)."""
    path, out, args = _one_image_run(model, tmp_path, base_rgb)
    assert main([*args, "--working-width", "256"]) == 0
    saved = m360.load(out / path.stem)
    assert saved.disparity.shape == (256, 512)
    assert saved.metadata["options"]["working_width"] == 256
    rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    direct = m360.estimate(
        rgb, str(model), align="none", blend="mean", input_size=(32, 48), working_width=256
    )
    np.testing.assert_array_equal(saved.disparity, direct.disparity)
    report = m360.batch.run(
        path, out, model=str(model), align="none", blend="mean", formats=("npy",),
        input_size=(32, 48), working_width=256, progress=False,
    )  # fmt: skip
    assert len(report.skipped) == 1
    assert main([*args, "--working-width", "native"]) == 0  # another result: redone
    assert m360.load(out / path.stem).metadata["options"]["working_width"] == 512
    assert main([*args, "--working-width", "63"]) == 2  # odd: InputError, a usage error
    assert main([*args, "--working-width", "wide"]) == 2


# --------------------------------------------------------------------------------------------
# Batch edges (issue 23): names at the OS limits, garbage manifests, what folder scans take,
# busy images, full disks.

_NAME_MAX = 255  # Linux, macOS, Windows: bytes per file name (UTF-8 here)


def _fast(model: Path) -> dict[str, Any]:
    return {"model": str(model), "align": "none", "blend": "mean", "input_size": (32, 48),
            "progress": False}  # fmt: skip


def _dotfiles(out: Path) -> list[str]:
    return sorted(p.name for p in out.rglob(".*"))


def test_names_at_the_os_limit_fail_alone_and_temporaries_and_locks_are_hashed(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """A legal 255-byte file name (its outputs cannot be named) and a long .csv output column
    fail alone, before any work, naming NAME_MAX; a 230-byte stem, whose outputs are legal but
    whose temporaries and lock (``.NAME.XXXXXXXX.tmp``) would not be, is done. It used to be an
    OSError traceback from the lock file that aborted the whole run."""
    small = cv2.imencode(".png", base_rgb[::4, ::4, ::-1])[1].tobytes()
    folder = tmp_path / "in"
    folder.mkdir()
    longest = "é" * 125 + "x.png"  # 255 bytes in UTF-8: the longest legal name
    near = "n" * 230 + ".png"
    for name in ("ok.png", longest, near):
        assert len(name.encode()) <= _NAME_MAX
        (folder / name).write_bytes(small)
    # The name checks are the OS's: this temporary name is what used to be made, and it is refused.
    with pytest.raises(OSError) as refused:
        os.close(os.open(folder / f".{near[:-4]}.disparity.npy.abcdefgh.tmp", os.O_CREAT, 0o600))
    assert refused.value.errno == errno.ENAMETOOLONG
    out = tmp_path / "out"
    code = main(["run", str(folder), "-o", str(out), "--model", str(model), *FAST, "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err, err
    assert "2 done, 0 already done, 1 failed" in err
    record = json.loads((out / "failures.jsonl").read_text())
    assert record["input"] == str(folder / longest) and record["error"] == "InputError"
    assert "NAME_MAX" in record["message"] and "is 265 bytes" in record["message"]  # 251 + 14
    assert m360.load(out / near[:-4]).disparity.shape == (128, 256)
    assert _dotfiles(out) == []  # the hashed temporaries and lock were removed

    # A .csv output column too long for the file system, as a name or as a folder.
    manifest = tmp_path / "list.csv"
    manifest.write_text(f"in/ok.png,{'o' * 250}\nin/ok.png,{'d' * 256}/x\nin/ok.png,fine\n")
    report = m360.batch.run(manifest, tmp_path / "out2", **_fast(model))
    assert [o.stem for o in report.done] == ["fine"]
    assert [(o.stem[:3], o.error) for o in report.failed] == [("ooo", "InputError")] * 1 + [
        ("ddd", "InputError")
    ]
    assert all("NAME_MAX" in (o.message or "") for o in report.failed)
    assert sorted(p.name for p in (tmp_path / "out2").iterdir()) == [
        "failures.jsonl",
        "fine.depth.npy",
        "fine.disparity.npy",
        "fine.json",
        "fine.preview.png",
    ]  # fmt: skip  (no folder for the refused output)


def test_a_path_over_path_max_fails_alone(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    """An output path longer than PATH_MAX (here 17 folders of 250 bytes) fails alone, naming
    the limit, and no folder of it is made."""
    (image,) = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 1)
    deep = "/".join(f"{k:02d}" + "p" * 248 for k in range(17))
    assert len(str(tmp_path / "out" / deep).encode()) > 4096
    manifest = tmp_path / "list.csv"
    manifest.write_text(f"{image},{deep}/x\n{image},shallow\n")
    report = m360.batch.run(manifest, tmp_path / "out", **_fast(model))
    assert [o.stem for o in report.done] == ["shallow"]
    (failed,) = report.failed
    assert failed.error == "InputError" and "PATH_MAX" in (failed.message or "")
    assert not [p for p in (tmp_path / "out").iterdir() if p.is_dir()]


def test_temporary_names_and_locks_of_long_names_are_hashed(tmp_path: Path) -> None:
    """m360.io's atomic writes and the batch claim take any legal name: their own names are
    hashed when ``.NAME.XXXXXXXX.tmp`` / ``.NAME.lock`` would pass 255 bytes."""
    files = m360.io.files
    for size in (1, 241, 242, 255):
        name = "t" * size
        prefix = files.temporary_prefix(name)
        hashed = size + 14 > _NAME_MAX
        expected = (
            "." + hashlib.sha1(name.encode()).hexdigest()[:16] + "." if hashed else f".{name}."
        )
        assert prefix == expected, size
        target = tmp_path / name
        files.save_npy(target, np.arange(3.0))
        np.testing.assert_array_equal(np.load(target), np.arange(3.0))
        target.unlink()
    # A stale temporary of a hashed name is found and removed by its set's clean-up.
    stem = tmp_path / ("s" * 241)
    stale = tmp_path / (files.temporary_prefix(stem.name + ".disparity.npy") + "abcdefgh.tmp")
    stale.write_bytes(b"half")
    other = tmp_path / (files.temporary_prefix("other.disparity.npy") + "abcdefgh.tmp")
    other.write_bytes(b"another set's")
    assert files.remove_stale_temporaries(stem) == [stale]
    assert other.exists()
    other.unlink()
    # The claim of a 250-byte stem: its lock is hashed, exclusive, and removed afterwards.
    stem = tmp_path / ("c" * 250)
    with m360.batch.image.claim(stem) as first:
        with m360.batch.image.claim(stem) as second:
            assert first and not second
        (lock,) = tmp_path.iterdir()
        assert lock.name == "." + hashlib.sha1(stem.name.encode()).hexdigest()[:16] + ".lock"
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("suffix", "content", "line", "says"),
    [
        (".txt", b"pano.png\n\xff\xfe\x00garbage\n", 2, "not UTF-8"),
        (".csv", b"input,output\npano.png,a\x00b\n", 2, "U+0000 (NUL)"),
        (".txt", b"pano.png\n\x1b[31mred\n", 2, "U+001B"),
        (".csv", b"pano.png,a\n" + b"x" * 9000 + b"\n", 2, "longer than two paths"),
        (".txt", b"a/pano.png\n# b\nb/pano.png\n", 3, "lines 1 and 3 both write the output pano"),
        (".csv", b"x.png,same\ny.png,other\nz.png,same\n", 3, "lines 1 and 3 both write"),
    ],
)
def test_a_garbage_manifest_is_a_usage_error_before_any_folder_is_made(
    model: Path, tmp_path: Path, suffix: str, content: bytes, line: int, says: str,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """Random bytes, binary, absurd lines and two lines writing one output refuse the whole
    manifest (exit 2, naming the line), before OUT or any folder exists. Duplicate outputs are
    refused rather than renamed: a rerun must find each image's outputs under the same name."""
    manifest = tmp_path / f"list{suffix}"
    manifest.write_bytes(content)
    out = tmp_path / "out"
    assert main(["run", str(manifest), "-o", str(out), "--model", str(model)]) == 2
    err = capsys.readouterr().err
    assert f"line{'s' * ('lines' in says)} " in err and says in err, err
    if "lines" not in says:
        assert f"line {line}:" in err, err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(m360.InputError, match="manifest"):
        m360.batch.run(manifest, out, **_fast(model))
    assert not out.exists()


def test_a_manifest_of_missing_files_fails_line_by_line_and_makes_no_folders(
    model: Path, tmp_path: Path, base_rgb: np.ndarray
) -> None:
    """2,000 text lines naming files that do not exist, into sub-folders: every line fails alone
    (ReadError), the run ends, and OUT holds only failures.jsonl (it used to keep a folder per
    line). A corrupt file that exists fails too and its new folders are removed again; a good
    image next to it keeps its folder."""
    lines = [f"dir{k}/photo {k}.jpg,sub{k}/deeper/out{k}" for k in range(2000)]
    manifest = tmp_path / "list.csv"
    manifest.write_text("\n".join(lines) + "\n")
    report = m360.batch.run(manifest, tmp_path / "out", **_fast(model))
    assert len(report.failed) == 2000 and {o.error for o in report.failed} == {"ReadError"}
    assert report.exit_code == 1
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["failures.jsonl"]
    assert len((tmp_path / "out" / "failures.jsonl").read_text().splitlines()) == 2000

    (good,) = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 1)
    (tmp_path / "in" / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    manifest.write_text(f"in/corrupt.png,a/b/c/corrupt\nin/corrupt.png,keep/x\n{good},keep/ok\n")
    report = m360.batch.run(manifest, tmp_path / "out2", **_fast(model))
    assert [o.stem for o in report.failed] == ["a/b/c/corrupt", "keep/x"]
    assert [o.stem for o in report.done] == ["keep/ok"]
    assert sorted(p.name for p in (tmp_path / "out2").iterdir()) == ["failures.jsonl", "keep"]
    assert len(list((tmp_path / "out2" / "keep").iterdir())) == 4  # ok's 4 files, nothing else


def _write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def test_folder_scans_take_hdr_and_leave_out_depth_maps_and_m360_outputs(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder scan takes every format the CLI takes when named (Radiance .hdr included) and
    leaves out, each with its reason in the summary, m360's outputs (a previous run into the
    same folder) and depth maps: a single-channel 16-bit PNG, a single-channel float EXR or
    TIFF. A depth map named explicitly is tried."""
    folder = tmp_path / "photos"
    small = base_rgb[::4, ::4]
    _panoramas(folder, small.copy(), 1)  # pano_00.png
    assert cv2.imwrite(str(folder / "radiance.hdr"), small[:, :, ::-1].astype(np.float32) / 255)
    _write_exr(folder / "linear.exr", {"RGB": small.astype(np.float32) / 255})  # a photo
    depth = np.linspace(1.0, 9.0, small.shape[0] * small.shape[1], dtype=np.float32)
    depth = depth.reshape(small.shape[:2])
    assert cv2.imwrite(str(folder / "kinect.png"), (depth * 1000).astype(np.uint16))
    _write_exr(folder / "depth_half.exr", {"Z": depth.astype(np.float16)})
    _write_exr(folder / "depth_float.exr", {"depth": depth})
    assert cv2.imwrite(str(folder / "depth.tif"), depth)
    args = ["run", str(folder), "-o", str(folder), "--model", str(model), "--formats",
            "npy,png16,exr", "--confidence", "--align", "none", "--blend", "mean",
            "--input-size", "32", "48", "--no-progress"]  # fmt: skip
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "3 done, 0 already done, 0 failed" in err, err
    assert sorted(p.stem for p in folder.glob("*.json")) == ["linear", "pano_00", "radiance"]
    assert "left out of folder scans: 4 file(s)" in err
    assert "depth.tif: a single-channel float TIFF: a depth map" in err
    # The rerun into the same folder sees its own outputs (png16, exr, previews) and leaves them
    # out: nothing new is taken as a photo.
    report = m360.batch.run(
        folder, folder, formats=("npy", "png16", "exr"), confidence=True, **_fast(model)
    )
    assert report.exit_code == 0 and len(report.skipped) == 3 and not report.done
    reasons = {Path(o.input).name: o.message for o in report.excluded}
    assert reasons["kinect.png"] == "a single-channel 16-bit PNG: a depth map, not a photo"
    assert reasons["depth_half.exr"] == "a single-channel float EXR: a depth map, not a photo"
    assert reasons["depth_float.exr"] == "a single-channel float EXR: a depth map, not a photo"
    assert reasons["pano_00.depth.png"] == "an m360 output (*.depth.png)"
    assert reasons["radiance.confidence.exr"] == "an m360 output (*.confidence.exr)"
    assert reasons["linear.preview.png"] == "an m360 output (*.preview.png)"
    kinds = (".depth.", ".disparity.", ".confidence.", ".preview.")
    outputs = {  # every image file the first run wrote (.npy is not an image suffix)
        p.name for p in folder.iterdir() if p.suffix != ".npy" and any(k in p.name for k in kinds)
    }
    assert len(outputs) == 3 * (3 * 2 + 1)  # 3 images: 3 quantities in png16 and exr, preview
    assert set(reasons) == outputs | {
        "kinect.png",
        "depth_half.exr",
        "depth_float.exr",
        "depth.tif",
    }
    # Named explicitly, a depth map is tried (here as a grey photo).
    named = m360.batch.run(folder / "kinect.png", tmp_path / "named", **_fast(model))
    assert [o.stem for o in named.done] == ["kinect"]
    # A folder holding only left-out files: a usage error that says what was left out.
    only = tmp_path / "only"
    only.mkdir()
    (only / "kinect.png").write_bytes((folder / "kinect.png").read_bytes())
    with pytest.raises(m360.InputError, match=r"no images found.*kinect\.png: a single-channel"):
        m360.batch.run(only, tmp_path / "x", **_fast(model))


def test_nan_only_inputs_fail_in_a_batch_as_in_the_api(model: Path, tmp_path: Path) -> None:
    """A panorama of NaN only: whatever m360's reader makes of it, the batch does the same,
    and an error there is a failure of that image (never a success)."""
    nan = np.full((64, 128, 3), np.nan, np.float32)
    _write_exr(tmp_path / "nan.exr", {"RGB": nan})
    try:
        rgb = m360.io.read_image(tmp_path / "nan.exr")
        api_error = None
    except m360.M360Error as exc:
        api_error = type(exc).__name__
    report = m360.batch.run(tmp_path / "nan.exr", tmp_path / "out", **_fast(model))
    (outcome,) = report.outcomes
    if api_error is not None:
        assert (outcome.status, outcome.error, report.exit_code) == ("failed", api_error, 1)
    else:
        direct = m360.estimate(rgb, str(model), align="none", blend="mean", input_size=(32, 48))
        assert outcome.status == "done"
        np.testing.assert_array_equal(
            m360.load(tmp_path / "out" / "nan").disparity, direct.disparity
        )


def test_images_busy_in_another_run_give_exit_3_unless_done_by_the_end(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, capsys: pytest.CaptureFixture[str]
) -> None:
    """An image claimed by another run (its lock held here) is not a success: exit 3 and the
    summary says to rerun. If the other run finishes it before this run ends (its files copied
    in from a finished run when this run reports it busy), it counts as already done: exit 0."""
    inputs = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 2)
    out = tmp_path / "out"
    args = ["run", str(tmp_path / "in"), "-o", str(out), "--model", str(model), *FAST,
            "--input-size", "32", "48", "--no-progress"]  # fmt: skip
    with m360.batch.image.claim(out / "pano_01"):
        assert main(args) == 3
    err = capsys.readouterr().err
    assert "1 done, 0 already done, 0 failed, 1 busy in another run" in err
    assert "1 image was being written by another run: rerun to finish it" in err
    assert main(args) == 0  # the rerun finishes it
    assert "1 done, 1 already done, 0 failed" in capsys.readouterr().err

    finished = tmp_path / "finished"
    options = {**_fast(model), "input_size": (32, 48)}
    assert m360.batch.run(inputs[1], finished, **options).exit_code == 0
    again = tmp_path / "again"

    def other_run_finishes(outcome: m360.batch.ImageOutcome) -> None:
        if outcome.status == "busy":
            for path in finished.glob("pano_01.*"):
                (again / path.name).write_bytes(path.read_bytes())

    with m360.batch.image.claim(again / "pano_01"):
        report = m360.batch.run(inputs, again, on_outcome=other_run_finishes, **options)
    assert [o.status for o in report.outcomes] == ["done", "skipped"] and report.exit_code == 0


@pytest.mark.parametrize(
    ("code", "says"),
    [
        (errno.ENOSPC, "no space left on device (ENOSPC) while writing"),
        (errno.EDQUOT, "disk quota exceeded (EDQUOT) while writing"),
        (errno.EROFS, "read-only file system (EROFS) while writing"),
    ],
)
def test_a_full_disk_is_named_and_leaves_no_file(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, monkeypatch: pytest.MonkeyPatch,
    code: int, says: str,
) -> None:  # fmt: skip
    """The disk fills while the preview is written (after the arrays): the image fails with a
    message naming the disk, not "unexpected; please report it", and its temporary and partial
    files are gone; the run goes on to the next image."""
    inputs = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 2)
    out = tmp_path / "out"

    def disk_full(path: Path, image: np.ndarray) -> Path:
        with m360.io.files.atomic_path(path) as tmp:
            tmp.write_bytes(b"half a preview")
            raise OSError(code, os.strerror(code))

    monkeypatch.setattr(m360.io.writing, "save_png", disk_full)
    report = m360.batch.run(inputs, out, **_fast(model))
    assert [o.error for o in report.failed] == ["OSError", "OSError"]
    for outcome, path in zip(report.failed, inputs, strict=True):
        assert outcome.message == f"{says} {out / path.stem}.*: " + (
            "write to a writable OUT and rerun" if code == errno.EROFS else "free space and rerun"
        )
    assert sorted(p.name for p in out.iterdir()) == ["failures.jsonl"]  # no temporary, no lock


def test_a_disk_too_full_for_locks_or_failures_jsonl_still_reports_every_image(
    model: Path, tmp_path: Path, base_rgb: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Neither a lock file nor a failures.jsonl line that cannot be written stops the run."""
    inputs = _panoramas(tmp_path / "in", base_rgb[::4, ::4].copy(), 2)

    def no_space(*args: Any) -> Any:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(m360.batch.image, "_lock_current", no_space)
    monkeypatch.setattr(m360.batch.runner, "append_failure", no_space)
    report = m360.batch.run(inputs, tmp_path / "out", **_fast(model))
    assert [o.stem for o in report.failed] == ["pano_00", "pano_01"]
    assert all("no space left on device" in (o.message or "") for o in report.failed)
    summary = report.summary()
    assert "failures.jsonl could not be written: No space left on device" in summary
    assert report.exit_code == 1


_REAL = real_data.PANOS


@real_data.requires_real
def test_a_scan_of_real_panoramas_takes_every_one_and_the_hdr_files_run(
    model: Path, tmp_path: Path
) -> None:
    """The 16 real panoramas (PNG, Radiance HDR, JPEG) are all taken by a folder scan (the
    .hdr ones used to be skipped silently) and none is mistaken for a depth map; the two HDR
    files run through a batch from a folder of links to them."""
    jobs, problems = m360.batch.collect(_REAL, tmp_path / "unused")
    assert problems == [] and len(jobs) == 16
    assert sorted(j.name for j in jobs if j.input.suffix == ".hdr") == [
        "potsdamer_platz_1k", "st_fagans_interior_1k",
    ]  # fmt: skip
    folder = tmp_path / "links"
    folder.mkdir()
    for hdr in sorted(_REAL.glob("*.hdr")):
        (folder / hdr.name).symlink_to(hdr)
    report = m360.batch.run(folder, tmp_path / "out", **_fast(model))
    assert [o.stem for o in report.done] == ["potsdamer_platz_1k", "st_fagans_interior_1k"]
    for outcome in report.done:
        saved = m360.load(tmp_path / "out" / outcome.stem)
        assert saved.disparity.shape == (512, 1024) and np.isfinite(saved.disparity).all()


def test_the_depth_map_rules_read_the_channels_the_writers_wrote(tmp_path: Path) -> None:
    """Each rule against files whose layout is known from how they were written: one channel
    of 16 bits or float is a depth map; grey 8-bit, RGB of any depth, and a truncated header
    are photos (a file that cannot be read is tried, and fails with the reason)."""
    leave_out = m360.batch._inputs.leave_out
    grey = np.arange(32 * 64, dtype=np.uint16).reshape(32, 64)
    cases: dict[str, tuple[Any, bool]] = {
        "grey16.png": (grey, True),
        "grey8.png": (grey.astype(np.uint8), False),
        "rgb16.png": (np.dstack([grey] * 3), False),
        "grey16.tif": (grey, True),
        "float.tif": (grey.astype(np.float32), True),
        "rgb8.tif": (np.dstack([grey.astype(np.uint8)] * 3), False),
        "rgbf.tif": (np.dstack([grey.astype(np.float32)] * 3), False),
    }
    for name, (image, is_depth) in cases.items():
        assert cv2.imwrite(str(tmp_path / name), image)
        assert (leave_out(tmp_path / name) is not None) == is_depth, name
    for channels, is_depth in (({"Y": grey.astype(np.float32)}, True),
                               ({"R": grey.astype(np.float16), "G": grey.astype(np.float16),
                                 "B": grey.astype(np.float16)}, False)):  # fmt: skip
        _write_exr(tmp_path / "x.exr", channels)
        assert (leave_out(tmp_path / "x.exr") is not None) == is_depth, channels.keys()
    data = (tmp_path / "grey16.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:20])  # cut inside the IHDR chunk
    assert leave_out(tmp_path / "cut.png") is None
    exr = (tmp_path / "x.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(exr[:30])  # cut inside the header
    assert leave_out(tmp_path / "cut.exr") is None
