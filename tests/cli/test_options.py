"""The shared options of dlacli/cli/options.py: one suffix check for every file a command writes,
one parser for --gaussians, the defaults and limits from dlacli.limits, and the commands built from
the factories (no command writes its own copy of a check)."""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest
import typer

from dlacli import limits
from dlacli.cli import options
from dlacli.cli.app import main
from dlacli.errors import DlaInputError

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "formats" / "examples"
CLI = REPO / "src" / "dlacli" / "cli"


@pytest.fixture
def work(tmp_path):
    shutil.copy(EXAMPLES / "avatar.npz", tmp_path / "av.npz")
    return tmp_path


def refused(argv, capsys) -> str:
    """Exit code 2 and exactly one `error: ...` line on stderr; returns that line."""
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert info.value.code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------------------------
# the suffix check


def test_check_suffix():
    path = Path("out/Clip.MP4")
    assert options.check_suffix(path, (".mp4",), "video") is path  # any case in the name
    with pytest.raises(DlaInputError) as err:
        options.check_suffix(Path("a.gif"), (".mp4",), "video")
    assert (
        err.value.where == "a.gif" and "'.gif' is not a video format" in err.value.problem and ".mp4" in str(err.value)
    )
    with pytest.raises(DlaInputError, match=r"has no suffix; use \.usdc, \.usda or \.usd for an animation"):
        options.check_suffix(Path("anim"), limits.USD_SUFFIXES, "animation")
    with pytest.raises(DlaInputError, match=r"use \.npz \(or --steps K\)$"):
        options.check_suffix(Path("a.txt"), (".npz",), "avatar", " (or --steps K)")


# command, the file option's place in argv, the suffixes the message offers
WRONG_SUFFIX = [
    (["render", "{av}", "-o", "{w}/r", "--turntable", "1", "--video", "{bad}"], ".mp4"),
    (["animate", "{av}", "walk", "-o", "{bad}"], ".usdc, .usda or .usd"),
    (["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--preview", "{bad}"], ".mp4"),
    (["view", "{av}", "-o", "{bad}"], ".html or .htm"),
    (["export", "{av}", "-o", "{bad}"], ".ply, .spz, .splat or .glb"),
    (["export", "{av}", "--rig", "-o", "{bad}"], ".usdc, .usda or .usd"),
    (["edit", "swap", "{av}", "{av}", "-r", "face", "-o", "{bad}"], ".npz"),
    (["interp", "{av}", "{av}", "-o", "{bad}"], ".npz"),
    (["interp", "{av}", "{av}", "-o", "{w}/blend", "--steps", "2", "--video", "{bad}"], ".mp4"),
    (["motion", "convert", "walk", "-o", "{bad}"], ".npz"),
    (["motion", "preview", "walk", "-o", "{bad}"], ".mp4"),
    (["body", "regions", "-o", "{bad}"], ".png"),
    (["lift", "{w}/views", "-o", "{bad}"], ".npz"),
    (["lift", "{w}/views", "-o", "{w}/a.npz", "--ply", "{bad}"], ".ply"),
    (["bench", "regions", "-o", "{bad}"], ".png"),
    (["bench", "speed", "--jsonl", "{bad}"], ".jsonl"),
    (["bench", "report", "{w}/r.jsonl", "-o", "{bad}"], ".md"),
]


@pytest.mark.parametrize("argv, offered", WRONG_SUFFIX, ids=[" ".join(a[:2]) + f" {a[-2]}" for a, _ in WRONG_SUFFIX])
@pytest.mark.parametrize("name", ["x.txt", "noext"])
def test_a_wrong_suffix_names_the_file(argv, offered, name, work, capsys):
    bad = work / name
    line = refused([a.format(w=work, av=work / "av.npz", bad=bad) for a in argv], capsys)
    assert line.startswith(f"error: {bad}: ") and offered in line, line
    assert sorted(p.name for p in work.iterdir()) == ["av.npz"]  # nothing written


def test_a_suffix_in_capitals_is_accepted(work, capsys):
    with pytest.raises(SystemExit) as info:
        main(["interp", str(work / "av.npz"), str(work / "av.npz"), "-o", str(work / "B.NPZ")])
    assert info.value.code == 0, capsys.readouterr().err
    assert (work / "B.NPZ").is_file()


# ------------------------------------------------------------------------------------------------
# --gaussians: one parser


def test_gaussians_parser():
    top = limits.MAX_GAUSSIANS
    assert options.gaussian_count(None) is None and options.gaussian_number(None) is None
    assert options.gaussian_count(" AUTO ") == "auto"
    assert options.gaussian_count("2") == 2 and options.gaussian_number(str(top)) == top
    for bad in ("1", str(top + 1), "lots", "2.5"):
        for parse in (options.gaussian_count, options.gaussian_number):
            with pytest.raises(typer.BadParameter):
                parse(bad)
    with pytest.raises(typer.BadParameter, match="expected an integer, got 'auto'"):
        options.gaussian_number("auto")


