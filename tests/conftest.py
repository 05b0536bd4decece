"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FORMATS = REPO / "formats"


def shared_data_dir() -> Path:
    """../shared/data beside the checkout (CI puts it there), or $DLA_SHARED_DATA."""
    env = os.environ.get("DLA_SHARED_DATA")
    path = Path(env) if env else REPO.parent / "shared" / "data"
    if not path.is_dir():
        raise RuntimeError(f"third-party test data not found at {path}; set DLA_SHARED_DATA")
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    return shared_data_dir()


@pytest.fixture(scope="session")
def formats_dir() -> Path:
    return FORMATS
