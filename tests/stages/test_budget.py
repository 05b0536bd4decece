"""The Gaussian budget (dlacli.stages.budget): the chooser on toy quality curves, the additive-error
model, carrying a recorded count to other cameras, and `--gaussians auto` on a lifted avatar."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dlacli.stages.budget import (
    LADDER,
    auto_gaussians,
    choose_for_views,
    choose_gaussians,
    measure_budget,
    predicted_psnr,
    recorded_budget,
    sampling_noise,
    scaled_count,
    subject_pixels,
)

N = 4096  # the count the test avatar is lifted with
COUNTS = (256, 1024, 4096)


def _oracle_choice(scores: dict[int, float], tol: float) -> int:
    """Written differently from choose_gaussians: walk the counts upwards and stop at the first
    one that no score beats by more than tol."""
    usable = {n: s for n, s in scores.items() if not (isinstance(s, float) and (math.isnan(s) or s == -math.inf))}
    for n in sorted(usable):
        if all(usable[n] >= s - tol for s in usable.values()):
            return n
    raise AssertionError("unreachable")


def test_choose_gaussians_on_toy_quality_curves():
    # saturating: best 22.0, 0.2 dB below it is 21.8, first count at or above: 16,384
    curve = {4096: 20.0, 8192: 21.5, 16384: 21.85, 32768: 21.95, 65536: 22.0}
    assert choose_gaussians(curve) == 16384
    assert choose_gaussians(curve, tolerance_db=0.0) == 65536
    assert choose_gaussians(curve, tolerance_db=5.0) == 4096
    # a peak in the middle (too many Gaussians blur): the best is 32,768, nothing smaller is close
    assert choose_gaussians({4096: 18.0, 16384: 19.0, 32768: 20.0, 131072: 19.9}) == 32768
    # the boundary is inclusive (values exact in binary): 21.75 = 22.0 - 0.25
    assert choose_gaussians({1: 21.75, 2: 22.0}, tolerance_db=0.25) == 1
    # failed renders never win; a perfect score is only matched by another
    assert choose_gaussians({4096: float("nan"), 8192: -math.inf, 16384: 20.0}) == 16384
    assert choose_gaussians({4096: 40.0, 8192: math.inf}) == 8192
    rng = np.random.default_rng(3)
    for _ in range(200):
        counts = sorted(rng.choice(2 ** np.arange(1, 20), size=rng.integers(1, 8), replace=False).tolist())
        scores = {int(n): float(v) for n, v in zip(counts, rng.normal(20.0, 1.0, len(counts)))}
        tol = float(rng.uniform(0.0, 1.0))
        assert choose_gaussians(scores, tol) == _oracle_choice(scores, tol)
    for bad in ({}, {4096: float("nan")}):
        with pytest.raises(ValueError):
            choose_gaussians(bad)
    with pytest.raises(ValueError):
        choose_gaussians(curve, tolerance_db=-0.1)


def test_additive_error_model():
    p = 21.0
    e = 10 ** (-p / 10)
    # no sampling noise: exactly the reference's score; noise of (10^(0.02) - 1) e costs 0.2 dB
    s_02 = (10**0.02 - 1) * e
    got = predicted_psnr({1: 0.0, 2: s_02, 3: 10 * e}, p)
    assert got[1] == pytest.approx(p, abs=1e-12)
    assert got[2] == pytest.approx(p - 0.2, abs=1e-9)
    assert got[3] == pytest.approx(p - 10 * math.log10(11), abs=1e-9)
    # choosing on predicted scores = the smallest count whose noise exceeds the least noise by at
    # most (10^(tol/10) - 1) (e + least noise): the rule the module doc states
    noise = {4096: 4e-3, 8192: 1.2e-3, 16384: 6e-4, 32768: 4e-4, 65536: 3e-4}
    limit = (10**0.02 - 1) * (e + min(noise.values()))
    expected = min(n for n, s in noise.items() if s - min(noise.values()) <= limit)
    assert choose_gaussians(predicted_psnr(noise, p)) == expected == 16384


def test_scaled_count_follows_the_area_the_person_covers():
    assert scaled_count(16384, 100.0, 100.0) == 16384
    assert scaled_count(16384, 100.0, 200.0) == 65536  # twice as tall: 4x the area
    assert scaled_count(16384, 100.0, 150.0) == 65536  # 36,864 rounded up to the ladder
    assert scaled_count(16384, 100.0, 50.0) == 4096
    assert scaled_count(16384, 100.0, 10.0) == LADDER[0]
    assert scaled_count(131072, 100.0, 400.0) == LADDER[-1]  # more than the ladder holds
    # half as tall as float64 measures it: 0.1 / (0.3 - 0.1) is 0.5000000000000001, whose square
    # times 16,384 is 4,096.000000000002; a real rounding that must not take the next rung
    assert 0.1 / (0.3 - 0.1) > 0.5
    assert scaled_count(16384, 0.3 - 0.1, 0.1) == 4096
    assert scaled_count(16384, 100.0, 50.001) == 8192  # a real difference does (4,096.16)
    with pytest.raises(ValueError):
        scaled_count(16384, 0.0, 10.0)


@pytest.fixture(scope="module")
def lifted(subject):
    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    views = read_views(subject)
    return lift(views, UnprojectConfig(steps=0, gaussians=N)).avatar, views


# float32 rounding steps a rendered pixel may differ by between two renders of the same scene on
# another machine (the compositing of the Gaussians that cover it, each a few multiply-adds)
PIXEL_OPS = 256


def test_measure_budget_is_masked_psnr_of_the_renders(lifted, tol):
    from dlacli.bench.metrics import masked_psnr
    from dlacli.stages.render import render_avatar

    avatar, views = lifted
    scores = measure_budget(avatar, views, COUNTS)
    assert list(scores) == list(COUNTS)
    gt = views.images * views.masks[..., None]
    pixel = tol(np.float32, 1.0, ops=PIXEL_OPS)  # colours in [0, 1]
    for n in COUNTS:
        shots = sorted(render_avatar(avatar, views.cameras, views.times, n_gaussians=n), key=lambda s: s.camera)
        want = masked_psnr(np.stack([s.rgba[..., :3] for s in shots]), gt, views.masks)
        # pixels off by <= d move the MSE by <= 2 d rmse (Cauchy-Schwarz), PSNR by 10 / ln 10 of its ratio
        rmse = 10 ** (-want / 20)
        assert scores[n] == pytest.approx(want, abs=10 / math.log(10) * 2 * pixel / rmse)


def test_sampling_noise_is_half_the_difference_of_two_seeds(lifted, tol):
    from dlacli.stages.render import render_avatar

    avatar, views = lifted
    noise = sampling_noise(avatar, views.cameras, (256, 1024))
    for n, s in noise.items():
        a, b = (
            np.stack(
                [
                    x.rgba
                    for x in sorted(
                        render_avatar(avatar, views.cameras, views.times, n_gaussians=n, seed=k), key=lambda x: x.camera
                    )
                ]
            )
            for k in (0, 1)
        )
        sel = np.maximum(a[..., 3], b[..., 3]) > 0.5
        want = 0.5 * np.mean((a[..., :3][sel].astype(np.float64) - b[..., :3][sel]) ** 2)
        # each render's pixels off by <= p move each difference by <= 2 p: s by <= 2 p sqrt(2 s)
        pixel = tol(np.float32, 1.0, ops=PIXEL_OPS)
        assert s == pytest.approx(want, abs=2 * pixel * math.sqrt(2 * want))
        assert s > 0  # two different sample sets do not draw the same image


def test_lift_auto_records_its_choice_and_animate_auto_carries_it(lifted, tmp_path):
    from dlacli.avatar.posed import sample_settings
    from dlacli.io.avatar import read_avatar, write_avatar
    from dlacli.types import Cameras

    avatar, views = lifted
    chosen, choice = choose_for_views(avatar, views, COUNTS)
    assert choice.count == choose_gaussians(measure_budget(avatar, views, COUNTS))
    write_avatar(chosen, tmp_path / "a.npz")  # the record is JSON (no inf / NaN)
    back = read_avatar(tmp_path / "a.npz")
    assert sample_settings(back) == (choice.count, 0)
    rec = recorded_budget(back)
    assert rec["count"] == choice.count and rec["render_size"] == views.masks.shape[1]
    assert rec["subject_px"] == pytest.approx(subject_pixels(avatar, views.cameras))
    # the input cameras: the same count; half the focal length (the person half as tall): a quarter
    assert auto_gaussians(back, views.cameras, COUNTS).count == choice.count
    ks = views.cameras.Ks.clone()
    ks[:, :2, :2] *= 0.5
    half = Cameras(views.cameras.viewmats, ks, views.cameras.width, views.cameras.height)
    assert subject_pixels(avatar, half) == pytest.approx(0.5 * rec["subject_px"], rel=1e-6)
    got = auto_gaussians(back, half, COUNTS)
    assert got.rule == "recorded" and got.count == scaled_count(choice.count, 2.0, 1.0, COUNTS)
    # without a record: self-consistency, the choice on the predicted scores of its noise
    plain = auto_gaussians(avatar, views.cameras, COUNTS)
    assert plain.rule == "self-consistency"
    assert plain.count == choose_gaussians(predicted_psnr(plain.noise))


def _main(argv, capsys):
    from dlacli.cli.app import main

    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return info.value.code, out, err


def test_cli_gaussians_auto(lifted, tmp_path, capsys):
    from PIL import Image

    from dlacli.io.avatar import write_avatar

    avatar, views = lifted
    chosen, choice = choose_for_views(avatar, views, COUNTS)
    write_avatar(chosen, tmp_path / "a.npz")
    code, _, err = _main(
        ["render", tmp_path / "a.npz", "--turntable", 2, "--size", 32, "--gaussians", "auto", "-o", tmp_path / "r"],
        capsys,
    )
    assert code == 0, err
    assert "--gaussians auto" in err and "lift-time budget" in err
    assert len(list((tmp_path / "r").glob("f*_c*.png"))) == 2
    assert Image.open(tmp_path / "r" / "f0000_c000.png").size == (32, 32)
    code, _, err = _main(
        [
            "animate",
            tmp_path / "a.npz",
            "wave",
            "-o",
            tmp_path / "w.usda",
            "--gaussians",
            "AUTO",
            "--preview-size",
            32,
            "--fps",
            2,
        ],
        capsys,
    )
    assert code == 0, err
    count = int(err.split("--gaussians auto: ")[1].split(" ")[0].replace(",", ""))
    assert count in LADDER
    from dlacli.limits import MAX_GAUSSIANS

    for bad in ("1", "lots", str(MAX_GAUSSIANS + 1)):
        code, _, err = _main(
            ["render", tmp_path / "a.npz", "--turntable", 1, "--gaussians", bad, "-o", tmp_path / "x"], capsys
        )
        assert code == 2 and err.startswith("error: --gaussians:") and len(err.strip().splitlines()) == 1, err


def test_default_lift_records_a_budget_and_the_commands_draw_it(subject, tmp_path, capsys):
    """`dla lift` without --gaussians measures and records the budget; render and animate draw it
    (carried to their cameras), view and export its count; an explicit --gaussians N wins."""
    from dlacli.avatar.posed import sample_settings
    from dlacli.io.avatar import read_avatar
    from dlacli.io.views import read_views
    from dlacli.stages.render import turntable_cameras

    av = tmp_path / "a.npz"
    code, _, err = _main(["lift", subject, "-o", av, "--steps", 0], capsys)
    assert code == 0, err
    back = read_avatar(av)
    rec = recorded_budget(back)
    assert rec is not None and rec["measured_on"] == "input views"
    scores = {int(n): s for n, s in rec["psnr_masked"].items()}
    assert sorted(scores) == list(LADDER) and rec["count"] == choose_gaussians(scores)
    # the record is the measurement: the chosen count's re-render scores what it says (the file may
    # hold z as float16, within 1e-3 of its largest value: formats/avatar.md; that moves it by < 0.01 dB)
    views = read_views(subject)
    assert measure_budget(back, views, (rec["count"],))[rec["count"]] == pytest.approx(scores[rec["count"]], abs=0.01)
    assert sample_settings(back)[0] == rec["count"]
    # render: the budget carried to the turntable's person size, announced on stderr
    code, _, err = _main(["render", av, "--turntable", 1, "--size", 48, "-o", tmp_path / "r"], capsys)
    assert code == 0, err
    want = scaled_count(rec["count"], rec["subject_px"], subject_pixels(back, turntable_cameras(back, 1, 48)))
    assert f"note: the avatar's budget: {want:,} Gaussians" in err
    # an explicit count wins: no note
    code, _, err = _main(
        ["render", av, "--turntable", 1, "--size", 48, "--gaussians", 300, "-o", tmp_path / "s"], capsys
    )
    assert code == 0 and "budget" not in err, err
    # animate: the budget at its preview cameras (AUTO_VIEWS turntable cameras of --preview-size)
    from dlacli.stages.budget import AUTO_VIEWS

    code, _, err = _main(["animate", av, "wave", "-o", tmp_path / "w.usda", "--preview-size", 32, "--fps", 2], capsys)
    assert code == 0, err
    px = subject_pixels(back, turntable_cameras(back, AUTO_VIEWS, 32))
    assert f"note: the avatar's budget: {scaled_count(rec['count'], rec['subject_px'], px):,} Gaussians" in err
    # view and export (no cameras): the recorded count
    code, _, err = _main(["view", av, "-o", tmp_path / "v.html"], capsys)
    assert code == 0, err
    html = (tmp_path / "v.html").read_text()
    assert f'"gaussians": {rec["count"]}' in html or f'"gaussians":{rec["count"]}' in html
    code, _, err = _main(["export", av, "-o", tmp_path / "a.ply"], capsys)
    assert code == 0, err
    head = (tmp_path / "a.ply").read_bytes()[:400].decode("ascii", "replace")
    assert f"element vertex {rec['count']}\n" in head
    code, _, err = _main(["export", av, "-o", tmp_path / "b.ply", "--gaussians", 300], capsys)
    assert code == 0 and "element vertex 300\n" in (tmp_path / "b.ply").read_bytes()[:400].decode("ascii", "replace")


def test_a_refined_lift_records_the_count_it_was_refined_at(subject, tmp_path, capsys):
    """A refined avatar is fitted to its sample points: `dla lift` (auto) refines with
    LIFT_GAUSSIANS points and records that count as its budget, scored on the input views."""
    from dlacli.io.avatar import read_avatar
    from dlacli.io.views import read_views
    from dlacli.limits import LIFT_GAUSSIANS

    av = tmp_path / "a.npz"
    code, _, err = _main(["lift", subject, "-o", av, "--steps", 2], capsys)
    assert code == 0, err
    back = read_avatar(av)
    rec = recorded_budget(back)
    assert rec is not None and rec["count"] == LIFT_GAUSSIANS
    assert back.extra["lift"]["gaussians"] == LIFT_GAUSSIANS and back.extra["samples"]["count"] == LIFT_GAUSSIANS
    assert list(rec["psnr_masked"]) == [str(LIFT_GAUSSIANS)]
    score = measure_budget(back, read_views(subject), (LIFT_GAUSSIANS,))[LIFT_GAUSSIANS]
    assert score == pytest.approx(rec["psnr_masked"][str(LIFT_GAUSSIANS)], abs=0.01)


def test_an_avatar_without_a_budget_keeps_its_lifted_count(lifted, tmp_path, capsys):
    """An avatar lifted with --gaussians N (or before budgets): render draws extra.samples.count,
    no budget note; with no samples record either, DEFAULT_GAUSSIANS."""
    from dataclasses import replace

    from dlacli.avatar.posed import sample_settings
    from dlacli.io.avatar import write_avatar
    from dlacli.limits import DEFAULT_GAUSSIANS
    from dlacli.stages.budget import budget_default

    avatar, views = lifted
    assert recorded_budget(avatar) is None and budget_default(avatar, views.cameras) is None
    assert sample_settings(avatar)[0] == N
    old = replace(avatar, extra={k: v for k, v in avatar.extra.items() if k != "samples"})
    assert sample_settings(old)[0] == DEFAULT_GAUSSIANS
    write_avatar(avatar, tmp_path / "a.npz")
    code, _, err = _main(["render", tmp_path / "a.npz", "--turntable", 1, "--size", 32, "-o", tmp_path / "r"], capsys)
    assert code == 0 and "budget" not in err, err
    # the image is the render with the lifted count (and differs from one with another count)
    from PIL import Image

    from dlacli.io.avatar import read_avatar
    from dlacli.stages.render import render_avatar, turntable_cameras

    back = read_avatar(tmp_path / "a.npz")  # as the command read it (z may be float16 in the file)
    png = np.asarray(Image.open(tmp_path / "r" / "f0000_c000.png"), np.float64) / 255
    cams = turntable_cameras(back, 1, 32)
    for n, same in ((N, True), (N // 4, False)):
        (shot,) = render_avatar(back, cams, [None], None, n_gaussians=n)
        assert (np.abs(np.clip(shot.rgba, 0, 1) - png).max() <= 0.5 / 255 + 1e-6) == same
