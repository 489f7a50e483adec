"""Shared pytest fixtures for the Tessera test suite."""

from __future__ import annotations

from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parent.parent
#: the real scans, read in place (never copied into the repo): ../shared/data from the root
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` relative to the project root; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available: {SHARED_DATA} does not exist")
    return SHARED_DATA
