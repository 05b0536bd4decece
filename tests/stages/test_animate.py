"""Render and animate an avatar lifted from a synthetic subject: file names, frame and instance
counts, USD validity, preview video, agreement with the ground-truth novel poses, bad motions."""

from __future__ import annotations

import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pytest
from PIL import Image

from dlacli.bench.metrics import alpha_iou
from dlacli.body.builtin_motions import builtin_motion
from dlacli.io.avatar import write_avatar
from dlacli.io.motion import write_motion
from dlacli.io.usd_read import read_usd, validate_usd
from dlacli.io.views import read_transforms, read_views
from dlacli.stages.lift.methods.unproject import UnprojectConfig
from dlacli.stages.lift.unproject import lift
from dlacli.types import Motion

N = 4096


def _dla(*args):
    return subprocess.run([sys.executable, "-m", "dlacli.cli.app", *map(str, args)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def avatar_path(subject, tmp_path_factory):
    path = tmp_path_factory.mktemp("avatar") / "avatar.npz"
    write_avatar(lift(read_views(subject), UnprojectConfig(steps=0, gaussians=N)).avatar, path)
    return path


def test_animate_usd_and_preview(avatar_path, tmp_path):
    out, preview = tmp_path / "wave.usdc", tmp_path / "wave.mp4"
    r = _dla("animate", avatar_path, "wave", "-o", out, "--preview", preview, "--gaussians", N, "--preview-size", 64)
    assert r.returncode == 0, r.stderr
    motion = builtin_motion("wave")
    anim = read_usd(out)
    assert anim.positions.shape == (motion.num_frames, N, 3)
    assert anim.fps == motion.fps
    assert validate_usd(out) == []
    # the Gaussians follow the body: frame-to-frame motion is small, and the waving hand moves
    steps = np.linalg.norm(np.diff(anim.positions, axis=0), axis=-1)
    assert np.percentile(steps, 99) < 0.05
    assert steps.max() > 0.005
    frames = [f for f in imageio.get_reader(preview)]
    assert len(frames) == motion.num_frames and frames[0].shape[:2] == (64, 64)
    assert np.mean(frames[len(frames) // 2]) > 2  # something is drawn


def test_render_novel_poses_matches_ground_truth(subject, avatar_path, tmp_path):
    novel = subject / "novel_poses"
    out = tmp_path / "renders"
    r = _dla(
        "render",
        avatar_path,
        "--cameras",
        novel / "transforms.json",
        "--motion",
        novel / "motion.npz",
        "-o",
        out,
        "--gaussians",
        N,
    )
    assert r.returncode == 0, r.stderr
    meta = read_transforms(novel)
    expected = sorted(f"f{t:04d}_c{c:03d}.png" for c, t in enumerate(meta["times"]))
    assert sorted(p.name for p in out.iterdir()) == expected
    gt = read_views(novel, require_body=False)
    for c, t in enumerate(meta["times"]):
        rgba = np.asarray(Image.open(out / f"f{t:04d}_c{c:03d}.png"), np.float32) / 255
        # the avatar, posed by the motion, covers the same pixels as the ground-truth subject
        assert alpha_iou(rgba[..., 3], gt.masks[c]) > 0.55


def test_render_turntable_and_video(avatar_path, tmp_path):
    out = tmp_path / "turn"
    r = _dla(
        "render",
        avatar_path,
        "--turntable",
        3,
        "--size",
        48,
        "-o",
        out,
        "--video",
        tmp_path / "t.mp4",
        "--gaussians",
        N,
    )
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == [f"f0000_c{c:03d}.png" for c in range(3)]
    assert len([f for f in imageio.get_reader(tmp_path / "t.mp4")]) == 3


def test_unknown_motion_joint_is_one_line(avatar_path, tmp_path):
    bad = tmp_path / "bad.npz"
    write_motion(
        Motion(["upperarm01.L", "tail01"], np.zeros((3, 2, 3), np.float32), np.zeros((3, 3)), np.zeros((3, 3)), 30.0),
        bad,
    )
    out = tmp_path / "out.usdc"
    r = _dla("animate", avatar_path, bad, "-o", out, "--gaussians", N)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "tail01" in lines[0], r.stderr
    assert not out.exists()


def test_missing_motion_and_bad_schema(avatar_path, tmp_path):
    out = tmp_path / "out.usdc"
    r = _dla("animate", avatar_path, "moonwalk", "-o", out)
    assert r.returncode == 2 and "moonwalk" in r.stderr and not out.exists()
    r = _dla("animate", avatar_path, "walk", "-o", out, "--schema", "voxels")
    assert r.returncode == 2 and "--schema" in r.stderr and not out.exists()
