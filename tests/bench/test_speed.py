"""`dla bench speed`: speed rows and their schema, same-run ratios, the report's speed tables, and
tiny real runs of the splat and USD suites (what they record, never how fast it was)."""

from __future__ import annotations

from dataclasses import replace

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
        ({"counts": [1.0]}, "counts"),
        ({"counts": {"covering_per_pixel": -1.0}}, "covering_per_pixel"),
        ({"counts": {"covering_per_pixel": "many"}}, "covering_per_pixel"),
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


def test_the_render_table_keeps_the_latest_run_of_each_gaussian_count_and_size():
    rows = [
        speed_row("render", case, "cpu", {"gaussians": n, "size": size, "frames": 30}, s, 3, run, "cpu")
        for run, n, size, case, s in (
            ("r1", 32768, 512, "playback_frame", 0.050),
            ("r2", 32768, 512, "playback_frame", 0.040),
            ("r3", 131072, 512, "playback_frame", 0.080),
            ("r3", 131072, 512, "animation_frame", 0.050),
            ("r4", 131072, 1024, "playback_frame", 0.200),  # a later run at another size keeps r3
        )
    ]
    md = "\n".join(speed_markdown(rows))
    assert "Runs r2, r3, r4 on cpu." in md and "r1" not in md
    assert "| playback_frame | frames=30 gaussians=131072 size=1024 | cpu | 200.0 | - | 5.0 fps |" in md
    assert "| playback_frame | frames=30 gaussians=32768 size=512 | cpu | 40.0 | - | 25.0 fps |" in md
    assert "| animation_frame | frames=30 gaussians=131072 size=512 | cpu | 50.0 | - | 20.0 fps |" in md


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


def test_a_tiny_dream_run(monkeypatch):
    """The stages run for real at smoke size; the whole command's fresh interpreters (a warm-up
    and one run per case, ~10 s each here) are replaced by a recorder of what would run."""
    from dlacli.bench import speed_stages
    from dlacli.bench.speed_config import quick_config
    from dlacli.paths import sample_keypoints, sample_photo

    ran = []
    monkeypatch.setattr(speed_stages, "cli_seconds", lambda argv: (ran.append(argv), (0.5 + len(ran), True))[1])
    cfg = quick_config()
    cfg.repeats = 1
    rows = S.run(["dream"], cfg, log=lambda s: None)
    assert len(ran) == 3 and ran[0] == ran[1] and ran[2][: len(ran[1])] == ran[1]
    assert ran[1][:2] == ["dream", str(sample_photo())] and "--keypoints" not in ran[1]
    assert ran[1][ran[1].index("--res") + 1] == "64" and ran[1][ran[1].index("--fit-steps") + 1] == "3"
    assert ran[2][len(ran[1]) :] == ["--keypoints", str(sample_keypoints())]
    assert all(check_row(dict(r)) == r for r in rows)
    by_case = {r["case"]: r for r in rows}
    assert list(by_case) == [
        "command",
        "command_keypoints",
        "detect",
        "fit",
        "views_body",
        "views_body_prior",  # the shipped completion prior on top
        "views_shell",
        "plausibility",
        "write",
    ]
    assert all(r["suite"] == "dream" and r["seconds"] > 0 and r["repeats"] == 1 for r in rows)
    assert by_case["command"]["seconds"] == 2.5 and by_case["command_keypoints"]["seconds"] == 3.5
    assert by_case["command"]["method"] == "cli" and by_case["command"]["config"] == {"res": 64, "fit_steps": 3}
    assert by_case["fit"]["config"] == {"fit_steps": 3} and by_case["views_body"]["config"] == {"res": 64}
    assert all(by_case[c]["first_seconds"] > 0 for c in ("detect", "fit", "write"))
    assert len({r["run"] for r in rows}) == 1


def test_cli_seconds_reports_a_failing_command(tmp_path):
    from dlacli.bench.speed_config import cli_seconds

    with pytest.raises(RuntimeError, match="dream"):
        cli_seconds(["dream", str(tmp_path / "missing.png"), "-o", str(tmp_path / "out")])


