"""USD files and writes as an attacker makes them: a write that hits the file-size limit inside pxr
is `cannot write` (exit 2, no file left), pxr's own warnings never reach the terminal, and error
lines quote what a file holds as a short escaped excerpt (formats/usd.md)."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dlacli.cli.app import main
from dlacli.errors import DlaInputError, excerpt, one_line
from dlacli.io.usd import tf_message
from dlacli.io.usd_read import read_usd, summarize_usd

BIG = "9" * 20_000  # an integer literal far out of range, 20 KB long
HEADER = '#usda 1.0\n(\n    customLayerData = {{\n        string "dla:format" = "{fmt}"\n    }}\n)\n\n'


def _layer(tmp_path, name: str, body: str, fmt: str = "dla.usd/1"):
    path = tmp_path / name
    path.write_text(HEADER.format(fmt=fmt) + body, encoding="utf-8")
    return path


def _dla(capfd, *argv) -> tuple[int, str, str]:
    """Exit code, stdout and stderr of `dla argv`, captured at the file descriptors (pxr writes
    its diagnostics there, not through sys.stderr)."""
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return info.value.code, out, err


# --- writes that hit the file-size limit -------------------------------------------------------

_WRITE = """
import json, resource, sys
from pathlib import Path
import numpy as np
from dlacli.errors import DlaInputError
from dlacli.io.usd import write_usd
from dlacli.io.usd_rig import RigAsset, write_rig_usd

folder, limit = Path(sys.argv[1]), int(sys.argv[2])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
rng = np.random.default_rng(0)
n, v = 5000, 20000
quats = np.zeros((3, n, 4), np.float32)
quats[..., 0] = 1
rig = RigAsset(joint_names=["root"], parents=np.array([-1]), bind_transforms=np.eye(4)[None],
               points=rng.normal(size=(v, 3)).astype(np.float32), normals=np.tile(np.float32([0, 0, 1]), (v, 1)),
               faces=rng.integers(0, v, (v, 3)), uv=rng.uniform(size=(v, 2)).astype(np.float32),
               face_uv=rng.integers(0, v, (v, 3)), vertex_rgb=np.full((v, 3), 0.5, np.float32),
               joint_indices=np.zeros((v, 1), np.int32), joint_weights=np.ones((v, 1), np.float32),
               texture=np.zeros((4, 4, 3), np.uint8))
errors = {}
for name in ("a.usdc", "a.usda", "rig.usdc"):
    try:
        if name.startswith("rig"):
            write_rig_usd(folder / name, rig)
        else:
            write_usd(folder / name, rng.normal(size=(3, n, 3)), quats, np.full((n, 3), 0.1), np.full((n, 3), 0.5),
                      np.ones(n), fps=24.0)
    except DlaInputError as err:
        errors[name] = [err.where, err.problem]
print(json.dumps(errors))
"""


def test_writes_over_the_file_size_limit_are_cannot_write(tmp_path):
    """A real RLIMIT_FSIZE (20 KB): pxr fails inside its export; write_usd and write_rig_usd say
    `cannot write (File too large)` about the file asked for, and leave nothing behind."""
    folder = tmp_path / "out"
    folder.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", _WRITE, str(folder), "20000"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    import json

    errors = json.loads(done.stdout.strip().splitlines()[-1])
    names = ("a.usdc", "a.usda", "rig.usdc")
    assert errors == {name: [str(folder / name), "cannot write (File too large)"] for name in names}
    assert list(folder.iterdir()) == []  # no partial file, no temporary, no texture without its USD
    assert "Warning" not in done.stderr and "Error in" not in done.stderr


_ANIMATE = """
import os, resource, sys
from dlacli.cli.app import main

def dla(*argv):
    try:
        main(list(argv))
    except SystemExit as exit:
        return exit.code

