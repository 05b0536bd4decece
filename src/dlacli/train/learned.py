"""`dla train --method learned`: the options of the command -> the schedule of train/loop.py."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from dlacli.errors import DlaInputError

# per-preset defaults of the schedule (an option given on the command line wins); see docs/train.md
SCHEDULES = {
    "tiny": dict(steps_low=300, steps_full=300, low_size=48, full_size=96, lr_g=1e-3, lr_d=1e-5, batch=2, targets=2),
    "small": dict(
        steps_low=2000, steps_full=4000, low_size=128, full_size=256, lr_g=3e-4, lr_d=3e-6, batch=4, targets=2
    ),
    "paper": dict(
        steps_low=20000, steps_full=60000, low_size=256, full_size=512, lr_g=1e-4, lr_d=1e-6, batch=8, targets=2
    ),
}
STAGES = ("low", "full", "both")


def train_from_options(data: Path, output: Path, o: Mapping[str, Any]) -> Path:
    """Train on `data` into the run folder `output`; -> the last generator checkpoint's folder."""
    from dlacli.nn.learned import PRESET_NAMES, VARIANTS
    from dlacli.train.loop import TrainConfig, train

    preset = o.get("preset") or "tiny"
    if preset not in PRESET_NAMES:
        raise DlaInputError("--preset", f"unknown preset {preset!r} (available: {', '.join(PRESET_NAMES)})")
    variant, stage, alexnet = o.get("variant", "full"), o.get("stage", "both"), o.get("alexnet")
    if variant not in VARIANTS:
        raise DlaInputError("--variant", f"unknown variant {variant!r} (available: {', '.join(VARIANTS)})")
    if stage not in STAGES:
        raise DlaInputError("--stage", f"must be low, full or both, got {stage!r}")
    if alexnet is not None and not Path(alexnet).is_file():
        raise DlaInputError(alexnet, "no such file")
    given = {k: o.get(k) for k in SCHEDULES[preset] if o.get(k) is not None}
    settings = {**SCHEDULES[preset], **given}
    if stage == "low":
        settings["steps_full"] = 0
    elif stage == "full":
        settings["steps_low"] = 0
    cfg = TrainConfig(
        preset=preset,
        variant=variant,
        validation=o["validation"],
        eval_every=o["eval_every"],
        checkpoint_every=o["checkpoint_every"],
        seed=o["seed"],
        alexnet=str(alexnet or ""),
        **settings,
    )
    if cfg.total_steps == 0:
        raise DlaInputError("--stage", "no steps to train")
    record = train(data, output, cfg, resume=bool(o.get("resume")))
    # under torchrun, ranks other than 0 write nothing and their record names no checkpoint
    return output / record["checkpoint"] / "generator" if record.get("checkpoint") else output
