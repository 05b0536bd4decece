"""The CLI contract under hostile and careless input: one line `error: ...`, exit 2, no traceback,
no partial output, inputs never destroyed, memory and time bounded by what the input holds.

Each test builds its own hostile input; commands run through `dlacli.cli.app.main` (what the
`dla` script calls), in-process, or in a subprocess where a signal or a hang is the point.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from dlacli.cli.app import main

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "formats" / "examples"


def run(argv, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return info.value.code, out, err


def refused(argv, capsys, *words: str) -> str:
    """The command exits 2 with exactly one `error: ...` line on stderr that contains `words`."""
    code, _, err = run(argv, capsys)
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every entry under `folder` (names and file bytes), to show nothing changed."""
    return {
        str(p.relative_to(folder)): (p.read_bytes() if p.is_file() and not p.is_symlink() else None)
        for p in sorted(folder.rglob("*"))
    }


@pytest.fixture
def work(tmp_path):
    """A folder with an avatar, a view folder and a user's own file."""
    shutil.copy(EXAMPLES / "avatar.npz", tmp_path / "av.npz")
    shutil.copytree(EXAMPLES / "views", tmp_path / "views")
    (tmp_path / "notes.txt").write_text("my notes\n")
    return tmp_path


# ---------------------------------------------------------------------------------------------
# data loss: outputs never replace an input or anything that is not ours


def test_output_that_names_an_input_is_refused(work, capsys):
    before = snapshot(work)
    refused(["render", work / "av.npz", "-o", work / "av.npz", "--turntable", "2"], capsys, "av.npz", "a file")
    refused(
        ["edit", "swap", work / "av.npz", work / "av.npz", "--region", "face", "-o", work / "av.npz"], capsys, "input"
    )
    refused(["interp", work / "av.npz", work / "av.npz", "-o", work / "av.npz"], capsys, "input")
    refused(["lift", work / "views", "-o", work / "a.npz", "--ply", work / "views" / "body.json"], capsys, ".ply")
    os.symlink(work / "views" / "body.json", work / "link.ply")  # a link to an input is that input
    refused(["lift", work / "views", "-o", work / "a.npz", "--ply", work / "link.ply"], capsys, "input")
    refused(["lift", work / "views", "-o", work / "a.npz", "--ply", work / "a_contact.png"], capsys, ".ply")
    refused(["lift", work / "views", "-o", work / "a.npz", "--ply", work / "a.npz"], capsys, ".ply")
    os.remove(work / "link.ply")
    assert snapshot(work) == before


def test_view_page_over_an_input_or_a_non_file(work, capsys):
    """dla view writes AVATAR.html by default: an avatar that is itself named .html is refused."""
    shutil.copy(work / "av.npz", work / "av.html")
    os.mkfifo(work / "pipe.html")
    (work / "dir.html").mkdir()
    before = snapshot(work)
    refused(["view", work / "av.html"], capsys, "av.html", "input")
    refused(["view", work / "av.npz", "-o", work / "av.npz"], capsys, "av.npz", ".html")
    refused(["view", work / "av.npz", "-o", work / "pipe.html"], capsys, "pipe.html", "FIFO")
    refused(["view", work / "av.npz", "-o", work / "dir.html"], capsys, "dir.html", "folder")
    refused(["view", work / "av.npz", "-o", work / "notes.txt" / "v.html"], capsys, "not a folder")
    assert snapshot(work) == before


def test_contact_sheet_over_an_input_image(work, capsys):
    """lift writes NAME_contact.png beside NAME.npz: when that is one of the input images, refuse."""
    meta = json.loads((work / "views" / "transforms.json").read_text())
    meta["frames"][0]["file_path"] = "a_contact.png"
    shutil.copy(work / "views" / "images" / "view_000.png", work / "views" / "a_contact.png")
    (work / "views" / "transforms.json").write_text(json.dumps(meta))
    before = snapshot(work)
    refused(["lift", work / "views", "-o", work / "views" / "a.npz"], capsys, "a_contact.png", "input")
    assert snapshot(work) == before


