"""The lift method "learned": the U-Net + cross-attention encoder + GPD of a `dla train`
checkpoint, then `steps` of refining Z through the frozen decoder (stages/lift/learned.py)."""

from __future__ import annotations

from dataclasses import dataclass

from dlacli.limits import MAX_IMAGE_SIZE, MAX_LIFT_STEPS, MIN_IMAGE_SIZE
from dlacli.stages.lift.methods import Method, Missing, Progress, check_range, register


@dataclass(frozen=True)
class LearnedConfig:
    """The checkpoint (folder or hash) and the refinement (None: the stage's default size)."""

    checkpoint: str = ""
    steps: int = 0
    render_size: int | None = None  # refinement renders the views at this size

    def __post_init__(self):
        if not self.checkpoint:
            raise Missing("checkpoint", "a dla train checkpoint folder or its hash")
        check_range("steps", self.steps, 0, MAX_LIFT_STEPS)
        check_range("render_size", self.render_size, MIN_IMAGE_SIZE, MAX_IMAGE_SIZE)


def lift_learned(views, config: LearnedConfig, progress: Progress | None = None, novel=None):
    from dlacli.stages.lift.learned import lift_learned as run

    extra = {} if config.render_size is None else {"render_size": config.render_size}
    return run(views, config.checkpoint, steps=config.steps, progress=progress, novel=novel, **extra)


def install_learned(config: LearnedConfig) -> None:
    """Animate, render and edit find a learned avatar's decoder by the checkpoint hash it records."""
    from dlacli.avatar.checkpoint import install_checkpoint, resolve_checkpoint

    install_checkpoint(resolve_checkpoint(config.checkpoint))


register(
    Method(
        "learned",
        LearnedConfig,
        lift_learned,
        "U-Net + cross-attention encoder + GPD from checkpoint=PATH",
        install=install_learned,
    )
)
