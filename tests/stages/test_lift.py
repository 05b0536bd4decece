"""Lift on a synthetic subject: re-rendering reproduces the input views; refinement helps;
bad view folders fail with one line and leave no output."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dlacli.bench.metrics import alpha_iou, masked_psnr, psnr
from dlacli.io.avatar import read_avatar
from dlacli.io.ply import read_ply
from dlacli.io.views import read_views
from dlacli.stages.lift import LiftConfig, lift
from dlacli.stages.render import render_avatar

N = 32_768  # Gaussians: enough for 128 px views


def _scores(avatar, views):
    shots = list(render_avatar(avatar, views.cameras, [None] * len(views), None, N))
    pred = np.stack([s.rgba for s in shots])
    gt = views.images * views.masks[..., None]
    return psnr(pred[..., :3], gt), masked_psnr(pred[..., :3], gt, views.masks), alpha_iou(pred[..., 3], views.masks)


@pytest.fixture(scope="module")
def lifted(subject):
    views = read_views(subject)
    return views, lift(views, LiftConfig(steps=0, gaussians=N)), lift(views, LiftConfig(steps=8, gaussians=N))


def test_unprojection_reproduces_inputs(lifted):
    views, plain, _ = lifted
    whole, inside, iou = _scores(plain.avatar, views)
    # floors measured on this subject at 128 px: 21.9 dB / 18.2 dB / 0.74 (an all-black guess: ~15 dB)
    black = psnr(np.zeros_like(views.images), views.images * views.masks[..., None])
    assert whole > max(20.0, black + 4.0)
    assert inside > 16.0
    assert iou > 0.65


def test_refinement_improves_inputs(lifted):
    views, plain, refined = lifted
    assert _scores(refined.avatar, views)[0] > _scores(plain.avatar, views)[0] + 1.5
    assert refined.avatar.extra["lift"]["steps"] == 8


def test_unstructured_gaussians_lie_on_the_person(lifted):
    views, plain, _ = lifted
    g = plain.unstructured
    cams = views.cameras
    # every unstructured Gaussian projects into the person's mask of the view it came from or is
    # inside all silhouettes (an independent visual-hull check with the full-resolution masks)
    pts = g.means.numpy().astype(np.float64)
    inside_all = np.ones(len(pts), bool)
    for v in range(len(views)):
        w2c, k = cams.viewmats[v].double().numpy(), cams.Ks[v].double().numpy()
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        u = np.floor(k[0, 0] * pc[:, 0] / pc[:, 2] + k[0, 2]).astype(int)
        r = np.floor(k[1, 1] * pc[:, 1] / pc[:, 2] + k[1, 2]).astype(int)
        ok = (u >= 0) & (u < cams.width) & (r >= 0) & (r < cams.height)
        m = np.zeros(len(pts), bool)
        m[ok] = views.masks[v][r[ok], u[ok]] > 0.25
        inside_all &= m
    assert inside_all.mean() > 0.95
    assert np.all(g.opacities.numpy() > 0.5)  # low-opacity filtering


def _dla(*args):
    return subprocess.run([sys.executable, "-m", "dlacli.cli.app", *map(str, args)], capture_output=True, text=True)


def test_cli_writes_avatar_ply_and_contact_sheet(subject, tmp_path):
    out = tmp_path / "avatar.npz"
    r = _dla("lift", subject, "-o", out, "--steps", "1", "--gaussians", "4096", "--ply", tmp_path / "g.ply")
    assert r.returncode == 0, r.stderr
    avatar = read_avatar(out)
    assert avatar.z.shape == (14, 256, 256) and avatar.encoder == "unproject" and avatar.decoder == "identity"
    assert len(read_ply(tmp_path / "g.ply")) > 1000
    from PIL import Image

    sheet = Image.open(tmp_path / "avatar_contact.png")
    assert sheet.size == (4 * 256, 2 * 256)


def _one_line_failure(r, needle, *absent):
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, r.stderr
    for path in absent:
        assert not path.exists()


def test_views_without_body_json(subject, tmp_path):
    views = tmp_path / "views"
    shutil.copytree(subject, views)
    (views / "body.json").unlink()
    out = tmp_path / "a.npz"
    _one_line_failure(_dla("lift", views, "-o", out), "body.json", out)


def test_mismatched_image_sizes(subject, tmp_path):
    from PIL import Image

    views = tmp_path / "views"
    shutil.copytree(subject, views)
    first = json.loads((views / "transforms.json").read_text())["frames"][1]["file_path"]
    Image.open(views / first).resize((64, 64)).save(views / first)
    out = tmp_path / "a.npz"
    _one_line_failure(_dla("lift", views, "-o", out), "64x64", out, tmp_path / "a_contact.png")


def test_empty_mask(subject, tmp_path):
    from PIL import Image

    views = tmp_path / "views"
    shutil.copytree(subject, views)
    first = json.loads((views / "transforms.json").read_text())["frames"][0]["file_path"]
    rgba = np.array(Image.open(views / first))
    rgba[..., 3] = 0
    Image.fromarray(rgba).save(views / first)
    out = tmp_path / "a.npz"
    _one_line_failure(_dla("lift", views, "-o", out), "mask", out)
