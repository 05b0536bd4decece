"""The toolkit's registries: lift methods (stages/lift/methods/), dream backends
(stages/dream/backends/) and trainings (train/methods.py) each keep their entries, by name, in a
`Registry`, so that every command, benchmark and result row finds them by that one name."""

from __future__ import annotations

from typing import Generic, TypeVar

from dlacli.errors import DlaInputError

T = TypeVar("T")


class Registry(dict, Generic[T]):
    """name -> entry (an object with a `name`), in the order registered (`sort`: names() sorted)."""

    def __init__(self, what: str, sort: bool = False):
        super().__init__()
        self.what, self.sort = what, sort

    def add(self, entry: T) -> T:
        """Add (or replace) `entry` under its name; returns it."""
        self[entry.name] = entry
        return entry

    def names(self) -> list[str]:
        return sorted(self) if self.sort else list(self)

    def choose(self, name: str, where: str) -> T:
        """The entry called `name`, else a one-line error (for option `where`) listing the known ones."""
        if name not in self:
            raise DlaInputError(where, f"unknown {self.what} {name[:40]!r} (one of: {', '.join(self.names())})")
        return self[name]
