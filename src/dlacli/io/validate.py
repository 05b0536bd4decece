"""Small validation helpers shared by the readers in dlacli.io.

Every helper raises `DlaInputError(where, problem)` with a one-line problem; `where` is the file
(optionally followed by ":key") so the message names what is wrong and where.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, one_line


def load_json(path: str | os.PathLike) -> Any:
    """Parse a JSON file; a missing, unreadable, oversized, malformed (e.g. truncated) or
    absurdly nested file is a DlaInputError."""
    from dlacli.io.files import MAX_JSON_BYTES, read_text

    path = Path(path)
    return parse_json(read_text(path, MAX_JSON_BYTES), path)


MAX_JSON_DEPTH = 64  # arrays and objects nested deeper are refused: no dla file nests more than 6


def parse_json(text: str | bytes, where: Any, name: str = "", constants: bool = True) -> Any:
    """json.loads with every failure as one DlaInputError: syntax, undecodable bytes, nesting
    deeper than MAX_JSON_DEPTH (deeper than Python's recursion limit never reaches a RecursionError
    either), integers of more digits than Python converts. `constants=False` also refuses NaN,
    Infinity and -Infinity, which JSON itself does not have. Every JSON file and string dla reads
    goes through here."""
    what = f"{name} is " if name else ""

    def no_constant(word: str):
        raise ValueError(f"{word} is not a JSON number")

    try:
        value = json.loads(text, **({} if constants else {"parse_constant": no_constant}))
    except json.JSONDecodeError as err:
        raise DlaInputError(where, f"{what}not valid JSON: {err.msg} at line {err.lineno} column {err.colno}") from None
    except UnicodeDecodeError as err:
        raise DlaInputError(where, f"{what}not UTF-8 text (byte {err.start})") from None
    except RecursionError:
        raise DlaInputError(where, f"{what}JSON nested too deeply (at most {MAX_JSON_DEPTH} levels are read)") from None
    except ValueError as err:  # e.g. int digits limit, NaN with constants=False
        raise DlaInputError(where, f"{what}not valid JSON ({one_line(err)})") from None
    depth = json_depth(value)
    if depth > MAX_JSON_DEPTH:
        raise DlaInputError(where, f"{what}JSON nested {depth} levels deep; at most {MAX_JSON_DEPTH} are read")
    return value


def json_depth(value: Any) -> int:
    """How deeply arrays and objects nest in a parsed JSON value (0 for a number or string),
    counted without recursion."""
    depth, stack = 0, [(value, 1)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            item = item.values()
        elif not isinstance(item, list):
            continue
        depth = max(depth, level)
        stack.extend((child, level + 1) for child in item if isinstance(child, (dict, list)))
    return depth


def check_format(found: Any, supported: str, where: Any) -> None:
    """`found` must equal `supported` (e.g. "dla.body/1"); otherwise say what was found."""
    if found is None:
        raise DlaInputError(where, f"missing 'format' key (expected {supported!r})")
    if found != supported:
        family = supported.rsplit("/", 1)[0]
        if isinstance(found, str) and found.startswith(family + "/"):
            problem = f"format {excerpt(found)} is not supported by this version of dla (it reads {supported!r})"
        else:
            problem = f"format is {excerpt(found)}, expected {supported!r}"
        raise DlaInputError(where, problem)


def require_keys(mapping: Any, keys: tuple[str, ...] | list[str], where: Any, what: str = "") -> None:
    """`mapping` must be a dict holding every key in `keys`."""
    if not isinstance(mapping, dict):
        raise DlaInputError(
            where, f"expected a JSON object{' for ' + what if what else ''}, found {type(mapping).__name__}"
        )
    missing = [k for k in keys if k not in mapping]
    if missing:
        raise DlaInputError(where, f"missing key{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}")


def as_float(value: Any, where: Any, name: str) -> float:
    """A finite real number (JSON number or numeric 0-d array); bools and strings are rejected."""
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "fiu":
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DlaInputError(where, f"{name} must be a number, found {_describe(value)}")
    try:
        value = float(value)
    except OverflowError:  # a JSON integer of hundreds of digits
        raise DlaInputError(where, f"{name} is too large to be a number dla uses") from None
    if not math.isfinite(value):
        raise DlaInputError(where, f"{name} is not finite ({value})")
    return value


def as_array(value: Any, shape: tuple[int | None, ...], where: Any, name: str, dtype=np.float32) -> np.ndarray:
    """A finite numeric array of `shape` (None = any size) converted to `dtype`.

    Accepts nested JSON lists or numpy arrays; bool, string and object data are rejected.
    """
    odd = _odd_items(value) if isinstance(value, (list, tuple)) else None
    if odd is bool:  # JSON true/false would read as 1/0
        raise DlaInputError(where, f"{name} must hold numbers, found true/false")
    if odd is int:
        raise DlaInputError(where, f"{name} holds an integer beyond 64 bits, too large to be a number dla uses")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError, OverflowError):
        raise DlaInputError(where, f"{name} is not a rectangular array of numbers") from None
    if arr.dtype.kind not in "fiu":
        raise DlaInputError(where, f"{name} must hold numbers, found {_describe(value)} (dtype {arr.dtype})")
    check_shape(arr, shape, where, name)
    arr = arr.astype(dtype)
    check_finite(arr, where, name)
    return arr


def _odd_items(value) -> type | None:
    """bool if nested lists hold a JSON true/false, int if one of their integers does not fit 64
    bits (numpy would make an object array of them), else None; walked without recursion."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, bool):
            return bool
        if isinstance(item, int) and abs(item) > _LARGEST_INT:
            return int
        if isinstance(item, (list, tuple)):
            stack.extend(item)
    return None


