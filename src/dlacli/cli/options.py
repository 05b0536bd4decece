"""Option callbacks shared by the commands (typer's ranges let NaN through: every comparison with
NaN is false)."""

from __future__ import annotations

import contextlib
import math
from typing import Iterator

import typer

from dlacli.errors import DlaInputError
from dlacli.limits import MAX_GAUSSIANS


def finite(value: float | None) -> float | None:
    """A float option must be a finite number (or absent)."""
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"must be a finite number, got {value}")
    return value


@contextlib.contextmanager
def naming(**files) -> Iterator[None]:
    """Errors that stages raise about an in-memory part ("views", "pose", "phenotype", "avatar")
    name the user's file instead, e.g. `naming(pose=views / "body.json")`; the part's name stays
    at the front of the problem when it says more than the file does."""
    try:
        yield
    except DlaInputError as err:
        target = files.get(err.where or "")
        if target is None:
            raise
        problem = err.problem if err.where in ("views", "avatar") else f"{err.where}: {err.problem}"
        raise DlaInputError(target, problem) from None




def gaussian_count(value: str | None) -> int | str | None:
    """--gaussians: an integer in [2, MAX_GAUSSIANS], or "auto" (dlacli.stages.budget)."""
    if value is None or value.strip().lower() == "auto":
        return None if value is None else "auto"
    try:
        n = int(value)
    except ValueError:
        raise typer.BadParameter(f"expected an integer or 'auto', got {value[:40]!r}") from None
    if not 2 <= n <= MAX_GAUSSIANS:
        raise typer.BadParameter(f"{n} is not in the range 2<=x<={MAX_GAUSSIANS}")
    return n


def auto_note(choice) -> str:
    """The line `--gaussians auto` prints on stderr (a `dlacli.stages.budget.BudgetChoice`)."""
    how = "from the avatar's lift-time budget" if choice.rule == "recorded" else "by sampling noise (no budget recorded)"
    return f"note: --gaussians auto: {choice.count:,} Gaussians for a person {choice.subject_px:.0f} px tall, {how}"
