"""Shared fixtures: the real sample recordings live outside the project."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``$EVCAL_SHARED_DATA`` or ``../shared/data`` next to the repository; skip if absent."""
    env = os.environ.get("EVCAL_SHARED_DATA")
    path = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not path.is_dir():
        pytest.skip(f"shared sample data not found at {path} (set EVCAL_SHARED_DATA)")
    return path
