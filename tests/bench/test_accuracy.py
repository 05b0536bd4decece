"""`dla bench accuracy` (bench/accuracy.py): method specs, the three splits, and one small run."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.errors import DlaInputError


def test_method_specs():
    """The suite reads the registry's specs (dlacli.stages.lift.methods) and the older spellings as
    what they meant; a method has one name whatever its setting."""
    from dlacli.limits import LIFT_STEPS
    from dlacli.stages.lift.methods import parse_methods

    specs = parse_methods("unproject, refine:50, refine:150@256, learned:/runs/a/generator, learned:/r:b/g:20, refine")
    assert [(s.name, s.options()) for s in specs] == [
        ("unproject", {"steps": 0}),
        ("unproject", {"steps": 50}),
        ("unproject", {"steps": 150, "render_size": 256}),
        ("learned", {"checkpoint": "/runs/a/generator", "steps": 0}),
        ("learned", {"checkpoint": "/r:b/g", "steps": 20}),
        ("unproject", {"steps": LIFT_STEPS}),  # bare `refine`, as `dla bench stability` reads it
    ]
    text = "unproject:steps=0, unproject:steps=50, unproject:steps=150,render_size=256, "
    text += "learned:checkpoint=/r:b/g,steps=20"
    new = parse_methods(text)
    assert [(s.name, s.options()) for s in new] == [(s.name, s.options()) for s in specs[:3] + specs[4:5]]
    for bad in ("", "refine:x", "refine:0", "learned", "magic", "unproject:steps=-1", "unproject:colour=1"):
        with pytest.raises(DlaInputError, match="--methods"):
            parse_methods(bad)


def test_pose_frames_split_by_camera():
    from types import SimpleNamespace

    from dlacli.bench.accuracy import split_indices

    views = SimpleNamespace(extra={"synth": {"azimuths": [0.0, 120.0, 240.0]}}, __len__=None)
    views = type("V", (), {"extra": views.extra, "__len__": lambda self: 6})()
    got = split_indices(views)
    np.testing.assert_array_equal(got["novel_poses"], [0, 3])
    np.testing.assert_array_equal(got["novel_view_pose"], [1, 2, 4, 5])


def test_a_small_run_scores_every_split(tmp_path):
    from dlacli.bench.accuracy import SPLITS, peak_rss_mb, run, score_avatar
    from dlacli.bench.rows import check_row
    from dlacli.stages.lift.methods import parse_methods

    ballast = np.ones(2 * 2**30 // 8)  # 2 GiB touched here: the child's peak must not include it
    rows = run([8101], parse_methods("unproject"), res=64, novel_views=2, novel_poses=1, log=lambda s: None)
    assert all(r["peak_mb"] < peak_rss_mb() - 1024 for r in rows), [r["peak_mb"] for r in rows]
    del ballast
    assert [r["split"] for r in rows] == list(SPLITS)
    for r in rows:
        check_row(r)
        assert r["method"] == "unproject" and r["subject"] == 8101 and r["config"]["wardrobe"] == "heldout"
        assert r["seconds"] > 0 and r["peak_mb"] > 50  # a fresh process with torch loaded
        m = r["metrics"]
        assert 5 < m["psnr_masked"] < 60 and 0 < m["iou"] <= 1 and 0 < m["ssim"] <= 1
    # the scores are those of the avatar lifted and rendered here, directly (to 1e-3 dB / 1e-4:
    # the child process's lift agrees with this one's to float32 accumulation order, not bit for bit)
    from dlacli.data.synth import synth
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    folder = synth(8101, tmp_path / "s", res=64, novel_views=2, novel_poses=1, appearance="lit", wardrobe="heldout")
    direct = score_avatar(lift(read_views(folder), UnprojectConfig(steps=0)).avatar, folder)
    for r in rows:
        for k, v in direct[r["split"]].items():
            assert abs(r["metrics"][k] - v) <= (1e-3 if k.startswith("psnr") else 1e-4), (r["split"], k)


def test_a_residual_row_names_its_network_by_hash(tmp_path):
    """The residual lift's network is no decoder (the avatar records no checkpoint): its row
    names the weights by the hash the lift records, given or shipped (rows of two networks must
    not pool under one label), and no empty preset / variant fields."""
    from dlacli.avatar.checkpoint import save_checkpoint
    from dlacli.bench.accuracy import run
    from dlacli.nn.residual import ResidualNet, ResidualNetConfig
    from dlacli.stages.lift.methods import parse_methods
    from dlacli.stages.lift.observations import feature_count
    from dlacli.stages.lift.residual import load_residual

    cfg = ResidualNetConfig(features=feature_count(), width=8, resolution=32, gaussians=4096)
    digest = save_checkpoint(tmp_path / "ck", ResidualNet(cfg), cfg)
    rows = run(
        [8102],
        parse_methods(f"residual:checkpoint={tmp_path / 'ck'},residual"),
        res=48,
        novel_views=1,
        novel_poses=1,
        log=lambda s: None,
    )
    shipped = load_residual(None)[1]
    assert shipped != digest and len(rows) == 6
    for r, expected in zip(rows, [digest] * 3 + [shipped] * 3):
        assert r["config"]["checkpoint"] == expected[:16]
        assert "preset" not in r["config"] and "variant" not in r["config"]


def test_kept_subjects_are_reused(tmp_path, monkeypatch):
    """With keep, the subjects are written once under keep/<settings>/ and a second run reuses
    them (no synth call) and scores the same; other settings get a folder of their own."""
    import dlacli.data.synth as synth_module
    from dlacli.bench.accuracy import run
    from dlacli.stages.lift.methods import parse_methods

    kw = dict(res=48, novel_views=1, novel_poses=1, log=lambda s: None, keep=tmp_path / "keep")
    first = run([8102], parse_methods("unproject"), **kw)
    (settings,) = (tmp_path / "keep").iterdir()
    assert (settings / "s8102" / "transforms.json").is_file()
    stamp = (settings / "s8102" / "transforms.json").stat().st_mtime_ns

    def no_synth(*args, **kwargs):
        raise AssertionError("a kept subject was synthesised again")

    monkeypatch.setattr(synth_module, "synth", no_synth)
    again = run([8102], parse_methods("unproject"), **kw)
    assert (settings / "s8102" / "transforms.json").stat().st_mtime_ns == stamp
    for a, b in zip(again, first, strict=True):  # the same files lifted again: float32 order at most
        assert a["metrics"] == pytest.approx(b["metrics"], rel=1e-5), a["split"]
    with pytest.raises(AssertionError, match="synthesised again"):  # albedo is another subject
        run([8102], parse_methods("unproject"), appearance="albedo", **kw)
