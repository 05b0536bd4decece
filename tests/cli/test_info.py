"""`dla info` on every golden file in formats/examples/, plain and --json; bad input exits 2."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dlacli.cli.app import app

EXAMPLES = Path(__file__).resolve().parents[2] / "formats" / "examples"
GOLDEN = sorted(p for p in EXAMPLES.iterdir() if not p.name.startswith(".") and p.suffix != ".md")
EXPECTED_KIND = {"body.json": "body", "motion.npz": "motion", "avatar.npz": "avatar", "views": "views"}


def _dla(*args: str) -> subprocess.CompletedProcess:
    """The installed `dla` console script (or its entry point when the script is not on disk)."""
    script = Path(sys.executable).with_name("dla")
    cmd = [str(script)] if script.exists() else [sys.executable, "-c", "from dlacli.cli.app import main; main()"]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=120)


def test_the_examples_of_this_part_exist():
    assert set(EXPECTED_KIND) <= {p.name for p in GOLDEN}


@pytest.mark.parametrize("path", GOLDEN, ids=lambda p: p.name)
def test_info_on_every_golden_file(path):
    runner = CliRunner()
    plain = runner.invoke(app, ["info", str(path)])
    assert plain.exit_code == 0, plain.output
    lines = plain.stdout.splitlines()
    assert lines[0].split() == ["path", str(path)]
    assert any(line.split()[:1] == ["kind"] for line in lines)

    as_json = runner.invoke(app, ["info", "--json", str(path)])
    assert as_json.exit_code == 0, as_json.output
    summary = json.loads(as_json.stdout)
    assert summary["path"] == str(path)
    assert isinstance(summary["kind"], str) and isinstance(summary["format"], str)
    if path.name in EXPECTED_KIND:
        assert summary["kind"] == EXPECTED_KIND[path.name]
        assert summary["format"] == f"dla.{summary['kind']}/1"
    # the plain listing shows the same keys as the JSON object, one per line
    assert [line.split()[0] for line in lines] == list(summary)


def test_json_summaries_agree_with_the_files():
    body = json.loads((EXAMPLES / "body.json").read_text())
    s = json.loads(CliRunner().invoke(app, ["info", "--json", str(EXAMPLES / "body.json")]).stdout)
    assert s["phenotype"] == body["phenotype"] and s["posed_bones"] == len(body["pose"])
    with np.load(EXAMPLES / "motion.npz") as m:
        frames, fps = m["rotations"].shape[0], float(m["fps"])
    s = json.loads(CliRunner().invoke(app, ["info", "--json", str(EXAMPLES / "motion.npz")]).stdout)
    assert (s["frames"], s["fps"]) == (frames, fps)
    meta = json.loads((EXAMPLES / "views" / "transforms.json").read_text())
    s = json.loads(CliRunner().invoke(app, ["info", "--json", str(EXAMPLES / "views")]).stdout)
    assert (s["views"], s["width"], s["height"]) == (len(meta["frames"]), meta["w"], meta["h"])
    named = CliRunner().invoke(app, ["info", "--json", str(EXAMPLES / "views" / "transforms.json")])
    named = json.loads(named.stdout)
    assert named.pop("path").endswith("transforms.json") and s.pop("path").endswith("views")
    assert named == s  # the folder's transforms.json stands for the folder


def _bad_inputs(tmp_path):
    cut = tmp_path / "cut.npz"
    data = (EXAMPLES / "avatar.npz").read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    bad_body = tmp_path / "body.json"
    bad_body.write_text(json.dumps({"format": "dla.body/2"}))
    views = tmp_path / "views"
    views.mkdir()
    (views / "transforms.json").write_text('{"frames": [')
    big = tmp_path / "big.ply"  # a log-scale of 100: exp overflows float32 (issue 20)
    ply = (EXAMPLES / "gaussians_sh0.ply").read_bytes()
    big.write_bytes(ply.replace(struct.pack("<f", math.log(0.2)), struct.pack("<f", 100.0), 1))
    zipped = tmp_path / "zip70.npz"  # "version needed to extract" 7.0: zipfile's NotImplementedError
    npz = (EXAMPLES / "motion.npz").read_bytes()
    zipped.write_bytes(npz.replace(b"PK\x01\x02-\x03-", b"PK\x01\x02-\x03F"))
    return [
        (cut, "not a readable .npz file"),
        (bad_body, "'dla.body/2' is not supported"),
        (views, "not valid JSON"),
        (tmp_path / "missing.ply", "no such file"),
        (big, "holds a log-scale of 100"),
        (zipped, "unsupported zip feature"),
    ]


def _check_one_line(path, needle, returncode, stdout, stderr):
    assert returncode == 2, (path, stderr)
    assert stdout == ""
    err = stderr.strip("\n")
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith(f"error: {path}") and needle in err, err


def test_bad_input_through_the_installed_script(tmp_path):
    path, needle = _bad_inputs(tmp_path)[0]
    result = _dla("info", str(path))
    _check_one_line(path, needle, result.returncode, result.stdout, result.stderr)


def test_bad_inputs_exit_2_with_one_line(tmp_path, monkeypatch, capsys):
    from dlacli.cli.app import main

    for path, needle in _bad_inputs(tmp_path):
        monkeypatch.setattr(sys, "argv", ["dla", "info", str(path)])
        with pytest.raises(SystemExit) as exit_info:
            main()
        out = capsys.readouterr()
        _check_one_line(path, needle, exit_info.value.code, out.out, out.err)
