"""antimatter15 `.splat`: 32 bytes a Gaussian, no header (formats/splat.md).

Record (little-endian): position 3 x float32, scale 3 x float32 (linear standard deviations),
colour R, G, B, A as uint8 (rgb = 0.5 + SH_C0 f_dc clamped to [0, 1], A = opacity), rotation
4 x uint8 (w, x, y, z) quantised as round(q * 128 + 128) clipped to [0, 255]. SH above degree 0 is
dropped. Records are sorted by size x opacity, largest first (the order antimatter15's converter
writes and its viewer streams in), unless `sort=False`.

The writer takes Gaussians in the file's own coordinates (the stage picks them, see
docs/export.md); `checked_arrays` is the shared validation the other splat writers use too.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.atomic import atomic_path
from dlacli.io.validate import check_log_scales
from dlacli.types import SH_C0, Gaussians

RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))])
assert RECORD.itemsize == 32


def _numpy(name: str, value, tail: tuple[int, ...], n: int | None) -> np.ndarray:
    torch = sys.modules.get("torch")  # a tensor exists only once torch is imported
    if torch is not None and isinstance(value, torch.Tensor):
        value = value.detach().cpu().double().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1 + len(tail) or arr.shape[1:] != tail or (n is not None and arr.shape[0] != n):
        want = "[" + ", ".join(["N" if n is None else str(n), *map(str, tail)]) + "]"
        raise DlaInputError(f"gaussians.{name}", f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise DlaInputError(f"gaussians.{name}", "contains NaN or Inf")
    return arr


def checked_arrays(gaussians: Gaussians) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """float64 numpy (means [N, 3], unit quats [N, 4] (w, x, y, z), scales [N, 3] > 0,
    opacities [N] clipped to [0, 1], sh [N, K, 3]) of one set of Gaussians, or a DlaInputError."""
    if not isinstance(gaussians, Gaussians) or gaussians.batch_shape:
        raise DlaInputError("gaussians", "expected one set of Gaussians (no batch dimensions)")
    means = _numpy("means", gaussians.means, (3,), None)  # [N, 3]
    n = means.shape[0]
    quats = _numpy("quats", gaussians.quats, (4,), n)  # [N, 4]
    scales = _numpy("scales", gaussians.scales, (3,), n)  # [N, 3]
    opacities = _numpy("opacities", gaussians.opacities, (), n)  # [N]
    sh = _numpy("sh", gaussians.sh, (gaussians.sh.shape[-2], 3), n)  # [N, K, 3]
    if np.any(scales <= 0):
        raise DlaInputError("gaussians.scales", "scales must be > 0")
    norm = np.linalg.norm(quats, axis=-1, keepdims=True)  # [N, 1]
    if np.any(norm == 0):
        raise DlaInputError("gaussians.quats", "contains a zero quaternion")
    return means, quats / norm, scales, np.clip(opacities, 0.0, 1.0), sh


def to_u8(x: np.ndarray) -> np.ndarray:
    """Round half away from zero (C's `round`, what the reference encoders use) and clip to [0, 255]."""
    return np.clip(np.sign(x) * np.floor(np.abs(x) + 0.5), 0, 255).astype(np.uint8)


def size_opacity_order(scales: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """[N] indices, largest s_x s_y s_z x opacity first (stable for ties)."""
    return np.argsort(-(np.prod(scales, axis=-1) * opacities), kind="stable")


def encode_splat(gaussians: Gaussians, sort: bool = True) -> np.ndarray:
    """[N] RECORD structured array of the Gaussians (sorted by size x opacity unless sort=False)."""
    means, quats, scales, opacities, sh = checked_arrays(gaussians)
    rgb = np.clip(0.5 + SH_C0 * sh[:, 0, :], 0.0, 1.0)  # [N, 3]
    quats = np.where(quats[:, :1] < 0, -quats, quats)  # q and -q are one rotation: w >= 0
    rec = np.empty(means.shape[0], dtype=RECORD)
    rec["position"] = means
    rec["scale"] = scales
    rec["rgba"] = to_u8(np.concatenate([rgb, opacities[:, None]], axis=1) * 255.0)
    rec["rot"] = to_u8(quats * 128.0 + 128.0)
    if not np.all(np.isfinite(rec["scale"])) or np.any(rec["scale"] <= 0):
        raise DlaInputError("gaussians.scales", "a scale is outside float32's range")
    return rec[size_opacity_order(scales, opacities)] if sort else rec


def write_splat(gaussians: Gaussians, path: str | os.PathLike, sort: bool = True) -> None:
    """Write a .splat file (atomically); see the module docstring for the layout."""
    rec = encode_splat(gaussians, sort=sort)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(rec.tobytes())


def decode_splat(data: bytes, where: str | os.PathLike = "splat") -> dict[str, np.ndarray]:
    """Arrays of a .splat file's bytes, float32: means [N, 3], scales [N, 3], rgb [N, 3],
    opacities [N], quats [N, 4] (w, x, y, z), decoded as antimatter15's viewer does:
    (byte - 128) / 128, then normalised."""
    if len(data) % RECORD.itemsize:
        raise DlaInputError(where, f"{len(data)} bytes is not a whole number of 32-byte .splat records")
    rec = np.frombuffer(data, dtype=RECORD)
    q = (rec["rot"].astype(np.float64) - 128.0) / 128.0  # [N, 4]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise DlaInputError(where, f"record {int(np.flatnonzero(norm[:, 0] == 0)[0])} has a zero rotation")
    rgba = rec["rgba"].astype(np.float32) / 255.0
    out = {
        "means": rec["position"].astype(np.float32),
        "scales": rec["scale"].astype(np.float32),
        "rgb": rgba[:, :3],
        "opacities": rgba[:, 3],
        "quats": (q / norm).astype(np.float32),
    }
    for name in ("means", "scales"):
        if not np.all(np.isfinite(out[name])):
            raise DlaInputError(where, f"a record's {name[:-1]} is NaN or Inf")
    if np.any(out["scales"] <= 0):
        raise DlaInputError(where, "a record's scale is <= 0")
    check_log_scales(np.log(out["scales"].astype(np.float64)), where, "scale")  # the .ply's range of sizes
    return out


def read_splat(path: str | os.PathLike) -> Gaussians:
    """Read a .splat file into SH-degree-0 Gaussians (activated values, float32)."""
    import torch

    from dlacli.io.files import read_bytes

    a = decode_splat(read_bytes(path), path)
    t = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in a.items()}
    return Gaussians.from_rgb(t["means"], t["quats"], t["scales"], t["opacities"], t["rgb"])


def summarize_splat(path: str | os.PathLike) -> dict:
    """JSON-able summary of a .splat (used by `dla info`)."""
    from dlacli.io.files import read_bytes
    from dlacli.io.ply import gaussian_stats

    a = decode_splat(read_bytes(path), path)
    return {
        "kind": "gaussians.splat",
        "format": "splat (antimatter15, 32 bytes a splat)",
        **gaussian_stats(a["means"], a["scales"], a["opacities"], 0),
    }
