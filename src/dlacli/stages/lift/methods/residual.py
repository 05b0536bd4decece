"""The lift method "residual": mesh unprojection corrected by the residual network of a `dla
train --method residual` checkpoint (or the weights shipped in the package), then `steps` of
refinement (stages/lift/residual.py)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from dlacli.stages.lift.methods import Method, Progress, register
from dlacli.stages.lift.methods.unproject import UnprojectConfig


@dataclass(frozen=True)
class ResidualConfig:
    """The checkpoint (folder or hash; None: the shipped weights) and the unprojection's settings
    (None: the network's training resolution and Gaussian count, the lift's defaults otherwise)."""

    checkpoint: str | None = None
    steps: int = 0
    resolution: int | None = None  # UV side of Z
    gaussians: int | None = None  # Gaussians sampled while refining and rendering
    render_size: int | None = None  # refinement renders at most this many pixels on the long side
    seed: int | None = None  # seed of the Gaussian sample points
    hull: str | None = None  # where the unprojection's rays off the body stop: round or box

    def __post_init__(self):
        self.unprojection()  # the same bounds

    def unprojection(self) -> UnprojectConfig:
        """The unprojection (and refinement) this lift corrects, as the unproject method's config."""
        fields = {f.name for f in dataclasses.fields(UnprojectConfig)}
        return UnprojectConfig(**{k: v for k, v in dataclasses.asdict(self).items() if k in fields})


def lift_residual(views, config: ResidualConfig, progress: Progress | None = None, novel=None):
    from dlacli.stages.lift.residual import lift_residual as run

    return run(views, config, progress, novel)


def install_residual(config: ResidualConfig) -> None:
    """A residual network with the colour gain is its avatars' decoder, found by hash elsewhere."""
    from dlacli.avatar.checkpoint import install_checkpoint, resolve_checkpoint
    from dlacli.stages.lift.residual import SHIPPED

    install_checkpoint(SHIPPED if config.checkpoint is None else resolve_checkpoint(config.checkpoint))


register(
    Method(
        "residual",
        ResidualConfig,
        lift_residual,
        "mesh unprojection corrected by a small trained UV network (checkpoint=PATH or the shipped weights)",
        install=install_residual,
    )
)
