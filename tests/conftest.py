"""Shared test setup: Warp's kernel cache in the project, paths to shared data, small fixtures."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from sync4d.config_schemas import register_schemas  # noqa: E402

# the components' Configs are the schemas of their YAML options: Hydra must know them before composing
register_schemas()

SHARED_DATA = Path(os.environ.get("SYNC4D_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared third-party test data folder; tests that need it skip with a reason when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (set SYNC4D_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT
