"""Hostile motion files: every one is a one-line DlaInputError naming the file, in bounded
memory and time (never a traceback, a hang, or an allocation sized by what a header claims).
Every file is written here, a few bytes each."""

from __future__ import annotations

import io
import os
import struct
import sys
import threading
import tracemalloc
import zipfile

import numpy as np
import pytest

from dlacli.body.retarget import resample_motion
from dlacli.cli.app import main
from dlacli.errors import DlaInputError
from dlacli.io.amass import read_amass
from dlacli.io.asf_amc import read_amc, read_asf
from dlacli.io.bvh import MAX_DEPTH, MAX_FRAMES, MAX_JOINTS, read_bvh
from dlacli.io.files import MAX_TEXT_BYTES
from dlacli.io.motion import read_motion
from dlacli.io.npz_bounds import MAX_MEMBERS, check_npz_bounds
from dlacli.stages.motion.source import load_motion
from dlacli.types import Motion

MiB = 1 << 20


def _error(read, path, *args, peak_mib: float = 20.0) -> str:
    """The one-line message `read(path)` raises, which names the file; the Python heap peak
    while reading (numpy's allocations included) stays under `peak_mib`."""
    tracemalloc.start()
    try:
        with pytest.raises(DlaInputError) as info:
            read(path, *args)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{path}: "), msg
    assert peak < peak_mib * MiB, f"{peak / MiB:.0f} MiB peak for {msg}"
    return msg


def _write(tmp_path, name, text: str | bytes):
    path = tmp_path / name
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


# ---------------------------------------------------------------------------------------------
# BVH


def bvh(channels="CHANNELS 3 Zrotation Yrotation Xrotation", frames="2", frame_time="0.04", data="1 2 3\n4 5 6\n"):
    return (
        f"HIERARCHY\nROOT Hips\n{{\n OFFSET 0 0 0\n {channels}\n End Site\n {{\n  OFFSET 0 1 0\n }}\n}}\n"
        f"MOTION\nFrames: {frames}\nFrame Time: {frame_time}\n{data}"
    )


def test_the_valid_template_reads(tmp_path):
    skel = read_bvh(_write(tmp_path, "ok.bvh", bvh()))
    assert skel.num_frames == 2 and skel.fps == 25.0


def test_a_40_byte_file_claiming_200_million_frames(tmp_path):
    tiny = "HIERARCHY ROOT a { OFFSET 0 0 0 }\nMOTION\nFrames: 200000000\nFrame Time: 1\n"
    assert len(tiny) < 80
    assert "no CHANNELS" in _error(read_bvh, _write(tmp_path, "zero.bvh", tiny), peak_mib=4)
    for channels in ("CHANNELS 0", "CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 1 Xrotation"):
        path = _write(tmp_path, "claim.bvh", bvh(channels, frames="200000000", data="0 0 0\n"))
        msg = _error(read_bvh, path, peak_mib=4)
        assert ("truncated" in msg and "200000000" in msg) or "no CHANNELS" in msg


@pytest.mark.parametrize(
    "frame_time, problem",
    [
        ("0", "must be > 0"),
        ("-0.04", "must be > 0"),
        ("nan", "must be > 0"),
        ("inf", "must be > 0"),
        ("1e-5", "at most 1000 fps"),
        ("1e-320", "at most 1000 fps"),
        ("fast", "bad MOTION header"),
    ],
)
def test_bad_frame_time(tmp_path, frame_time, problem):
    assert problem in _error(read_bvh, _write(tmp_path, "t.bvh", bvh(frame_time=frame_time)))


