"""Shared test fixtures; `tolerance` (fixture `tol`), the per-dtype tolerance rule of the numeric
tests; `count_frames` (fixture `frames_in`), a text-only frame count of BVH/AMC files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
FORMATS = REPO / "formats"
THIRD_PARTY = REPO / "tests" / "data" / "third_party"  # see its LICENSES.md


def eps(dtype) -> float:
    """Machine epsilon (the spacing of floats at 1.0) of a numpy or torch floating dtype."""
    if type(dtype).__module__.startswith("torch"):
        import torch

        return float(torch.finfo(dtype).eps)
    return float(np.finfo(dtype).eps)


def tolerance(dtype, magnitude: float = 1.0, ops: int = 1) -> float:
    """Absolute tolerance for comparing two results of size ~`magnitude` computed in `dtype`
    through ~`ops` rounding steps each: ops * eps(dtype) * magnitude.

    Why: each rounding step has relative error <= u = eps / 2, so a result reached through n
    steps (a sum of n terms, a chain of n products) is off by <= ~n u |magnitude| (Higham's
    gamma_n); two such results differ by <= 2 n u |magnitude| = n eps |magnitude|. Per dtype, as
    in kornia's tolerance table: float16 ~1e-3, float32 ~1.2e-7, float64 ~2.2e-16 times the
    magnitude and the depth of the computation. State `ops` (what was counted) at the call.
    """
    return ops * eps(dtype) * abs(float(magnitude))


@pytest.fixture(scope="session")
def tol():
    """`tolerance` as a fixture (tests import nothing from conftest under --import-mode=importlib):
    `def test_x(tol): ... atol=tol(np.float32, 3.7, ops=20)`."""
    return tolerance


@pytest.fixture(scope="session")
def third_party_data() -> Path:
    """tests/data/third_party: the third-party files the tests read (cut to what they use)."""
    return THIRD_PARTY


def count_frames(path: Path) -> int:
    """Frames in a BVH or AMC file counted from its text alone (an oracle independent of the
    parsers): BVH, the non-blank lines after `Frame Time:`; AMC, the lines holding only a frame
    number."""
    lines = Path(path).read_text().splitlines()
    if Path(path).suffix.lower() == ".amc":
        return sum(line.strip().isdigit() for line in lines)
    start = next(i for i, line in enumerate(lines) if line.startswith("Frame Time:")) + 1
    return sum(bool(line.strip()) for line in lines[start:])


@pytest.fixture(scope="session")
def frames_in():
    """`count_frames` as a fixture: `frames_in(path)`."""
    return count_frames


@pytest.fixture(scope="session")
def formats_dir() -> Path:
    return FORMATS


@pytest.fixture
def dla(capsys):
    """`dla(*argv)` runs the CLI in this process (so what a test registered is known to it) ->
    (exit code, stdout, stderr)."""

    def run(*argv) -> tuple[int, str, str]:
        from dlacli.cli.app import main

        with pytest.raises(SystemExit) as info:
            main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return info.value.code, out, err

    return run
