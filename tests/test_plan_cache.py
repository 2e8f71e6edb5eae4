"""The disk plan cache: results bit-identical with and without it, damaged files rebuilt,
concurrent builders, the off switch, and the `m360 plans` command.

Every test uses its own M360_HOME. The Rust unit tests (rust/m360-core/src/plan_cache.rs) check
each kind of damage (including resealed files with out-of-bounds indices) map by map.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import m360
import m360.synthetic as syn
import numpy as np
import pytest
from m360 import M360Error, _core, plan_cache
from m360.cli import main
from m360.estimators import SimulatedEstimator
from m360.geometry import clear_plan_cache, plan_for

WIDTH = 256
SCENE = syn.room(2)


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    monkeypatch.setenv("M360_HOME", str(tmp_path / "home"))
    monkeypatch.delenv(plan_cache.ENV_SWITCH, raising=False)
    plan_cache.set_enabled(None)
    clear_plan_cache()
    yield tmp_path / "home"
    plan_cache.set_enabled(None)
    clear_plan_cache()


def _estimate() -> bytes:
    """Default estimate (alignment + consensus) on a fresh in-process plan: its result's bytes."""
    clear_plan_cache()
    layout = m360.Layout.icosahedron(WIDTH)
    rgb, _ = syn.render(SCENE, WIDTH)
    res = m360.estimate(rgb, SimulatedEstimator(SCENE, layout, seed=1), layout=layout)
    assert np.isfinite(res.disparity).mean() > 0.99
    parts = [res.disparity, res.depth] + ([] if res.confidence is None else [res.confidence])
    return b"".join(np.ascontiguousarray(p).tobytes() for p in parts)


def _stats() -> dict[str, int]:
    return plan_for(m360.Layout.icosahedron(WIDTH)).cache_stats()


def _plan_files(home: Path) -> dict[str, bytes]:
    folder = home / "plans"
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())} if folder.exists() else {}


def test_results_are_bit_identical_with_and_without_the_cache(home: Path) -> None:
    plan_cache.set_enabled(False)
    without = _estimate()
    assert _plan_files(home) == {}
    plan_cache.set_enabled(None)  # on by default
    building = _estimate()
    # Tangent taps, ERP taps, overlap samples (the weight maps are computed, never stored).
    assert _stats()["saved"] == _stats()["built"] == 3
    files = _plan_files(home)
    assert len(files) == _stats()["saved"]
    assert all(name.endswith(_core.PLAN_FORMAT + _core.PLAN_FILE_SUFFIX) for name in files)
    loading = _estimate()
    # The taps read their files in place (memory-mapped); the small overlap samples
    # are copied, as is everything on Windows.
    mapped = 0 if sys.platform == "win32" else sum(not n.startswith("overlaps-") for n in files)
    assert _stats() == {
        "loaded": len(files), "built": 0, "saved": 0, "rejected": 0, "mapped": mapped,
    }  # fmt: skip
    assert without == building == loading
    assert _plan_files(home) == files


def _flip_payload_byte(data: bytes) -> bytes:
    at = len(data) - len(data) // 3
    return data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1 :]


def _random_bytes(data: bytes) -> bytes:
    return np.random.default_rng(0).integers(0, 256, len(data), dtype=np.uint8).tobytes()


def _other_format(data: bytes) -> bytes:
    # The format version field (bytes 8..12) of another release; the header checksum no
    # longer matches either (the Rust tests reseal such files to reach the version check).
    return data[:8] + (99).to_bytes(4, "little") + data[12:]