def test_folder_outputs_never_replace_a_users_file_or_folder(work, capsys):
    before = snapshot(work)
    refused(["synth", "--seed", "1", "-o", work / "notes.txt"], capsys, "notes.txt", "not a folder dla wrote")
    refused(
        ["dream", work / "views" / "images" / "view_000.png", "-o", work / "views" / "images" / "view_000.png"],
        capsys,
        "view_000.png",
    )
    refused(
        ["render", work / "av.npz", "--turntable", "2", "-o", work], capsys, "did not write"
    )  # holds the user's files
    refused(["render", work / "views" / "av.npz", "--turntable", "1", "-o", work / "views"], capsys)
    assert snapshot(work) == before


def test_output_folder_holding_an_input_is_refused(work, capsys):
    (work / "out").mkdir()
    shutil.copy(work / "av.npz", work / "out" / "f0000_c000.png")  # named like a render, but it is our input
    refused(["render", work / "out" / "f0000_c000.png", "--turntable", "1", "-o", work / "out"], capsys, "input")
    assert (work / "out" / "f0000_c000.png").read_bytes() == (work / "av.npz").read_bytes()


def test_fifo_device_and_folder_outputs_are_refused(work, capsys):
    os.mkfifo(work / "pipe.npz")
    os.symlink("/dev/null", work / "null.npz")
    (work / "dir.npz").mkdir()
    for target, kind in (("pipe.npz", "FIFO"), ("null.npz", "device"), ("dir.npz", "folder")):
        refused(["interp", work / "av.npz", work / "av.npz", "-o", work / target], capsys, target, kind)
    assert os.path.islink(work / "null.npz") and (work / "dir.npz").is_dir()


def test_parent_that_is_a_file_and_missing_parents_are_left_alone(work, capsys):
    refused(["interp", work / "av.npz", work / "av.npz", "-o", work / "notes.txt" / "x.npz"], capsys, "not a folder")
    # a failing command creates no parent folders: the views are broken here
    (work / "views" / "transforms.json").write_text("{")
    refused(["lift", work / "views", "-o", work / "new" / "deep" / "a.npz"], capsys, "transforms.json")
    assert not (work / "new").exists()


# ---------------------------------------------------------------------------------------------
# unbounded memory and hangs from tiny files


def test_ply_header_claiming_a_billion_vertices(work, capsys):
    head = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
        b"property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    (work / "big.ply").write_bytes(head + b"\0" * 24)
    refused(["info", work / "big.ply"], capsys, "big.ply", "1000000000")
    ascii_head = head.replace(b"binary_little_endian", b"ascii")
    (work / "big_ascii.ply").write_bytes(ascii_head + b"0 0 0\n")
    refused(["info", work / "big_ascii.ply"], capsys, "big_ascii.ply")


def _npy(shape, data: bytes) -> bytes:
    header = repr({"descr": "<f4", "fortran_order": False, "shape": tuple(shape)}).encode()
    header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + data


def test_npz_whose_header_claims_more_than_it_holds(work, capsys):
    with zipfile.ZipFile(work / "claim.npz", "w") as zf:
        zf.writestr("format.npy", _npy((), b""))  # not even a string: irrelevant, the bound comes first
        zf.writestr("z.npy", _npy((14, 100000, 100000), b"\0" * 64))
    refused(["info", work / "claim.npz"], capsys, "claim.npz", "z.npy")


