"""A new lift method as it lands: this one file (its config and its lift function) plus one
`register(Method(...))` entry (made by tests/stages/test_methods.py). The toy is the mesh
unprojection with no refinement, recorded under its own name: what `dla lift --method toy`,
`dla bench accuracy --methods toy` and the result rows must all know it by."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

NAME = "toy"


@dataclass(frozen=True)
class ToyConfig:
    gaussians: int = 2048  # sampled when its avatar is drawn (few: its renders are quick)

    def __post_init__(self):
        if not 2 <= self.gaussians <= 65_536:
            raise ValueError(f"gaussians must be in [2, 65536], got {self.gaussians}")


def lift_toy(views, config: ToyConfig, progress=None, novel=None):
    """views -> LiftResult: an unprojection at a small UV resolution, named after the toy."""
    from dlacli.stages.lift.methods import make_spec

    result = make_spec("unproject", resolution=32, gaussians=config.gaussians).lift(views, progress, novel)
    extra = {**result.avatar.extra, NAME: dataclasses.asdict(config)}
    result.avatar = dataclasses.replace(result.avatar, encoder=NAME, extra=extra)
    return result
