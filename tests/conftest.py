"""Shared fixtures: where the third-party recordings are, and a skip when they are absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("VLP_SHARED", REPO.parent / "shared"))
DATA = SHARED / "data"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data``; the test is skipped cleanly when a fresh clone has no ``../shared`` beside it."""
    if not DATA.is_dir():
        pytest.skip(f"reference data not found at {DATA} (set VLP_SHARED to the shared folder)")
    return DATA
