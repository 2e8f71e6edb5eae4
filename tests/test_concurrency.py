"""m360 called from many threads and processes at once, on fresh layouts: no hang, same results.

Each case runs ``tests/concurrency_jobs.py`` in a fresh interpreter under a timeout, so a
deadlock fails the test (the interpreter is killed) instead of hanging the suite. Regression
test of the hang found with three threads on fresh layouts: plans were built inside the shared
thread pool while queued work waited on the same build.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

JOBS = Path(__file__).with_name("concurrency_jobs.py")
#: Generous: the calls take about a minute on a loaded 2-core machine; a deadlock never ends.
WATCHDOG_SECONDS = 600


def run_jobs(mode: str, layouts: int, workers: int) -> str:
    try:
        done = subprocess.run(
            [sys.executable, str(JOBS), mode, str(layouts), str(workers)],
            capture_output=True,
            text=True,
            timeout=WATCHDOG_SECONDS,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"{mode}: no result after {WATCHDOG_SECONDS} s (deadlock?): {exc.stdout!r}")
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


def test_eight_threads_on_twenty_fresh_layouts_match_the_serial_run() -> None:
    out = run_jobs("threads", layouts=20, workers=8)
    assert "160 calls on 20 fresh layouts, 8 workers" in out


def test_first_calls_from_three_threads_on_fresh_layouts_finish() -> None:
    # Before the fix this hung within 30 trials (measured: the old build was killed by a 180 s
    # timeout on this recipe, the fixed one finishes it in seconds).
    out = run_jobs("first-calls", layouts=30, workers=3)
    assert "first calls: 30 fresh layouts" in out


@pytest.mark.parametrize("start_method", ["fork", "spawn"])
def test_processes_sharing_nothing_match_the_serial_run(start_method: str) -> None:
    # The parent has used m360 (its thread pool exists) before it forks: a forked child must
    # start its own pool instead of waiting for threads it did not inherit.
    out = run_jobs(start_method, layouts=3, workers=2)
    assert "24 calls on 3 fresh layouts, 2 workers" in out
