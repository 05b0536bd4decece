"""`dla train`: train a method's networks (the trainings of dlacli.train.methods) on a synthetic dataset."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from dlacli.cli import options
from dlacli.errors import DlaInputError
from dlacli.limits import MAX_TRAIN_SEED
from dlacli.train.methods import SHARED, TRAININGS

_METHOD_HELP = "; ".join(f"{t.name} ({t.about})" for t in TRAININGS.values()) + "."


def train(
    ctx: typer.Context,
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
        help=_METHOD_HELP,
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
    """Train a method's networks (--method; the learned and residual lifts end to end through
    skinning and splatting).

    Runs on one process, or data-parallel under torchrun
    (`torchrun --nproc_per_node K $(which dla) train ...`: gloo on CPU, nccl on CUDA).
    Progress on stderr; the run folder's generator checkpoint is what `dla lift --method learned
    --checkpoint RUN/ckpt-N/generator` uses.
    """
    import os

    from dlacli.train.methods import get, taken_by

    chosen = get(method)
    if not data.exists():
        raise DlaInputError(data, "no such dataset folder")
    flags = {p.name: p.opts[0] for p in ctx.command.params if p.opts}
    for name in ctx.params:
        source = ctx.get_parameter_source(name)
        given = source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP")
        if given and name not in SHARED and name not in chosen.takes:
            raise DlaInputError(flags[name], f"applies to --method {' or '.join(taken_by(name))} only")
    path = chosen.run(data, output, dict(ctx.params))
    if os.environ.get("RANK", "0") == "0":  # under torchrun only rank 0 writes and reports
        typer.echo(str(path))


def register(app: typer.Typer) -> None:
    app.command("train")(train)
