"""Streamed video reading (io/video.open_video): frames, --start/--end/--fps selection, bad input.

The oracle: a tiny mp4 written here whose frame i is a flat grey of level 8 i, so every decoded
frame says which source frame it is (H.264 keeps flat greys within +-2 levels)."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.io.video import open_video, write_video

FPS = 25
COUNT = 25


@pytest.fixture(scope="module")
def grey_clip(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "grey.mp4"
    write_video([np.full((32, 48, 3), 8 * i, np.uint8) for i in range(COUNT)], path, FPS)
    return path


def _which(frame: np.ndarray) -> int:
    return int(round(float(frame.mean()) / 8.0))


def test_reads_every_frame_in_order(grey_clip):
    clip = open_video(grey_clip)
    assert (clip.width, clip.height, clip.source_fps, clip.fps) == (48, 32, FPS, FPS)
    got = [(k, t, _which(f), f.shape, f.dtype) for k, t, f in clip]
    assert [g[0] for g in got] == list(range(COUNT))
    assert [g[2] for g in got] == list(range(COUNT))
    np.testing.assert_allclose([g[1] for g in got], np.arange(COUNT) / FPS)
    assert all(g[3] == (32, 48, 3) and g[4] == np.uint8 for g in got)
    assert clip.expected_frames == COUNT
    assert [_which(f) for _, _, f in clip] == list(range(COUNT))  # a second pass decodes again


def test_start_end_and_resampling(grey_clip):
    clip = open_video(grey_clip, start=0.2, end=0.6)  # source frames 5..14 (t < 0.6)
    assert [_which(f) for _, _, f in clip] == list(range(5, 15))
    clip = open_video(grey_clip, fps=5)  # every 5th source frame: the nearest to k / 5 s
    got = list(clip)
    assert [_which(f) for _, _, f in got] == [0, 5, 10, 15, 20]
    np.testing.assert_allclose([t for _, t, _ in got], np.arange(5) / 5)
    clip = open_video(grey_clip, fps=10, start=0.4)  # nearest source frame to 0.4 + k / 10 s (ties: the later)
    assert [_which(f) for _, _, f in clip] == [10, 13, 15, 18, 20, 23]


@pytest.mark.parametrize(
    ("kwargs", "where"),
    [
        ({"start": 1.0, "end": 0.5}, "--end"),
        ({"start": 2.0}, "--start"),
        ({"fps": 50.0}, "--fps"),
        ({"start": -1.0}, "--start"),
    ],
)
def test_bad_options(grey_clip, kwargs, where):
    with pytest.raises(DlaInputError) as err:
        open_video(grey_clip, **kwargs)
    assert err.value.where == where


def test_not_a_video(tmp_path):
    bad = tmp_path / "clip.mp4"
    bad.write_text("not a video")
    with pytest.raises(DlaInputError, match="cannot read it as a video"):
        open_video(bad)
    with pytest.raises(DlaInputError, match="no such file"):
        open_video(tmp_path / "missing.mp4")


def test_a_phone_clip_stored_sideways_reads_upright(tmp_path, caplog):
    """A portrait clip stored sideways with a display rotation (what phones write): the frames
    come upright, as a player shows them, at the displayed size, and nothing is logged."""
    import subprocess

    import imageio_ffmpeg

    upright = np.zeros((48, 32, 3), np.uint8)  # portrait: 48 high, 32 wide
    upright[:16, :16] = 255  # a bright block in the top-left corner
    stored = tmp_path / "stored.mp4"
    write_video([np.rot90(upright, k=-1)] * 5, stored, FPS)  # turned clockwise: 32 high, 48 wide
    phone = tmp_path / "phone.mp4"
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-display_rotation", "90", "-i", str(stored)]
    subprocess.run([*cmd, "-c", "copy", str(phone)], check=True)
    clip = open_video(phone)
    assert (clip.width, clip.height) == (32, 48)
    frames = [f for _, _, f in clip]
    assert len(frames) == 5
    for f in frames:
        assert f.shape == (48, 32, 3)
        assert f[2:14, 2:14].mean() > 200 and f[20:, :].mean() < 40 and f[:, 20:].mean() < 40
    assert not [r for r in caplog.records if r.levelno >= 30], [r.getMessage() for r in caplog.records]


def test_a_still_image_reads_as_one_frame(tmp_path):
    """ffmpeg decodes a picture as a video of one frame with no duration: one frame comes out
    (not an error blaming --start, which the user did not give)."""
    from PIL import Image

    still = np.zeros((24, 40, 3), np.uint8)
    still[:, :20] = 200
    path = tmp_path / "still.png"
    Image.fromarray(still).save(path)
    clip = open_video(path)
    frames = [f for _, _, f in clip]
    assert len(frames) == 1 and frames[0].shape == (24, 40, 3)
    assert frames[0][:, :18].mean() > 190 and frames[0][:, 22:].mean() < 10
    assert list(open_video(path, start=1.0)) == []  # past its one frame (the command says so)
