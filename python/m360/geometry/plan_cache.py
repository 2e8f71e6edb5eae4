"""The disk plan cache: sampling maps built once, kept under ``$M360_HOME/plans``.

A plan (the taps between the ERP image and the tangents, the blend weights at the taps, the
alignment's overlap samples) depends only on the layout and the ERP size. Building it is most of
a first call's extra cost, so every map built is written to this folder, and a process that needs
a map loads it from there first (memory-mapped, checked, then read in place). On by default;
off with the environment variable ``M360_PLAN_CACHE=0`` or :func:`set_enabled`.

Files are named by the map, the layout's hash, the options, the file format and the build of
m360 that wrote them, so several versions can share the folder. A file that is truncated,
corrupt, foreign or of another format is never trusted: the map is rebuilt and the file
rewritten (with a warning on the ``m360.plan_cache`` logger). Writes are atomic, so processes
may share the folder. The folder is kept under a size limit (``M360_PLAN_CACHE_MAX_GB``, default
8; an 8K layout's default plan is about 1.8 GB): whenever a process opens a plan, the least
recently used files beyond it (by access or modification time) are deleted (:func:`trim`).
:func:`clear` empties it (``m360 plans`` shows its size), and deleting the folder by hand is
always safe.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .. import _core
from ..errors import InputError

__all__ = ["Usage", "clear", "directory", "enabled", "limit_bytes", "set_enabled", "trim", "usage"]

#: Environment variable that turns the cache off ("0", "false", "no", "off").
ENV_SWITCH = "M360_PLAN_CACHE"
#: Environment variable of the size limit in GB (10^9 bytes); default :data:`DEFAULT_LIMIT_GB`.
ENV_LIMIT = "M360_PLAN_CACHE_MAX_GB"
#: Default size limit of the folder, in GB.
DEFAULT_LIMIT_GB = 8.0

_override: bool | None = None


def enabled() -> bool:
    """Whether plans are looked up on and written to disk.

    Returns
    -------
    bool
        The value given to :func:`set_enabled`, else ``M360_PLAN_CACHE`` (default on).
    """
    if _override is not None:
        return _override
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in {"0", "false", "no", "off"}


def set_enabled(on: bool | None) -> None:
    """Turn the disk plan cache on or off for this process (``None``: follow the environment).

    Plans already in memory keep their maps; the switch applies to every map built or needed
    from the next call on.

    Parameters
    ----------
    on : bool or None
        ``True`` or ``False`` to override ``M360_PLAN_CACHE``; ``None`` to read it again.
    """
    global _override
    _override = None if on is None else bool(on)


def directory() -> Path:
    """Return the folder of plan files: ``$M360_HOME/plans`` (default: the user cache folder).

    Returns
    -------
    pathlib.Path
        The folder (it may not exist yet).
    """
    from .._home import home_dir

    return home_dir() / "plans"


def current() -> Path | None:
    """Return the folder plans use now: :func:`directory` if the cache is on, else ``None``."""
    return directory() if enabled() else None


@dataclass(frozen=True)
class Usage:
    """What the plan cache holds."""

    #: The folder.
    path: Path
    #: Number of plan files (leftover temporary files included).
    files: int
    #: Their total size in bytes.
    bytes: int
    #: Files written by another format or build of m360 (never read by this one).
    stale_files: int


def _plan_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    suffix = _core.PLAN_FILE_SUFFIX
    # Plan files, and the temporary files of writes (".<plan file name>.<pid>.<n>.tmp").
    return [
        p
        for p in folder.iterdir()
        if p.name.endswith(suffix) or (p.name.endswith(".tmp") and suffix + "." in p.name)
    ]


def _is_stale(path: Path) -> bool:
    return not path.name.endswith(f"-{_core.PLAN_FORMAT}{_core.PLAN_FILE_SUFFIX}")


def usage() -> Usage:
    """Count the files of the plan cache and their size.

    Returns
    -------
    Usage
        Folder, number of files, bytes, and how many are stale (of another m360 build).
    """
    folder = directory()
    files = _plan_files(folder)
    sizes = []
    for p in files:
        try:
            sizes.append(p.stat().st_size)
        except OSError:  # removed meanwhile
            sizes.append(0)
    return Usage(folder, len(files), sum(sizes), sum(map(_is_stale, files)))


def clear(*, stale_only: bool = False) -> int:
    """Delete plan files (safe at any time: a process that needs a map rebuilds it).

    Parameters
    ----------
    stale_only : bool
        Delete only files this build of m360 never reads (other versions or formats, and
        temporary files left by interrupted writes).

    Returns
    -------
    int
        Bytes freed.
    """
    freed = 0
    for p in _plan_files(directory()):
        if stale_only and not _is_stale(p):
            continue
        try:
            size = p.stat().st_size
            p.unlink()
        except OSError:  # removed meanwhile, or not ours to remove
            continue
        freed += size
    return freed


def limit_bytes() -> int:
    """Return the size limit of the plan folder in bytes (``M360_PLAN_CACHE_MAX_GB``, default 8).

    Raises
    ------
    InputError
        If the variable is not a non-negative number.
    """
    raw = os.environ.get(ENV_LIMIT, "").strip()
    if not raw:
        return int(DEFAULT_LIMIT_GB * 1e9)
    try:
        gb = float(raw)
    except ValueError:
        gb = float("nan")
    if not (gb >= 0 and gb != float("inf")):
        raise InputError(f"{ENV_LIMIT}={raw!r} must be a non-negative number of GB")
    return int(gb * 1e9)


def _last_used(path: Path) -> float:
    # Loading maps a file (which updates its access time where the file system records it);
    # writing sets its modification time.
    st = path.stat()
    return max(st.st_atime, st.st_mtime)


def trim(limit: int | None = None) -> int:
    """Delete the least recently used plan files until the folder holds at most ``limit`` bytes.

    Safe at any time: a process that has a file mapped keeps its pages, and one that needs a
    deleted map rebuilds it. Stale files (other builds of m360) go first.

    Parameters
    ----------
    limit : int, optional
        Bytes; default :func:`limit_bytes`.

    Returns
    -------
    int
        Bytes freed.
    """
    limit = limit_bytes() if limit is None else limit
    entries = []
    for p in _plan_files(directory()):
        try:
            entries.append((not _is_stale(p), _last_used(p), p.stat().st_size, p))
        except OSError:  # removed meanwhile
            continue
    total = sum(e[2] for e in entries)
    freed = 0
    for _, _, size, p in sorted(entries, key=lambda e: e[:2]):
        if total - freed <= limit:
            break
        try:
            p.unlink()
        except OSError:
            continue
        freed += size
    return freed
