"""The one registry of trainings, the methods `dla train --method NAME` runs: a name, a line for
help texts, the options it takes beyond the shared ones, and its entry.

Every training reads the shared options (SHARED: the data, the run folder, the steps of its last
stage, batch, learning rate, validation, evaluation and checkpoint intervals, seed); an option
outside SHARED that a training's `takes` does not name is refused when given (one line naming
the trainings that take it). A new training is its module with an entry `(data, output,
options) -> Path` plus one `register(Training(...))` line below (a test's toy registers itself).

Torch-free at import (the CLI builds its help from here); an entry imports its training when run.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dlacli.registry import Registry

# `dla train`'s options that every training reads, by parameter name
SHARED = frozenset(
    {"data", "output", "method", "steps_full", "batch", "lr_g", "validation", "eval_every", "checkpoint_every", "seed"}
)
# (data, output, every option's value by parameter name) -> the path `dla train` prints
Entry = Callable[[Path, Path, Mapping[str, Any]], Path]


@dataclass(frozen=True)
class Training:
    name: str
    about: str  # one line for help texts
    run: Entry
    takes: frozenset[str] = frozenset()  # the options beyond SHARED it reads


TRAININGS: Registry[Training] = Registry("method")
register = TRAININGS.add  # add (or replace) an entry; returns it
names = TRAININGS.names


def get(name: str, where: str = "--method") -> Training:
    """The method called `name`, else a one-line error listing the known ones."""
    return TRAININGS.choose(name, where)


def taken_by(option: str) -> list[str]:
    """The trainings that take `option` (a parameter name outside SHARED)."""
    return [t.name for t in TRAININGS.values() if option in t.takes]


def _entry(module: str) -> Entry:
    """`module.train_from_options`, imported when the training runs (not for `dla train --help`)."""

    def run(data: Path, output: Path, options: Mapping[str, Any]) -> Path:
        return importlib.import_module(module).train_from_options(data, output, options)

    return run


register(
    Training(
        "learned",
        "U-Net + encoder + GPD, the paper's (two stages: --steps-low at --low-size, then --steps-full at --full-size)",
        _entry("dlacli.train.learned"),
        frozenset(
            {"preset", "steps_low", "low_size", "full_size", "targets", "lr_d", "alexnet", "variant", "stage", "resume"}
        ),
    )
)
register(
    Training(
        "residual",
        "the small network that corrects mesh unprojection (one stage: --steps-full steps at --full-size)",
        _entry("dlacli.train.residual"),
        frozenset({"preset", "full_size", "targets", "resume", "gain", "gain_only", "supersample", "init"}),
    )
)
register(
    Training(
        "completion",
        "the completion prior of `dla dream`: what the photo does not show, from synthetic subjects' front views",
        _entry("dlacli.train.completion"),
        frozenset({"resume", "jobs", "target_light"}),
    )
)
register(
    Training(
        "lifter",
        "the 2D-to-3D pose lifter of `dla motion from-video`, from motion files",
        _entry("dlacli.train.lifter"),
    )
)
