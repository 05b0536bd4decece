""".npz bounds: refuse archives that would make `np.load` allocate more than a cap.

`np.load` trusts two things an attacker controls: the zip's members (a few KB can inflate to
GBs: a zip bomb) and each .npy header (numpy allocates the whole array the header declares
*before* reading any data). `check_npz_bounds` reads neither: it checks the file is a regular
file of at most `max_bytes`, the zip's central directory (member count, declared unpacked sizes
against `max_bytes`), and each .npy header (shape x itemsize against the member's declared
size, which zipfile never exceeds when unpacking, and which cannot exceed what the member's
packed size can give). Only a few hundred bytes per member are read.
"""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path
from typing import IO, Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, one_line

MAX_NPZ_BYTES = 4096 * 2**20  # default cap: the file, and its arrays unpacked (files.MAX_BINARY_BYTES)
MAX_MEMBERS = 4096
_HEADER_BYTES = 10_000  # numpy's own default limit on a .npy header
# the most a packed byte can unpack to, per compression method (deflate's limit is ~1032:1)
_MAX_RATIO = {zipfile.ZIP_STORED: 1, zipfile.ZIP_DEFLATED: 1032}


def check_npz_bounds(path: str | os.PathLike, max_bytes: int = MAX_NPZ_BYTES) -> None:
    """DlaInputError (naming `path`) unless `path` is a regular .npz file that `np.load` can
    unpack within `max_bytes`; see the module docstring. Object (pickle) arrays are left for
    `np.load(allow_pickle=False)` to refuse."""
    from dlacli.io.files import open_input

    path = Path(path)
    with open_input(path, max_bytes) as f:
        check_zip_bounds(f, path, max_bytes)


def check_zip_bounds(f: IO[bytes], where: Any, max_bytes: int = MAX_NPZ_BYTES) -> None:
    """`check_npz_bounds` on an open, seekable binary file (left open; position undefined)."""
    head = f.read(4)
    if head not in (b"PK\x03\x04", b"PK\x05\x06"):
        raise DlaInputError(where, "not a readable .npz file (no zip header)")
    f.seek(0)
    _check_directory(f, where)
    try:
        zf = zipfile.ZipFile(f)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as err:
        raise npz_error(where, err) from None
    with zf:
        infos = zf.infolist()
        total = sum(info.file_size for info in infos)
        if total > max_bytes:
            raise DlaInputError(
                where,
                f"its {len(infos)} arrays would unpack to {total:,} bytes; at most {max_bytes / 2**20:g} MiB is read",
            )
        for info in infos:
            ratio = _MAX_RATIO.get(info.compress_type)
            if ratio is not None and info.file_size > info.compress_size * ratio + 1024:
                raise DlaInputError(
                    where,
                    f"member {excerpt(info.filename)} claims {info.file_size:,} bytes unpacked from "
                    f"{info.compress_size:,} packed, more than its method can give (corrupt or hostile file)",
                )
            if info.filename.endswith(".npy"):
                _check_member(zf, info, where, max_bytes)


def npz_error(where: Any, err: Exception) -> DlaInputError:
    """What any failure of zipfile or numpy on an .npz says: one short line (their messages may
    quote a member's raw name or bytes, so they pass through `one_line`)."""
    if isinstance(err, NotImplementedError):  # e.g. a zip "version needed to extract" above 6.3
        return DlaInputError(where, f"unsupported zip feature ({one_line(err)}); dla reads the zips numpy writes")
    if isinstance(err, ValueError) and "pickle" in str(err).lower():
        problem = "holds pickled Python objects, which dla never reads (store strings as unicode arrays)"
        return DlaInputError(where, problem)
    if isinstance(err, ValueError):
        return DlaInputError(where, f"not a readable .npz file ({one_line(err)})")
    return DlaInputError(where, f"not a readable .npz file ({type(err).__name__}: {one_line(err)})")


def _check_directory(f: IO[bytes], where: Any) -> None:
    """Refuse zips whose central directory alone would be a memory bomb (millions of members)."""
    end = getattr(zipfile, "_EndRecData", None)  # private but stable since Python 2; skip if gone
    if end is None:
        return
    try:
        rec = end(f)
    except (OSError, ValueError, EOFError):
        rec = None
    if rec is None:
        raise DlaInputError(where, "not a readable .npz file (no zip end record: truncated?)")
    entries = rec[getattr(zipfile, "_ECD_ENTRIES_TOTAL", 4)]
    if entries > MAX_MEMBERS:
        raise DlaInputError(where, f"a zip of {entries:,} members; at most {MAX_MEMBERS} are read")
    f.seek(0)


def _check_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: Any, max_bytes: int) -> None:
    name = info.filename
    try:
        with zf.open(info) as m:
            version = np.lib.format.read_magic(m)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(m, max_header_size=_HEADER_BYTES)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(m, max_header_size=_HEADER_BYTES)
            else:
                reader = getattr(np.lib.format, "_read_array_header", None)
                if reader is None:
                    raise ValueError(f"unsupported .npy format version {version}")
                shape, _, dtype = reader(m, version, max_header_size=_HEADER_BYTES)
    except DlaInputError:
        raise
    except NotImplementedError as err:  # a compression method or zip feature zipfile lacks
        raise npz_error(where, err) from None
    except Exception as err:  # bad magic or header, CRC errors, truncated members
        raise DlaInputError(
            where, f"not a readable .npz file (member {excerpt(name)}: {type(err).__name__}: {one_line(err)})"
        ) from None
    if dtype.hasobject:
        return  # np.load(allow_pickle=False) refuses it with its own message
    count = math.prod(int(n) for n in shape)
    nbytes = count * dtype.itemsize
    if count > max_bytes or nbytes > info.file_size:
        raise DlaInputError(
            where,
            f"member {excerpt(name)} declares a {tuple(shape)} {dtype} array ({nbytes:,} bytes) but holds "
            f"{info.file_size:,} bytes (corrupt or hostile file)",
        )