def test_npz_zip_bomb(work, capsys):
    """Members whose zip directory claims 8 GiB of content in all: refused from the directory
    alone, before anything is inflated."""
    with zipfile.ZipFile(work / "bomb.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("z.npy", _npy((4,), b"\0" * 16))
        zf.writestr("canonical.npy", _npy((4,), b"\0" * 16))
    data = bytearray((work / "bomb.npz").read_bytes())
    at = 0
    for _ in range(2):
        at = data.index(b"PK\x01\x02", at)
        data[at + 24 : at + 28] = struct.pack("<I", 0xFFFFFFFE)  # uncompressed size: 4 GiB - 2
        at += 4
    (work / "bomb.npz").write_bytes(bytes(data))
    refused(["animate", work / "bomb.npz", "walk", "-o", work / "o.usdc"], capsys, "bomb.npz", "MiB")
    refused(["view", work / "bomb.npz", "-o", work / "o.html"], capsys, "bomb.npz", "MiB")
    assert not (work / "o.usdc").exists() and not (work / "o.html").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["lift", "{views}", "-o", "{w}/a.npz", "--resolution", "1000000"],
        ["lift", "{views}", "-o", "{w}/a.npz", "--gaussians", "1000000000"],
        ["render", "{av}", "-o", "{w}/r", "--turntable", "4", "--size", "1000000"],
        ["render", "{av}", "-o", "{w}/r", "--turntable", "100000000"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--fps", "1e9"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--gaussians", "1000000000"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--preview-size", "100000"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--tolerance", "1e9"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--tolerance", "-1"],
        ["animate", "{av}", "walk", "-o", "{w}/a.usdc", "--tolerance", "nan"],
        ["view", "{av}", "-o", "{w}/v.html", "--gaussians", "1000000000"],
        ["view", "{av}", "--motion", "walk", "-o", "{w}/v.html", "--fps", "1e9"],
        ["interp", "{av}", "{av}", "-o", "{w}/o", "--steps", "100000000"],
        ["interp", "{av}", "{av}", "-o", "{w}/o.npz", "--t", "nan"],
        ["dream", "{views}/images/view_000.png", "-o", "{w}/v", "--res", "100000"],
        ["synth", "--seed", "1", "-o", "{w}/s", "--res", "100000"],
        ["synth", "--seed", "1", "-o", "{w}/s", "--novel-views", "100000000"],
        ["edit", "swap", "{av}", "{av}", "-r", "face", "-o", "{w}/o.npz", "--feather", "inf"],
        ["export", "{av}", "-o", "{w}/a.ply", "--gaussians", "1000000000"],
        ["export", "{av}", "-o", "{w}/a.ply", "--motion", "walk", "--frame", "100000000"],
        ["export", "{av}", "-o", "{w}/a.ply", "--motion", "walk", "--frame", "0", "--fps", "1e9"],
    ],
)
def test_flags_have_upper_bounds(argv, work, capsys):
    before = snapshot(work)
    argv = [a.format(w=work, views=work / "views", av=work / "av.npz") for a in argv]
    line = refused(argv, capsys)
    assert line.split(":")[1].strip() == argv[-2]  # names the option
    assert snapshot(work) == before


def test_symlink_to_dev_zero_is_not_read(work, capsys):
    for name in ("z.npz", "z.ply", "body.json", "z.usda"):
        os.symlink("/dev/zero", work / name)
        refused(["info", work / name], capsys, name, "device")


