"""Outputs: checked before any work, written atomically, never over an input or a stranger's file.

The rules every command follows (README, "Bad input"):
- `check_outputs` runs before the first input is read: an output may not be one of the command's
  inputs, may not replace anything but a regular file (file outputs) or a folder that is empty or
  holds only what dla writes there (folder outputs), and its parent may not be a file.
- `atomic_path` / `atomic_dir` write to a temporary name beside the target and rename it into place
  only when the block succeeds. Parent folders they had to create are removed again on failure.
- `output_group` makes every atomic write inside it wait for the group: the side files of a command
  (contact sheet, .ply, preview video) land together with its main output or not at all.
- Temporary names carry the writer's process id (`.NAME.dla-PID-XXXX.tmp`); a writer sweeps the
  temporaries of dead dla processes from the folder it writes into (a run killed with SIGKILL).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import fnmatch
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from dlacli.errors import DlaInputError
from dlacli.io.files import kind_of

_TEMP = re.compile(r"^\..*\.dla-(\d+)-[^.]+\.(tmp|old)(\.[^.]*)?$")
_GROUP: contextvars.ContextVar[list | None] = contextvars.ContextVar("dla_output_group", default=None)
_WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _normal_mode(path: Path, is_dir: bool) -> None:
    """mkstemp/mkdtemp create private (0600/0700) entries; give them the usual umask-based mode."""
    os.chmod(path, (0o777 if is_dir else 0o666) & ~_umask())


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def sweep_stale(folder: Path) -> None:
    """Remove temporaries that dead dla processes left in `folder` (only names dla makes)."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        m = _TEMP.match(entry.name)
        if m is None or int(m.group(1)) == os.getpid() or _pid_alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)
            else:
                os.unlink(entry.path)


def _make_parents(parent: Path) -> list[Path]:
    """Create `parent` and missing ancestors; return the folders created, deepest first."""
    created = []
    p = parent
    while not os.path.lexists(p):
        created.append(p)
        p = p.parent
    if os.path.lexists(p) and not p.is_dir():
        raise DlaInputError(p, "is not a folder, so nothing can be written inside it")
    for folder in reversed(created):
        try:
            folder.mkdir()
        except FileExistsError:
            pass
        except OSError as err:
            _remove_folders([f for f in created if f.exists()])
            raise DlaInputError(folder, f"cannot create the folder ({err.strerror})") from None
    return created


def _remove_folders(folders: Iterable[Path]) -> None:
    for folder in folders:  # deepest first; only if still empty
        with contextlib.suppress(OSError):
            folder.rmdir()


def _discard(tmp: Path, is_dir: bool) -> None:
    if is_dir:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _install(tmp: Path, path: Path, is_dir: bool) -> None:
    """Rename the finished temporary onto its target."""
    _normal_mode(tmp, is_dir)
    if is_dir and os.path.lexists(path):
        old = Path(tempfile.mkdtemp(prefix=f".{path.name}.dla-{os.getpid()}-", suffix=".old", dir=path.parent))
        os.replace(path, old / "x")
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def _as_write_error(err: OSError, path: Path) -> DlaInputError | None:
    if err.errno in _WRITE_ERRORS:
        return DlaInputError(path, f"cannot write ({err.strerror})")
    return None


@contextlib.contextmanager
def _atomic(path: str | os.PathLike, is_dir: bool, cache: bool) -> Iterator[Path]:
    path = Path(path)
    created = _make_parents(path.parent)
    sweep_stale(path.parent)
    prefix = f".{path.name if is_dir else path.stem}.dla-{os.getpid()}-"
    try:
        if is_dir:
            tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=path.parent))
        else:
            fd, name = tempfile.mkstemp(prefix=prefix, suffix=f".tmp{path.suffix}", dir=path.parent)
            os.close(fd)
            tmp = Path(name)
    except OSError as err:
        _remove_folders(created)
        raise _as_write_error(err, path) or err from None
    group = None if cache else _GROUP.get()
    try:
        try:
            yield tmp
        except OSError as err:
            raise _as_write_error(err, path) or err from None
        if not is_dir and not tmp.exists():
            raise DlaInputError(path, "the writer produced no file")
        if group is not None:
            group.append((tmp, path, is_dir, created))
        else:
            _install(tmp, path, is_dir)
    except BaseException:
        _discard(tmp, is_dir)
        _remove_folders(created)
        raise


