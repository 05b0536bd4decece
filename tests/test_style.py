"""The code style CI holds the project to: ruff's linter and formatter, with pyproject.toml's
configuration, over src and tests (docs/architecture.md, "The layers": ruff passes over src and tests)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args, "src", "tests"], cwd=REPO, capture_output=True, text=True, timeout=300
    )


def test_ruff_lint_passes():
    done = _ruff("check", "--no-cache")
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]


def test_ruff_format_is_applied():
    done = _ruff("format", "--check", "--no-cache")
    assert done.returncode == 0, "run `ruff format src tests`:\n" + done.stdout[-4000:] + done.stderr[-2000:]
