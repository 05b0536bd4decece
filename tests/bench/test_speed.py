"""`dla bench speed`: speed rows and their schema, same-run ratios, the report's speed tables, and
tiny real runs of the splat and USD suites (what they record, never how fast it was)."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.bench import speed as S
from dlacli.bench.report import speed_markdown
from dlacli.bench.rows import check_row, speed_row
from dlacli.bench.speed_stages import walk_like
from dlacli.errors import DlaInputError


def test_speed_rows_pass_the_schema():
    row = speed_row("splat", "fwd", "numba", {"n": 10, "res": 16}, 0.01, 5, "r1", "cpu", min_seconds=0.009, peak_mb=3.0)
    assert check_row(dict(row)) == row and row["kind"] == "speed" and "split" not in row
    skipped = speed_row("splat", "fwd", "gsplat", {}, None, 0, "r1", "cpu", skipped="no CUDA device")
    assert check_row(dict(skipped)) == skipped
    for change, needle in (
        ({"seconds": None}, "skipped"),
        ({"seconds": -1.0}, "seconds"),
        ({"repeats": 1.5}, "repeats"),
        ({"run": 3}, "run"),
        ({"peak_mb": float("inf")}, "peak_mb"),
        ({"torch_loaded": "no"}, "torch_loaded"),
    ):
        with pytest.raises(DlaInputError, match=needle):
            check_row({**row, **change})
    with pytest.raises(ValueError, match="speedy"):
        speed_row("splat", "fwd", "numba", {}, 0.01, 1, "r1", "cpu", speedy=True)


def test_ratios_pair_rows_of_one_run():
    rows = [
        speed_row("splat", "fwd", m, {"n": 10, **({"round": r} if m.startswith("numba") else {})}, s, 3, run, "cpu")
        for run, m, r, s in (
            ("a", "torch", 0, 1.0),
            ("a", "numba", 0, 0.1),
            ("a", "numba", 1, 0.3),
            ("a", "numba", 2, 0.2),
            ("b", "numba", 0, 5.0),
            ("a", "numba_baseline", 0, 0.4),
            ("a", "numba_baseline", 1, 0.4),
        )
    ]
    got = {(q["run"], q["method"]): q["ratio"] for q in S.ratios(rows, "torch")}
    assert got == {
        ("a", "numba"): pytest.approx(1.0 / 0.2),
        ("a", "numba_baseline"): pytest.approx(1.0 / 0.4),
    }  # run b has no torch row
    base = {(q["run"], q["method"]): q["ratio"] for q in S.ratios(rows, "numba_baseline")}
    assert base[("a", "numba")] == pytest.approx(0.4 / 0.2)
    md = "\n".join(speed_markdown([r for r in rows if r["run"] == "a"]))
    assert (
        "| fwd | n=10 | numba | 200.0 | - | 5x torch, baseline / current 2.000 |" in md
    )  # round 2; ratios over rounds
    md = "\n".join(speed_markdown(rows))
    assert "Run b" in md and "Run a" not in md  # only the latest run of a suite is shown


def test_a_tiny_splat_run():
    cfg = S.SpeedConfig(splat_cases=((256, 32),), splat_paths=("numba", "torch"), repeats=1)
    rows = S.run(["splat"], cfg, log=lambda s: None)
    assert all(check_row(dict(r)) == r for r in rows)
    measured = {(r["case"], r["method"]): r for r in rows if r["seconds"] is not None}
    assert set(measured) == {(c, m) for c in ("fwd", "fwd_bwd") for m in ("numba", "torch")} | (
        {("fwd", "gsplat"), ("fwd_bwd", "gsplat")} if S._gsplat_note() is None else set()
    )
    assert all(r["seconds"] > 0 and r["config"] == {"n": 256, "res": 32, "sh_degree": 0} for r in measured.values())
    assert measured[("fwd", "numba")]["first_seconds"] > 0 and measured[("fwd_bwd", "numba")].get("peak_mb") is not None
    if S._gsplat_note() is not None:
        (skip,) = [r for r in rows if r["seconds"] is None]
        assert skip["method"] == "gsplat" and skip["skipped"] == S._gsplat_note()
    assert len({r["run"] for r in rows}) == 1


def test_a_tiny_usd_run_and_the_walk():
    cfg = S.SpeedConfig(usd_gaussians=64, frames=3, usd_tolerances_mm=(0.0,), usd_schemas=("points",), repeats=1)
    (row,) = S.run(["usd"], cfg, log=lambda s: None)
    assert row["items"] == 64 * 3 and row["size_mib"] > 0 and row["config"]["schema"] == "points"
    positions, quats, scales, rgb, opacities = walk_like(3, 64)
    assert positions.shape == (3, 64, 3) and quats.shape == (3, 64, 4) and scales.shape == (64, 3)
    assert np.allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-6)
    # every Gaussian turns about +X only (w, x, 0, 0), at most 30 degrees
    assert np.all(quats[..., 2:] == 0) and np.all(
        np.abs(2 * np.arccos(np.clip(quats[..., 0], -1, 1))) <= np.radians(30) + 1e-6
    )


def test_cli_refusals(capsys, tmp_path):
    from dlacli.cli.app import main

    for argv, needle in (
        (["--suite", "splat,nope"], "nope"),
        (["--baseline", str(tmp_path)], "dlacli"),
        (["--splat-cases", "5"], "--splat-cases"),
        (["--jsonl", str(tmp_path / "r.txt")], "r.txt"),
    ):
        with pytest.raises(SystemExit) as info:
            main(["bench", "speed", *argv])
        err = capsys.readouterr().err
        assert info.value.code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
