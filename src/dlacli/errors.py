"""The one error type for bad user input, and the one way a message quotes that input.

`DlaInputError` carries a one-line message that names the file (or argument) and the problem;
the CLI prints it as `error: <message>` and exits with code 2, without a traceback. Whatever a
message quotes from a file (a name, a value, a library's complaint that echoes raw bytes) goes
through `excerpt`, so that a message stays one short line whatever the file holds.
"""

from __future__ import annotations

import os

EXCERPT_CHARS = 60  # the most characters of quoted input in one message (quotes and escapes included)


def excerpt(value: object, limit: int = EXCERPT_CHARS) -> str:
    """`value` quoted and escaped as Python's repr does (a str or bytes; anything else by its
    repr), cut to at most about `limit` characters: a longer one ends in "..." and says how long
    it was, e.g. 'abcdef...' (1,048,576 characters). Control characters, line breaks and
    invisible Unicode show as escapes, so the excerpt is always one printable line."""
    if not isinstance(value, (str, bytes, bytearray)):  # a parsed value: its repr, bounded as it is built
        import reprlib

        shown = reprlib.Repr()
        shown.maxstring = shown.maxother = shown.maxlong = limit
        try:
            text = " ".join(shown.repr(value).split())
        except ValueError:  # an int of more digits than Python prints
            text = f"<{type(value).__name__} too large to show>"
        return text if len(text) <= limit else text[: max(limit - 3, 1)] + "..."
    text = repr(value)
    if len(text) <= limit:
        return text
    keep = max(limit - 3, 1)  # characters of `value` to show, shrunk until their escapes fit
    while True:
        head = repr(value[:keep])[:-1]  # drop the closing quote: the excerpt is open-ended
        if len(head) <= limit - 3 or keep == 1:
            break
        keep = max(keep * (limit - 3) // len(head) - 1, 1)
    unit = "bytes" if isinstance(value, (bytes, bytearray)) else "characters"
    return f"{head}... ({len(value):,} {unit})"


def excerpts(values, most: int = 5) -> str:
    """Several quoted inputs (e.g. unknown keys): the first `most` as `excerpt`s, then how many
    more, e.g. 'a', 'b', 'c' and 12 more."""
    values = list(values)
    shown = ", ".join(excerpt(v, 40) for v in values[:most])
    return shown + (f" and {len(values) - most:,} more" if len(values) > most else "")


def one_line(err: BaseException | str, limit: int = 120) -> str:
    """A library's error message (or any text) as one printable line of at most about `limit`
    characters: whitespace runs become one space, other control and invisible characters show as
    escapes, and a longer text ends in "..." (parsers echo raw input: zipfile a member's name or
    bytes, json a number of thousands of digits)."""
    text = " ".join(str(err).split()) or type(err).__name__
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[: 4 * limit])
    return text if len(text) <= limit else text[: limit - 3] + "..."


class DlaInputError(Exception):
    """Bad input from the user: a missing or malformed file, an invalid argument."""

    def __init__(self, where: str | os.PathLike | None, problem: str):
        self.where = str(where) if where is not None else None
        self.problem = problem
        super().__init__(f"{self.where}: {problem}" if self.where else problem)

    def __reduce__(self):  # picklable (raised in worker processes, e.g. `dla synth --jobs`)
        return (DlaInputError, (self.where, self.problem))
