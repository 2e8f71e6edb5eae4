"""360° video (m360.video, `m360 video`): the reader against the encoder, frame selection,
resume after SIGKILL, scene cuts, failed frames, the temporal term on a synthetic walk."""

from __future__ import annotations

import fractions
import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import batch_helpers
import cv2
import m360
import numpy as np
import pytest
from m360.evaluation import sequence as sq
from m360.evaluation.metrics import depth_metrics
from m360.geometry import default_layout

av = pytest.importorskip("av", reason="PyAV (m360[video]) is needed to encode test clips")

FAST = {"align": "none", "blend": "mean"}


@pytest.fixture(autouse=True)
def isolated_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))


def _coded(index: int, width: int = 256, height: int = 128) -> np.ndarray:
    """A frame that carries its index in 8 white/black blocks (survives lossy coding)."""
    image = np.full((height, width, 3), 60, np.uint8)
    image[: height // 2, :, 0] = (index * 37) % 256
    block = width // 8
    for bit in range(8):
        if (index >> bit) & 1:
            image[height // 2 :, bit * block : (bit + 1) * block] = 255
    return image


def _index_of(rgb: np.ndarray) -> int:
    height, width = rgb.shape[:2]
    block = width // 8
    lower = rgb[height // 2 + 8 :, :, 2].astype(np.float64)
    return sum(
        1 << bit
        for bit in range(8)
        if lower[:, bit * block + 6 : (bit + 1) * block - 6].mean() > 160
    )


def _encode(path: Path, count: int, *, codec: str = "libx264", times_ms: list[int] | None = None):
    """Encode ``count`` coded frames at 24 fps (or at the given times, ms); B-frames, GOP 8."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=24)
        stream.width, stream.height, stream.pix_fmt = 256, 128, "yuv420p"
        stream.options = {"g": "8", "bf": "2"} if codec == "libx264" else {"g": "8"}
        if times_ms is not None:
            stream.codec_context.time_base = fractions.Fraction(1, 1000)
        for index in range(count):
            frame = av.VideoFrame.from_ndarray(_coded(index), format="rgb24")
            if times_ms is not None:
                frame.pts, frame.time_base = times_ms[index], fractions.Fraction(1, 1000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


# --------------------------------------------------------------------------------------------
# Reading.


@pytest.mark.parametrize("codec", ["libx264", "mpeg4"])
def test_every_frame_of_a_clip_is_read_once_in_order_with_the_encoders_times(
    tmp_path: Path, codec: str
) -> None:
    if codec not in av.codecs_available:
        pytest.skip(f"this PyAV has no {codec} encoder")
    clip = _encode(tmp_path / "clip.mp4", 30, codec=codec)
    source = m360.video.probe(clip)
    assert (source.kind, source.frames, source.exact) == ("video", 30, True)
    assert source.fps == pytest.approx(24.0) and (source.width, source.height) == (256, 128)
    got = list(m360.video.frames(clip))
    assert [f.index for f in got] == list(range(30))
    assert [_index_of(f.rgb) for f in got] == list(range(30))  # the encoder's frames, in order
    assert [f.time for f in got] == pytest.approx([k / 24 for k in range(30)], abs=1e-6)
    assert all(f.rgb.shape == (128, 256, 3) and f.rgb.dtype == np.uint8 for f in got)


def test_variable_frame_rate_keeps_exact_indices_and_times(tmp_path: Path) -> None:
    """Where OpenCV's reader counts 53 frames for 50 and seeks short (docs/video.md)."""
    times = list(np.cumsum([0] + [30 if k % 3 else 70 for k in range(1, 40)]))
    clip = _encode(tmp_path / "vfr.mkv", 40, times_ms=[int(t) for t in times])
    got = list(m360.video.frames(clip))
    assert [_index_of(f.rgb) for f in got] == list(range(40))
    assert [f.time for f in got] == pytest.approx([t / 1000 for t in times], abs=1e-6)
    picked = list(m360.video.frames(clip, start=0.5, end=1.0))  # seconds: by presentation time
    expected = [k for k, t in enumerate(times) if 500 <= t < 1000]
    assert [f.index for f in picked] == expected
    assert [_index_of(f.rgb) for f in picked] == expected


def test_frame_selection_seeks_to_the_right_frames(tmp_path: Path) -> None:
    clip = _encode(tmp_path / "clip.mp4", 30)
    picked = list(m360.video.frames(clip, every=3, start=4, end=20))
    assert [f.index for f in picked] == [4, 7, 10, 13, 16, 19]
    assert [_index_of(f.rgb) for f in picked] == [4, 7, 10, 13, 16, 19]
    assert [f.index for f in m360.video.frames(clip, start=28)] == [28, 29]
    assert list(m360.video.frames(clip, start=40)) == []
    for bad in ({"every": 0}, {"start": -1}, {"end": "x"}, {"start": float("nan")}):
        with pytest.raises(m360.InputError):
            list(m360.video.frames(clip, **bad))


def test_a_folder_of_frames_is_a_video_in_natural_name_order(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    for index in (0, 1, 2, 10, 11):
        cv2.imwrite(str(folder / f"frame{index}.png"), _coded(index)[:, :, ::-1])
    (folder / "notes.txt").write_text("not a frame")
    got = list(m360.video.frames(folder, fps=10))
    assert [_index_of(f.rgb) for f in got] == [0, 1, 2, 10, 11]  # frame2 before frame10
    assert [f.index for f in got] == [0, 1, 2, 3, 4]
    assert [f.time for f in got] == pytest.approx([0, 0.1, 0.2, 0.3, 0.4])
    assert [f.path.name for f in m360.video.frames(folder, every=2)] == [
        "frame0.png",
        "frame2.png",
        "frame11.png",
    ]
    assert m360.video.probe(folder).frames == 5
    with pytest.raises(m360.InputError, match="fps"):
        list(m360.video.frames(folder, start=0.5))  # seconds need times


def test_missing_pyav_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    clip = _encode(tmp_path / "clip.mp4", 3)
    monkeypatch.setitem(sys.modules, "av", None)
    with pytest.raises(m360.InputError, match=r'pip install "m360\[video\]"'):
        list(m360.video.frames(clip))


def test_not_a_video_is_a_read_error(tmp_path: Path) -> None:
    fake = tmp_path / "fake.mp4"
    fake.write_bytes(b"\x00" * 1000)
    with pytest.raises(m360.ReadError, match=r"fake\.mp4"):
        list(m360.video.frames(fake))
    with pytest.raises(m360.ReadError, match="does not exist"):
        m360.video.probe(tmp_path / "missing.mp4")


# --------------------------------------------------------------------------------------------
# Runs.


def _walk_frames(folder: Path, seed: int, count: int, width: int = 256, first: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    walk = sq.walk(seed, count, erp_width=width)
    for k in range(count):
        rgb, _ = walk.render(k)
        assert cv2.imwrite(str(folder / f"f{first + k:04d}.png"), rgb[:, :, ::-1])


def _sidecar(out: Path, index: int) -> dict:
    return json.loads((out / f"{index:06d}.json").read_text())


def _arrays(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("*.npy"))}


def test_a_scene_cut_restarts_the_temporal_term(tmp_path: Path) -> None:
    """Two walks in one folder: the second starts as if it were a video of its own."""
    both, second = tmp_path / "both", tmp_path / "second"
    _walk_frames(both, 3, 4)
    _walk_frames(both, 8, 3, first=4)
    _walk_frames(second, 8, 3)
    model = batch_helpers.Gated(None)
    report = m360.video.run(both, tmp_path / "out", model=model, progress=False, **FAST)
    assert report.exit_code == 0 and len(report.done) == 7
    records = [_sidecar(tmp_path / "out", k)["temporal"] for k in range(7)]
    assert [r["reset"] for r in records] == [
        "first frame",
        None,
        None,
        None,
        "scene cut",
        None,
        None,
    ]
    assert [r.get("cut", False) for r in records] == [False] * 4 + [True, False, False]
    alone = m360.video.run(second, tmp_path / "alone", model=model, progress=False, **FAST)
    assert alone.exit_code == 0
    for k in range(3):  # the same bytes as the second walk on its own
        for quantity in ("disparity", "depth"):
            name = f"{quantity}.npy"
            a = np.load(tmp_path / "out" / f"{4 + k:06d}.{name}")
            b = np.load(tmp_path / "alone" / f"{k:06d}.{name}")
            np.testing.assert_array_equal(a, b)


def test_a_corrupt_frame_fails_alone(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    _walk_frames(folder, 5, 5)
    bad = sorted(folder.iterdir())[2]
    bad.write_bytes(bad.read_bytes()[:200])  # truncated PNG
    out = tmp_path / "out"
    report = m360.video.run(folder, out, model=batch_helpers.Gated(None), progress=False, **FAST)
    assert report.exit_code == 1
    assert [o.stem for o in report.failed] == ["000002"]
    assert [o.stem for o in report.done] == ["000000", "000001", "000003", "000004"]
    lines = (out / "failures.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["output"] == "000002"
    assert json.loads(lines[0])["error"] == "ReadError"
    assert not list(out.glob("000002*"))
    assert _sidecar(out, 3)["temporal"]["reset"] == "previous frame failed"  # no term across it
    again = m360.video.run(folder, out, model=batch_helpers.Gated(None), progress=False, **FAST)
    assert len(again.skipped) == 4 and [o.stem for o in again.failed] == ["000002"]


def test_a_frame_whose_files_cannot_be_written_fails_alone(tmp_path: Path) -> None:
    """Frame 2's files are written on the writer thread while frame 3 is estimated: when that
    write fails, frame 3 is redone without the temporal term, as a run writing in line would,
    and the outcomes stay in frame order."""
    folder = tmp_path / "frames"
    _walk_frames(folder, 5, 5)
    out = tmp_path / "out"
    (out / "000002.disparity.npy").mkdir(parents=True)  # a folder where a file must go
    report = m360.video.run(folder, out, model=batch_helpers.Gated(None), progress=False, **FAST)
    assert report.exit_code == 1
    assert [o.stem for o in report.outcomes] == [f"{k:06d}" for k in range(5)]
    assert [o.stem for o in report.failed] == ["000002"]
    assert _sidecar(out, 3)["temporal"]["reset"] == "previous frame failed"
    assert _sidecar(out, 4)["temporal"]["reset"] is None  # the term goes on after it
    # The same bytes as frames 3-4 computed afresh: a run of those frames alone.
    alone = tmp_path / "alone"
    _walk_frames(alone, 5, 5)
    for extra in sorted(alone.iterdir())[:3]:
        extra.unlink()
    reference = m360.video.run(
        alone, tmp_path / "ref", model=batch_helpers.Gated(None), progress=False, **FAST
    )
    assert reference.exit_code == 0
    ref = _arrays(tmp_path / "ref")
    assert ref["000000.disparity.npy"] == (out / "000003.disparity.npy").read_bytes()
    assert ref["000001.disparity.npy"] == (out / "000004.disparity.npy").read_bytes()


def test_frame_selection_and_resume_by_fingerprint(tmp_path: Path) -> None:
    clip = _encode(tmp_path / "clip.mp4", 12)
    out = tmp_path / "out"
    model = batch_helpers.Gated(None)
    first = m360.video.run(clip, out, model=model, every=4, progress=False, **FAST)
    assert [o.stem for o in first.done] == ["000000", "000004", "000008"]
    meta = _sidecar(out, 4)
    assert meta["frame"]["index"] == 4 and meta["frame"]["time"] == pytest.approx(4 / 24)
    again = m360.video.run(clip, out, model=model, every=4, progress=False, **FAST)
    assert len(again.skipped) == 3 and not again.done
    other = m360.video.run(clip, out, model=model, every=4, temporal="none", progress=False, **FAST)
    assert len(other.done) == 3  # another temporal mode is another output: redone
    with pytest.raises(m360.InputError, match="no prior of its own"):
        m360.video.run(clip, out, model=model, prior=np.ones((8, 16)), progress=False)
    run_file = json.loads((out / m360.video.RUN_FILE).read_text())
    assert run_file["frames"] == ["000000", "000004", "000008"]


def test_preview_video_has_every_frame_and_one_colour_scale(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    _walk_frames(folder, 2, 4)
    out = tmp_path / "out"
    report = m360.video.run(
        folder, out, model=batch_helpers.Gated(None), preview_video=True, progress=False, **FAST
    )
    assert report.preview_video == out / "preview.mp4"
    decoded = list(m360.video.frames(out / "preview.mp4"))
    assert len(decoded) == 4
    values = np.concatenate([m360.load(out / f"{k:06d}").disparity.ravel() for k in range(4)])
    lo, hi = np.percentile(values[np.isfinite(values)], (2, 98))
    assert report.colour_scale == pytest.approx((lo, hi), rel=0.02)
    assert json.loads((out / "video.json").read_text())["preview_video"]["disparity_range"] == (
        pytest.approx(list(report.colour_scale))
    )


_GATED_VIDEO = """
import sys, m360, batch_helpers
gate = sys.argv[3] or None
batch = int(sys.argv[4]) if len(sys.argv) > 4 else 1
report = m360.video.run(sys.argv[1], sys.argv[2], model=batch_helpers.Gated(gate),
                        align="none", blend="mean", progress=False, frame_batch=batch)
print(report.summary(), file=sys.stderr)
sys.exit(report.exit_code)
"""


def _read_exactly(fd: int, count: int, proc: subprocess.Popen) -> None:
    got = 0
    while got < count:
        ready, _, _ = select.select([fd], [], [], 120)  # only a guard against a hung run
        assert ready, f"the run stalled after {got} of {count} frame starts"
        got += len(os.read(fd, count - got))
        assert proc.poll() is None, "the run ended before it could be stopped"


def _wait_until(done: Callable[[], bool], proc: subprocess.Popen) -> None:
    """Poll ``done`` until it holds; fail after 120 s or when the run ended (a guard only)."""
    deadline = time.monotonic() + 120
    while not done():
        assert time.monotonic() < deadline, "the run never got there"
        assert proc.poll() is None, "the run ended before it could be stopped"
        time.sleep(0.01)


def _gated_walk(tmp_path: Path) -> tuple[dict[str, str], Path, Path, list[str]]:
    """8 walk frames, a reference run of them without a gate; (env, reference, out, command):
    the command runs the frames into ``out``, given then the gate folder (or "")."""
    folder = tmp_path / "frames"
    _walk_frames(folder, 4, 8)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    env["M360_HOME"] = str(tmp_path / "home")
    reference, out = tmp_path / "reference", tmp_path / "out"
    subprocess.run(
        [sys.executable, "-c", _GATED_VIDEO, str(folder), str(reference), ""],
        env=env,
        check=True,
        capture_output=True,
        timeout=300,
    )
    return env, reference, out, [sys.executable, "-c", _GATED_VIDEO, str(folder), str(out)]


@pytest.mark.skipif(sys.platform == "win32", reason="needs FIFOs and process groups")
@pytest.mark.parametrize("batch", [1, 3])
def test_a_killed_run_redoes_only_unfinished_frames_with_the_same_bytes(
    tmp_path: Path, batch: int
) -> None:
    """SIGKILL with 3 frames done and the 4th in the network; the rerun does the other 5 from
    the 3rd frame's state and writes what a run never stopped writes. With frame_batch=3 the
    network's second call (frames 3-5) is the one stopped, and a frame_batch=1 run is the
    reference."""
    env, reference, out, cmd = _gated_walk(tmp_path)
    gate = tmp_path / "gate"
    gate.mkdir()
    started, tokens = batch_helpers.make_gate(str(gate))
    proc = subprocess.Popen(
        [*cmd, str(gate), str(batch)], env=env, stderr=subprocess.PIPE, start_new_session=True
    )
    calls = 3 // batch  # the network calls of the first 3 frames
    try:
        os.write(tokens, b"t" * calls)
        _read_exactly(started, calls + 1, proc)  # the 4th frame waits in the network
        # The 3rd frame's files are written on the run's writer thread while the 4th is
        # estimated: nothing blocks that write, so wait for its sidecar (a guard, not a race).
        _wait_until(lambda: (out / "000002.json").is_file(), proc)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    finished = {p.name: p.stat().st_mtime_ns for p in out.glob("*.json")}
    assert sorted(finished) == ["000000.json", "000001.json", "000002.json"]
    # What a writer killed half-way leaves: temporaries of the 4th frame's files.
    for name in ("000003.disparity.npy", "000003.temporal.npy"):
        (out / f".{name}.abcdefgh.tmp").write_bytes(b"partial")
    rerun = subprocess.run([*cmd, "", str(batch)], env=env, capture_output=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr.decode()
    assert "5 done, 3 already done, 0 failed" in rerun.stderr.decode()
    assert {k: (out / k).stat().st_mtime_ns for k in finished} == finished  # not redone
    assert _arrays(out) == _arrays(reference)  # every array and state, byte for byte
    assert len(_arrays(out)) == 8 * 3
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries, locks


@pytest.mark.skipif(sys.platform == "win32", reason="needs FIFOs and SIGINT to a process")
def test_ctrl_c_stops_the_run_and_a_rerun_finishes_it_with_the_same_bytes(tmp_path: Path) -> None:
    """SIGINT with 3 frames written, the 4th in the network on an estimate worker and the 5th
    waiting for its turn: the run finishes the frame in flight, stops (exit 130, "interrupted")
    and leaves no thread behind; a rerun redoes only the frames not written and writes what a
    run never stopped writes. Tokens for every frame are given after the signal, so whichever
    comes first, the signal or the 4th frame's end, the run ends and the rerun agrees."""
    env, reference, out, cmd = _gated_walk(tmp_path)
    gate = tmp_path / "gate"
    gate.mkdir()
    started, tokens = batch_helpers.make_gate(str(gate))
    proc = subprocess.Popen([*cmd, str(gate)], env=env, stderr=subprocess.PIPE)
    try:
        os.write(tokens, b"ttt")
        _read_exactly(started, 4, proc)  # frame 3 waits in the network
        _wait_until(lambda: (out / "000002.json").is_file(), proc)
        os.kill(proc.pid, signal.SIGINT)
        os.write(tokens, b"t" * 8)  # no frame waits forever in the gate
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr.decode()
    assert "interrupted" in stderr.decode()
    finished = {p.name: p.stat().st_mtime_ns for p in out.glob("[0-9]*.json")}  # frames'
    assert {"000000.json", "000001.json", "000002.json"} <= set(finished)
    rerun = subprocess.run([*cmd, ""], env=env, capture_output=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr.decode()
    assert f"{8 - len(finished)} done, {len(finished)} already done" in rerun.stderr.decode()
    assert {k: (out / k).stat().st_mtime_ns for k in finished} == finished  # not redone
    assert _arrays(out) == _arrays(reference)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries, locks


def test_a_video_that_is_not_equirectangular_is_refused_before_any_frame(tmp_path: Path) -> None:
    clip = tmp_path / "wide.mp4"
    with av.open(str(clip), "w") as container:
        stream = container.add_stream("mpeg4", rate=24)
        stream.width, stream.height, stream.pix_fmt = 320, 128, "yuv420p"
        for _ in range(2):
            image = np.zeros((128, 320, 3), np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    with pytest.raises(m360.InputError, match="320x128"):
        m360.video.run(clip, tmp_path / "out", model=batch_helpers.Gated(None), progress=False)
    assert not (tmp_path / "out").exists()


def test_a_second_run_into_a_busy_folder_is_refused(tmp_path: Path) -> None:
    from m360.batch.image import claim

    folder = tmp_path / "frames"
    _walk_frames(folder, 1, 2)
    out = tmp_path / "out"
    out.mkdir()
    with claim(out / "video") as claimed:
        assert claimed
        report = m360.video.run(folder, out, model=batch_helpers.Gated(None), progress=False)
    assert report.exit_code == 3 and not list(out.glob("*.json"))


def test_cli_video(tmp_path: Path) -> None:
    from m360.cli import main

    clip = _encode(tmp_path / "clip.mp4", 6)
    out = tmp_path / "out"
    model = tmp_path / "tiny.onnx"
    import onnx_graphs as g

    g.affine_of_mean(model, 1.0, 3.0)
    argv = ["video", str(clip), "-o", str(out), "--model", str(model), "--every", "2"]
    argv += ["--start", "1", "--formats", "png16", "--no-progress", "--align", "none"]
    argv += ["--blend", "mean", "--input-size", "64", "96", "--threads", "1", "--frame-batch", "2"]
    assert main(argv) == 0
    assert sorted(p.name for p in out.glob("*.json")) == [
        "000001.json",
        "000003.json",
        "000005.json",
        "video.json",
    ]
    assert json.loads((out / "video.json").read_text())["engine"]["frame_batch"] == 2
    assert main([*argv[:3], "--start", "0.1s", *argv[3:5], "--end", "x"]) == 2


def test_video_on_the_subdivided_layout(tmp_path: Path) -> None:
    """subdivisions=1: every frame on the 80-tangent layout (its scaled grids), each frame's
    bytes those of m360.estimate with the same options (no temporal term), in batches of 2
    too; the resume fingerprint holds it (the default layout redoes the frames)."""
    import onnx_graphs as g

    folder = tmp_path / "frames"
    _walk_frames(folder, 4, 3)
    model = str(g.affine_of_mean(tmp_path / "tiny.onnx", 1.0, 3.0))
    kw = {"model": model, "input_size": (32, 48), "threads": 1, "temporal": "none"}
    first = m360.video.run(folder, tmp_path / "one", subdivisions=1, progress=False, **kw)
    two = m360.video.run(
        folder, tmp_path / "two", subdivisions=1, frame_batch=2, progress=False, **kw
    )
    assert len(first.done) == len(two.done) == 3
    assert _arrays(tmp_path / "one") == _arrays(tmp_path / "two")
    meta = _sidecar(tmp_path / "one", 1)
    assert "80 cameras" in meta["options"]["layout"]
    assert meta["options"]["align"]["levels"] == [[2, 2], [4, 4]]
    rgb = cv2.imread(str(sorted(folder.iterdir())[1]))[:, :, ::-1]
    alone = m360.estimate(rgb, model, subdivisions=1, input_size=(32, 48), threads=1)
    np.testing.assert_array_equal(
        np.load(tmp_path / "one" / "000001.disparity.npy"), alone.disparity
    )
    again = m360.video.run(folder, tmp_path / "one", progress=False, **kw)
    assert len(again.done) == 3  # the 20 default tangents: another result


# --------------------------------------------------------------------------------------------
# The synthetic walk and the temporal term.


def test_scene_cuts_are_found_and_turns_are_not() -> None:
    from m360.video.temporal import grey_of

    greys = [grey_of(sq.walk(seed, 2, erp_width=256).render(1)[0]) for seed in (1, 6)]
    assert m360.video.scene_cut(greys[1], greys[0])[0]
    turned = np.roll(greys[0], greys[0].shape[1] // 3, axis=1)  # the camera turned 120°
    cut, correlation = m360.video.scene_cut(turned, greys[0])
    assert not cut and correlation == pytest.approx(1.0, abs=1e-4)


def test_flicker_metric_against_known_changes() -> None:
    walk = sq.walk(3, 6, erp_width=128)
    truth = [walk.render(k)[1] for k in range(6)]
    assert np.nanmax(sq.flicker(truth, truth, walk.positions)) < 2e-3  # the truth: none
    wobble = [d * (1.1 if k % 2 else 1.0) for k, d in enumerate(truth)]
    flicker = sq.flicker(wobble, truth, walk.positions)
    expected = [0.1, 1 / 1.1 - 1] * 3
    np.testing.assert_allclose(flicker, np.abs(expected[:5]), atol=3e-3)
    moved = np.linalg.norm(np.diff(walk.positions, axis=0), axis=1)
    assert np.allclose(moved, moved[0]) and moved[0] > 0  # a steady walk
    for k in range(6):  # the camera keeps its distance from everything
        assert walk.scene_at(k).camera_clearance() >= sq.CLEARANCE


def test_the_temporal_term_removes_flicker_without_losing_accuracy() -> None:
    """A 256-wide walk with the simulated network's per-tile errors drawn anew per frame: the
    smoothed video flickers under a third of the per-frame one, and is as accurate."""
    walk = sq.walk(2, 10, erp_width=256)
    layout = default_layout(256)
    estimator = sq.SequenceEstimator(walk, layout)
    truth = [walk.render(k)[1] for k in range(10)]
    results = {}
    for mode in ("none", "smooth"):
        temporal = m360.video.Temporal(mode)
        state, depths, absrel = None, [], []
        for k in range(10):
            rgb = walk.render(k)[0]
            grey, confidence, _ = temporal.prepare(rgb, state)
            result = m360.estimate(rgb, estimator, layout=layout)
            disparity, state, _ = temporal.apply(result.disparity, grey, confidence, state)
            depths.append(1 / disparity)
            absrel.append(depth_metrics(disparity, truth[k])["abs_rel"])
        flicker = float(np.median(sq.flicker(depths, truth, walk.positions)))
        results[mode] = (flicker, float(np.mean(absrel)))
    assert results["smooth"][0] < results["none"][0] / 3, results
    assert results["smooth"][1] <= results["none"][1] + 0.002, results


def test_the_previous_frame_goes_to_the_stitch_as_a_prior(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With Temporal(prior=True) each frame after the first (and not after a cut) gets the
    previous frame's state as the stitch's prior, in the run's units, with the image-change
    confidence; none without alignment, none by default."""
    import m360.pipeline.estimate as pipeline_estimate

    real = pipeline_estimate.finish
    calls: list[dict] = []

    def finish(prepared, raw, **keywords):  # every frame's stitch starts here
        names = ("prior", "prior_kind", "prior_confidence")
        calls.append({k: keywords[k] for k in names if k in keywords})
        return real(prepared, raw, **keywords)

    monkeypatch.setattr(pipeline_estimate, "finish", finish)
    folder = tmp_path / "frames"
    _walk_frames(folder, 3, 3)
    model = batch_helpers.Gated(None)
    out = tmp_path / "out"
    with_prior = m360.video.Temporal("smooth", prior=True)
    run = m360.video.run(
        folder, out, model=model, temporal=with_prior, progress=False, blend="mean"
    )
    assert run.exit_code == 0
    assert calls[0] == {} and len(calls) == 3
    for k, prior in enumerate(calls[1:], start=1):
        state = m360.video.TemporalState.load(out / f"{k - 1:06d}{m360.video.STATE_SUFFIX}")
        np.testing.assert_array_equal(prior["prior"], state.disparity + state.velocity)
        assert prior["prior_kind"] == "disparity"
        confidence = prior["prior_confidence"]
        assert confidence.shape == state.disparity.shape
        assert 0 <= confidence.min() and confidence.max() <= 1 and confidence.mean() > 0.5
    assert [_sidecar(out, k)["temporal"]["prior"] for k in range(3)] == [False, True, True]
    calls.clear()
    m360.video.run(
        folder, tmp_path / "none", model=model, temporal=with_prior, progress=False, **FAST
    )
    assert calls == [{}, {}, {}]  # align="none": no prior
    calls.clear()
    m360.video.run(folder, tmp_path / "default", model=model, progress=False, blend="mean")
    assert calls == [{}, {}, {}]  # the default: steps 4-5 only (measured, docs/video.md)


def test_a_damaged_packet_of_a_video_fails_its_frame_alone(tmp_path: Path) -> None:
    """The decoder drops a frame it cannot decode without an error; the frame is reported lost
    and the frames after it keep the encoder's numbers (ranked by timestamp, not counted)."""
    clip = _encode(tmp_path / "clip.mkv", 40)
    with av.open(str(clip)) as container:  # where the 20th packet's bytes lie in the file
        packets = [(p.pos, p.size) for p in container.demux(video=0) if p.size]
    pos, size = packets[20]
    data = bytearray(clip.read_bytes())
    data[pos + size - size // 2 : pos + size] = bytes(size // 2)  # half its payload zeroed
    clip.write_bytes(bytes(data))
    frames = list(m360.video.frames(clip, on_error="yield"))
    assert [f.index for f in frames] == list(range(40))
    assert [f.index for f in frames if f.error is not None] == [20]
    assert isinstance(frames[20].error, m360.ReadError) and frames[20].rgb is None
    assert frames[20].time == pytest.approx(20 / 24, abs=1e-3)  # MKV: millisecond times
    assert [_index_of(f.rgb) for f in frames[:20]] == list(range(20))
    with pytest.raises(m360.ReadError, match="frame 20 of"):
        list(m360.video.frames(clip))
    out = tmp_path / "out"
    report = m360.video.run(clip, out, model=batch_helpers.Gated(None), progress=False, **FAST)
    assert report.exit_code == 1
    assert [o.stem for o in report.failed] == ["000020"] and len(report.done) == 39
    failures = (out / "failures.jsonl").read_text().splitlines()
    assert len(failures) == 1 and json.loads(failures[0])["output"] == "000020"
    assert _sidecar(out, 21)["temporal"]["reset"] == "previous frame failed"


# --------------------------------------------------------------------------------------------
# Frame batches: one network call for several frames, then each frame in order.


class _Counted:
    """Wraps an estimator: records the tangents of every call; refuses frame ``bad`` (any
    call holding its tangents raises) and, with ``one_frame``, any call of several frames."""

    output_kind = "affine_disparity"
    name = "counted"

    def __init__(self, inner: sq.SequenceEstimator, bad: int | None = None, one_frame=False):
        self.inner, self.bad, self.one_frame = inner, bad, one_frame
        self.layout = inner.layout
        self.calls: list[list[int]] = []  # the frames of each call

    def predict(self, tangents: np.ndarray) -> np.ndarray:
        n = len(self.layout)
        shown = [self.inner.frame_of(tangents[k : k + n]) for k in range(0, len(tangents), n)]
        self.calls.append(shown)
        if self.bad in shown:
            raise RuntimeError(f"frame {self.bad} breaks the network")
        if self.one_frame and len(shown) > 1:
            raise RuntimeError("one frame at a time")
        return self.inner.predict(tangents)


def _walk_run(tmp_path: Path, count: int = 7, seed: int = 4) -> tuple[Path, sq.SequenceEstimator]:
    folder = tmp_path / "frames"
    _walk_frames(folder, seed, count)
    walk = sq.walk(seed, count, erp_width=256)
    images = [cv2.imread(str(p))[:, :, ::-1] for p in sorted(folder.iterdir())]
    return folder, sq.SequenceEstimator(walk, default_layout(256), images=images)


@pytest.mark.parametrize("temporal", ["smooth", "prior"])
def test_frame_batches_write_the_bytes_of_frame_by_frame(tmp_path: Path, temporal: str) -> None:
    """frame_batch=3 on 7 frames: calls of frames [0, 1, 2], [3, 4, 5], then 6 alone, and every
    array and temporal state byte for byte as frame_batch=1 (m360.estimate per frame), with
    the previous frame as the stitch's prior too (given to finish, not to prepare)."""
    folder, inner = _walk_run(tmp_path)
    mode = m360.video.Temporal("smooth", prior=True) if temporal == "prior" else temporal
    outs, calls = {}, {}
    for batch in (1, 3):
        model = _Counted(inner)
        out = tmp_path / f"out{batch}"
        report = m360.video.run(
            folder, out, model=model, temporal=mode, progress=False, frame_batch=batch
        )
        assert report.exit_code == 0 and len(report.done) == 7 and not report.notes
        outs[batch], calls[batch] = _arrays(out), model.calls
    assert calls[1] == [[k] for k in range(7)]
    assert calls[3] == [[0, 1, 2], [3, 4, 5], [6]]
    assert len(outs[3]) == 7 * 3 and outs[3] == outs[1]
    if temporal == "prior":
        assert [_sidecar(tmp_path / "out3", k)["temporal"]["prior"] for k in range(3)] == [
            False,
            True,
            True,
        ]
    # The same outputs, the same fingerprint: a run with another frame_batch skips them all.
    for k in range(7):
        assert (
            _sidecar(tmp_path / "out3", k)["batch"]["fingerprint"]
            == (_sidecar(tmp_path / "out1", k)["batch"]["fingerprint"])
        )
    again = m360.video.run(
        folder, tmp_path / "out3", model=_Counted(inner), temporal=mode, progress=False
    )
    assert len(again.skipped) == 7 and not again.done


def test_a_frame_whose_prediction_fails_fails_alone_in_a_batch(tmp_path: Path) -> None:
    """The call of frames [3, 4, 5] raises: each of them runs its own call, only frame 4 fails,
    and the run writes what frame_batch=1 writes with the same network."""
    folder, inner = _walk_run(tmp_path)
    outs = {}
    for batch in (1, 3):
        model = _Counted(inner, bad=4)
        out = tmp_path / f"out{batch}"
        report = m360.video.run(folder, out, model=model, progress=False, frame_batch=batch)
        assert report.exit_code == 1 and [o.stem for o in report.failed] == ["000004"]
        assert len(report.done) == 6 and not report.notes
        lines = (out / "failures.jsonl").read_text().splitlines()
        assert [json.loads(line)["output"] for line in lines] == ["000004"]
        assert _sidecar(out, 5)["temporal"]["reset"] == "previous frame failed"
        outs[batch] = _arrays(out)
    assert model.calls == [[0, 1, 2], [3, 4, 5], [3], [4], [5], [6]]  # batching goes on
    assert len(outs[3]) == 6 * 3 and outs[3] == outs[1]


@pytest.mark.parametrize("temporal", ["none", "smooth"])
def test_frames_are_estimated_two_at_once_with_the_bytes_of_stills(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, temporal: str
) -> None:
    """The local engine stitches a frame while the next one's network runs (the first stitch
    waits for frame 1's network call: one frame at a time would wait forever, so the watchdog
    fails it), the network's calls stay in frame order, and each frame is m360.estimate's
    result on it, then the temporal term's in order, byte for byte."""
    import threading

    import m360.pipeline.estimate as pipeline_estimate

    folder, inner = _walk_run(tmp_path)
    next_called = threading.Event()

    class Watched(_Counted):
        def predict(self, tangents: np.ndarray) -> np.ndarray:
            out = super().predict(tangents)
            if self.calls[-1] == [1]:
                next_called.set()
            return out

    real = pipeline_estimate.finish
    stitches: list[int] = []
    overlapped: list[bool] = []
    first = threading.Lock()

    def finish(prepared, raw, **keywords):
        with first:
            stitches.append(len(stitches))
            mine = stitches[-1]
        if mine == 0:  # the first stitch (frame 0's): frame 1's network runs meanwhile
            overlapped.append(next_called.wait(timeout=120))
        return real(prepared, raw, **keywords)

    monkeypatch.setattr(pipeline_estimate, "finish", finish)
    model = Watched(inner)
    report = m360.video.run(
        folder, tmp_path / "out", model=model, temporal=temporal, progress=False
    )
    assert report.exit_code == 0 and len(report.done) == 7
    assert overlapped == [True]
    assert model.calls == [[k] for k in range(7)]
    monkeypatch.setattr(pipeline_estimate, "finish", real)
    mode = m360.video.Temporal(temporal)
    state = None
    for frame in m360.video.frames(folder):
        still = m360.estimate(frame.rgb, inner)
        grey, confidence, _ = mode.prepare(frame.rgb, state)
        expected, state, _ = mode.apply(still.disparity, grey, confidence, state)
        written = np.load(tmp_path / "out" / f"{frame.index:06d}.disparity.npy")
        assert written.tobytes() == expected.tobytes(), frame.index
        if temporal == "none":
            assert written.tobytes() == still.disparity.tobytes()


def test_network_turns_go_in_ticket_order_whichever_thread_comes_first() -> None:
    """Tickets used from threads started in reverse order still call in ticket order; a ticket
    given up passes its turn on; closing wakes a waiting ticket with CancelledError."""
    import threading
    from concurrent.futures import CancelledError

    from m360.video._ahead import NetworkTurns

    turns = NetworkTurns()
    tickets = [turns.ticket() for _ in range(4)]
    order: list[int] = []

    def use(ticket: int) -> None:
        if ticket == 2:
            turns.release(ticket)  # no call: its turn passes on
            return
        with turns.call(ticket):
            order.append(ticket)
        turns.release(ticket)  # after its call: nothing

    threads = [threading.Thread(target=use, args=(t,)) for t in reversed(tickets)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
        assert not thread.is_alive(), "a turn never came"
    assert order == [0, 1, 3]
    late, errors = turns.ticket() + 1, []  # a ticket whose turn never comes

    def wait() -> None:
        try:
            with turns.call(late):
                pass
        except CancelledError as exc:
            errors.append(exc)

    waiting = threading.Thread(target=wait)
    waiting.start()
    turns.close()
    waiting.join(timeout=60)
    assert not waiting.is_alive() and len(errors) == 1


def test_an_estimator_of_one_frame_at_a_time_goes_on_frame_by_frame(tmp_path: Path) -> None:
    folder, inner = _walk_run(tmp_path)
    reference = m360.video.run(folder, tmp_path / "ref", model=_Counted(inner), progress=False)
    model = _Counted(inner, one_frame=True)
    report = m360.video.run(folder, tmp_path / "out", model=model, progress=False, frame_batch=3)
    assert report.exit_code == reference.exit_code == 0
    assert model.calls == [[0, 1, 2], *([k] for k in range(7))]
    assert len(report.notes) == 1 and "one frame at a time" in report.notes[0]
    assert _arrays(tmp_path / "out") == _arrays(tmp_path / "ref")


def test_frame_batch_is_capped_by_memory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With memory for one frame's estimate and no more, frames go one at a time (a note),
    and one frame is estimated at a time (a note)."""
    from m360.pipeline.memory import estimate_memory

    folder, inner = _walk_run(tmp_path, count=3)
    one = estimate_memory(256, 256, "consensus", default_layout(256))
    monkeypatch.setenv("M360_MEMORY_LIMIT", str(one + 1000))
    model = _Counted(inner)
    report = m360.video.run(folder, tmp_path / "out", model=model, progress=False, frame_batch=3)
    assert report.exit_code == 0 and model.calls == [[0], [1], [2]]
    assert len(report.notes) == 2 and "1 frame estimated at a time, not 2" in report.notes[0]
    assert "frame_batch 3 lowered to 1" in report.notes[1]
    monkeypatch.setenv("M360_MEMORY_LIMIT", str(one + 10 * 2**30))  # room to spare
    model = _Counted(inner)
    report = m360.video.run(folder, tmp_path / "more", model=model, progress=False, frame_batch=3)
    assert model.calls == [[0, 1, 2]] and not report.notes


def test_frame_batch_options(tmp_path: Path) -> None:
    folder, inner = _walk_run(tmp_path, count=2)

    class Panoramic:  # only its role matters: refused before any frame
        kind = "panoramic"
        output_kind = "distance"

        def predict(self, image: np.ndarray) -> np.ndarray:
            raise AssertionError("no frame should run")

    for layout_option in ({"padding": 0.3}, {"subdivisions": 1}):
        with pytest.raises(m360.InputError, match="padding and subdivisions do not apply"):
            m360.video.run(folder, tmp_path / "pano", model=Panoramic(), **layout_option)
    assert not (tmp_path / "pano").exists()
    for bad in (0, 1.5, "2"):
        with pytest.raises(m360.InputError, match="frame_batch"):
            m360.video.run(folder, tmp_path / "out", model=inner, frame_batch=bad)
    with pytest.raises(m360.InputError, match="not to chunked runs"):
        m360.video.run(folder, tmp_path / "out", model=inner, chunk=4, frame_batch=2)


def test_prepare_then_finish_is_estimate(tmp_path: Path) -> None:
    """m360.estimate split in two around its network call: the same bytes, also with a prior
    given only to finish; misuse is an InputError."""
    from m360.pipeline.estimate import finish, prepare

    folder, inner = _walk_run(tmp_path, count=2)
    rgb = cv2.imread(str(next(folder.iterdir())))[:, :, ::-1].copy()
    prior = np.full((32, 64), 0.5, np.float32)
    whole = m360.estimate(rgb, inner, prior=prior, prior_kind="affine_disparity", sky="nan")
    prepared = prepare(rgb, inner, sky="nan")
    assert prepared.tangents.shape == (20, *prepared.layout.tangent_shape, 3)
    raw = inner.predict(prepared.release())
    split = finish(prepared, raw, prior=prior, prior_kind="affine_disparity")
    for name in ("disparity", "depth", "confidence", "tangents"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name))
    assert split.options == whole.options and set(split.timings) == set(whole.timings)
    with pytest.raises(m360.InputError, match="already released"):
        prepared.release()
    early = prepare(rgb, inner, prior=prior, prior_kind="affine_disparity")
    with pytest.raises(m360.InputError, match="give it once"):
        finish(early, raw, prior=prior, prior_kind="affine_disparity")
    with pytest.raises(m360.ModelError, match="expected float"):
        finish(prepare(rgb, inner), raw[:3])
    with pytest.raises(m360.InputError, match="acts through the alignment"):
        finish(prepare(rgb, inner, align="none"), raw, prior=prior, prior_kind="disparity")
    with pytest.raises(m360.InputError, match="panoramic"):
        prepare(rgb, inner, kind="panoramic")


def _bilinear_wrapped(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Independent bilinear upsampling with pixel centres, rows clamped, columns wrapped."""
    height, width = shape
    h, w = values.shape[:2]
    col = (np.arange(width) + 0.5) * w / width - 0.5
    row = np.clip((np.arange(height) + 0.5) * h / height - 0.5, 0, h - 1)
    c0 = np.floor(col).astype(int)
    fx = (col - c0)[None, :, None]
    c0, c1 = c0 % w, (c0 + 1) % w
    r0 = np.minimum(np.floor(row).astype(int), h - 2)
    fy = (row - r0)[:, None, None]
    top = values[r0][:, c0] * (1 - fx) + values[r0][:, c1] * fx
    bottom = values[r0 + 1][:, c0] * (1 - fx) + values[r0 + 1][:, c1] * fx
    return top * (1 - fy) + bottom * fy


@pytest.mark.parametrize("shape", [(256, 512), (200, 400), (75, 150)])
def test_the_state_grows_bilinearly_across_the_seam(shape: tuple[int, int]) -> None:
    from m360.video.temporal import _grow

    values = np.random.default_rng(3).random((32, 64, 2)).astype(np.float32)
    got = _grow(values, shape)  # 512 and 128 are multiples of 64 (the resize path), 150 not
    np.testing.assert_allclose(got, _bilinear_wrapped(values, shape), atol=2e-6)


def test_the_gauge_fit_is_the_weighted_least_squares_without_the_worst_fifth() -> None:
    from m360.video.temporal import _fit_gauge

    rng = np.random.default_rng(5)
    current = rng.random((64, 128)).astype(np.float32) + 0.5
    target = 1.7 * current + 0.3 + rng.normal(0, 0.01, current.shape).astype(np.float32)
    target[:8] += 5.0  # an eighth of the map moved: left out by the refit
    weight = np.where(rng.random(current.shape) < 0.1, 0.2, 1.0).astype(np.float32)
    a, b = _fit_gauge(current, target, weight) or (np.nan, np.nan)
    # The oracle: numpy's lstsq on the same steps.
    keep = weight > 0.5
    x, y, w = current[keep].astype(float), target[keep].astype(float), weight[keep].astype(float)
    for _ in range(2):
        design = np.stack([x, np.ones_like(x)], 1) * np.sqrt(w)[:, None]
        fit = np.linalg.lstsq(design, y * np.sqrt(w), rcond=None)[0]
        inliers = np.abs(fit[0] * x + fit[1] - y) <= np.quantile(
            np.abs(fit[0] * x + fit[1] - y), 0.8
        )
        x, y, w = x[inliers], y[inliers], w[inliers]
    assert a == pytest.approx(fit[0], rel=1e-9) and b == pytest.approx(fit[1], rel=1e-9)
    assert a == pytest.approx(1.7, abs=0.01) and b == pytest.approx(0.3, abs=0.01)


def test_the_state_shrinks_to_the_area_average_of_finite_pixels() -> None:
    from m360.video.temporal import shrink

    rng = np.random.default_rng(7)
    disparity = (0.2 + rng.random((512, 1024))).astype(np.float32)  # 2 x 2 blocks per cell
    blocks = disparity.reshape(256, 2, 512, 2)
    np.testing.assert_allclose(shrink(disparity), blocks.mean(axis=(1, 3)), rtol=1e-6)
    holed = disparity.copy()
    holed[::2, ::2] = np.nan  # a quarter of each block unknown: the mean of the other three
    holed[:2, :2] = np.nan  # a whole block unknown: NaN
    cells = holed.reshape(256, 2, 512, 2)
    count = np.isfinite(cells).sum(axis=(1, 3))
    total = np.nansum(cells, axis=(1, 3))
    expected = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    np.testing.assert_allclose(shrink(holed), expected, rtol=1e-6)
