"""Option callbacks shared by the commands (typer's ranges let NaN through: every comparison with
NaN is false)."""

from __future__ import annotations

import contextlib
import math
from typing import Iterator

import typer

from dlacli.errors import DlaInputError


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