DAMAGES = {
    "truncated": lambda data: data[: len(data) // 2],
    "flipped byte in payload": _flip_payload_byte,
    "foreign (random bytes)": _random_bytes,
    "other format version": _other_format,
    "empty": lambda data: b"",
}


@pytest.mark.parametrize("damage", DAMAGES)
def test_a_damaged_file_is_rebuilt_and_rewritten(
    home: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    expected = _estimate()
    files = _plan_files(home)
    (name,) = [n for n in files if n.startswith("erp-taps-")]
    (home / "plans" / name).write_bytes(DAMAGES[damage](files[name]))
    with caplog.at_level(logging.WARNING, logger="m360.plan_cache"):
        assert _estimate() == expected
    assert _stats()["rejected"] == 1 and _stats()["built"] == 1
    assert _plan_files(home) == files  # rewritten, byte for byte
    (record,) = [r for r in caplog.records if r.name == "m360.plan_cache"]
    assert name in record.getMessage() and "rejected" in record.getMessage()


def test_files_of_other_builds_are_ignored_and_cleared_as_stale(home: Path) -> None:
    _estimate()
    files = _plan_files(home)
    folder = home / "plans"
    for name, data in files.items():
        other = name.replace(_core.PLAN_FORMAT, "v1-0.0.1+000000000000")
        (folder / other).write_bytes(data)
    (folder / ".leftover.m360plan.123.0.tmp").write_bytes(b"partial")
    (folder / "unrelated.txt").write_text("not ours")
    use = plan_cache.usage()
    assert (use.files, use.stale_files) == (2 * len(files) + 1, len(files) + 1)
    assert _estimate() and _stats()["loaded"] == len(files)  # its own files, not the others
    plan_cache.clear(stale_only=True)
    assert _plan_files(home) == {**files, "unrelated.txt": b"not ours"}
    assert plan_cache.clear() == sum(map(len, files.values()))
    assert plan_cache.usage().files == 0 and (folder / "unrelated.txt").exists()


@pytest.mark.parametrize("switch", ["env", "function"])
def test_cache_off_writes_nothing(home: Path, switch: str, monkeypatch: pytest.MonkeyPatch) -> None:
    if switch == "env":
        monkeypatch.setenv(plan_cache.ENV_SWITCH, "0")
    else:
        plan_cache.set_enabled(False)
    assert not plan_cache.enabled()
    m360.Layout.icosahedron(WIDTH).prepare()
    _estimate()
    assert not home.exists()
    assert _stats()["saved"] == 0 and _stats()["built"] == 3


def test_prepare_writes_the_cache_and_a_new_process_loads_it(home: Path) -> None:
    m360.Layout.icosahedron(WIDTH).prepare()
    assert len(_plan_files(home)) == 3  # tangent and ERP taps, overlaps (weight maps are computed)
    script = textwrap.dedent(
        f"""
        import m360
        from m360.geometry import plan_for
        layout = m360.Layout.icosahedron({WIDTH}).prepare()
        print(sorted(plan_for(layout).cache_stats().items()))
        """
    )
    env = {**os.environ, "M360_HOME": str(home)}
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    mapped = 0 if sys.platform == "win32" else 2  # tangent and ERP taps (overlaps: copied)
    assert out.stdout.strip() == str(
        sorted({"built": 0, "loaded": 3, "rejected": 0, "saved": 0, "mapped": mapped}.items())
    )


#: Says "ready" once it holds the FIFO gate open, waits for one byte from it (the test writes
#: one per builder once all are ready), then builds the plan, estimates, and prints the
#: estimate's digest and the number of cache files the plan rejected.
_BUILDER = textwrap.dedent(
    f"""
    import hashlib, sys
    import m360, m360.synthetic as syn
    from m360.estimators import SimulatedEstimator
    from m360.geometry import plan_for
    gate = open(sys.argv[1], "rb", buffering=0)
    print("ready", flush=True)
    assert gate.read(1) == b"1"
    layout = m360.Layout.icosahedron({WIDTH})
    rgb, _ = syn.render(syn.room(2), {WIDTH})
    res = m360.estimate(rgb, SimulatedEstimator(syn.room(2), layout, seed=1), layout=layout)
    print(hashlib.sha256(res.disparity.tobytes()).hexdigest())
    print(plan_for(layout).cache_stats()["rejected"])
    """
)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs a FIFO for the gate")
def test_two_processes_building_the_same_plan_at_once_both_succeed(home: Path) -> None:
    gate = home.parent / "gate"
    os.mkfifo(gate)
    env = {**os.environ, "M360_HOME": str(home), "M360_NUM_THREADS": "1"}
    # Held open read-write by the test (Linux), so builders open it without blocking and wait in
    # read() until the test writes.
    writer = os.open(gate, os.O_RDWR)
    builders = [
        subprocess.Popen(
            [sys.executable, "-c", _BUILDER, str(gate)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    try:
        # A builder that dies early closes its stdout: readline returns "" and the test fails.
        assert [b.stdout.readline().strip() for b in builders if b.stdout] == ["ready"] * 2
        os.write(writer, b"11")  # both builders start building the same plan together
        outputs = [b.communicate(timeout=300) for b in builders]  # the watchdog
    finally:
        os.close(writer)
        for b in builders:
            b.kill()
    for b, (_, err) in zip(builders, outputs, strict=True):
        assert b.returncode == 0, err
    digests = {out.split()[0] for out, _ in outputs}
    assert len(digests) == 1 and all(out.split()[1] == "0" for out, _ in outputs)
    # Whichever rename won, the files are complete: a third process loads every map.
    files = _plan_files(home)
    assert len(files) == 3 and not [n for n in files if n.endswith(".tmp")]
    assert _estimate() and _stats()["rejected"] == 0 and _stats()["built"] == 0


def test_plans_command_shows_and_clears(home: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m360.Layout.icosahedron(WIDTH).prepare()
    size = sum(map(len, _plan_files(home).values()))
    assert main(["plans"]) == 0
    out = capsys.readouterr().out
    assert str(home / "plans") in out and f"3 files, {size / 1e6:.1f} MB" in out
    assert main(["plans", "clear"]) == 0
    assert _plan_files(home) == {}


def test_the_folder_is_trimmed_to_its_limit_least_recently_used_and_stale_first(
    home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = home / "plans"
    folder.mkdir(parents=True)
    suffix = f"-{_core.PLAN_FORMAT}{_core.PLAN_FILE_SUFFIX}"
    # (name, size, last used): a stale file used last, and three current ones.
    files = {
        "erp-taps-stale-v1-0.0.1+000000000000" + _core.PLAN_FILE_SUFFIX: (300, 4000),
        "erp-taps-a" + suffix: (400, 1000),
        "erp-taps-b" + suffix: (500, 3000),
        "erp-taps-c" + suffix: (600, 2000),
    }
    for name, (size, used) in files.items():
        (folder / name).write_bytes(b"x" * size)
        os.utime(folder / name, (used, used))
    (folder / "unrelated.txt").write_text("not ours")
    monkeypatch.setenv(plan_cache.ENV_LIMIT, "0.0000012")  # 1200 bytes
    assert plan_cache.limit_bytes() == 1200
    # Stale first (300), then the least recently used current file (400); 1100 stay.
    assert plan_cache.trim() == 700
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["erp-taps-b" + suffix, "erp-taps-c" + suffix, "unrelated.txt"]
    )
    assert plan_cache.trim() == 0
    assert plan_cache.trim(0) == 1100 and plan_cache.usage().files == 0


def test_a_new_plan_trims_the_folder_and_a_bad_limit_is_named(
    home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    m360.Layout.icosahedron(WIDTH).prepare()
    old = set(_plan_files(home))
    assert old
    monkeypatch.setenv(plan_cache.ENV_LIMIT, "0")
    m360.Layout.icosahedron(WIDTH + 64).prepare()  # opening it removes the other layout's files
    new = set(_plan_files(home))
    assert new and not (new & old)
    monkeypatch.setenv(plan_cache.ENV_LIMIT, "lots")
    with pytest.raises(M360Error, match="M360_PLAN_CACHE_MAX_GB='lots'"):
        m360.Layout.icosahedron(WIDTH + 128).prepare()