def atomic_path(path: str | os.PathLike, *, cache: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside `path`; it replaces `path` only if the block succeeds (and,
    inside `output_group`, only when the whole group does). `cache=True` ignores the group (cache
    files that are read back at once).

    The temporary name keeps the suffix, so libraries that pick a format by extension (USD,
    imageio) still see the right one.
    """
    return _atomic(path, False, cache)


def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; it replaces `path` (whole) only if the block
    succeeds (inside `output_group`: when the whole group does)."""
    return _atomic(path, True, False)


@contextlib.contextmanager
def output_group() -> Iterator[None]:
    """Every atomic write inside the block lands when the block succeeds, or none does."""
    if _GROUP.get() is not None:  # nested: the outer group decides
        yield
        return
    pending: list = []
    token = _GROUP.set(pending)
    try:
        yield
    except BaseException:
        for tmp, _, is_dir, created in reversed(pending):
            _discard(tmp, is_dir)
            _remove_folders(created)
        raise
    else:
        for tmp, path, is_dir, _ in pending:
            _install(tmp, path, is_dir)
    finally:
        _GROUP.reset(token)


# --------------------------------------------------------------------------------------------
# checks before any work


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _inside(child: Path, folder: Path) -> bool:
    try:
        child.resolve().relative_to(folder.resolve())
    except (ValueError, OSError, RuntimeError):
        return False
    return True


MAX_NAME = 200  # bytes of a file name: NAME_MAX is 255 on common file systems, temporaries add ~40


def _strangers(folder: Path, patterns: list[str], limit: int = 100_000) -> list[str]:
    """Paths under `folder` (relative, '/'-separated, at any depth) that match none of `patterns`:
    what replacing the folder would delete that dla did not write. A folder whose own path
    matches a pattern that ends in it (e.g. "images") is walked: its entries must match too
    (e.g. "images/view_*.png"), so a user's file inside a dla subfolder counts."""
    found, seen, stack = [], 0, [("", folder)]
    while stack:
        rel, here = stack.pop()
        try:
            entries = list(os.scandir(here))
        except OSError:
            continue
        for e in entries:
            seen += 1
            if seen > limit:
                return found + ["(more than 100,000 entries)"]
            name = f"{rel}{e.name}"
            if _TEMP.match(e.name):
                continue
            if not any(fnmatch.fnmatchcase(name, p) for p in patterns):
                found.append(name)
            elif e.is_dir(follow_symlinks=False):
                stack.append((name + "/", Path(e.path)))
    return found


def _check_parent(path: Path) -> None:
    if len(os.fsencode(path.name)) > MAX_NAME:
        raise DlaInputError(path, f"file name of {len(os.fsencode(path.name))} bytes is too long (at most {MAX_NAME})")
    p = path.parent
    while not os.path.lexists(p):
        p = p.parent
    if not p.is_dir():
        raise DlaInputError(path, f"cannot be written: {p} is not a folder")


def check_outputs(
    *,
    files: Iterable[str | os.PathLike | None] = (),
    folders: Iterable[tuple[str | os.PathLike, Iterable[str]] | None] = (),
    inputs: Iterable[str | os.PathLike | None] = (),
) -> None:
    """Refuse, before any work, outputs that would destroy something.

    files: output file paths; an existing one must be a regular file (or a link to one).
    folders: (path, patterns): an existing output folder must be empty or hold only entries whose
        relative paths (at any depth, '/'-separated) match `patterns` (what this command writes
        there), so that replacing it loses nothing of the user's.
    inputs: every file or folder the command reads; no output may be one of them, and no output
        folder may hold one.
    """
    ins = [Path(p) for p in inputs if p is not None]
    outs: list[Path] = []
    for raw in files:
        if raw is None:
            continue
        path = Path(raw)
        _check_parent(path)
        if os.path.lexists(path):
            try:
                mode = os.stat(path).st_mode
            except OSError as err:
                raise DlaInputError(path, f"cannot be replaced ({err.strerror})") from None
            if not stat.S_ISREG(mode):
                raise DlaInputError(path, f"exists and is {kind_of(mode)}; dla replaces only regular files")
        outs.append(path)
    for item in folders:
        if item is None:
            continue
        raw, patterns = item
        path = Path(raw)
        patterns = list(patterns)
        _check_parent(path)
        if os.path.lexists(path):
            if path.is_symlink() or not path.is_dir():
                mode = os.lstat(path).st_mode
                what = "a link" if stat.S_ISLNK(mode) else "a file" if stat.S_ISREG(mode) else kind_of(mode)
                raise DlaInputError(path, f"exists and is {what}, not a folder dla wrote; choose another output")
            strangers = _strangers(path, patterns)
            if strangers:
                raise DlaInputError(
                    path,
                    f"exists and holds files dla did not write there ({', '.join(sorted(strangers)[:3])}"
                    f"{', ...' if len(strangers) > 3 else ''}); remove it or choose another output",
                )
            for inp in ins:
                if os.path.lexists(inp) and _inside(inp, path):
                    raise DlaInputError(path, f"holds the input {inp}; replacing the folder would delete it")
        outs.append(path)
    for i, out in enumerate(outs):
        for inp in ins:
            if os.path.lexists(out) and os.path.lexists(inp) and _same(out, inp):
                raise DlaInputError(out, f"is also an input of this command ({inp}); write to another path")
        for other in outs[:i]:
            if os.path.abspath(other) == os.path.abspath(out) or _same(other, out):
                raise DlaInputError(out, "is given as two different outputs")
