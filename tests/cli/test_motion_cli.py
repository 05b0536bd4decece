"""`dla motion convert|preview`: files written and read back by independent readers; bad input
is one line on stderr and exit code 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from typer.testing import CliRunner

from dlacli.cli.app import app, main
from dlacli.io.motion import read_motion


def _dla(*args: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("dla")
    cmd = [str(script)] if script.exists() else [sys.executable, "-c", "from dlacli.cli.app import main; main()"]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=300)


def _main(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    """The console entry point in-process: (exit code, stderr)."""
    monkeypatch.setattr(sys, "argv", ["dla", *args])
    with pytest.raises(SystemExit) as exit_info:
        main()
    return exit_info.value.code, capsys.readouterr().err


def test_convert_bvh_with_resampling(tmp_path, third_party_data, frames_in):
    out, src = tmp_path / "m.npz", third_party_data / "motion" / "131_01.bvh"
    result = CliRunner().invoke(app, ["motion", "convert", str(src), "-o", str(out), "--fps", "30"])
    assert result.exit_code == 0, result.output
    motion = read_motion(out)
    kept = (frames_in(src) - 1) // 4 + 1  # 120 -> 30 fps: every 4th frame, the first included
    assert motion.fps == 30.0 and motion.num_frames == kept and len(motion.bone_labels) == 104
    with np.load(out) as raw:  # the file itself, as numpy sees it
        assert str(raw["format"]) == "dla.motion/1" and raw["rotations"].shape == (kept, 104, 3)


def test_convert_amc_with_explicit_and_found_asf(tmp_path, third_party_data, frames_in):
    d = third_party_data / "motion"
    runner = CliRunner()
    found, spec, option = tmp_path / "a.npz", tmp_path / "b.npz", tmp_path / "c.npz"
    assert (
        runner.invoke(app, ["motion", "convert", str(d / "cmu_01_01.amc"), "-o", str(found), "--fps", "10"]).exit_code
        == 0
    )
    assert (
        runner.invoke(
            app, ["motion", "convert", f"{d / 'cmu_01_01.amc'}:{d / 'cmu_01.asf'}", "-o", str(spec), "--fps", "10"]
        ).exit_code
        == 0
    )
    assert (
        runner.invoke(
            app,
            [
                "motion",
                "convert",
                str(d / "cmu_01_01.amc"),
                "--asf",
                str(d / "cmu_01.asf"),
                "-o",
                str(option),
                "--fps",
                "10",
            ],
        ).exit_code
        == 0
    )
    a, b, c = read_motion(found), read_motion(spec), read_motion(option)
    assert a.num_frames == (frames_in(d / "cmu_01_01.amc") - 1) // 12 + 1  # 120 -> 10 fps: every 12th
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(a.rotations, c.rotations)


def test_convert_builtin_and_native_roundtrip(tmp_path):
    runner = CliRunner()
    first, second = tmp_path / "walk.npz", tmp_path / "again.npz"
    assert runner.invoke(app, ["motion", "convert", "walk", "-o", str(first)]).exit_code == 0
    assert runner.invoke(app, ["motion", "convert", str(first), "-o", str(second)]).exit_code == 0
    a, b = read_motion(first), read_motion(second)
    assert a.bone_labels == b.bone_labels and a.fps == b.fps == 30.0
    np.testing.assert_array_equal(a.rotations, b.rotations)


@pytest.mark.parametrize(
    "content, name, problem",
    [
        (
            "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Xrotation Zrotation\n}\nMOTION\nFrames: "
            "1\nFrame Time: 0.1\n0 0 0\n",
            "order.bvh",
            "unsupported rotation order",
        ),
        (
            "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: "
            "0\nFrame Time: 0.1\n",
            "empty.bvh",
            "0 frames",
        ),
        (
            "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: "
            "2\nFrame Time: 0.1\n1 2 3\n4 5\n",
            "cut.bvh",
            "truncated",
        ),
        (
            "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: "
            "1\nFrame Time: 0.1\n1 nan 3\n",
            "nan.bvh",
            "non-finite",
        ),
        ("1\nroot 0 0 0 0 0 0\n", "lonely.amc", "no ASF skeleton found"),
        ("", "motion.txt", "unsupported motion file type"),
    ],
)
def test_bad_inputs_exit_2_with_one_line(tmp_path, monkeypatch, capsys, content, name, problem):
    path = tmp_path / name
    path.write_text(content)
    code, err = _main(monkeypatch, capsys, "motion", "convert", str(path), "-o", str(tmp_path / "out.npz"))
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: ") and problem in lines[0]
    assert not (tmp_path / "out.npz").exists()


def test_unknown_spec_and_bad_options(tmp_path, monkeypatch, capsys):
    result = _dla("motion", "convert", "moonwalk", "-o", str(tmp_path / "m.npz"))  # the real script
    assert (
        result.returncode == 2
        and result.stderr == "error: moonwalk: no such file, and not a built-in motion (idle, walk, turnaround, wave)\n"
    )
    code, err = _main(monkeypatch, capsys, "motion", "convert", "walk", "-o", str(tmp_path / "m.npz"), "--fps", "-3")
    assert code == 2 and "--fps" in err and len(err.strip().splitlines()) == 1
    code, err = _main(monkeypatch, capsys, "motion", "preview", "walk", "-o", str(tmp_path / "m.gif"))
    assert code == 2 and ".mp4" in err


def test_preview_writes_a_readable_mp4(tmp_path):
    out = tmp_path / "wave.mp4"
    result = CliRunner().invoke(app, ["motion", "preview", "wave", "-o", str(out), "--fps", "5", "--res", "64"])
    assert result.exit_code == 0, result.output
    reader = imageio.get_reader(out)  # imageio-ffmpeg decodes it independently
    frames = list(reader.iter_data())
    reader.close()
    assert len(frames) == 3 * 5 + 1 and frames[0].shape == (64, 64, 3)
    # the body is in the picture: a bright, skin-coloured blob on the dark background
    centre = np.stack(frames)[:, 8:56, 20:44].astype(float)
    assert centre.mean() > 1.5 * np.stack(frames)[:, :8, :8].astype(float).mean()
    assert not list(tmp_path.glob(".*tmp*"))  # the atomic writer left nothing behind


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--start", "2", "--end", "1"], "error: --end: must be after --start"),
        (["--start", "5"], "error: --start: 5 s is at or after the video's end"),
        (["--fps", "50"], "error: --fps: 50 is above the video's own rate"),
    ],
)
def test_from_video_bad_options(tmp_path, monkeypatch, capsys, args, message):
    from dlacli.io.video import write_video

    clip = tmp_path / "clip.mp4"
    write_video([np.zeros((32, 32, 3), np.uint8)] * 10, clip, 10)
    out = tmp_path / "m.npz"
    code, err = _main(monkeypatch, capsys, "motion", "from-video", str(clip), "-o", str(out), *args)
    assert code == 2 and err.startswith(message) and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_from_video_bad_lifter_weights(tmp_path, monkeypatch, capsys):
    """--lifter: a missing file, a foreign file, a file that is not a lifter's (another torch
    save) each give one line naming the file, and nothing is written."""
    import torch

    from dlacli.io.video import write_video

    clip = tmp_path / "clip.mp4"
    write_video([np.zeros((32, 32, 3), np.uint8)] * 4, clip, 10)
    out = tmp_path / "m.npz"
    from safetensors.torch import save_file

    junk, other = tmp_path / "junk.safetensors", tmp_path / "other.safetensors"
    junk.write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    save_file({"w": torch.zeros(2)}, str(other), metadata={"config": '{"width": 8, "depth": 3}'})
    cases = [(tmp_path / "none.safetensors", "no such lifter weights file")]
    cases += [(junk, "not pose-lifter weights"), (other, "not pose-lifter weights")]
    for path, problem in cases:
        code, err = _main(monkeypatch, capsys, "motion", "from-video", str(clip), "-o", str(out), "--lifter", str(path))
        assert code == 2 and err.startswith(f"error: {path}: {problem}") and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_from_video_not_a_video_and_no_person(tmp_path, monkeypatch, capsys):
    pytest.importorskip("mediapipe")
    from dlacli.io.video import write_video

    bad, out, preview = tmp_path / "clip.mp4", tmp_path / "m.npz", tmp_path / "p.mp4"
    bad.write_bytes(b"\x00" * 100)
    code, err = _main(monkeypatch, capsys, "motion", "from-video", str(bad), "-o", str(out))
    assert code == 2 and "cannot read it as a video" in err and len(err.strip().splitlines()) == 1, err
    empty = tmp_path / "empty.mp4"
    write_video([np.full((32, 32, 3), 90, np.uint8)] * 4, empty, 10)
    code, err = _main(
        monkeypatch, capsys, "motion", "from-video", str(empty), "-o", str(out), "--preview", str(preview)
    )
    assert code == 2 and "no person found in any frame" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() and not preview.exists() and bad.read_bytes() == b"\x00" * 100


def test_from_video_reports_filled_frames(tmp_path, monkeypatch, capsys):
    """The command's thin layer: the stage's result (stubbed: no detector here) is written as a
    motion and the frames with no person are reported on stderr, as ranges."""
    from dlacli.io.video import write_video
    from dlacli.stages.motion import video as motion_video
    from dlacli.stages.motion.video import ClipDetections, VideoMotion
    from dlacli.types import Motion

    clip = tmp_path / "clip.mp4"
    write_video([np.zeros((32, 32, 3), np.uint8)] * 10, clip, 10)
    found = np.ones(10, bool)
    found[[0, 4, 5, 6]] = False
    det = ClipDetections(np.zeros((10, 17, 3)), np.zeros((10, 17, 4)), found, 32, 32, 10.0, np.arange(10) / 10, [6])
    motion = Motion(["head"], np.zeros((10, 1, 3)), np.zeros((10, 3)), np.zeros((10, 3)), 10.0)
    stub = VideoMotion(motion, det, None, [(0, 0), (4, 6)], {"detect": 0.0, "fit": 0.0})
    monkeypatch.setattr(motion_video, "video_to_motion", lambda clip, **kw: stub)
    out = tmp_path / "m.npz"
    code, err = _main(monkeypatch, capsys, "motion", "from-video", str(clip), "-o", str(out))
    assert code in (0, None), err
    assert "no person in 4 of 10 frames (0, 4-6, 1 of them showing another person" in err
    assert read_motion(out).num_frames == 10