GAUSSIAN_COMMANDS = {
    "render": ["render", "{av}", "-o", "{w}/r", "--turntable", "1"],
    "animate": ["animate", "{av}", "walk", "-o", "{w}/a.usdc"],
    "view": ["view", "{av}", "-o", "{w}/v.html"],
    "export": ["export", "{av}", "-o", "{w}/a.ply"],
    "lift": ["lift", "{w}/views", "-o", "{w}/a.npz"],
    "bench speed": ["bench", "speed", "--suite", "startup"],
}
NO_AUTO = {"view", "export", "bench speed"}  # no cameras to budget for


@pytest.mark.parametrize("name, command", list(GAUSSIAN_COMMANDS.items()), ids=list(GAUSSIAN_COMMANDS))
def test_gaussians_option_of_every_command(name, command, work, capsys):
    argv = [a.format(w=work, av=work / "av.npz") for a in command]
    for bad in ("1", str(limits.MAX_GAUSSIANS + 1), "lots"):
        assert refused([*argv, "--gaussians", bad], capsys).startswith("error: --gaussians: ")
    if name in NO_AUTO:
        assert "expected an integer, got 'auto'" in refused([*argv, "--gaussians", "auto"], capsys)
    assert sorted(p.name for p in work.iterdir()) == ["av.npz"]


def test_animate_frames_times_gaussians_is_bounded(work, capsys):
    """The bound on posed Gaussian-frames is checked where the count is known (stages.animate)."""
    count = limits.MAX_GAUSSIAN_FRAMES // 64 + 1  # over the bound for any motion of 64 frames or more (walk: 133)
    line = refused(["animate", work / "av.npz", "walk", "-o", work / "a.usdc", "--gaussians", count], capsys)
    assert line.startswith("error: --gaussians: ") and "Gaussian-frames" in line


# ------------------------------------------------------------------------------------------------
# defaults and limits written once


def test_limits_are_the_ones_the_layers_use():
    from dlacli import types
    from dlacli.avatar import posed  # render's, animate's, ... count check (sample_settings)

    assert options.MAX_GAUSSIANS == posed.MAX_GAUSSIANS == limits.MAX_GAUSSIANS
    assert types.MAX_FPS == limits.MAX_FPS


def test_help_quotes_the_default_count():
    from dlacli.cli.app import app

    export = typer.main.get_command(app).commands["export"]
    (gaussians,) = [p for p in export.params if p.name == "gaussians"]
    assert f"else {limits.DEFAULT_GAUSSIANS:,})" in gaussians.help


def test_lift_and_bench_quote_the_limits():
    from dlacli.bench.speed import SpeedConfig
    from dlacli.cli.app import app

    commands = typer.main.get_command(app).commands
    lift = {p.name: p for p in commands["lift"].params}
    assert f"{limits.LIFT_GAUSSIANS:,}" in lift["gaussians"].help
    assert f"({limits.BUDGET_LADDER[0]:,} ... {limits.BUDGET_LADDER[-1]:,})" in lift["gaussians"].help
    assert f"default {limits.LIFT_STEPS}," in lift["steps"].help and lift["steps"].max == limits.MAX_LIFT_STEPS
    assert (lift["resolution"].min, lift["resolution"].max) == (
        limits.MIN_IMAGE_SIZE,
        limits.MAX_LIFT_RESOLUTION,
    )
    assert lift["seed"].max == limits.MAX_SEED and lift["seed"].default == limits.DEFAULT_SAMPLE_SEED
    bench = {name: {p.name: p for p in c.params} for name, c in commands["bench"].commands.items()}
    assert f"(default {SpeedConfig().gaussians:,})" in bench["speed"]["gaussians"].help
    assert bench["budget"]["counts"].default == ",".join(map(str, limits.BUDGET_LADDER))
    assert bench["stability"]["steps"].max == bench["regions"]["steps"].max == limits.MAX_LIFT_STEPS
    assert bench["regions"]["seed"].max == limits.MAX_SEED
    for name in ("pipeline", "accuracy", "regions", "stability", "speed"):
        assert bench[name]["res"].max == limits.MAX_IMAGE_SIZE, name


def _suffix_checks(tree: ast.AST) -> int:
    """`if <...>.suffix... <op> ...:` tests in a module: a command checking a suffix itself."""
    return sum(
        isinstance(node, ast.If)
        and any(isinstance(sub, ast.Attribute) and sub.attr == "suffix" for sub in ast.walk(node.test))
        for node in ast.walk(tree)
    )


@pytest.mark.parametrize("path", sorted(CLI.glob("*.py")), ids=lambda p: p.name)
def test_commands_use_the_shared_checks(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    if path.name != "options.py":
        assert _suffix_checks(tree) == 0, (
            f"{path.name} checks a suffix itself: use options.check_suffix or options.output"
        )
    called = {
        getattr(node.func, "attr", getattr(node.func, "id", ""))
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
    }
    assert "sample_settings" not in called, f"{path.name}: the stage resolves count and seed (call it once, there)"