@pytest.mark.parametrize(
    "text, problem",
    [
        (bvh().split("MOTION")[0], "no MOTION section"),
        (bvh().split("Frames")[0], "lacks 'Frames'"),
        (bvh(data="").replace("Frame Time: 0.04\n", ""), "lacks 'Frame Time'"),
        (bvh(frames="-5"), "-5 frames"),
        (bvh(frames="2.5"), "bad MOTION header"),
        (bvh(frames="9" * 5000), "bad MOTION header"),
        (bvh(data="1 2 3 4\n5 6 7\n"), "line 14: 4 values, expected 3"),
        (bvh(data="1 2\n5 6 7\n"), "line 14: 2 values, expected 3"),
        (bvh(data="1 2 3\n4 5\n"), "truncated: the last frame (line 15) has 2 of 3 values"),
        (bvh(data="1 2 3\n"), "truncated"),
        (bvh(data="1 2 3\n4 5 6\n7 8 9\n\n10 11 12\n"), "2 frame line(s) more than Frames: 2"),
        (bvh(data="1 2 3\n4 x 6\n"), "non-numeric value 'x'"),
        (bvh(data="1 2 3\n4 inf 6\n"), "non-finite"),
        ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n", "unexpected end of HIERARCHY"),
        ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\nMOTION\nFrames: 1\n", "unexpected end of HIERARCHY"),
        (bvh().replace("ROOT Hips", "ROOT " + "H" * 300), "joint name of 300 characters"),
        ("\x00\xff" * 50, "not a BVH file"),
        ("", "not a BVH file"),
    ],
)
def test_bad_motion_sections(tmp_path, text, problem):
    assert problem in _error(read_bvh, _write(tmp_path, "bad.bvh", text))


def _nested(depth: int) -> str:
    opening = "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 1 Xrotation\n" for k in range(1, depth))
    closing = "}\n" * depth
    data = " ".join(["0"] * (depth + 2))
    return (
        f"HIERARCHY\nROOT j0\n{{\nOFFSET 0 0 0\nCHANNELS 3 Xposition Yposition Zposition\n"
        f"{opening}{closing}MOTION\nFrames: 1\nFrame Time: 0.04\n{data}\n"
    )


def test_deep_nesting_is_capped_without_recursion(tmp_path):
    assert f"nested more than {MAX_DEPTH} deep" in _error(read_bvh, _write(tmp_path, "deep.bvh", _nested(3000)))
    assert read_bvh(_write(tmp_path, "ok.bvh", _nested(MAX_DEPTH))).num_joints == MAX_DEPTH  # the cap itself reads


def test_too_many_joints(tmp_path):
    joints = "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\n}}\n" for k in range(MAX_JOINTS + 5))
    text = (
        f"HIERARCHY\nROOT r\n{{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n{joints}}}\nMOTION\nFrames: 1\nFrame Time: 1\n0\n"
    )
    assert f"more than {MAX_JOINTS} joints" in _error(read_bvh, _write(tmp_path, "wide.bvh", text))


def test_many_frames_are_refused_before_they_are_built(tmp_path):
    """Enough lines for MAX_FRAMES + 1 one-channel frames (0.4 MB): refused before the [T, J, 3, 3]
    rotations are allocated."""
    text = bvh("CHANNELS 1 Xrotation", frames=str(MAX_FRAMES + 1), data="0\n" * (MAX_FRAMES + 1))
    assert f"at most {MAX_FRAMES:,}" in _error(read_bvh, _write(tmp_path, "long.bvh", text), peak_mib=10)


# ---------------------------------------------------------------------------------------------
# ASF / AMC

ASF_HEAD = (
    ":version 1.10\n:name t\n:units\n  length 0.45\n  angle deg\n:root\n"
    "   order TX TY TZ RX RY RZ\n   axis XYZ\n   position 0 0 0\n   orientation 0 0 0\n"
)


def asf(names: list[str], hierarchy: list[str]) -> str:
    bones = "".join(
        f"  begin\n     name {n}\n     direction 0 1 0\n     length 1\n     axis 0 0 0 XYZ\n     dof rx\n  end\n"
        for n in names
    )
    return (
        ASF_HEAD
        + ":bonedata\n"
        + bones
        + ":hierarchy\n  begin\n"
        + "".join(f"    {h}\n" for h in hierarchy)
        + "  end\n"
    )