avatar, warm, out, limit = sys.argv[1:5]
dla("animate", avatar, "walk", "-o", warm, "--tolerance", "0")  # loads the body model, fills every cache
os.remove(warm)
resource.setrlimit(resource.RLIMIT_FSIZE, (int(limit), int(limit)))
print(f"exit={dla('animate', avatar, 'walk', '-o', out, '--tolerance', '0')}", file=sys.stderr)
"""


def _small_avatar():
    """A valid avatar of 1,024 Gaussians on a 32 x 32 map."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.types import PHENOTYPE_KEYS, Avatar, BodyParams

    rng = np.random.default_rng(7)
    z = np.zeros((gm.CHANNELS, 32, 32), np.float32)
    z[gm.OPACITY] = 1.0
    z[gm.RGB] = rng.uniform(0.1, 0.9, (3, 32, 32))
    z[gm.ROTATION.start] = 1.0  # identity rotations
    z[gm.LOG_SCALE] = np.log(2.0)
    body = BodyParams(phenotype={k: 0.5 for k in PHENOTYPE_KEYS})
    return Avatar(
        z=z,
        encoder="unproject",
        decoder="identity",
        body=body,
        uv_layout="anny",
        extra={"samples": {"count": 1024, "seed": 4}},
    )


def test_dla_animate_over_the_file_size_limit(tmp_path):
    """The command line: `error: <file>: cannot write (File too large)`, exit 2, no file."""
    from dlacli.io.avatar import write_avatar

    write_avatar(_small_avatar(), tmp_path / "av.npz")
    (tmp_path / "warm").mkdir()
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "walk.usdc"
    args = [tmp_path / "av.npz", tmp_path / "warm" / "walk.usdc", out, 300_000]
    command = [sys.executable, "-c", _ANIMATE, *map(str, args)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    lines = done.stderr.strip().splitlines()
    assert lines[-2:] == [f"error: {out}: cannot write (File too large)", "exit=2"], done.stderr[-3000:]
    assert list((tmp_path / "out").iterdir()) == []


# --- pxr's warnings ------------------------------------------------------------------------------


def test_pxr_warnings_stay_off_the_terminal_on_a_run_that_succeeds(tmp_path, capfd):
    """A double written as an out-of-range integer literal parses (as a double) with a pxr warning."""
    path = _layer(tmp_path, "ok.usda", 'def Xform "Avatar"\n{\n    double x = 99999999999999999999999999\n}\n')
    code, out, err = _dla(capfd, "info", path)
    assert code == 0 and "usd" in out
    assert err == ""


def test_pxr_warnings_stay_off_the_terminal_on_a_run_that_fails(tmp_path, capfd):
    path = _layer(tmp_path, "big.usda", f'def Xform "Avatar"\n{{\n    int x = {BIG}\n}}\n')
    code, _, err = _dla(capfd, "info", path)
    assert code == 2 and "Warning" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: not a readable USD file ("), err[:2000]
    assert "(20,000 characters)" in lines[0] and len(lines[0]) < 600, lines[0]
    assert max(len(run) for run in re.findall(r"9+", lines[0])) <= 60  # the literal, as an excerpt


def test_without_a_diagnostic_trap_the_warnings_are_silenced_too(tmp_path, capfd, monkeypatch):
    """usd-core releases without Tf.DiagnosticTrap: pxr's file descriptor 2 is pointed away meanwhile."""
    from pxr import Tf

    monkeypatch.delattr(Tf, "DiagnosticTrap")
    path = _layer(tmp_path, "ok.usda", 'def Xform "Avatar"\n{\n    double x = 99999999999999999999999999\n}\n')
    assert summarize_usd(path)["kind"] == "usd"
    print("after", file=sys.stderr)  # stderr works again afterwards
    assert capfd.readouterr().err == "after\n"


# --- error lines quote excerpts ------------------------------------------------------------------


def test_a_long_or_hostile_format_value_is_quoted_as_an_excerpt(tmp_path):
    for value, shown in (
        ("x" * 20_000, "'" + "x" * 55 + "... (20,000 characters)"),
        ("\x1b[31mRED", "'\\x1b[31mRED'"),
    ):
        path = _layer(tmp_path, "f.usda", 'def Xform "Avatar"\n{\n}\n', fmt=value)
        with pytest.raises(DlaInputError) as err:
            read_usd(path)
        assert f"customLayerData 'dla:format' is {shown}, expected 'dla.usd/1'" in str(err.value), str(err.value)[:300]
        assert "\x1b" not in str(err.value) and len(str(err.value)) < 300


def test_long_prim_names_in_pxr_errors_are_cut(tmp_path):
    name = "N" * 20_000
    inner = f'    def Xform "{name}"\n    {{\n        int x = {BIG}\n    }}\n'
    path = _layer(tmp_path, "n.usda", f'def Xform "Avatar"\n{{\n{inner}}}\n')
    with pytest.raises(DlaInputError) as err:
        read_usd(path)
    message = str(err.value)
    assert len(message) < 600 and "N" * 61 not in message and "9" * 61 not in message, message[:1000]


def test_pxr_parse_errors_name_the_file_once_without_pxr_internals(tmp_path):
    """pxr's parse error names the file again (its full path) and its grammar rule (~1 KB of C++
    templates in pxr's internal namespace): the line keeps the file's name, the place and what
    was found there, within the bound every reader keeps (tests/io/test_fuzz.py)."""
    folder = tmp_path / ("d" * 100) / ("e" * 100)
    folder.mkdir(parents=True)
    path = _layer(folder, "p.usda", 'def Xform "Avatar"\n{\n    float3[] extent.timeSam\n}\n')
    with pytest.raises(DlaInputError) as err:
        read_usd(path)
    message = str(err.value)
    assert message.startswith(f"{path}: not a readable USD file (p.usda:10:21: parse error matching "), message
    assert "at 'timeSam' in </Avatar.extent>" in message, message
    assert str(path) not in message[len(str(path)) :] and "pxrInternal" not in message, message
    assert len(message) - len(str(path)) <= 300, message


def test_usd_messages_quote_through_the_one_excerpt_helper():
    """io/usd*.py quote through dlacli.errors (no copy of their own): a value from a file as an
    `excerpt`, a prim path as a `one_line`."""
    import dlacli.io.usd as usd
    import dlacli.io.usd_read as usd_read

    for module in (usd, usd_read):
        assert not hasattr(module, "clipped") and not hasattr(module, "MAX_QUOTE")
        assert getattr(module, "excerpt", excerpt) is excerpt
    assert excerpt("dla.usd/9") == "'dla.usd/9'"  # short values as before (repr)
    assert excerpt(None) == "None" and excerpt(3) == "3"
    assert excerpt("it's\n") == '"it\'s\\n"'
    assert excerpt("\x1b" * 100) == "'" + "\\x1b" * 13 + "... (100 characters)"
    assert one_line("/Avatar/Points/Part000") == "/Avatar/Points/Part000"
    assert one_line("a" * 200, 10) == "aaaaaaa..."


def test_tf_message_keeps_the_message_and_cuts_the_values():
    class Fake(Exception):
        pass

    parse = "Error in 'Parse' at line 48 in file textParserHelpers.h"
    err = Fake(
        textwrap.dedent(f"""
        {parse} : 'Failed to parse value at '{BIG}' in </Avatar.x>'
        {parse} : 'f.usda:3:4: Failed to parse value at '{BIG}' in </Avatar.x>'
        Error in 'Open' at line 1 in file stage.cpp : 'Failed to open layer @f.usda@'""")
    )
    assert tf_message(err) == (
        f"f.usda:3:4: Failed to parse value at '{'9' * 55}... (20,000 characters) in "
        "</Avatar.x>; Failed to open layer @f.usda@"
    )
    noise = tf_message(Fake("\x00" * 10_000))
    assert "\x00" not in noise and len(noise) < 400, noise
