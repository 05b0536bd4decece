"""Gaussians .ply: the INRIA 3D Gaussian Splatting layout (formats/gaussians-ply.md).

On disk (stored space): `x y z nx ny nz f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3`, with
opacity as a logit, scales as logs, colour as SH coefficients and the quaternion w first.
In memory (`types.Gaussians`, activated space): linear opacity, linear scales, unit quaternions.

The functional core is `stored_to_activated` / `activated_to_stored` (numpy, no files); the readers
and writers wrap them with plyfile.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, one_line
from dlacli.io.atomic import atomic_path
from dlacli.io.validate import check_log_scales
from dlacli.types import Gaussians, sh_degree_for_coeffs

OPACITY_EPS = 1e-7  # activated opacities are clamped to [eps, 1 - eps] before the logit

# f_rest count per colour channel -> SH degree (K - 1 higher coefficients per channel).
_REST_PER_CHANNEL = {0: 0, 3: 1, 8: 2, 15: 3}

_BASE_BEFORE_REST = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
_BASE_AFTER_REST = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
_NORMALS = ("nx", "ny", "nz")


def property_names(sh_degree: int) -> list[str]:
    """The exact INRIA property order for a given SH degree 0..3."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return [*_BASE_BEFORE_REST, *(f"f_rest_{i}" for i in range(n_rest)), *_BASE_AFTER_REST]