def test_asf_chains_and_cycles(tmp_path):
    deep = [f"b{k}" for k in range(300)]
    chain = ["root b0"] + [f"b{k} b{k + 1}" for k in range(299)]
    assert f"more than {MAX_DEPTH} deep" in _error(read_asf, _write(tmp_path, "deep.asf", asf(deep, chain)))
    many = [f"b{k}" for k in range(3000)]
    chain = ["root b0"] + [f"b{k} b{k + 1}" for k in range(2999)]
    assert "more than" in _error(read_asf, _write(tmp_path, "many.asf", asf(many, chain)))
    assert "two parents" in _error(read_asf, _write(tmp_path, "cycle.asf", asf(["a", "b"], ["root a", "a b", "b a"])))
    assert "two parents" in _error(read_asf, _write(tmp_path, "twice.asf", asf(["a", "b"], ["root a b", "a b"])))
    assert "not reachable" in _error(
        read_asf, _write(tmp_path, "island.asf", asf(["a", "b", "c"], ["root c", "a b", "b a"]))
    )
    assert "not reachable" in _error(read_asf, _write(tmp_path, "self.asf", asf(["a", "b"], ["root b", "a a"])))
    assert "root a child" in _error(read_asf, _write(tmp_path, "root.asf", asf(["a"], ["root a", "a root"])))
    ok = read_asf(_write(tmp_path, "ok.asf", asf(["a", "b"], ["root a", "a b"])))
    assert list(ok.bones) == ["a", "b"]


@pytest.mark.parametrize(
    "amc, problem",
    [
        ("1\nroot 0 0 0 0 0 0\na 1\n2\nroot 0 0 0 0 0 0\n", "frame 2 lacks bone 'a'"),
        ("1\nroot 0 0 0 0 0 0\na 1 2\n", "bone 'a' has 2 values"),
        ("1\nroot 0 0 0 0 0\na 1\n", "bone 'root' has 5 values"),
        ("1\nroot 0 0 0 0 0 0\na nan\n", "non-finite"),
        ("1\nroot 0 0 0 0 0 0\na 1e999\n", "non-finite"),
        ("1\nroot 0 0 0 0 0 0\na x\n", "non-numeric"),
        ("root 0 0 0 0 0 0\n", "data before the first frame"),
        ("1\nroot 0 0 0 0 0 0\nzz 1\n", "bone 'zz' is not in the skeleton"),
        (":FULLY-SPECIFIED\n# only comments\n", "no frames"),
    ],
)
def test_bad_amc(tmp_path, amc, problem):
    skel = _write(tmp_path, "s.asf", asf(["a"], ["root a"]))
    assert problem in _error(read_amc, _write(tmp_path, "m.amc", amc), skel)


def test_amc_reads_with_the_template(tmp_path):
    skel = read_amc(
        _write(tmp_path, "m.amc", "1\nroot 0 0 0 0 0 0\na 1\n\n\n2\nroot 1 0 0 0 0 0\na 2\n"),
        _write(tmp_path, "s.asf", asf(["a"], ["root a"])),
    )
    assert skel.num_frames == 2 and skel.names == ["root", "a"]


# ---------------------------------------------------------------------------------------------
# not regular files, too large files (BVH, ASF, AMC and npz alike)


def _in_time(fn, seconds: float = 10.0):
    """Run fn in a thread; it must finish within `seconds` (a FIFO must not hang it)."""
    box = {}

    def run():
        try:
            fn()
        except BaseException as err:  # noqa: BLE001 - handed to the test
            box["err"] = err

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "the reader blocked"
    return box.get("err")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
