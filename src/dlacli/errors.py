"""The one error type for bad user input.

`DlaInputError` carries a one-line message that names the file (or argument) and the problem;
the CLI prints it as `error: <message>` and exits with code 2, without a traceback.
"""

from __future__ import annotations

import os


class DlaInputError(Exception):
    """Bad input from the user: a missing or malformed file, an invalid argument."""

    def __init__(self, where: str | os.PathLike | None, problem: str):
        self.where = str(where) if where is not None else None
        self.problem = problem
        super().__init__(f"{self.where}: {problem}" if self.where else problem)

    def __reduce__(self):  # picklable (raised in worker processes, e.g. `dla synth --jobs`)
        return (DlaInputError, (self.where, self.problem))
