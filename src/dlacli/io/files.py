"""Inputs: regular files only, read with a size cap, and paths kept inside their folder.

Every reader in dlacli.io opens user files through here, so that a FIFO never hangs a command,
a link to /dev/zero is never read to the end, a tiny file cannot claim gigabytes, and a view
folder cannot pull in files from elsewhere unless the user allows it.
"""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path

from dlacli.errors import DlaInputError, excerpt, one_line

MiB = 1 << 20
# Caps on what one input file may be: far above any real artifact of its kind, far below what
# would exhaust a 24 GB machine.
MAX_JSON_BYTES = 64 * MiB
MAX_TEXT_BYTES = 512 * MiB  # BVH, AMC, ASF
MAX_BINARY_BYTES = 4096 * MiB  # .ply, .npz, .usd* (the file itself; npz members are checked too)
MAX_NPZ_UNPACKED = 1024 * MiB  # all arrays of one .npz: an avatar's maps or a 200,000-frame motion fit in far less
MAX_IMAGE_BYTES = 512 * MiB
MAX_IMAGE_PIXELS = 8192 * 8192  # one photo or view: 67 MP (decoded RGBA float32 = 1 GiB)


def kind_of(mode: int) -> str:
    """What a non-regular file is, for messages: "a folder", "a FIFO", "a device", ..."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def open_input(path: str | os.PathLike, max_bytes: int = MAX_BINARY_BYTES) -> io.BufferedReader:
    """Open a regular file for binary reading; DlaInputError if it is missing, not a regular file
    (checked on the opened descriptor, without blocking on a FIFO) or larger than `max_bytes`."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise DlaInputError(path, "no such file") from None
    except IsADirectoryError:
        raise DlaInputError(path, "is a folder, not a regular file") from None
    except OSError as err:
        raise DlaInputError(path, f"cannot open the file ({err.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise DlaInputError(path, f"is {kind_of(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise DlaInputError(
                path,
                f"is {st.st_size} bytes; dla reads at most {max_bytes} bytes ({max_bytes / MiB:.0f} MiB) for this "
                "kind of file",
            )
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def check_input(path: str | os.PathLike, max_bytes: int = MAX_BINARY_BYTES) -> int:
    """The checks of `open_input` without keeping the file open; returns its size in bytes."""
    with open_input(path, max_bytes) as f:
        return os.fstat(f.fileno()).st_size


def read_bytes(path: str | os.PathLike, max_bytes: int = MAX_BINARY_BYTES) -> bytes:
    """The whole content of a regular file of at most `max_bytes`."""
    with open_input(path, max_bytes) as f:
        size = os.fstat(f.fileno()).st_size
        data = f.read(size + 1)  # never reserve the cap itself; +1 shows a file that grew
    if len(data) > max_bytes or len(data) > size:  # grew while we read it
        raise DlaInputError(path, "changed size while it was read")
    return data


def read_text(path: str | os.PathLike, max_bytes: int = MAX_TEXT_BYTES, errors: str = "strict") -> str:
    """A regular UTF-8 text file of at most `max_bytes`; undecodable bytes are a DlaInputError
    unless `errors="replace"`."""
    data = read_bytes(path, max_bytes)
    try:
        return data.decode("utf-8", errors=errors)
    except UnicodeDecodeError as err:
        raise DlaInputError(path, f"is not UTF-8 text (byte {err.start})") from None


def inside(folder: str | os.PathLike, rel: str, where: object, name: str, allow_outside: bool = False) -> Path:
    """`folder / rel`, refused when `rel` is absolute, climbs out with `..`, or resolves (through
    links) to a place outside `folder`; `allow_outside=True` accepts all of these."""
    folder = Path(folder)
    path = folder / rel
    if allow_outside:
        return path
    if os.path.isabs(rel):
        raise DlaInputError(
            where,
            f"{name} {excerpt(rel)} is an absolute path; dla reads only files inside the folder (--allow-outside to "
            "permit)",
        )
    try:
        path.resolve().relative_to(folder.resolve())
    except ValueError:
        raise DlaInputError(
            where,
            f"{name} {excerpt(rel)} leads outside the folder; dla reads only files inside it (--allow-outside to "
            "permit)",
        ) from None
    except (OSError, RuntimeError) as err:  # link loops
        raise DlaInputError(where, f"{name} {excerpt(rel)} cannot be resolved ({one_line(err)})") from None
    return path


def open_image(path: str | os.PathLike, max_pixels: int = MAX_IMAGE_PIXELS):
    """A PIL image opened lazily from (the bytes of) a regular file, its declared size checked
    against `max_pixels` before any pixel is decoded (decompression bombs). The caller closes it
    and decodes it inside `decoding(path)`."""
    import warnings

    from PIL import Image

    data = read_bytes(path, MAX_IMAGE_BYTES)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data))
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as err:
        raise DlaInputError(path, f"image too large to decode ({one_line(err)})") from None
    except (OSError, ValueError, SyntaxError) as err:
        raise DlaInputError(path, f"not a readable image ({one_line(err)})") from None
    w, h = im.size
    if w * h > max_pixels or w <= 0 or h <= 0:
        im.close()
        raise DlaInputError(path, f"image is {w}x{h} pixels; dla reads at most {max_pixels / 1e6:.0f} megapixels")
    return im


class decoding:
    """Context for decoding an image opened by `open_image`: Pillow's errors on junk, truncation
    and oversized chunks become one-line DlaInputErrors naming the file."""

    def __init__(self, path: str | os.PathLike):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, kind, err, tb):
        if (
            err is not None
            and isinstance(err, (OSError, ValueError, SyntaxError, EOFError))
            and not isinstance(err, DlaInputError)
        ):
            raise DlaInputError(self.path, f"not a readable image ({one_line(err)})") from None
        return False