_LARGEST_INT = 2**63 - 1


def check_shape(arr: np.ndarray, shape: tuple[int | None, ...], where: Any, name: str) -> None:
    """`arr.shape` must match `shape`, where None matches any size."""
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise DlaInputError(where, f"{name} has shape {tuple(arr.shape)}, expected {expected}")


def check_finite(arr: np.ndarray, where: Any, name: str) -> None:
    """No NaN or Inf in `arr`."""
    if arr.size and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise DlaInputError(where, f"{name} has {bad} non-finite value{'s' if bad > 1 else ''} (NaN or Inf)")


# Physical bounds for body and motion values: an axis-angle of 1e4 rad is already ~1600 turns and
# a root 100 km from the origin is no scene dla renders; beyond them float32 skinning overflows.
MAX_ANGLE = 1e4  # radians
MAX_DISTANCE = 1e5  # metres


# Gaussian sizes (formats/gaussians-ply.md, "Reading"): a standard deviation is at most MAX_SCALE
# (no Gaussian is wider than the farthest distance dla accepts) and at least MIN_SCALE (a
# thousandth of a proton's radius, so nothing real is smaller), so that the scale, its square (the
# covariance) and the square's inverse are all finite, non-zero float32 numbers when rendered.
# exp(89) is already infinite in float32; log-scales beyond the range say the file is broken.
MIN_SCALE = 1e-18  # metres
MAX_SCALE = MAX_DISTANCE  # metres
LOG_SCALE_RANGE = (math.log(MIN_SCALE), math.log(MAX_SCALE))  # about (-41.4, 11.5)


def check_log_scales(log_scales: np.ndarray, where: Any, name: str) -> None:
    """Every log-scale of `log_scales` (finite, any shape) in LOG_SCALE_RANGE: its scale between
    MIN_SCALE and MAX_SCALE. For an avatar's map, whose log-scales multiply a texel's size, the
    same range bounds the multiplier."""
    low, high = LOG_SCALE_RANGE
    if log_scales.size and not (float(log_scales.min()) >= low and float(log_scales.max()) <= high):
        worst = float(log_scales.max()) if float(log_scales.max()) > high else float(log_scales.min())
        raise DlaInputError(
            where,
            f"{name} holds a log-scale of {worst:.4g} (scale {math.exp(min(worst, 700)):.3g}); "
            f"dla reads log-scales in [{low:.1f}, {high:.1f}] (scales from {MIN_SCALE:g} to {MAX_SCALE:g})",
        )