# --------------------------------------------------------------------------------------------
# functional core: stored <-> activated (numpy)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    """Numerically stable logistic function, float64."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    pos = x >= 0
    out[pos] = 1.0 / (1.0 + np.exp(-x[pos]))
    ex = np.exp(x[~pos])
    out[~pos] = ex / (1.0 + ex)
    return out


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def stored_to_activated(
    opacity_logit: np.ndarray,  # [N]
    log_scales: np.ndarray,  # [N, 3]
    rots: np.ndarray,  # [N, 4] (w, x, y, z), any non-zero norm
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> opacities [N] in [0, 1], scales [N, 3], unit quats [N, 4]; float64 (caller casts).

    Raises ValueError naming the first zero-length quaternion.
    """
    rots = np.asarray(rots, dtype=np.float64)
    norm = np.linalg.norm(rots, axis=-1, keepdims=True)  # [N, 1]
    if rots.shape[0] and not np.all(norm > 0):
        bad = int(np.flatnonzero(~(norm[:, 0] > 0))[0])
        raise ValueError(f"rot_0..3 of vertex {bad} is a zero quaternion")
    return _sigmoid(opacity_logit), np.exp(np.asarray(log_scales, dtype=np.float64)), rots / norm


def activated_to_stored(
    opacities: np.ndarray,  # [N] in [0, 1]
    scales: np.ndarray,  # [N, 3] > 0
    quats: np.ndarray,  # [N, 4] (w, x, y, z)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> opacity logits [N] (after clamping to [1e-7, 1 - 1e-7]), log scales [N, 3],
    unit quats [N, 4]; float64."""
    quats = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(quats, axis=-1, keepdims=True)  # [N, 1]
    return _logit(opacities), np.log(np.asarray(scales, dtype=np.float64)), quats / norm


def sh_from_ply_columns(f_dc: np.ndarray, f_rest: np.ndarray) -> np.ndarray:
    """f_dc [N, 3], f_rest [N, 3 * (K - 1)] channel-major -> sh [N, K, 3]."""
    n = f_dc.shape[0]
    rest = f_rest.reshape(n, 3, f_rest.shape[1] // 3).transpose(0, 2, 1)  # [N, K - 1, 3]
    return np.concatenate([f_dc[:, None, :], rest], axis=1)


def sh_to_ply_columns(sh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sh [N, K, 3] -> f_dc [N, 3], f_rest [N, 3 * (K - 1)] channel-major (R's, then G's, B's)."""
    n = sh.shape[0]
    return sh[:, 0, :], sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (sh.shape[1] - 1))


# --------------------------------------------------------------------------------------------
# reading


MAX_HEADER_BYTES = 1 << 20


def _check_counts(path: Path, f) -> None:
    """The header's element counts must fit in the bytes the file holds (a 1 KB file claiming
    10^9 vertices is refused before anything is allocated)."""
    import io

    import plyfile

    head = f.read(MAX_HEADER_BYTES)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise DlaInputError(path, "not a valid PLY file (no 'ply' magic or no end_header in the first 1 MiB)")
    end = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
    try:
        header = plyfile.PlyData._parse_header(io.BytesIO(head[:end]))
    except plyfile.PlyHeaderParseError as err:
        raise DlaInputError(path, f"not a valid PLY file ({one_line(err)})") from None
    body = os.fstat(f.fileno()).st_size - end
    need = 0
    for el in header.elements:
        row = 0
        for prop in el.properties:
            if isinstance(prop, plyfile.PlyListProperty):
                len_dtype, _ = prop.list_dtype()
                row += 2 if header.text else np.dtype(len_dtype).itemsize
            else:
                row += 2 if header.text else np.dtype(prop.dtype()).itemsize
        need += el.count * max(row, 1)
    if need > body:
        counts = one_line(", ".join(f"{el.count} {el.name}" for el in header.elements))
        raise DlaInputError(
            path, f"header declares {counts}, which needs at least {need} bytes, but the file holds {max(body, 0)}"
        )
    f.seek(0)


def _open(path: Path):
    """PlyData with its data read into memory, or a one-line DlaInputError."""
    import plyfile

    from dlacli.io.files import open_input

    try:
        with open_input(path) as f:
            _check_counts(path, f)
            return plyfile.PlyData.read(f, mmap=False)
    except plyfile.PlyHeaderParseError as err:
        raise DlaInputError(path, f"not a valid PLY file ({one_line(err)})") from None
    except plyfile.PlyParseError as err:
        raise DlaInputError(path, f"malformed or truncated PLY data ({one_line(err)})") from None
    except (ValueError, EOFError, OSError, UnicodeDecodeError, IndexError) as err:
        raise DlaInputError(path, f"unreadable PLY file ({type(err).__name__}: {one_line(err)})") from None


def _sh_degree_from_rest(path: Path, names: list[str]) -> int:
    rest = [n for n in names if n.startswith("f_rest_")]
    expected = {f"f_rest_{i}" for i in range(len(rest))}
    if set(rest) != expected:
        raise DlaInputError(path, "f_rest_* properties are not numbered 0..n-1 without gaps")
    if len(rest) % 3 or len(rest) // 3 not in _REST_PER_CHANNEL:
        raise DlaInputError(path, f"{len(rest)} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)")
    return _REST_PER_CHANNEL[len(rest) // 3]


def _column(path: Path, vertex, name: str) -> np.ndarray:
    values = np.asarray(vertex.data[name], dtype=np.float64)  # [N]
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise DlaInputError(path, f"property {excerpt(name)} is {values[bad]} at vertex {bad} (NaN/Inf)")
    return values


def _read(path: Path) -> tuple[Any, tuple[np.ndarray, ...], list[str]]:
    """(PlyData, float32 (means [N, 3], quats [N, 4], scales [N, 3], opacities [N], sh [N, K, 3])
    activated, extra property names); numpy only, so `dla info` needs no torch."""
    ply = _open(path)
    if "vertex" not in [el.name for el in ply.elements]:
        raise DlaInputError(path, "no 'vertex' element (not a Gaussians .ply)")
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    for prop in vertex.properties:
        if prop.name in ("x", "y", "z") or prop.name.startswith(("f_", "scale_", "rot_", "opacity")):
            if getattr(prop, "len_dtype", None) is not None:  # a list property
                raise DlaInputError(path, f"property {excerpt(prop.name)} is a list, expected a scalar")
    degree = _sh_degree_from_rest(path, names)
    needed = property_names(degree)
    for name in needed:
        if name in _NORMALS:
            continue
        if name not in names:
            raise DlaInputError(path, f"missing vertex property {name!r}")

    def cols(keys) -> np.ndarray:  # [N, len(keys)] float64
        if not keys:
            return np.zeros((vertex.count, 0))
        return np.stack([_column(path, vertex, k) for k in keys], axis=-1)

    means = cols(("x", "y", "z"))  # [N, 3]
    f_dc = cols(("f_dc_0", "f_dc_1", "f_dc_2"))  # [N, 3]
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    f_rest = cols([f"f_rest_{i}" for i in range(n_rest)])  # [N, n_rest]
    logits = cols(("opacity",))[:, 0]  # [N]
    log_scales = cols(("scale_0", "scale_1", "scale_2"))  # [N, 3]
    rots = cols(("rot_0", "rot_1", "rot_2", "rot_3"))  # [N, 4]
    check_log_scales(log_scales, path, "scale_0..2")  # exp stays finite in float32, and sane
    try:
        opacities, scales, quats = stored_to_activated(logits, log_scales, rots)
    except ValueError as err:
        raise DlaInputError(path, str(err)) from None
    sh = sh_from_ply_columns(f_dc, f_rest)  # [N, K, 3]

    arrays = tuple(np.ascontiguousarray(a, dtype=np.float32) for a in (means, quats, scales, opacities, sh))
    extras = [n for n in names if n not in needed]
    return ply, arrays, extras


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS .ply (binary little/big endian or ascii) into activated float32 Gaussians.

    Unknown extra properties are ignored, float64 properties accepted, normals optional.
    """
    import torch

    return Gaussians(*(torch.from_numpy(a) for a in _read(Path(path))[1]))


def _encoding(ply) -> str:
    if ply.text:
        return "ascii"
    order = ply.byte_order
    if order == "=":
        order = "<" if sys.byteorder == "little" else ">"
    return "binary_little_endian" if order == "<" else "binary_big_endian"


def summarize_ply(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of a Gaussians .ply (used by `dla info`)."""
    path = Path(path)
    ply, (means, _, scales, opacities, sh), extras = _read(path)
    return {
        "kind": "gaussians.ply",
        "format": "3dgs-ply (INRIA)",
        **gaussian_stats(means, scales, opacities, sh_degree_for_coeffs(sh.shape[1])),
        "encoding": _encoding(ply),
        "extra_properties": extras,
    }


def gaussian_stats(means: np.ndarray, scales: np.ndarray, opacities: np.ndarray, sh_degree: int) -> dict[str, Any]:
    """The numbers `dla info` shows for any splat file: count, SH degree, bounding box, mean
    opacity and the (lower) median of all scales."""
    n = means.shape[0]
    means = np.asarray(means, np.float64)
    scales = np.sort(np.asarray(scales, np.float64), axis=None)
    return {
        "count": n,
        "sh_degree": sh_degree,
        "bbox_min": means.min(axis=0).tolist() if n else None,
        "bbox_max": means.max(axis=0).tolist() if n else None,
        "opacity_mean": float(np.asarray(opacities, np.float64).mean()) if n else None,
        "scale_median": float(scales[(scales.size - 1) // 2]) if n else None,  # the lower median
    }


# --------------------------------------------------------------------------------------------
# writing


def _as_numpy(name: str, value, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    torch = sys.modules.get("torch")  # a tensor exists only once torch is imported
    if torch is not None and isinstance(value, torch.Tensor):
        value = value.detach().cpu().double().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail or (n is not None and arr.shape[0] != n):
        want = "[" + ", ".join(["N" if n is None else str(n), *map(str, shape_tail)]) + "]"
        raise DlaInputError(f"gaussians.{name}", f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise DlaInputError(f"gaussians.{name}", "contains NaN or Inf")
    return arr


def write_ply(gaussians: Gaussians, path: str | os.PathLike) -> None:
    """Write Gaussians as a binary little-endian float32 INRIA 3DGS .ply (atomically).

    Normals are written as zeros; opacities are clamped to [1e-7, 1 - 1e-7] before the logit;
    quaternions are normalised. Scales must be > 0.
    """
    import plyfile

    if not isinstance(gaussians, Gaussians):
        raise DlaInputError("gaussians", f"expected a Gaussians, got {type(gaussians).__name__}")
    means = _as_numpy("means", gaussians.means, (3,), None)  # [N, 3]
    n = means.shape[0]
    quats = _as_numpy("quats", gaussians.quats, (4,), n)  # [N, 4]
    scales = _as_numpy("scales", gaussians.scales, (3,), n)  # [N, 3]
    opacities = _as_numpy("opacities", gaussians.opacities, (), n)  # [N]
    k = gaussians.sh.shape[1]
    sh = _as_numpy("sh", gaussians.sh, (k, 3), n)  # [N, K, 3]
    if np.any(scales <= 0):
        raise DlaInputError("gaussians.scales", "scales must be > 0 (they are stored as logs)")
    if np.any(np.linalg.norm(quats, axis=-1) == 0):
        raise DlaInputError("gaussians.quats", "contains a zero quaternion")
    logits, log_scales, unit_quats = activated_to_stored(opacities, scales, quats)
    f_dc, f_rest = sh_to_ply_columns(sh)

    names = property_names(gaussians.sh_degree)
    columns = np.concatenate(
        [means, np.zeros((n, 3)), f_dc, f_rest, logits[:, None], log_scales, unit_quats], axis=1
    ).astype("<f4")  # [N, P]
    assert columns.shape[1] == len(names)
    data = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        data[name] = columns[:, i]
    element = plyfile.PlyElement.describe(data, "vertex")
    with atomic_path(path) as tmp:
        plyfile.PlyData([element], text=False, byte_order="<").write(str(tmp))
