"""The lift method "unproject": mesh unprojection into Z, then `steps` of refinement through
skinning and splatting (stages/lift/unproject.py). Its config is the one every caller of that
stage passes, from `dla lift` to the residual lift and its training."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from dlacli.limits import (
    DEFAULT_SAMPLE_SEED,
    LIFT_GAUSSIANS,
    LIFT_LR,
    LIFT_RESOLUTION,
    LIFT_STEPS,
    MAX_GAUSSIANS,
    MAX_IMAGE_SIZE,
    MAX_LIFT_RESOLUTION,
    MAX_LIFT_STEPS,
    MAX_SEED,
    MIN_GAUSSIANS,
    MIN_IMAGE_SIZE,
)
from dlacli.stages.lift.methods import Method, Progress, check, check_range, register

MAX_WEIGHT = 1e6  # the largest loss weight a spec may set
HULLS = ("round", "box")  # where the lift's rays off the body stop (stages/lift/hull.py)
# what a field left at None means; w_smooth and hull stay None: the stage chooses them from the
# views (stages/lift/unproject.py `smoothness`, `hull_shape`)
DEFAULTS = dict(
    resolution=LIFT_RESOLUTION,
    grid=128,
    gaussians=LIFT_GAUSSIANS,
    render_size=512,
    lr=LIFT_LR,
    w_mask=1.0,
    w_ssim=0.2,
    seed=DEFAULT_SAMPLE_SEED,
    view_colour=True,
)


@dataclass(frozen=True)
class UnprojectConfig:
    """Mesh unprojection, then `steps` Adam steps of refinement. A field left at None takes its
    value from DEFAULTS when the stage runs, so result rows record only what a spec set."""

    steps: int = 0  # refinement steps (0: unprojection only); `dla lift` takes LIFT_STEPS
    resolution: int | None = None  # the Gaussian map F (= Z) is resolution x resolution
    grid: int | None = None  # unstructured Gaussians: one per pixel of a grid x grid downsampled view
    gaussians: int | None = None  # sampled while refining, and recorded
    render_size: int | None = None  # refinement renders at most this many pixels on the long side
    lr: float | None = None  # the refinement's Adam learning rate
    w_mask: float | None = None  # weight of the mask L1 in the refinement's loss
    w_ssim: float | None = None  # weight of 1 - SSIM
    # weight of the normal offsets' roughness; None: DREAM_W_SMOOTH for a folder `dla dream` wrote, else 0
    w_smooth: float | None = None
    seed: int | None = None  # seed of the Gaussian sample points
    view_colour: bool | None = None  # measure the views' view-dependent falloff and model it
    # where rays off the body stop: round (the silhouettes' rounded hull) or box (their
    # intersection); None: round for true views, box for a folder `dla dream` wrote
    hull: str | None = None

    def __post_init__(self):
        check_range("steps", self.steps, 0, MAX_LIFT_STEPS)
        check(self.hull in (None, *HULLS), f"hull must be one of {', '.join(HULLS)}, got {self.hull}")
        check(self.lr is None or 0 < self.lr <= 1, f"lr must be in (0, 1], got {self.lr}")
        for name in ("w_mask", "w_ssim", "w_smooth"):
            check_range(name, getattr(self, name), 0, MAX_WEIGHT)
        check_range("resolution", self.resolution, MIN_IMAGE_SIZE, MAX_LIFT_RESOLUTION)
        check_range("grid", self.grid, 1, MAX_IMAGE_SIZE)
        check_range("gaussians", self.gaussians, MIN_GAUSSIANS, MAX_GAUSSIANS)
        check_range("render_size", self.render_size, MIN_IMAGE_SIZE, MAX_IMAGE_SIZE)
        check_range("seed", self.seed, 0, MAX_SEED)

    def resolved(self) -> UnprojectConfig:
        """This config with every field left at None that DEFAULTS names set to its default."""
        return dataclasses.replace(self, **{k: v for k, v in DEFAULTS.items() if getattr(self, k) is None})


def lift_unproject(views, config: UnprojectConfig, progress: Progress | None = None, novel=None):
    from dlacli.stages.lift.unproject import lift

    return lift(views, config, progress=progress, novel=novel)


register(
    Method(
        "unproject",
        UnprojectConfig,
        lift_unproject,
        "mesh unprojection, no weights; steps=N refines",
        lift_defaults={"steps": LIFT_STEPS},
    )
)