def _run_cli(args, timeout, **kw):
    return subprocess.run(
        [sys.executable, "-c", "from dlacli.cli.app import main; main()", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        **kw,
    )


def test_fifo_inputs_do_not_hang(work):
    os.mkfifo(work / "pipe.npz")
    os.mkfifo(work / "views" / "body.json.fifo")
    os.replace(work / "views" / "body.json.fifo", work / "views" / "body.json")
    for args in (
        ["info", work / "pipe.npz"],
        ["animate", work / "pipe.npz", "walk", "-o", work / "o.usdc"],
        ["lift", work / "views", "-o", work / "a.npz"],
    ):
        result = _run_cli(args, timeout=120)
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith("error: ") and "FIFO" in result.stderr and "Traceback" not in result.stderr


# ---------------------------------------------------------------------------------------------
# tracebacks


def test_deeply_nested_json(work, capsys):
    (work / "body.json").write_text("[" * 100_000 + "]" * 100_000)
    refused(["info", work / "body.json"], capsys, "body.json", "nested")
    (work / "views" / "transforms.json").write_text('{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}")
    refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "transforms.json")


def _png_header_only(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def test_png_decompression_bomb(work, capsys):
    (work / "bomb.png").write_bytes(_png_header_only(100_000, 100_000))
    refused(["dream", work / "bomb.png", "-o", work / "v"], capsys, "bomb.png")
    shutil.copy(work / "bomb.png", work / "views" / "images" / "view_000.png")
    refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "view_000.png")
    assert not (work / "v").exists() and not (work / "a.npz").exists()


def test_usage_errors_are_one_line(capsys):
    for argv in (
        ["lift"],
        ["lift", "v"],
        ["nosuch"],
        ["lift", "v", "-o", "a.npz", "--steps", "x"],
        ["lift", "v", "-o", "a.npz", "--bogus"],
        ["animate", "a.npz"],
    ):
        line = refused(argv, capsys)
        assert "--help" in line


def test_full_disk_is_one_line_and_leaves_nothing(work, capsys, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np.lib.format, "write_array", full)
    refused(
        ["interp", work / "av.npz", work / "av.npz", "-o", work / "out" / "b.npz"], capsys, "b.npz", "No space left"
    )
    assert not (work / "out").exists()
    assert not [p for p in work.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------------------------------------
# partial output


def test_side_files_land_only_with_the_main_output(work, capsys, monkeypatch):
    """interp --steps K --video: when the video fails, no avatar folder appears either."""
    import dlacli.io.video as video
    import dlacli.stages.render as render

    class Shot:
        rgba = np.zeros((16, 16, 4), np.float32)

    monkeypatch.setattr(
        render, "render_avatar", lambda *a, **k: iter([Shot()])
    )  # the golden avatar is a format example, not renderable

    def broken(frames, path, fps, background=0.0):
        with video.atomic_path(path) as tmp:
            tmp.write_bytes(b"")
            raise video.DlaInputError(path, "ffmpeg wrote an empty video")

    monkeypatch.setattr(video, "write_video", broken)
    refused(
        [
            "interp",
            work / "av.npz",
            work / "av.npz",
            "-o",
            work / "morph",
            "--steps",
            "2",
            "--video",
            work / "morph.mp4",
            "--size",
            "16",
        ],
        capsys,
        "morph.mp4",
    )
    assert not (work / "morph").exists() and not (work / "morph.mp4").exists()
    assert not [p for p in work.iterdir() if p.name.startswith(".")]


def test_empty_video_is_never_renamed_into_place(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    from dlacli.errors import DlaInputError
    from dlacli.io.video import write_video

    class Silent:  # an ffmpeg that accepts frames and writes nothing
        def append_data(self, frame):
            pass

        def close(self):
            pass

    monkeypatch.setattr(imageio, "get_writer", lambda *a, **k: Silent())
    with pytest.raises(DlaInputError, match="empty video"):
        write_video([np.zeros((16, 16, 3), np.uint8)], tmp_path / "v.mp4", 10)
    assert list(tmp_path.iterdir()) == []


def test_sigterm_leaves_no_temporaries(tmp_path):
    """dla synth renders inside its temporary folder: SIGTERM there must remove it."""
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from dlacli.cli.app import main; main()",
            "synth",
            "--seed",
            "3",
            "-o",
            str(tmp_path / "s"),
            "--res",
            "64",
            "--novel-views",
            "40",
            "--novel-poses",
            "20",
        ],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 300
    while (
        not [p for p in tmp_path.iterdir() if ".dla-" in p.name] and time.monotonic() < deadline and proc.poll() is None
    ):
        time.sleep(0.05)
    assert proc.poll() is None, "synth finished before it could be interrupted"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip() == f"error: terminated by signal {int(signal.SIGTERM)}"
    assert list(tmp_path.iterdir()) == []


def test_stale_temporaries_of_dead_runs_are_swept(work, capsys):
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale_file = work / f".b.dla-{dead.pid}-abc123.tmp.npz"
    stale_dir = work / f".morph.dla-{dead.pid}-abc123.tmp"
    stale_file.write_bytes(b"half")
    stale_dir.mkdir()
    mine = work / ".notes.tmp"  # not a name dla makes: left alone
    mine.write_text("x")
    code, _, err = run(["interp", work / "av.npz", work / "av.npz", "-o", work / "b.npz"], capsys)
    assert code == 0, err
    assert not stale_file.exists() and not stale_dir.exists() and mine.exists()


# ---------------------------------------------------------------------------------------------
# escapes: a view folder reads only its own files


@pytest.mark.parametrize("kind", ["absolute", "dotdot", "symlink"])
def test_view_paths_stay_inside_the_folder(work, capsys, kind):
    secret = work / "secret.png"
    shutil.copy(work / "views" / "images" / "view_001.png", secret)
    meta = json.loads((work / "views" / "transforms.json").read_text())
    if kind == "absolute":
        meta["frames"][0]["file_path"] = str(secret)
    elif kind == "dotdot":
        meta["frames"][0]["file_path"] = "../secret.png"
    else:
        os.symlink(secret, work / "views" / "images" / "link.png")
        meta["frames"][0]["file_path"] = "images/link.png"
    (work / "views" / "transforms.json").write_text(json.dumps(meta))
    refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "frames[0].file_path", "--allow-outside")
    refused(["info", work / "views"], capsys, "frames[0].file_path")

    from dlacli.io.views import read_views

    views = read_views(work / "views", allow_outside=True)  # the user may allow it
    assert views.images.shape[0] == 2


# ---------------------------------------------------------------------------------------------
# messages name the file or the option


def test_stage_errors_name_the_users_file(work, capsys):
    body = json.loads((work / "views" / "body.json").read_text())
    body["pose"] = {"no_such_bone": [0.0, 0.0, 0.0]}
    (work / "views" / "body.json").write_text(json.dumps(body))
    line = refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "no_such_bone")
    assert line.startswith(f"error: {work / 'views' / 'body.json'}: ")


