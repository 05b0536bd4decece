"""`dla train --method lifter` (dlacli.train.lifter.run_lifter_training): a short run from motion
files writes weights that `dla motion from-video` can load, records what it trained on, and
refuses the other methods' options in one line."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from dlacli.cli.app import main
from dlacli.nn.lifter import load_lifter
from dlacli.train import lifter as lifter_train


@pytest.fixture()
def motions(third_party_data, tmp_path):
    d = tmp_path / "motions"
    d.mkdir()
    for name in ("131_01.bvh", "131_02.bvh"):
        shutil.copy(third_party_data / "motion" / name, d / name)
    (d / "notes.txt").write_text("not a motion")
    return d


def test_a_short_run_writes_loadable_weights(motions, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(lifter_train, "SHAPES", 2)
    monkeypatch.setattr(lifter_train, "PER_SHAPE", 64)
    out = tmp_path / "run"
    args = ["train", "--method", "lifter", "--data", str(motions), "-o", str(out)]
    with pytest.raises(SystemExit) as info:
        main([*args, "--steps-full", "3", "--batch", "8", "--validation", "1"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == str(out / "lifter.safetensors")
    record = json.loads((out / "train.json").read_text())
    assert record["validation_files"] == ["131_01.bvh"] and record["train_files"] == ["131_02.bvh"]
    assert record["format"] == "dla.lifter-run/1" and record["steps"] == 3
    assert record["motion_frames"] > 0 and record["random_poses"] > 0
    (last,) = record["history"]  # fewer steps than a log interval: one record, at the end
    assert last["step"] == 3 and last["loss"] > 0 and 0 < last["val_limb_angle_deg"] < 180
    model = load_lifter(out / "lifter.safetensors")
    x = torch.zeros(2, 54)
    assert model(x).shape == (2, 17, 3)


@pytest.mark.parametrize(
    ("extra", "flag"),
    [(["--preset", "tiny"], "--preset"), (["--gain"], "--gain"), (["--validation", "2"], "--validation")],
)
def test_refusals_are_one_line(motions, tmp_path, capsys, extra, flag):
    with pytest.raises(SystemExit) as info:
        main(["train", "--method", "lifter", "--data", str(motions), "-o", str(tmp_path / "r"), *extra])
    err = capsys.readouterr().err.strip()
    assert info.value.code == 2 and len(err.splitlines()) == 1 and flag in err, err
    assert not (tmp_path / "r").exists()
