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
from dlacli.stages.lift.methods.unproject import UnprojectConfig
from dlacli.stages.lift.unproject import lift
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
    return views, lift(views, UnprojectConfig(steps=0, gaussians=N)), lift(views, UnprojectConfig(steps=8, gaussians=N))


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
    # synth's albedo appearance is headlit: colour depends on the view, so the view-cosine decoder
    assert avatar.z.shape == (15, 256, 256) and avatar.encoder == "unproject" and avatar.decoder == "view-cosine"
    assert sum("decoder view-cosine" in line for line in r.stderr.splitlines()) == 1, r.stderr
    assert len(read_ply(tmp_path / "g.ply")) > 1000
    from PIL import Image

    sheet = Image.open(tmp_path / "avatar_contact.png")
    assert sheet.size == (5 * 256, 2 * 256)  # 4 input views + the first of synth's novel_views/
    note = [line for line in r.stderr.splitlines() if "first novel view, masked PSNR" in line]
    assert len(note) == 1 and "novel_views" in note[0], r.stderr


def test_contact_sheet_without_ground_truth(subject, tmp_path):
    """A view folder with no novel_views/ (dream's) gets the 4-column sheet and no note; the
    fifth column of a synth folder is its first novel view next to the avatar's render of it."""
    import shutil

    from PIL import Image

    views = tmp_path / "views"
    shutil.copytree(subject, views, ignore=shutil.ignore_patterns("novel_views", "novel_poses"))
    r = _dla("lift", views, "-o", tmp_path / "a.npz", "--steps", "0", "--gaussians", "4096")
    assert r.returncode == 0, r.stderr
    assert Image.open(tmp_path / "a_contact.png").size == (4 * 256, 2 * 256)
    assert "novel view" not in r.stderr
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    novel = read_views(subject / "novel_views", require_body=False)
    res = lift(read_views(subject), UnprojectConfig(steps=0, gaussians=4096), novel=novel)
    pred, truth, mask = res.novel_view
    assert np.array_equal(truth, novel.images[0] * novel.masks[0][..., None]) or np.allclose(
        truth, novel.images[0] * novel.masks[0][..., None], atol=1e-6
    )  # 128 px: not resized
    tile = res.contact_sheet[256:, 4 * 256 :]  # bottom row, fifth column: the render
    assert tile[1:-1, 1:-1].max() > 0 and pred.shape == truth.shape


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


def test_refinement_improves_novel_views(subject):
    """Refinement must not trade novel views for the inputs (issue: it used to lower the novel
    views' masked PSNR while improving the silhouette). On this subject (seed 5 at 128 px, in no
    tuning run), 32,768 Gaussians: novel-view masked PSNR 16.06 dB after unprojection, 16.68 after
    20 steps (the previous refinement, which moved colours too: 16.24 -> 15.15); alpha IoU
    0.773 -> 0.848. Floors: +0.3 dB and +0.04 IoU (about half the measured gains)."""
    from dlacli.bench.pipeline import _score
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    views = read_views(subject)
    novel = read_views(subject / "novel_views", require_body=False)
    before = _score(lift(views, UnprojectConfig(steps=0, gaussians=32768)).avatar, novel)
    after = _score(lift(views, UnprojectConfig(steps=20, gaussians=32768)).avatar, novel)
    assert after["psnr_masked"] >= before["psnr_masked"] + 0.3, (before, after)
    assert after["iou"] >= before["iou"] + 0.04, (before, after)


def test_refinement_compares_a_window_that_loses_nothing(subject):
    """refine compares the views only in a window around the subject (stages/lift/unproject.subject_crops);
    its first loss equals the whole-image loss computed here from a whole-image render
    (L1 + mask L1 + 0.2 (1 - SSIM)), to float32 summation error, and every window holds its
    view's whole mask."""
    import torch

    from dlacli.avatar import gaussian_map as gm
    from dlacli.body.model import get_body_model
    from dlacli.nn.losses import ssim_map
    from dlacli.stages.lift import unproject as stage
    from dlacli.stages.lift.refine import subject_crops

    views = read_views(subject)
    cfg = UnprojectConfig(steps=1, gaussians=N).resolved()
    vertices = get_body_model().forward_body(views.body).vertices[0].numpy()
    unstructured, _, eyes = stage.unstructured_gaussians(views, vertices, cfg.grid)
    fmap = stage.unproject_to_uv(unstructured, eyes, vertices, cfg.resolution)
    samples = gm.make_samples(N, 0)
    _, history = stage.refine(fmap, views, vertices, cfg, None, samples)

    frames = gm.sample_frames(torch.from_numpy(vertices)[None], samples)
    (g,) = gm.gaussians_at_frames(torch.from_numpy(fmap).float(), samples, frames)
    rgb_t, mask_t, cams = views.targets(cfg.render_size)
    rgb, alpha = stage._render(g, cams, None)
    whole = (rgb - rgb_t).abs().mean() + (alpha - mask_t).abs().mean() + 0.2 * (1 - ssim_map(rgb, rgb_t).mean())
    assert history[0] == pytest.approx(float(whole), rel=1e-5)

    x0, y0, w, h = subject_crops(mask_t, g.means.numpy().astype(np.float64), cams)
    assert w * h < cams.width * cams.height  # a real saving on this subject
    for i in range(len(views)):
        inside = mask_t[i, y0[i] : y0[i] + h, x0[i] : x0[i] + w].sum()
        assert float(inside) == pytest.approx(float(mask_t[i].sum()), rel=1e-6)