def test_motion_convert_over_its_source(work, capsys):
    shutil.copy(EXAMPLES / "motion.npz", work / "m.npz")
    before = (work / "m.npz").read_bytes()
    refused(["motion", "convert", work / "m.npz", "-o", work / "m.npz"], capsys, "input")
    assert (work / "m.npz").read_bytes() == before


def test_absurd_body_and_motion_values_are_refused(work, capsys):
    """Values no body or motion can have (overflowing float32 skinning) are refused on reading."""
    from dlacli.io.avatar import read_avatar, write_avatar
    from dlacli.io.motion import read_motion, write_motion

    body = json.loads((work / "views" / "body.json").read_text())
    body["pose"] = {"upperarm01.L": [1e30, 0.0, 0.0]}
    (work / "views" / "body.json").write_text(json.dumps(body))
    refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "body.json", "pose['upperarm01.L']")
    with np.load(EXAMPLES / "motion.npz") as golden:  # written by hand: dla's writer refuses these
        arrays = {k: golden[k] for k in golden.files}
    np.savez(work / "far.npz", **{**arrays, "root_translation": arrays["root_translation"] + 1e9})
    refused(["motion", "convert", work / "far.npz", "-o", work / "o.npz"], capsys, "far.npz", "root_translation")
    motion = read_motion(EXAMPLES / "motion.npz")
    motion.bone_labels = ["not_a_bone", *motion.bone_labels[1:]]
    write_motion(motion, work / "alien.npz")
    refused(["motion", "convert", work / "alien.npz", "-o", work / "o.npz"], capsys, "alien.npz", "not_a_bone")
    avatar = read_avatar(work / "av.npz")
    avatar.uv_layout = "smplx"
    write_avatar(avatar, work / "smplx.npz")
    refused(["render", work / "smplx.npz", "--turntable", "1", "-o", work / "r"], capsys, "smplx.npz", "uv_layout")
    assert not (work / "o.npz").exists() and not (work / "r").exists()


