"""Where m360 keeps files between runs: ``$M360_HOME`` (models, plans)."""

from __future__ import annotations

import os
from pathlib import Path


def home_dir() -> Path:
    """m360's cache folder: ``$M360_HOME``, default the platform's user cache dir."""
    home = os.environ.get("M360_HOME")
    if home:
        return Path(home).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("m360"))
