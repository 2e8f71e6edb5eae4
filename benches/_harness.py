"""Shared helpers of the benchmark scripts in ``benches/``: timing, memory, metadata, tables, JSON.

Benchmarks are scripts that print a table (warmup, several repeats, median and IQR, pinned seeds,
recorded metadata); they are not timed unit tests.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "ProcessRss",
    "Timing",
    "bench_argparser",
    "fresh_process_rss",
    "measure",
    "metadata",
    "peak_rss_mb",
    "print_table",
    "timing_of",
    "write_json",
]

# ru_maxrss is in bytes on macOS and in KiB elsewhere.
_RSS_PER_MB = 1024 * 1024 if sys.platform == "darwin" else 1024


@dataclass(frozen=True)
class Timing:
    """Wall-clock times of repeated runs, in seconds."""

    runs: list[float]
    median: float
    iqr: float
    min: float


def measure(fn: Callable[[], Any], *, repeats: int = 5, warmup: int = 1) -> Timing:
    """Time ``fn()`` with ``time.perf_counter``: ``warmup`` untimed calls, then ``repeats`` timed.

    Returns
    -------
    Timing
        All runs, their median, interquartile range (q75 - q25) and minimum, in seconds.
    """
    if repeats < 1 or warmup < 0:
        raise ValueError(f"need repeats >= 1 and warmup >= 0, got {repeats} and {warmup}")
    for _ in range(warmup):
        fn()
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return timing_of(runs)


def timing_of(runs: Sequence[float]) -> Timing:
    """Median, interquartile range (q75 - q25) and minimum of times measured elsewhere."""
    runs = list(runs)
    if not runs:
        raise ValueError("no runs")
    if len(runs) >= 2:
        q = statistics.quantiles(runs, n=4, method="inclusive")
        iqr = q[2] - q[0]
    else:
        iqr = 0.0
    return Timing(runs=runs, median=statistics.median(runs), iqr=iqr, min=min(runs))


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MB (``getrusage(RUSAGE_SELF)``).

    On Linux this figure survives fork + exec: a child's ``ru_maxrss`` starts at its parent's
    high-water mark. Use :func:`fresh_process_rss` to measure an operation's memory.
    """
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / _RSS_PER_MB


@dataclass(frozen=True)
class ProcessRss:
    """Peak RSS of one fresh interpreter, in MB.

    ``baseline_mb`` is the peak after the setup (imports) and ``peak_mb`` the peak at exit, both
    read in the same child, so ``delta_mb`` = what the measured code added on top of its imports.
    ``source`` names the counter: ``"VmHWM"`` (Linux, /proc/self/status: the high-water mark of
    the child's own address space, which exec starts afresh) or ``"ru_maxrss"`` (elsewhere; on
    Linux it would start at the parent's peak).
    """

    baseline_mb: float
    peak_mb: float
    source: str

    @property
    def delta_mb(self) -> float:
        return self.peak_mb - self.baseline_mb


_RSS_CHILD = """
import sys
def _hwm():
    try:
        with open('/proc/self/status') as fh:
            for line in fh:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) * 1024, 'VmHWM'
    except OSError:
        pass
    import resource
    per = 1 if sys.platform == 'darwin' else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * per, 'ru_maxrss'
exec(compile({setup!r}, '<bench setup>', 'exec'))
_base, _src = _hwm()
exec(compile({code!r}, '<bench>', 'exec'))
_peak, _src = _hwm()
sys.stdout.write('\\n__PEAK_RSS__ %d %d %s\\n' % (_base, _peak, _src))
"""


def fresh_process_rss(
    code: str, *, setup: str = "import numpy as np, m360", timeout: float | None = None
) -> ProcessRss:
    """Peak RSS of a fresh interpreter (same ``sys.executable`` and environment) that runs
    ``setup`` then ``code``; the baseline is read after ``setup`` in that same process.

    The child is a new interpreter (exec), and on Linux it reads its own VmHWM, which does not
    inherit this process's high-water mark (``ru_maxrss`` does, across fork + exec, so a bench
    that has grown would report its own peak as the child's). ``code`` runs in the namespace of
    ``setup``. Raises ``RuntimeError`` with the child's stderr if it fails.
    """
    wrapper = _RSS_CHILD.format(setup=setup, code=code)
    proc = subprocess.run(
        [sys.executable, "-c", wrapper], capture_output=True, text=True, timeout=timeout
    )
    if proc.returncode != 0:
        raise RuntimeError(f"snippet failed (exit {proc.returncode}):\n{proc.stderr}")
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("__PEAK_RSS__ "):
            _, base, peak, source = line.split()
            mb = 1024.0 * 1024.0
            return ProcessRss(baseline_mb=int(base) / mb, peak_mb=int(peak) / mb, source=source)
    raise RuntimeError("snippet did not report its peak RSS")


def _git_commit() -> str | None:
    root = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    dirty = subprocess.run(
        ["git", "--no-optional-locks", "-C", str(root), "status", "--porcelain", "-uno"],
        capture_output=True,
        text=True,
        timeout=5,
    ).stdout.strip()
    return commit + ("-dirty" if dirty else "")


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def metadata() -> dict[str, Any]:
    """Context of a benchmark run: commit, CPU, thread settings, versions, date."""
    try:
        import numpy

        numpy_version: str | None = numpy.__version__
    except ImportError:
        numpy_version = None
    try:
        import m360

        m360_version: str | None = getattr(m360, "__version__", None)
    except ImportError:
        m360_version = None
    return {
        "git_commit": _git_commit(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": numpy_version,
        "m360": m360_version,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "M360_NUM_THREADS": os.environ.get("M360_NUM_THREADS"),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
    }


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.3e}"
    return str(value)


def print_table(title: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Print rows as an aligned plain-text table (numbers right-aligned, text left-aligned)."""
    cells = [[_cell(v) for v in row] for row in rows]
    widths = [len(c) for c in columns]
    for row in cells:
        if len(row) != len(columns):
            raise ValueError(f"row has {len(row)} cells, expected {len(columns)}: {row}")
        widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
    numeric = [
        all(isinstance(r[i], (int, float)) for r in rows) if rows else False
        for i in range(len(columns))
    ]

    def fmt(row: Sequence[str]) -> str:
        return "  ".join(
            c.rjust(w) if num else c.ljust(w)
            for c, w, num in zip(row, widths, numeric, strict=True)
        ).rstrip()

    print(f"\n{title}")
    print(fmt(list(columns)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print(fmt(row))


def bench_argparser(description: str) -> argparse.ArgumentParser:
    """Parser with ``--repeats`` (5), ``--sizes`` ERP widths (2048 4096 8192), ``--json PATH``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (default 5)")
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[2048, 4096, 8192],
        help="ERP widths (default 2048 4096 8192)",
    )
    parser.add_argument("--json", type=Path, default=None, metavar="PATH", help="write results")
    return parser


def write_json(path: str | os.PathLike[str], rows: Sequence[Any], meta: dict[str, Any]) -> None:
    """Write ``{"metadata": meta, "rows": rows}`` as JSON (Timing values become dicts)."""

    def default(obj: Any) -> Any:
        if isinstance(obj, Timing):
            return asdict(obj)
        if isinstance(obj, ProcessRss):
            return {**asdict(obj), "delta_mb": obj.delta_mb}
        if hasattr(obj, "tolist"):
            return obj.tolist()
        if isinstance(obj, Path):
            return str(obj)
        raise TypeError(f"not JSON serialisable: {type(obj).__name__}")

    Path(path).write_text(
        json.dumps({"metadata": meta, "rows": list(rows)}, indent=2, default=default)
    )