def test_npz_claiming_gigabytes_of_arrays(work, capsys):
    """A 3 GiB array declared in a few hundred bytes: refused before numpy allocates it."""
    with zipfile.ZipFile(work / "x.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("z.npy", _npy((4,), b"\0" * 16))
    data = bytearray((work / "x.npz").read_bytes())
    at = data.index(b"PK\x01\x02")
    data[at + 24 : at + 28] = struct.pack("<I", 3 << 30)
    (work / "x.npz").write_bytes(bytes(data))
    refused(["render", work / "x.npz", "--turntable", "1", "-o", work / "r"], capsys, "x.npz", "MiB")


def test_usda_that_would_crash_the_usd_parser(work, capsys):
    """USD's text parser recurses per bracket and segfaults on deep nesting; junk bytes raise
    from inside pxr: both are refused before pxr sees the file."""
    (work / "deep.usda").write_text("#usda 1.0\n(\n" + 'def X "a" {\n' * 5000 + "}\n" * 5000 + ")\n")
    refused(["info", work / "deep.usda"], capsys, "deep.usda", "nests")
    (work / "junk.usda").write_bytes(b"#usda 1.0\n" + bytes([0xDA, 0xFF]) * 100)
    refused(["info", work / "junk.usda"], capsys, "junk.usda", "UTF-8")


def test_body_json_linking_out_of_the_view_folder(work, capsys):
    shutil.move(work / "views" / "body.json", work / "elsewhere.json")
    os.symlink(work / "elsewhere.json", work / "views" / "body.json")
    refused(["lift", work / "views", "-o", work / "a.npz"], capsys, "body.json", "--allow-outside")


def test_checkpoint_for_a_decoder_without_weights(work, capsys):
    os.mkfifo(work / "ckpt")
    refused(
        ["render", work / "av.npz", "--turntable", "1", "-o", work / "r", "--checkpoint", work / "ckpt"],
        capsys,
        "takes no checkpoint",
    )


def test_a_users_file_inside_a_dla_subfolder_is_never_deleted(work, capsys):
    (work / "out").mkdir()
    (work / "out" / "images").mkdir()
    (work / "out" / "images" / "view_000.png").write_bytes(b"x")  # what dla writes there ...
    (work / "out" / "images" / "notes.txt").write_text("mine")  # ... and what it does not
    refused(["dream", work / "views" / "images" / "view_000.png", "-o", work / "out"], capsys, "images/notes.txt")
    assert (work / "out" / "images" / "notes.txt").read_text() == "mine"


def test_names_too_long_for_the_file_system_are_refused_before_work(work, capsys):
    refused(["lift", work / "views", "-o", work / ("a" * 300 + ".npz")], capsys, "too long")


def test_frame_rates_and_camera_positions_no_input_has(work, capsys):
    bvh = (
        "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n"
        " End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 2\nFrame Time: 1e300\n0 0 0\n0 0 0\n"
    )
    (work / "slow.bvh").write_text(bvh)
    refused(["motion", "convert", work / "slow.bvh", "-o", work / "o.npz"], capsys, "slow.bvh", "fps")
    meta = json.loads((work / "views" / "transforms.json").read_text())
    meta["frames"][0]["transform_matrix"][0][3] = 1e300
    (work / "views" / "transforms.json").write_text(json.dumps(meta))
    refused(["render", work / "av.npz", "--cameras", work / "views", "-o", work / "r"], capsys, "translation")