@pytest.mark.parametrize("name", ["x.bvh", "x.amc", "x.asf", "x.npz"])
def test_a_fifo_is_refused_without_hanging(tmp_path, name):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    skel = _write(tmp_path, "s.asf", asf(["a"], ["root a"]))
    read = {"x.bvh": read_bvh, "x.amc": lambda p: read_amc(p, skel), "x.asf": read_asf, "x.npz": load_motion}[name]
    err = _in_time(lambda: read(fifo))
    assert isinstance(err, DlaInputError) and str(err).startswith(f"{fifo}: ") and "FIFO" in str(err)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
@pytest.mark.parametrize("name", ["zero.bvh", "zero.amc", "zero.npz"])
def test_a_link_to_dev_zero_is_refused_unread(tmp_path, name):
    link = tmp_path / name
    link.symlink_to("/dev/zero")
    skel = _write(tmp_path, "s.asf", asf(["a"], ["root a"]))
    read = {"zero.bvh": read_bvh, "zero.amc": lambda p: read_amc(p, skel), "zero.npz": load_motion}[name]
    err = _in_time(lambda: read(link))
    assert isinstance(err, DlaInputError) and str(err).startswith(f"{link}: ") and "device" in str(err)


def test_huge_files_are_refused_before_reading(tmp_path):
    path = tmp_path / "huge.bvh"
    with open(path, "wb") as f:  # sparse: no disk used
        f.truncate(MAX_TEXT_BYTES + 1)
    assert "MiB" in _error(read_bvh, path, peak_mib=4)
    os.rename(path, tmp_path / "huge.amc")
    assert "MiB" in _error(
        read_amc, tmp_path / "huge.amc", _write(tmp_path, "s.asf", asf(["a"], ["root a"])), peak_mib=4
    )
    big_asf = tmp_path / "big.asf"
    with open(big_asf, "wb") as f:
        f.truncate(17 * MiB)
    assert "MiB" in _error(read_asf, big_asf, peak_mib=4)


def test_a_folder_named_like_a_motion(tmp_path):
    (tmp_path / "clip.bvh").mkdir()
    assert "folder" in _error(read_bvh, tmp_path / "clip.bvh")
    assert "folder" in _error(load_motion, tmp_path / "clip.bvh")


# ---------------------------------------------------------------------------------------------
# AMASS npz


def amass(path, **override):
    arrays = {"poses": np.zeros((4, 156)), "trans": np.zeros((4, 3)), "mocap_framerate": np.array(60.0)}
    arrays.update(override)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


@pytest.mark.parametrize(
    "override, problem",
    [
        ({"poses": np.zeros((4, 156, 1))}, "numeric [T, 156|165|72] array"),
        ({"poses": np.zeros((4, 0))}, "0 values per frame"),
        ({"poses": np.zeros((4, 70))}, "70 values per frame"),
        ({"poses": np.zeros((4, 999))}, "999 values per frame"),
        ({"poses": np.zeros(4)}, "numeric [T, 156|165|72] array"),
        ({"poses": np.array("walk")}, "numeric"),
        ({"poses": np.full((4, 156), np.inf)}, "non-finite"),
        ({"poses": np.full((4, 156), 1e300)}, "beyond"),
        ({"trans": np.full((4, 3), 1e30)}, "beyond"),
        ({"trans": np.zeros((5, 3))}, "trans has shape (5, 3), expected (4, 3)"),
        ({"trans": np.zeros((4, 2))}, "trans has shape"),
        ({"mocap_framerate": np.array(0.0)}, "must be > 0"),
        ({"mocap_framerate": np.array(-60.0)}, "must be > 0"),
        ({"mocap_framerate": np.array(np.nan)}, "must be > 0"),
        ({"mocap_framerate": np.array(1e9)}, "above 1000"),
        ({"mocap_framerate": np.zeros(3)}, "must be one number"),
        ({"mocap_framerate": np.array("fast")}, "must be one number"),
    ],
)
def test_bad_amass_arrays(tmp_path, override, problem):
    assert problem in _error(read_amass, amass(tmp_path / "a.npz", **override))


