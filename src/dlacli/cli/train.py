"""`dla train`: train the learned method (U-Net, encoder, GPD) on a synthetic dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.errors import DlaInputError
from dlacli.limits import MAX_TRAIN_SEED

# per-preset defaults of the schedule (a flag given on the command line wins); see docs/train.md
_SCHEDULE = {
    "tiny": dict(steps_low=300, steps_full=300, low_size=48, full_size=96, lr_g=1e-3, lr_d=1e-5, batch=2, targets=2),
    "small": dict(
        steps_low=2000, steps_full=4000, low_size=128, full_size=256, lr_g=3e-4, lr_d=3e-6, batch=4, targets=2
    ),
    "paper": dict(
        steps_low=20000, steps_full=60000, low_size=256, full_size=512, lr_g=1e-4, lr_d=1e-6, batch=8, targets=2
    ),
}


def train(
    data: Path = typer.Option(
        ...,
        "--data",
        help="Dataset folder (`dla synth --seeds A-B -o DATA`) or one subject folder; for --method lifter a folder "
        "of motion files (.bvh, .amc with its .asf, .npz).",
    ),
    output: Path = options.output("Run folder: train.json, checkpoints, loss.png, val/."),
    method: str = typer.Option(
        "learned",
        "--method",
        help="learned (U-Net + encoder + GPD, the paper's), residual (the small network that corrects mesh "
        "unprojection; one stage: --steps-full steps at --full-size), completion (the completion prior of `dla "
        "dream`: what the photo does not show, from synthetic subjects' front views; --steps-full steps) or lifter "
        "(the 2D-to-3D pose lifter of `dla motion from-video`, from motion files; --steps-full steps).",
    ),
    preset: Optional[str] = typer.Option(
        None,
        "--preset",
        help="Network sizes and schedule: tiny (2 CPU cores, about an hour), small, paper (the paper's parameter "
        "counts). Default: tiny for learned, small for residual.",
    ),
    variant: str = typer.Option(
        "full", "--variant", help="full, learned-query (ablation A.ii) or no-conditioning (ablation B)."
    ),
    resume: bool = typer.Option(
        False, "--resume", help="Continue the run in OUTPUT from its last checkpoint (same settings)."
    ),
    stage: str = typer.Option(
        "both",
        "--stage",
        help="low (L_UG + L1 at the low size), full (every loss at the full size) or both, low first.",
    ),
    steps_low: Optional[int] = typer.Option(
        None, "--steps-low", min=0, max=10_000_000, help="Steps of stage low (default: the preset's, docs/train.md)."
    ),
    steps_full: Optional[int] = typer.Option(
        None, "--steps-full", min=0, max=10_000_000, help="Steps of stage full (default: the preset's)."
    ),
    low_size: Optional[int] = typer.Option(
        None, "--low-size", min=8, max=2048, help="Target render size of stage low, pixels (default: the preset's)."
    ),
    full_size: Optional[int] = typer.Option(
        None,
        "--full-size",
        min=8,
        max=2048,
        help="Target render size of stage full, pixels (default: the preset's; residual: the data's image size, "
        "as its corrections only hold at the size they were trained at).",
    ),
    batch: Optional[int] = typer.Option(
        None, "--batch", min=1, max=1024, help="Items per process per step (default: the preset's)."
    ),
    targets: Optional[int] = typer.Option(
        None, "--targets", min=1, max=64, help="Target images per item (default: the preset's)."
    ),
    lr_g: Optional[float] = typer.Option(
        None, "--lr", min=1e-8, max=1.0, help="Generator learning rate (default: the preset's; the paper: 1e-4)."
    ),
    lr_d: Optional[float] = typer.Option(
        None, "--lr-d", min=0.0, max=1.0, help="Discriminator learning rate (default: the preset's; the paper: 1e-6)."
    ),
    validation: int = typer.Option(
        2,
        "--validation",
        min=0,
        max=10_000,
        help="Subjects held out for validation: the lowest seeds, so the set stays when the dataset grows.",
    ),
    eval_every: int = typer.Option(
        50, "--eval-every", min=1, max=10_000_000, help="Validate (scores + val/step_N.png) every N steps."
    ),
    checkpoint_every: int = typer.Option(
        50, "--checkpoint-every", min=1, max=10_000_000, help="Checkpoint every N steps (and at the end)."
    ),
    alexnet: Optional[Path] = typer.Option(
        None,
        "--alexnet",
        help="Local AlexNet weights (torchvision layout, .safetensors or .pth) for the perceptual loss; without them: "
        "MS-SSIM.",
    ),
    seed: int = options.seed("Seed of initialisation, data order and noise.", default=0, maximum=MAX_TRAIN_SEED),
    gain: bool = typer.Option(
        False,
        "--gain",
        help="Residual only: also train F_delta, a colour gain conditioned on the target pose and rays.",
    ),
    init: Optional[str] = typer.Option(
        None,
        "--init",
        help="Residual only: start from this residual network (a checkpoint folder, its hash, or 'shipped': "
        "the weights in the package) instead of from scratch.",
    ),
    gain_only: bool = typer.Option(
        False,
        "--gain-only",
        help="Residual only, with --gain and --init: train F_delta alone; the corrections stay the init network's.",
    ),
    jobs: int = typer.Option(
        1, "--jobs", min=1, max=64, help="Completion only: processes that make the training samples (cached)."
    ),
    target_light: str = typer.Option(
        "world",
        "--target-light",
        help="Completion only, lit subjects: world (the targets lit by the subject's lights, fixed in its world) or "
        "photo (the lights turn with each target camera: the subject everywhere as lit as in the photo).",
    ),
    supersample: int = typer.Option(
        1,
        "--supersample",
        min=1,
        max=8,
        help="Residual only: render targets N times larger and box-filter them (corrections that hold at any size).",
    ),
) -> None:
    """Train the learned avatar networks end to end through skinning and splatting.

    Runs on one process, or data-parallel under torchrun
    (`torchrun --nproc_per_node K $(which dla) train ...`: gloo on CPU, nccl on CUDA).
    Progress on stderr; the run folder's generator checkpoint is what `dla lift --method learned
    --checkpoint RUN/ckpt-N/generator` uses.
    """
    from dlacli.nn.learned import PRESET_NAMES, VARIANTS
    from dlacli.train.loop import TrainConfig
    from dlacli.train.loop import train as run

    if method not in ("learned", "residual", "completion", "lifter"):
        raise DlaInputError("--method", f"must be learned, residual, completion or lifter, got {method!r}")
    if not data.exists():
        raise DlaInputError(data, "no such dataset folder")
    # the options that only some methods take (the rest: data, output, steps, batch, lr, seed, validation)
    only = {
        "--preset": (preset is not None, ("learned", "residual")),
        "--steps-low": (steps_low is not None, ("learned",)),
        "--low-size": (low_size is not None, ("learned",)),
        "--full-size": (full_size is not None, ("learned", "residual")),
        "--targets": (targets is not None, ("learned", "residual")),
        "--lr-d": (lr_d is not None, ("learned",)),
        "--alexnet": (alexnet is not None, ("learned",)),
        "--variant": (variant != "full", ("learned",)),
        "--stage": (stage != "both", ("learned",)),
        "--resume": (resume, ("learned", "residual", "completion")),
        "--jobs": (jobs != 1, ("completion",)),
        "--target-light": (target_light != "world", ("completion",)),
        "--gain": (gain, ("residual",)),
        "--gain-only": (gain_only, ("residual",)),
        "--supersample": (supersample != 1, ("residual",)),
        "--init": (init is not None, ("residual",)),
    }
    for flag, (given, methods) in only.items():
        if given and method not in methods:
            raise DlaInputError(flag, f"applies to --method {' or '.join(methods)} only")
    if method == "lifter":
        from dlacli.train.lifter import run_lifter_training

        path = run_lifter_training(
            data, output, steps=20_000 if steps_full is None else steps_full, batch=batch or 512, lr=lr_g or 1e-3,
            seed=seed, validation=validation,
        )  # fmt: skip
        typer.echo(str(path))
        return
    if method == "completion":
        _train_completion(
            data, output, resume, steps_full, batch, lr_g, validation, eval_every, checkpoint_every, seed, jobs,
            target_light,
        )  # fmt: skip
        return
    if method == "residual":
        _train_residual(
            data, output, preset or "small", resume, steps_full, full_size, batch, targets, lr_g, validation,
            eval_every, checkpoint_every, seed, gain, supersample, init, gain_only,
        )  # fmt: skip
        return
    preset = preset or "tiny"
    if preset not in PRESET_NAMES:
        raise DlaInputError("--preset", f"unknown preset {preset!r} (available: {', '.join(PRESET_NAMES)})")
    if variant not in VARIANTS:
        raise DlaInputError("--variant", f"unknown variant {variant!r} (available: {', '.join(VARIANTS)})")
    if stage not in ("low", "full", "both"):
        raise DlaInputError("--stage", f"must be low, full or both, got {stage!r}")
    if alexnet is not None and not alexnet.is_file():
        raise DlaInputError(alexnet, "no such file")
    given = dict(
        steps_low=steps_low,
        steps_full=steps_full,
        low_size=low_size,
        full_size=full_size,
        lr_g=lr_g,
        lr_d=lr_d,
        batch=batch,
        targets=targets,
    )
    settings = {**_SCHEDULE[preset], **{k: v for k, v in given.items() if v is not None}}
    if stage == "low":
        settings["steps_full"] = 0
    elif stage == "full":
        settings["steps_low"] = 0
    cfg = TrainConfig(
        preset=preset,
        variant=variant,
        validation=validation,
        eval_every=eval_every,
        checkpoint_every=checkpoint_every,
        seed=seed,
        alexnet=str(alexnet or ""),
        **settings,
    )
    if cfg.total_steps == 0:
        raise DlaInputError("--stage", "no steps to train")
    import os

    record = run(data, output, cfg, resume=resume)
    if os.environ.get("RANK", "0") == "0":  # under torchrun only rank 0 writes and reports
        typer.echo(str(output / record["checkpoint"] / "generator"))


_RESIDUAL = dict(steps=2000, batch=2, targets=4, lr=1e-3)  # docs/train.md "The residual lift"


def _train_residual(
    data, output, preset, resume, steps, size, batch, targets, lr, validation, eval_every, checkpoint_every, seed, gain,
    supersample, init, gain_only,
) -> None:  # fmt: skip
    import os

    from dlacli.train.data import image_size
    from dlacli.train.residual import ResidualTrainConfig, net_config, train_residual

    size = image_size(data) if size is None else size  # the scale the loss sees is the scale that holds
    given = dict(steps=steps, size=size, batch=batch, targets=targets, lr=lr)
    cfg = ResidualTrainConfig(
        preset=preset,
        validation=validation,
        eval_every=eval_every,
        checkpoint_every=checkpoint_every,
        seed=seed,
        gain=gain,
        supersample=supersample,
        init=init or "",
        gain_only=gain_only,
        **{**_RESIDUAL, **{k: v for k, v in given.items() if v is not None}},
    )
    net_config(cfg)  # an unknown preset is refused before any work
    if cfg.total_steps == 0:
        raise DlaInputError("--steps-full", "no steps to train")
    record = train_residual(data, output, cfg, resume=resume)
    if os.environ.get("RANK", "0") == "0":
        typer.echo(str(output / record["checkpoint"] / "generator"))


def _train_completion(
    data, output, resume, steps, batch, lr, validation, eval_every, checkpoint_every, seed, jobs, target_light
) -> None:  # fmt: skip
    from dlacli.train.completion import TARGET_LIGHTS, CompletionTrainConfig, train_completion

    if target_light not in TARGET_LIGHTS:
        raise DlaInputError("--target-light", f"must be {' or '.join(TARGET_LIGHTS)}, got {target_light!r}")
    given = dict(steps=steps, batch=batch, lr=lr)
    cfg = CompletionTrainConfig(
        validation=validation,
        eval_every=eval_every,
        checkpoint_every=checkpoint_every,
        seed=seed,
        target_light=target_light,
        **{k: v for k, v in given.items() if v is not None},
    )
    if cfg.total_steps == 0:
        raise DlaInputError("--steps-full", "no steps to train")
    record = train_completion(data, output, cfg, resume=resume, jobs=jobs)
    typer.echo(str(output / record["checkpoint"] / "prior"))


def register(app: typer.Typer) -> None:
    app.command("train")(train)
