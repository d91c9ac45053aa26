"""Where the real validation data is: ``$RECTIFY_SHARED_DATA``, else ``../shared/data`` beside the repository.

Every test that reads the shared data finds it here (or through the ``shared_data`` fixture of
``tests/conftest.py``, which uses this), so that one environment variable moves it or hides it
(``scripts/mutation_check.py`` points it at a folder that does not exist, as on a fresh clone).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SHARED_DATA", "shared_data_dir"]

ROOT = Path(__file__).resolve().parents[2]


def shared_data_dir() -> Path:
    """``$RECTIFY_SHARED_DATA`` when set and not empty, else ``ROOT/../shared/data``."""
    env = os.environ.get("RECTIFY_SHARED_DATA", "").strip()
    return Path(env) if env else ROOT.parent / "shared" / "data"


#: the shared data folder of this session (it may not exist: tests then skip)
SHARED_DATA = shared_data_dir()