def test_a_tiny_motion_run(monkeypatch):
    """The motion suite at smoke size: a synthetic clip is made and fitted in this process; the
    command's fresh interpreters are replaced by a recorder."""
    pytest.importorskip("mediapipe")
    from dlacli.bench import speed_stages
    from dlacli.bench.speed_config import quick_config

    ran = []
    monkeypatch.setattr(speed_stages, "cli_seconds", lambda argv: (ran.append(argv), (2.0, True))[1])
    cfg = quick_config()
    cfg.repeats = 1
    rows = S.run(["motion"], cfg, log=lambda s: None)
    models = speed_stages._installed_landmarks()  # full first, then lite / heavy where installed
    assert models[0] == "full" and len(ran) == 1 + len(models) and ran[0][:2] == ["motion", "from-video"]
    assert all(a == [*ran[0], "--landmarks", m] for a, m in zip(ran[1:], models))  # the warm-up, then each
    assert all(check_row(dict(r)) == r for r in rows)
    frames = int(round(cfg.motion_seconds * 30)) + 1
    assert all(r["items"] == frames and r["config"]["frames"] == frames and r["seconds"] > 0 for r in rows)
    for m in models:  # the default's rows keep their old config (no "landmarks" key)
        by_case = {r["case"]: r for r in rows if r["config"].get("landmarks", "full") == m}
        assert list(by_case) == ["from_video_command", "from_video_detect", "from_video_fit", "from_video_process_cpu"]
        assert by_case["from_video_command"]["seconds"] == 2.0


@pytest.mark.slow
def test_a_tiny_render_run_against_a_baseline_copy():
    """The render suite with --baseline: this package and the baseline (here the same source)
    alternate in fresh interpreters, pose + splat = playback per frame, and the report's
    baseline / current pairs them."""
    from pathlib import Path

    import dlacli
    from dlacli.bench.speed_config import quick_config

    src = str(Path(dlacli.__file__).parent.parent)
    cfg = replace(quick_config(), baseline=src, rounds=2, repeats=1)
    rows = S.run(["render"], cfg, log=lambda s: None)
    assert all(check_row(dict(r)) == r for r in rows)
    timed = [r for r in rows if r["case"] in ("pose_frame", "animation_frame", "playback_frame")]
    assert {(r["method"], r["config"]["round"]) for r in timed} == {
        (m, k) for m in ("cpu", "cpu_baseline") for k in (0, 1)
    }
    for method in ("cpu", "cpu_baseline"):
        for k in (0, 1):
            got = {r["case"]: r["seconds"] for r in timed if r["method"] == method and r["config"]["round"] == k}
            assert got["playback_frame"] == pytest.approx(got["pose_frame"] + got["animation_frame"], rel=1e-12)
            assert min(got.values()) > 0
    md = "\n".join(speed_markdown(rows))
    assert md.count("baseline / current") == 3 * 2  # the current rows of both rounds
    assert "turntable_image" in md


@pytest.mark.slow
def test_the_render_suite_counts_a_frame_and_draws_its_heat_map(tmp_path):
    """The composite_frame row: the exact kernel's time for one walk frame with its compositing
    counts (consistent: composited <= covering, a covered share in (0, 1)); --heatmap writes the
    PNG, and the report prints the counts."""
    from PIL import Image

    from dlacli.bench.speed_config import quick_config

    cfg = replace(quick_config(), repeats=1, heatmap=str(tmp_path / "maps"))
    rows = S.run(["render"], cfg, log=lambda s: None)
    (row,) = [r for r in rows if r["case"] == "composite_frame"]
    assert check_row(dict(row)) == row and row["seconds"] > 0
    c = row["counts"]
    assert 0 < c["covered_share"] < 1 and 0 < c["contributing_per_pixel"] <= c["covering_per_pixel"]
    png = tmp_path / "maps" / f"composite_{cfg.gaussians}_{cfg.res}px.png"
    assert Image.open(png).size[0] > 1000
    assert "a covered pixel" in "\n".join(speed_markdown(rows))
