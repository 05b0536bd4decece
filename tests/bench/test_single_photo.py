"""`dla bench accuracy --input photo` (bench/single_photo.py): the body alignment between the
dream's world and the subject's, a tiny end-to-end run, and that the scores tell a right dream
from a wrong one."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.types import BodyParams

SEED = 8131  # a subject no other test uses
METHOD = "unproject:resolution=64"  # a small lift: the tests compare dreams, not lifts


def _rotation(axis, angle: float) -> np.ndarray:
    from dlacli.geometry import axis_angle_to_matrix

    aa = np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle
    return axis_angle_to_matrix(aa)


@pytest.fixture(scope="module")
def posed_body():
    from dlacli.body.model import get_body_model, rotations_to_pose
    from dlacli.data.subject import relaxed_pose

    m = get_body_model()
    rot = relaxed_pose(np.random.default_rng(SEED), m.bone_labels, 20.0)
    verts = m.forward_body(BodyParams(pose=rotations_to_pose(rot, m))).vertices[0].double().numpy()
    return verts, np.asarray(m.faces, np.int64)


def test_alignment_recovers_a_known_similarity(posed_body):
    """A posed body moved by a known similarity: align_bodies recovers scale, rotation and
    translation (float64 round-off), leaves no residual, and maps cameras so each sees the moved
    body where it saw the original; cameras mapped there and back are unchanged."""
    from dlacli.bench.single_photo import align_bodies, surface_weights
    from dlacli.geometry import look_at_orbit_cameras, project_to_cameras

    verts, faces = posed_body
    s, r, t = 1.13, _rotation([0.3, -0.5, 0.8], 2.1), np.array([0.4, -1.7, 0.25])
    moved = s * verts @ r.T + t
    w = surface_weights(verts, faces)
    assert np.all(w >= 0) and w.sum() > 0
    got = align_bodies(verts, moved, w)
    assert abs(got.scale - s) < 1e-9
    np.testing.assert_allclose(got.rotation, r, atol=1e-9)
    np.testing.assert_allclose(got.translation, t, atol=1e-9)
    assert got.residual_mm < 1e-6
    np.testing.assert_allclose(got.points_to_true(verts), moved, atol=1e-9)

    cams = look_at_orbit_cameras((0.0, 0.0, -0.1), 3.0, [0.0, 90.0, 200.0], [8.0, 0.0, 30.0], 45.0, 128)
    px, depth = project_to_cameras(verts, cams)
    px_moved, depth_moved = project_to_cameras(moved, got.to_true(cams))
    np.testing.assert_allclose(px_moved, px, atol=1e-3)  # float32 viewmats: ~1e-4 px at 3 m
    np.testing.assert_allclose(depth_moved, s * depth, rtol=1e-5)
    back = got.to_dream(got.to_true(cams))
    np.testing.assert_allclose(back.viewmats.numpy(), cams.viewmats.numpy(), atol=1e-5)
    np.testing.assert_array_equal(back.Ks.numpy(), cams.Ks.numpy())


def test_alignment_honours_the_weights(posed_body):
    """surface_weights sum to the mesh's area; vertices of zero weight do not pull the fit: half
    the body moved by one similarity and half by another, weighted on the first half only, gives
    the first exactly (and a residual of that half alone)."""
    from dlacli.bench.single_photo import align_bodies, surface_weights

    verts, faces = posed_body
    w = surface_weights(verts, faces)
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert math.isclose(w.sum(), area, rel_tol=1e-12)
    left = verts[:, 0] > 0
    target = np.where(left[:, None], 0.9 * verts @ _rotation([0, 0, 1], 0.4).T + 0.2, verts - 0.3)
    got = align_bodies(verts, target, np.where(left, w, 0.0))
    assert abs(got.scale - 0.9) < 1e-9 and got.residual_mm < 1e-6
    np.testing.assert_allclose(got.rotation, _rotation([0, 0, 1], 0.4), atol=1e-9)
    assert align_bodies(verts, target, w).residual_mm > 10.0  # both halves weighted: no similarity fits


@pytest.fixture(scope="module")
def subject(tmp_path_factory):
    from dlacli.data.synth import synth

    return synth(
        SEED,
        tmp_path_factory.mktemp("subject") / "s",
        res=96,
        novel_views=3,
        novel_poses=1,
        appearance="lit",
        wardrobe="heldout",
    )


def _scored(views, subject):
    from dlacli.bench.single_photo import score_dream
    from dlacli.stages.lift.methods import parse_methods

    avatar = parse_methods(METHOD)[0].lift(views).avatar
    return score_dream(views, avatar, subject, SEED, "lit", "heldout")


def test_a_perfect_dream_beats_a_broken_one_and_survives_a_moved_world(subject):
    """The true views and the true body in place of the dream: no misalignment, the dreamed views
    equal the truth (both 8-bit renders of one subject: infinite PSNR, IoU 1). The same dream in
    a world turned, moved and scaled (cameras and body) scores the same: the alignment undoes it.
    Views 90 / 180 / 270 upside down (a broken dream) score far worse on the dreamed views and
    worse on every split of the avatar."""
    from dlacli.body.model import get_body_model
    from dlacli.geometry import similarity_cameras, similarity_fit
    from dlacli.io.views import read_views

    true = read_views(subject)
    perfect, info = _scored(true, subject)
    assert info["alignment_mm"] < 1e-3 and info["pose_alignment_mm"] < 1e-3
    assert perfect["dreamed_views"]["psnr_masked"] == math.inf and perfect["dreamed_views"]["iou"] == 1.0

    # a rigidly moved world: the body by its root rotation and translation, the cameras with it
    body = replace(true.body, root_rotation=np.array([0.0, 0.0, 0.9]), root_translation=np.array([0.3, -0.2, 0.1]))
    m = get_body_model()
    src = m.forward_body(true.body).vertices[0].double().numpy()
    dst = m.forward_body(body).vertices[0].double().numpy()
    s, r, t = similarity_fit(src, dst)
    assert abs(s - 1.0) < 1e-5
    moved, moved_info = _scored(replace(true, body=body, cameras=similarity_cameras(true.cameras, s, r, t)), subject)
    assert moved_info["alignment_mm"] < 0.1
    for split in ("novel_views", "novel_poses", "novel_view_pose"):
        assert abs(moved[split]["psnr_masked"] - perfect[split]["psnr_masked"]) < 0.2, split
        assert abs(moved[split]["iou"] - perfect[split]["iou"]) < 0.02, split
    assert moved["dreamed_views"]["psnr_masked"] > 40.0

    images, masks = true.images.copy(), true.masks.copy()
    images[1:], masks[1:] = images[1:, ::-1], masks[1:, ::-1]
    broken, _ = _scored(replace(true, images=images, masks=masks), subject)
    assert broken["dreamed_views"]["psnr_masked"] < 25.0 and broken["dreamed_views"]["iou"] < 0.8
    for split in ("novel_views", "novel_view_pose"):  # the avatar from the side and back
        assert broken[split]["psnr_masked"] < perfect[split]["psnr_masked"] - 1.0, split


def test_a_tiny_run_writes_photo_rows(monkeypatch, tmp_path):
    """One subject through detection, dream (a few fit steps), a small lift in a fresh process and
    the scoring: one row per split, the input and backend in the config, finite scores, the time
    of each stage; a dream that fails (no person found) gives rows with status "error"."""
    from dlacli.bench.rows import check_row, label, points
    from dlacli.bench.single_photo import PHOTO_SPLITS, run_photo
    from dlacli.stages.lift.methods import parse_methods

    kw = dict(res=128, novel_views=2, novel_poses=1, fit_steps=20, log=lambda s: None)
    rows = run_photo([SEED + 1], parse_methods(METHOD), ["template"], **kw)
    assert [r["split"] for r in rows] == list(PHOTO_SPLITS)
    for r in rows:
        check_row(r)
        assert r["config"]["input"] == "photo" and r["config"]["backend"] == "template"
        assert r["subject"] == SEED + 1 and label(r).startswith("photo/template unproject")
        assert all(math.isfinite(v) for v in r["metrics"].values())
        assert 0.0 < r["metrics"]["iou"] <= 1.0
        st = r["stages"]
        assert st["dream_s"] > 0 and st["lift_s"] > 0
        assert math.isclose(r["seconds"], st["dream_s"] + st["lift_s"], rel_tol=1e-3)
        assert 0.0 <= r["alignment_mm"] < 200.0 and 0.0 <= r["pose_alignment_mm"] < 200.0
        assert set(r["dreamed_per_view"]) == {"90", "180", "270"}
    assert len(points(rows, "dreamed_views")) == 1

    import dlacli.stages.dream.views as dream_stage

    def no_person(photo, out, **_):
        raise DlaInputError(str(photo), "no person detected")

    monkeypatch.setattr(dream_stage, "dream", no_person)
    failed = run_photo([SEED + 1], parse_methods(METHOD), ["template"], **{**kw, "novel_views": 1})
    assert [r["split"] for r in failed] == list(PHOTO_SPLITS)
    assert all(r["status"] == "error" and "no person" in r["error"] and r["metrics"] == {} for r in failed)
    for r in failed:
        check_row(r)
    assert points(failed, "novel_views") == []  # left out of tables and charts

    from dlacli.bench.charts import draw_chart
    from dlacli.bench.report import report_markdown

    page = report_markdown(rows + failed, "chart.png")
    assert "## dreamed views" in page and "| **photo/template unproject" in page
    assert "## Failed runs" in page and f"subject {SEED + 1}, photo/template unproject" in page
    assert draw_chart(rows + failed, tmp_path / "chart.png").stat().st_size > 0


def test_the_error_budgets_oracles(tmp_path):
    """The oracles replace part of the dream by the truth: "true_colours" on the subject's own
    folder re-renders its views 1-3 from its own cameras (so they equal synth's files to 8-bit
    rounding), "true_body" dreams on the true body (no misalignment left); a tiny run with
    oracles and two priors gives each its rows, and the views-only oracles no dreamed split."""
    from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
    from dlacli.bench.accuracy import subjects
    from dlacli.bench.rows import check_row, label
    from dlacli.bench.single_photo import PHOTO_SPLITS, oracle_folder, run_photo, truth_fit
    from dlacli.io.views import read_views
    from dlacli.nn.completion import CompletionConfig, CompletionNet
    from dlacli.stages.lift.methods import parse_methods

    ((seed, subject),) = subjects([SEED + 2], tmp_path, 128, 1, 1, "lit", "heldout")
    own = read_views(subject)
    out = oracle_folder("true_colours", subject, seed, subject, tmp_path / "tc", "body", 128, "lit", "heldout")
    again = read_views(out)
    diff = np.abs(again.images[1:] * again.masks[1:, ..., None] - own.images[1:] * own.masks[1:, ..., None])
    # 8-bit rounding of both; the cameras pass through an identity similarity fitted to round-off,
    # which may move an edge pixel's coverage across a rounding step
    assert (diff > 1.5 / 255).mean() < 1e-4 and diff.max() < 0.05
    np.testing.assert_array_equal(again.images[0], own.images[0])
    out = oracle_folder("true_body", subject, seed, subject, tmp_path / "tb", "body", 128, "lit", "heldout")
    body = read_views(out)
    assert body.extra["dream"]["oracle"] == "true_body" and body.body.phenotype == own.body.phenotype
    assert all(np.array_equal(body.body.pose[k], v) for k, v in own.body.pose.items())
    assert truth_fit(subject).mask_iou > 0.75  # the bare true body under the mask of its clothes and hair

    net = CompletionNet(CompletionConfig(width=8, resolution=32))
    save_checkpoint(tmp_path / "prior", net, net.config)
    kw = dict(res=128, novel_views=1, novel_poses=1, fit_steps=20, log=lambda s: None, oracles=True)
    rows = run_photo([SEED + 2], parse_methods(METHOD), ["body"], priors=["none", str(tmp_path / "prior")], **kw)
    for r in rows:
        check_row(r)
    groups = {}
    for r in rows:
        groups.setdefault((r["config"].get("prior"), r["config"].get("oracle")), []).append(r["split"])
    short = None
    for (prior, oracle), splits in groups.items():
        if prior not in (None, "none"):
            short = prior
        assert splits == list(PHOTO_SPLITS if oracle in (None, "true_body") else PHOTO_SPLITS[:3]), (prior, oracle)
    assert set(groups) == {("none", None), ("none", "true_body"), ("none", "true_colours"), (short, None),
                           (short, "true_body"), (None, "four_views")}  # fmt: skip
    assert short == load_checkpoint(tmp_path / "prior").hash[: len(short)]
    by = {(r["config"].get("prior"), r["config"].get("oracle"), r["split"]): r for r in rows}
    # an untrained prior is the rule: the same avatar, the same scores
    for split in PHOTO_SPLITS:
        assert by[("none", None, split)]["metrics"] == by[(short, None, split)]["metrics"]
    assert by[("none", "true_body", "novel_views")]["alignment_mm"] < 0.01
    assert "oracle=four_views" in label(by[(None, "four_views", "novel_views")])
    assert set(by[("none", None, "novel_views")]["regions"]) == {"novel_views", "dreamed_views"}


def test_rows_of_each_input_are_labelled_apart():
    """The 4-view input, and one photo through two dream backends: three labels, three chart
    groups, three points per split."""
    from dlacli.bench.rows import group, label, make_row, points

    metrics = {"psnr": 25.0, "psnr_masked": 18.0, "ssim": 0.9, "iou": 0.8}
    proto = {"steps": 0, "res": 256, "appearance": "lit", "wardrobe": "heldout"}
    configs = [proto, {**proto, "input": "photo", "backend": "shell"}, {**proto, "input": "photo", "backend": "body"}]
    rows = [make_row("unproject", c, "novel_views", 1.0, None, metrics, 1, "cpu") for c in configs]
    assert [label(r) for r in rows] == [
        "unproject steps=0",
        "photo/shell unproject steps=0",
        "photo/body unproject steps=0",
    ]
    assert len({group(r) for r in rows}) == 3 and len(points(rows, "novel_views")) == 3


def test_backends_and_inputs_are_checked(capsys):
    from dlacli.bench.single_photo import check_backends
    from dlacli.cli.app import main
    from dlacli.stages.dream.backends import BACKENDS

    assert check_backends([" template", "template", ""]) == ["template"]
    assert check_backends(list(BACKENDS)) == list(BACKENDS)  # every backend dream knows
    for bad in ([], ["magic"]):
        with pytest.raises(DlaInputError, match="--backend"):
            check_backends(bad)
    for args, where in ((["--input", "video"], "--input"), (["--input", "photo", "--backend", "magic"], "--backend")):
        with pytest.raises(SystemExit) as exit_:
            main(["bench", "accuracy", "--seeds", "9001", *args])
        assert exit_.value.code == 2 and f"error: {where}" in capsys.readouterr().err