def _npz(path, members: dict[str, bytes], compress=zipfile.ZIP_STORED):
    with zipfile.ZipFile(path, "w", compress) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _npy(shape, dtype="<f8", data: bytes = b"") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def test_npy_headers_that_lie_about_their_size(tmp_path):
    """numpy allocates the array a header declares before reading: 10^12 x 156 doubles here."""
    ok = {"trans.npy": _npy((1, 3), data=bytes(24)), "mocap_framerate.npy": _npy((), data=struct.pack("<d", 60.0))}
    path = _npz(tmp_path / "lie.npz", {"poses.npy": _npy((10**12, 156), data=bytes(64)), **ok})
    assert "declares a (1000000000000, 156) float64 array" in _error(read_amass, path, peak_mib=2)
    assert "declares" in _error(load_motion, path, peak_mib=2)
    path = _npz(tmp_path / "void.npz", {"poses.npy": _npy((10**15,), dtype="|V0"), **ok})  # 0-byte items
    assert "declares" in _error(read_amass, path, peak_mib=2)
    path = _npz(tmp_path / "junk.npz", {"poses.npy": b"\x93NUMPY\x01\x00\xff\xff garbage", **ok})
    assert "not a readable .npz file" in _error(read_amass, path, peak_mib=2)


def test_zip_bombs(tmp_path):
    zeros = _npy((8 * MiB // 8,), data=bytes(8 * MiB))  # 8 MiB of zeros, deflated to ~8 KB
    path = _npz(tmp_path / "bomb.npz", {"poses.npy": zeros}, zipfile.ZIP_DEFLATED)
    assert path.stat().st_size < 100_000
    assert "would unpack to" in _error(check_npz_bounds, path, 1 * MiB, peak_mib=2)
    # the central directory claims ~4 GiB per member: two of them exceed the shared 4 GiB cap
    path = _npz(
        tmp_path / "claim.npz",
        {"poses.npy": _npy((4, 156), data=bytes(8 * 4 * 156)), "trans.npy": _npy((4, 3), data=bytes(96))},
    )
    raw = bytearray(path.read_bytes())
    at = raw.find(b"PK\x01\x02")
    while at >= 0:
        raw[at + 24 : at + 28] = struct.pack("<I", 0xFFFFFFF0)
        at = raw.find(b"PK\x01\x02", at + 4)
    path.write_bytes(bytes(raw))
    assert "would unpack to" in _error(read_amass, path, peak_mib=2)
    # one member claims 100 MB (under the cap) from a few hundred packed bytes
    path = _npz(tmp_path / "one.npz", {"poses.npy": _npy((4, 156), data=bytes(8 * 4 * 156))})
    raw = bytearray(path.read_bytes())
    at = raw.find(b"PK\x01\x02")
    raw[at + 24 : at + 28] = struct.pack("<I", 100_000_000)
    path.write_bytes(bytes(raw))
    assert "claims 100,000,000 bytes unpacked from" in _error(read_amass, path, peak_mib=2)
    # millions of members would make the central directory itself a memory bomb
    path = tmp_path / "members.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for k in range(MAX_MEMBERS + 1):
            zf.writestr(f"m{k}", b"")
    assert "members" in _error(read_amass, path, peak_mib=5)


# ---------------------------------------------------------------------------------------------
# motion.npz (native)


def native(path, t=3, j=2, **override):
    arrays = {
        "format": np.array("dla.motion/1"),
        "model": np.array("anny"),
        "bone_labels": np.array([f"b{i}" for i in range(j)]),
        "rotations": np.zeros((t, j, 3), np.float32),
        "root_rotation": np.zeros((t, 3), np.float32),
        "root_translation": np.zeros((t, 3), np.float32),
        "fps": np.array(30.0),
    }
    arrays.update(override)
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "override, problem",
    [
        ({"rotations": np.zeros((3, 5, 3), np.float32)}, "rotations has shape (3, 5, 3), expected (*, 2, 3)"),
        ({"rotations": np.zeros((0, 2, 3), np.float32)}, "no frames"),
        ({"fps": np.array(0.0)}, "must be > 0"),
        ({"fps": np.array(-1.0)}, "must be > 0"),
        ({"fps": np.array(1000.5)}, "above 1000"),
        ({"fps": np.array(np.nan)}, "not finite"),
        ({"root_translation": np.full((3, 3), np.nan, np.float32)}, "non-finite"),
        ({"rotations": np.full((3, 2, 3), np.inf, np.float32)}, "non-finite"),
    ],
)
def test_bad_native_motions(tmp_path, override, problem):
    path = native(tmp_path / "m.npz", **override)
    assert problem in _error(read_motion, path)
    assert problem in _error(load_motion, path)


def test_native_motion_frame_cap_and_lying_header(tmp_path):
    t = MAX_FRAMES + 1
    path = native(
        tmp_path / "long.npz",
        t=t,
        j=0,
        root_rotation=np.zeros((t, 3), np.float32),
        root_translation=np.zeros((t, 3), np.float32),
    )
    assert f"at most {MAX_FRAMES:,}" in _error(read_motion, path, peak_mib=30)
    path = native(tmp_path / "m.npz")
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    members["rotations.npy"] = _npy((10**9, 2, 3), "<f4", bytes(72))
    assert "declares" in _error(read_motion, _npz(tmp_path / "lie.npz", members), peak_mib=2)


def test_resampling_cannot_explode(tmp_path):
    slow = Motion(
        ["a"],
        np.zeros((1000, 1, 3), np.float32),
        np.zeros((1000, 3), np.float32),
        np.zeros((1000, 3), np.float32),
        1e-3,
    )
    with pytest.raises(DlaInputError, match="--fps"):
        resample_motion(slow, 1000.0)
    tiny = Motion(
        ["a"], np.zeros((3, 1, 3), np.float32), np.zeros((3, 3), np.float32), np.zeros((3, 3), np.float32), 1e-320
    )
    with pytest.raises(DlaInputError, match="--fps"):
        resample_motion(tiny, 30.0)


def test_overflowing_positions_name_the_source(tmp_path):
    path = _write(
        tmp_path,
        "far.bvh",
        bvh(
            "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation",
            frames="1",
            data="1e300 1e300 1e300 0 0 0\n",
        ),
    )
    with pytest.raises(DlaInputError, match="overflow") as info:
        load_motion(path)
    assert str(info.value).startswith(f"{path}: ")


# ---------------------------------------------------------------------------------------------
# built-in names vs file names; the CLI


def test_a_builtin_name_wins_over_a_suffixless_file(tmp_path, monkeypatch):
    """A file called `walk` can never be a motion file (no suffix), so the name means the
    built-in; with a suffix the path is always the file."""
    monkeypatch.chdir(tmp_path)
    builtin = load_motion("walk")
    (tmp_path / "walk").write_text("junk")
    again = load_motion("walk")
    assert again.num_frames == builtin.num_frames and np.array_equal(again.rotations, builtin.rotations)
    (tmp_path / "walk.bvh").write_text("junk")
    with pytest.raises(DlaInputError, match="^walk.bvh: "):
        load_motion("walk.bvh")


def test_cli_one_line_exit_2(tmp_path, monkeypatch, capsys):
    cases = [_write(tmp_path, "claim.bvh", bvh(frames="200000000")), _write(tmp_path, "deep.bvh", _nested(3000))]
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.bvh")
        cases.append(tmp_path / "pipe.bvh")
    for path in cases:
        monkeypatch.setattr(sys, "argv", ["dla", "motion", "convert", str(path), "-o", str(tmp_path / "o.npz")])
        with pytest.raises(SystemExit) as info:
            main()
        err = capsys.readouterr().err
        assert info.value.code == 2 and err.startswith(f"error: {path}: ") and err.count("\n") == 1, err
