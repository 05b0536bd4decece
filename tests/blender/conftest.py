"""Blender checks run in a separate Python that has `bpy` (PyPI bpy pins numpy<2, so it cannot
share the project's .venv). Fixture `bpy_python`: that interpreter's path, from the environment
variable DLA_BPY_PYTHON, else <repo>/.venv-bpy/bin/python when it exists; the test is skipped
(with the reason) when neither is there."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def bpy_python() -> Path:
    given = os.environ.get("DLA_BPY_PYTHON")
    if given:
        path = Path(given)
        if not (path.is_file() and os.access(path, os.X_OK)):
            pytest.skip(f"DLA_BPY_PYTHON={given} is not an executable file")
        return path
    local = REPO / ".venv-bpy" / "bin" / "python"
    if local.is_file() and os.access(local, os.X_OK):
        return local
    pytest.skip(
        "no Python with bpy: set DLA_BPY_PYTHON or make .venv-bpy (python3.11 -m venv .venv-bpy; .venv-bpy/bin/pip "
        "install bpy==5.0.1)"
    )
