"""Where the real-data tier finds its networks and photos (docs/architecture.md, "Real data").

Three small trained depth networks and 16 real panoramas (1K to 12K) sit beside the repository,
never in it: in the folder ``shared/real`` next to the checkout (where CI provides it), or in
the folder ``M360_REAL_DATA`` names. Tests over them skip, saying why, where it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(
    os.environ.get("M360_REAL_DATA") or Path(__file__).resolve().parents[2] / "shared" / "real"
)
MODELS = ROOT / "models"
PANOS = ROOT / "panos"
MISSING = f"no real networks and photos at {ROOT} (set M360_REAL_DATA; CI provides them)"
#: Mark a test (or, as ``pytestmark``, a module) that needs the real data.
requires_real = pytest.mark.skipif(not (MODELS.is_dir() and PANOS.is_dir()), reason=MISSING)
