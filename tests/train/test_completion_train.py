"""`dla train --method completion` (train/completion.py): the front view is the one facing the
body; the sample's target agrees with the photo where both see the body (the cameras are mapped
into the subject's world right); the loop learns a known correction, resumes bit for bit, writes
its run folder, and the CLI refuses what does not apply."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from dlacli.errors import DlaInputError


def _fake_samples(dataset, resolution: int = 32) -> None:
    """Samples in the cache for every subject of `dataset`: random photo evidence, the rule's
    completion, and a target that is the completion darkened by half where the photo saw
    nothing (a correction a network can learn)."""
    from dlacli.io.atomic import atomic_path
    from dlacli.stages.dream.texture import complete, texel_samples
    from dlacli.train.completion import sample_path
    from dlacli.train.data import discover

    n = texel_samples(resolution)[0].size
    for k, (_, _, folder) in enumerate(discover(dataset)):
        rng = np.random.default_rng(k)
        colour = rng.uniform(0.2, 0.9, (n, 3)).astype(np.float32)
        weight = np.where(rng.random(n) < 0.4, rng.uniform(0.5, 1.0, n), 0.0).astype(np.float32)
        completed = complete(colour, weight, resolution)
        target = np.where(weight[:, None] > 0, completed, 0.5 * completed).astype(np.float32)
        sample = dict(colour=colour, weight=weight, completed=completed, target=target)
        sample.update(target_weight=np.ones(n, np.float32), photo=np.zeros((4, 4, 4), np.uint8))
        with atomic_path(sample_path(folder, resolution), cache=True) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **sample)


def _cfg(**kw):
    from dlacli.train.completion import CompletionTrainConfig

    base = dict(width=8, resolution=32, batch=1, steps=4, lr=3e-3, validation=1, eval_every=2, checkpoint_every=2)
    return CompletionTrainConfig(**{**base, **kw})


def test_front_view_faces_the_body():
    from dlacli.train.completion import front_view
    from dlacli.types import Cameras

    mats = []
    for az in (200.0, 290.0, 20.0, 110.0):  # azimuth 0: on the -Y side, where anny faces
        a = math.radians(az)
        c2w = np.eye(4)
        c2w[:3, 3] = [3 * math.sin(a), -3 * math.cos(a), 0.3]
        mats.append(c2w)
    views = type("V", (), {"cameras": Cameras.from_c2w_opengl(np.stack(mats), 100.0, 100.0, 32, 32, 64, 64)})
    assert front_view(views) == 2


def test_training_learns_a_known_correction_and_resumes_bit_for_bit(dataset, tmp_path):
    from dlacli.avatar.checkpoint import load_checkpoint
    from dlacli.nn.completion import CompletionNet
    from dlacli.train.completion import train_completion

    _fake_samples(dataset)
    record = train_completion(dataset, tmp_path / "a", _cfg(steps=40, eval_every=40, checkpoint_every=40))
    hist = record["history"]
    assert hist[0]["l1"] == hist[0]["rule_l1"]  # step 1 starts at the rule exactly (both rounded alike)
    assert np.mean([h["l1"] for h in hist[-5:]]) < 0.8 * hist[0]["l1"]
    val = record["validation"][-1]
    assert val["l1_hidden"] < val["base_l1_hidden"]  # the held-out subject improves too
    run = tmp_path / "a"
    rec = json.loads((run / "train.json").read_text())
    assert rec["format"] == "dla.train/1" and rec["settings"]["method"] == "completion" and rec["step"] == 40
    assert (run / "val" / "step_000040.png").is_file()
    loaded = load_checkpoint(run / "ckpt-000040" / "prior")
    assert isinstance(loaded.module, CompletionNet) and loaded.step == 40

    straight = train_completion(dataset, tmp_path / "b", _cfg())
    train_completion(dataset, tmp_path / "c", _cfg(), until=2)
    resumed = train_completion(dataset, tmp_path / "c", _cfg(), resume=True)
    assert [h["l1"] for h in straight["history"]] == [h["l1"] for h in resumed["history"]]
    a = load_checkpoint(tmp_path / "b" / "ckpt-000004" / "prior").module.state_dict()
    b = load_checkpoint(tmp_path / "c" / "ckpt-000004" / "prior").module.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(DlaInputError, match="other settings"):
        train_completion(dataset, tmp_path / "c", _cfg(lr=1e-2), resume=True)


def test_train_cli_refuses_options_of_other_methods(dataset, tmp_path, capsys):
    from dlacli.cli.app import main

    for args in (["--jobs", "2", "--method", "residual"], ["--method", "completion", "--gain"]):
        with pytest.raises(SystemExit) as exit_:
            main(["train", "--data", str(dataset), "-o", str(tmp_path / "r"), *args])
        assert exit_.value.code == 2
        assert "applies to --method" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # an unknown target lighting: one line, nothing written
        bad = ["--method", "completion", "--target-light", "sun"]
        main(["train", "--data", str(dataset), "-o", str(tmp_path / "t"), *bad])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith("error: --target-light:") and err.count("\n") == 1
    assert not (tmp_path / "t").exists()


@pytest.mark.slow
def test_a_real_samples_target_agrees_with_its_photo(tmp_path):
    """A 512 px lit subject (lights fixed in the world, as the training data) through detection
    and the fit: on texels both the photo and the target see well, the target's colours (the
    true subject rendered around the fitted body and baked back onto it) match the photo's within
    3 % of the range at the median (what differs: bilinear resampling at 256 and 512 px and the
    specular highlights, which move with the view; measured 1.3 %; cameras mapped into the wrong
    world would bake other garments' colours there: the rule's fill of hidden texels, for
    contrast, is ~7 % off); the targets cover most of the body."""
    from dlacli.data.synth import synth
    from dlacli.stages.dream.texture import SEEN
    from dlacli.train.completion import make_sample

    folder = synth(8133, tmp_path / "s", res=512, novel_views=0, novel_poses=0, appearance="lit")
    s = make_sample(folder, resolution=64)
    both = (s["weight"] > 0.9 * SEEN) & (s["target_weight"] > 0.5)
    assert both.mean() > 0.1 and (s["target_weight"] > 0.3).mean() > 0.5
    err = np.abs(s["target"] - s["colour"]).mean(1)[both]
    print("median |target - photo| on texels both see:", np.median(err))
    assert np.median(err) < 0.03
    assert s["photo"].shape == (512, 512, 4) and s["photo"].dtype == np.uint8
    # the targets lit as the photo is (the lights turn with each target camera): the same evidence,
    # the same match where the photo sees, other colours where it does not, a cache file of its own
    # (the targets' weights may differ a little: the bake's occluder rule reads the colours)
    from dlacli.train.completion import sample_path

    p = make_sample(folder, resolution=64, target_light="photo")
    for key in ("colour", "weight", "completed", "photo"):
        assert np.array_equal(p[key], s[key]), key
    assert np.mean(np.abs(p["target_weight"] - s["target_weight"]) > 0.05) < 0.02
    assert np.median(np.abs(p["target"] - p["colour"]).mean(1)[both]) < 0.03
    unseen = (s["weight"] == 0) & (s["target_weight"] > 0.5)
    assert np.abs(p["target"] - s["target"]).mean(1)[unseen].mean() > 0.01
    assert sample_path(folder, 64, "photo") != sample_path(folder, 64)