def check_magnitude(arr: np.ndarray, limit: float, where: Any, name: str, unit: str) -> None:
    """Every |value| of `arr` at most `limit` (after the finiteness check)."""
    if arr.size and float(np.max(np.abs(arr))) > limit:
        raise DlaInputError(
            where, f"{name} reaches {float(np.max(np.abs(arr))):.3g} {unit}; at most {limit:g} is supported"
        )


def as_str(value: Any, where: Any, name: str, allow_empty: bool = False) -> str:
    """A (non-empty) string; also accepts a 0-d numpy unicode array as stored in .npz files."""
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind == "U":
        value = str(value)
    if not isinstance(value, str):
        raise DlaInputError(where, f"{name} must be a string, found {_describe(value)}")
    if not value and not allow_empty:
        raise DlaInputError(where, f"{name} is an empty string")
    return value


def load_npz(path: str | os.PathLike, max_unpacked: int | None = None) -> dict[str, np.ndarray]:
    """Every array of an .npz file, loaded eagerly without pickles (so truncation shows up here);
    refused unread when its arrays would unpack to more than `max_unpacked` bytes (default
    files.MAX_NPZ_UNPACKED). With `npz_format`, the only way dla opens an .npz."""
    from dlacli.io.files import open_input

    path = Path(path)
    check_npz_bounds(path, max_unpacked)  # also the regular-file check and the zip magic
    try:
        with open_input(path) as f, np.load(f, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except DlaInputError:
        raise
    except Exception as err:  # zipfile.BadZipFile, NotImplementedError, EOFError, OSError on truncated files
        from dlacli.io.npz_bounds import npz_error

        raise npz_error(path, err) from None


def _describe(value: Any) -> str:
    if isinstance(value, (list, dict)) and len(value) > 8:  # no repr of a huge JSON value
        return f"{type(value).__name__} of {len(value):,} items"
    return f"{type(value).__name__} {excerpt(value, 40)}"


def dump_json(obj: Any, indent: int = 0) -> str:
    """JSON text, indented, with arrays of plain values (vectors, matrix rows) kept on one line."""
    pad = " " * indent
    if isinstance(obj, dict) and obj:
        items = [f"{pad}  {json.dumps(str(k))}: {dump_json(v, indent + 2)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(obj, (list, tuple)) and any(isinstance(x, (dict, list, tuple)) for x in obj):
        items = [f"{pad}  {dump_json(v, indent + 2)}" for v in obj]
        return "[\n" + ",\n".join(items) + f"\n{pad}]"
    return json.dumps(obj, allow_nan=False)


def save_npz(arrays: dict[str, Any], path: str | os.PathLike) -> None:
    """Write arrays as a compressed .npz, atomically and byte-for-byte deterministic (fixed zip
    timestamps, sorted members), at exactly `path` (no ".npz" is appended)."""
    import io
    import zipfile

    import numpy as np

    from dlacli.io.atomic import atomic_path

    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, buf.getvalue())


def npz_format(path: str | os.PathLike) -> str:
    """What an .npz holds: its `format` string (e.g. "dla.motion/1"), or "amass" for an AMASS
    motion (a `poses` array and no `format`); DlaInputError for anything else or a broken file."""
    import numpy as np

    from dlacli.io.files import open_input

    check_npz_bounds(path)
    try:
        with open_input(path) as f, np.load(f, allow_pickle=False) as data:
            if "format" in data.files:
                return str(data["format"])
            keys = set(data.files)
    except DlaInputError:
        raise
    except Exception as err:  # zip errors, truncated files
        from dlacli.io.npz_bounds import npz_error

        raise npz_error(path, err) from None
    if "poses" in keys:
        return "amass"
    raise DlaInputError(path, "npz with neither a 'format' key (dla.motion/1, dla.avatar/1) nor AMASS 'poses'")


def check_npz_bounds(path: str | os.PathLike, max_unpacked: int | None = None) -> None:
    """Refuse an .npz whose members would decompress to more than dla reads (zip bombs, .npy
    headers claiming more data than the member holds), before numpy allocates anything."""
    from dlacli.io.files import MAX_NPZ_UNPACKED
    from dlacli.io.npz_bounds import check_npz_bounds as check

    check(path, MAX_NPZ_UNPACKED if max_unpacked is None else max_unpacked)