def test_roughness_is_the_mean_squared_step_between_covered_neighbours():
    """`_roughness` against a direct count: 0 for offsets that move as a whole; for a checkerboard
    of +-a, every covered neighbour pair differs by 2a, so the mean is (2a / ROUGHNESS_UNIT)^2;
    the pairs are exactly the covered horizontal and vertical ones; and one bump's value is the
    sum over its covered pairs divided by their count."""
    import torch

    from dlacli.body.uv import uv_raster
    from dlacli.stages.lift.unproject import ROUGHNESS_UNIT, _neighbour_pairs, _roughness

    res = 64
    valid = uv_raster(res).mask
    pairs = right, down = _neighbour_pairs(res)
    np.testing.assert_array_equal(right.numpy(), valid[:, 1:] & valid[:, :-1])
    np.testing.assert_array_equal(down.numpy(), valid[1:] & valid[:-1])
    assert float(_roughness(torch.full((res, res), 0.02, dtype=torch.float64), pairs)) == 0.0
    a = 0.004
    board = torch.from_numpy(np.where((np.indices((res, res)).sum(0) % 2) == 0, a, -a))
    np.testing.assert_allclose(float(_roughness(board, pairs)), (2 * a / ROUGHNESS_UNIT) ** 2, rtol=1e-12)
    r, c = (
        np.argwhere(valid[1:-1, 1:-1] & valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:])[0] + 1
    )
    bump = torch.zeros((res, res), dtype=torch.float64)
    bump[r, c] = a  # 4 covered pairs differ by a
    count = float(right.sum() + down.sum())
    np.testing.assert_allclose(float(_roughness(bump, pairs)), 4 * (a / ROUGHNESS_UNIT) ** 2 / count, rtol=1e-12)


def test_the_roughness_weight_smooths_the_refined_normal_offsets(subject):
    """w_smooth > 0 makes the refined normal offsets smoother than w_smooth = 0 on the same views
    and steps (on the demo's views 30 steps gave 17.9 mm neighbour RMS without it, 1.3 mm at 0.1)."""
    import torch

    from dlacli.avatar import gaussian_map as gm
    from dlacli.stages.lift.unproject import _neighbour_pairs, _roughness

    views = read_views(subject)
    pairs = _neighbour_pairs(128)
    rough = []
    for w in (0.0, 0.1):
        avatar = lift(views, UnprojectConfig(steps=8, gaussians=8192, resolution=128, w_smooth=w)).avatar
        assert avatar.extra["lift"]["w_smooth"] == w
        z = avatar.z
        rough.append(float(_roughness(torch.from_numpy(np.asarray(z[gm.OFFSET][2], np.float64)), pairs)))
    print("roughness without / with the weight:", rough)
    assert rough[1] < 0.5 * rough[0]


def test_a_negative_roughness_weight_is_refused():
    from dlacli.errors import DlaInputError
    from dlacli.stages.lift.methods import parse_method

    with pytest.raises(DlaInputError, match="w_smooth must be in"):
        parse_method("unproject:steps=5,w_smooth=-1")


def test_the_roughness_weight_defaults_to_the_dreams_for_dreamed_views_only(subject):
    """Unset, the weight is DREAM_W_SMOOTH for a folder that `dla dream` wrote (transforms.json's
    `dla.dream`) and 0 for true views; a weight the spec sets wins either way."""
    import dataclasses

    from dlacli.stages.lift.unproject import DREAM_W_SMOOTH, smoothness

    views = read_views(subject)
    dreamed = dataclasses.replace(views, extra={**views.extra, "dream": {"backend": "body"}})
    assert "dream" not in views.extra and DREAM_W_SMOOTH > 0
    assert smoothness(UnprojectConfig(), views) == 0.0 and smoothness(UnprojectConfig(), dreamed) == DREAM_W_SMOOTH
    assert smoothness(UnprojectConfig(w_smooth=0.0), dreamed) == 0.0
    assert smoothness(UnprojectConfig(w_smooth=0.5), views) == 0.5
    # without refinement no weight was used, and the avatar says so
    unrefined = lift(dreamed, UnprojectConfig(steps=0, gaussians=8192, resolution=64)).avatar
    assert unrefined.extra["lift"]["w_smooth"] == 0.0
