"""`dla bench stability`: the perturbations against what they claim to do, failures recorded per
run, the rows' schema, the degradation summary and a tiny end-to-end run with its report."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import pytest

from dlacli.bench import stability as S
from dlacli.bench.rows import check_row, stability_row
from dlacli.errors import DlaInputError

SEED = 31  # a seed no other test uses


@pytest.fixture(scope="module")
def subject():
    return S.make_subject(SEED, 48, novel_views=1, novel_poses=1)


def _rng():
    return np.random.default_rng(0)


def test_subject_matches_dla_synth(subject, tmp_path):
    from dlacli.data.synth import synth
    from dlacli.io.views import read_views

    folder = synth(SEED, tmp_path / "s", res=48, novel_views=1, novel_poses=1)
    for mine, theirs in (
        (subject.views, read_views(folder)),
        (subject.novel_views, read_views(folder / "novel_views", require_body=False)),
        (subject.novel_poses, read_views(folder / "novel_poses", require_body=False)),
    ):
        assert np.allclose(mine.cameras.viewmats, theirs.cameras.viewmats, atol=1e-6)
        # synth writes 8-bit PNGs: half a step of 1/255
        assert np.abs(mine.masks - theirs.masks).max() <= 0.5 / 255 + 1e-6
        inside = theirs.masks > 0.99
        assert np.abs(mine.images[inside] - theirs.images[inside]).max() <= 0.5 / 255 + 1e-6
        assert mine.times == theirs.times


def test_view_perturbations_do_what_they_say(subject):
    from scipy.spatial.transform import Rotation

    from dlacli.body.model import pose_to_rotations
    from dlacli.data.cameras import TARGET
    from dlacli.geometry import camera_centers

    v = subject.views
    # pose noise: every bone turned by exactly the level, about some axis
    noisy = S.pose_noise(v, 10.0, _rng())
    a, b = pose_to_rotations(v.body.pose, "pose"), pose_to_rotations(noisy.body.pose, "pose")
    rel = Rotation.from_rotvec(b.astype(np.float64)) * Rotation.from_rotvec(a.astype(np.float64)).inv()
    angles = np.degrees(np.arccos(np.clip((np.trace(rel.as_matrix(), axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.allclose(angles, 10.0, atol=1e-3)  # float32 axis-angles: ~1e-5 rad
    # shape noise: the phenotype changes, stays in [0, 1]; level 0 changes nothing
    shaped = S.shape_noise(v, 0.2, _rng())
    assert shaped.body.phenotype != v.body.phenotype and all(0 <= x <= 1 for x in shaped.body.phenotype.values())
    assert S.shape_noise(v, 0.0, _rng()).body.phenotype == v.body.phenotype
    # colour shift: view 0 untouched, the others scaled by one gain per channel (where not clipped)
    shifted = S.colour_shift(v, 0.2, _rng())
    assert np.array_equal(shifted.images[0], v.images[0])
    for k in range(1, len(v)):
        sel = (v.masks[k] > 0.99) & (v.images[k].max(-1) > 0.05) & (shifted.images[k].max(-1) < 0.99)
        gains = shifted.images[k][sel] / v.images[k][sel]
        assert np.allclose(gains, gains.mean(0), rtol=1e-5) and not np.allclose(gains.mean(0), 1.0, atol=1e-3)
    # misregistration in pixels: view 0 untouched, the others' masks moved by exactly the level
    moved = S.misregister_px(v, 3.0, _rng())
    assert np.array_equal(moved.masks[0], v.masks[0])

    def centroid(m):
        ys, xs = np.nonzero(np.ones_like(m))
        return np.array([(ys * m.ravel()).sum(), (xs * m.ravel()).sum()]) / m.sum()

    for k in range(1, len(v)):
        assert np.linalg.norm(centroid(moved.masks[k]) - centroid(v.masks[k])) == pytest.approx(3.0, abs=0.05)
    # misregistration in degrees: the claimed camera orbits the rig's axis by +-level, same radius and height
    turned = S.misregister_deg(v, 5.0, _rng())
    c0, c1 = (
        camera_centers(v.cameras.viewmats).numpy() - TARGET,
        camera_centers(turned.cameras.viewmats).numpy() - TARGET,
    )
    assert np.allclose(c0[0], c1[0], atol=1e-5)
    for k in range(1, len(v)):
        d = math.degrees(math.atan2(c1[k, 1], c1[k, 0]) - math.atan2(c0[k, 1], c0[k, 0]))
        assert abs((d + 180) % 360 - 180) == pytest.approx(5.0, abs=1e-3)
        assert np.hypot(*c1[k, :2]) == pytest.approx(np.hypot(*c0[k, :2]), abs=1e-4) and c1[k, 2] == pytest.approx(
            c0[k, 2], abs=1e-5
        )
    # fewer views: the front always, then the sides, then the back
    for count, keep in S.VIEW_SUBSETS.items():
        fewer = S.fewer_views(v, count, _rng())
        assert len(fewer) == count and np.array_equal(fewer.images, v.images[list(keep)])
        assert np.array_equal(fewer.cameras.viewmats, v.cameras.viewmats[list(keep)])


def test_subject_perturbations(subject):
    far = S.make_subject(SEED, 48, 1, 1, distance=2 * 3.0)
    assert far.info["fill"] == pytest.approx(subject.info["fill"] / 2, abs=2 / 48)  # twice as far, half as tall
    assert np.array_equal(far.novel_views.images, subject.novel_views.images)  # scored on the standard rig
    touching = S.make_subject(SEED, 48, 1, 1, pose=lambda spec: S.self_contact(spec, 24.0))
    assert touching.info["hand_clearance_m"] < subject.info["hand_clearance_m"]
    assert np.array_equal(touching.novel_poses.images, subject.novel_poses.images)  # the clean subject's motion


@dataclass(frozen=True)
class _NoOptions:
    """The config of the toy methods below (they take none)."""


def test_runs_record_failures(subject):
    from dlacli.stages.lift import methods

    good = methods.make_spec("unproject").lift(subject.views).avatar

    def broken(views, config, progress, novel):
        raise RuntimeError("out of\nmemory")

    def toy(name, avatar):
        lift = lambda views, config, progress, novel: SimpleNamespace(avatar=avatar)  # noqa: E731
        return methods.Method(name, _NoOptions, lift, "toy")

    methods.register(methods.Method("t_broken", _NoOptions, broken, "raises"))
    methods.register(toy("t_nan", replace(good, z=np.full_like(good.z, np.nan))))
    empty_z = good.z.copy()
    empty_z[0] = -20.0  # every opacity logit: sigmoid ~2e-9
    methods.register(toy("t_empty", replace(good, z=empty_z)))
    try:
        spec = methods.parse_method
        assert S.run_one(spec("t_broken"), subject.views, subject)["error"] == "RuntimeError: out of memory"
        for name, status in (("t_broken", "error"), ("t_nan", "nan"), ("t_empty", "empty"), ("unproject", "ok")):
            result = S.run_one(spec(name), subject.views, subject)
            assert result["status"] == status, (name, result)
            assert (result["metrics"] != {}) == (status == "ok")
        assert S.visible_gaussians(good) > 0 and S.visible_gaussians(replace(good, z=empty_z)) == 0
    finally:
        for name in ("t_broken", "t_nan", "t_empty"):
            methods.METHODS.pop(name)
    with pytest.raises(DlaInputError, match="t_broken"):
        methods.parse_methods("t_broken")


def test_stability_rows_pass_the_schema():
    ok = stability_row(
        "unproject",
        {"res": 48},
        "novel_views",
        1.0,
        None,
        {"psnr": 25, "psnr_masked": 18, "ssim": 0.9, "iou": 0.9},
        "pose_noise",
        5.0,
        subject=1,
        device="cpu",
    )
    failed = stability_row(
        "unproject",
        {"steps": 50},
        "novel_poses",
        0.5,
        None,
        {},
        "fewer_views",
        1.0,
        "error",
        "ValueError: x",
        device="cpu",
    )
    for row in (ok, failed):
        assert check_row(dict(row)) == row
    for change, needle in (
        ({"status": "fine"}, "status"),
        ({"metrics": {}}, "psnr"),
        ({"level": float("inf")}, "level"),
        ({"perturbation": None}, "perturbation"),
        ({"kind": "stable"}, "kind"),
    ):
        with pytest.raises(DlaInputError, match=needle):
            check_row({**ok, **change})


def _toy(values: dict[float, float | None], method="m", pert="pose_noise", subject=1) -> list[dict]:
    rows = []
    for level, v in values.items():
        for split in ("novel_views", "novel_poses"):
            metrics = {} if v is None else {"psnr": v + 8, "psnr_masked": v, "ssim": 0.9, "iou": 0.9}
            rows.append(
                stability_row(
                    method,
                    {},
                    split,
                    1.0,
                    None,
                    metrics,
                    pert,
                    level,
                    "ok" if v is not None else "error",
                    None if v is not None else "boom",
                    subject=subject,
                    device="cpu",
                )
            )
    return rows


def test_drop_level_and_curves():
    rows = _toy({0.0: 20.0, 2.0: 19.5, 5.0: 18.1, 10.0: 17.9, 20.0: 12.0}) + _toy(
        {0.0: 21.0, 2.0: 20.5, 5.0: 17.9, 10.0: 18.0, 20.0: 13.0}, subject=2
    )
    c = S.curves(rows)["pose_noise"]["m"]
    assert [lv for lv, *_ in c] == [0.0, 2.0, 5.0, 10.0, 20.0]
    assert c[2][1] == pytest.approx(18.0) and c[2][2] == 2  # mean over the two subjects
    assert S.drop_level(c) == 5.0  # means 20.5, 20.0, 18.0, 17.95, 12.5: the first at or below 18.5
    assert S.drop_level(c, drop_db=3.0) == 20.0 and S.drop_level(c, drop_db=9.0) is None
    assert S.drop_level([(0.0, 20.0, 1, 0), (1.0, 19.0, 1, 0)]) is None
    assert S.drop_level([(0.0, 20.0, 1, 0), (1.0, float("nan"), 1, 1)]) == 1.0  # every subject failed


def test_a_tiny_run_and_its_report(tmp_path, capsys):
    from PIL import Image

    from dlacli.bench.charts import draw_stability_chart
    from dlacli.bench.report import stability_markdown
    from dlacli.bench.rows import append_rows
    from dlacli.stages.lift.methods import parse_methods

    pytest.importorskip("matplotlib")
    rows = S.run(
        [SEED],
        parse_methods("unproject"),
        ["fewer_views", "colour_shift"],
        res=48,
        levels=2,
        novel_views=1,
        novel_poses=1,
        log=lambda line: None,
    )
    assert len(rows) == 2 * 2 * 2  # perturbations x levels x splits
    assert all(check_row(dict(r)) == r and r["status"] == "ok" for r in rows)
    base = [
        r for r in rows if r["level"] == S.PERTURBATIONS[r["perturbation"]].levels[0] and r["split"] == "novel_views"
    ]
    assert len(base) == 2 and base[0]["metrics"] == base[1]["metrics"]  # one clean run, every perturbation's baseline
    assert {r["level"] for r in rows if r["perturbation"] == "fewer_views"} == {4.0, 1.0}
    md = "\n".join(stability_markdown(rows, "s.png"))
    assert "### fewer views (views)" in md and "No run produced NaN, an exception or an empty avatar." in md
    png = draw_stability_chart(rows, tmp_path / "s.png")
    image = np.asarray(Image.open(png).convert("RGB"))
    assert image.shape[1] > image.shape[0] and image.std() > 10  # two panels side by side, something drawn
    append_rows(tmp_path / "r.jsonl", rows + _toy({0.0: 20.0, 2.0: None}, method="m2"))
    from dlacli.cli.app import main

    with pytest.raises(SystemExit) as info:
        main(["bench", "report", str(tmp_path / "r.jsonl"), "-o", str(tmp_path / "b.md")])
    assert info.value.code == 0
    page = (tmp_path / "b.md").read_text()
    assert "![stability curves](b_stability.png)" in page and (tmp_path / "b_stability.png").is_file()
    assert "| m2 | pose_noise | 2 | 1 | error | boom |" in page and not (tmp_path / "b.png").exists()
    with pytest.raises(SystemExit) as info:
        main(["bench", "stability", "--methods", "unproject,nope"])
    assert info.value.code == 2 and "nope" in capsys.readouterr().err
