"""avatar.npz: an avatar code Z aligned with the body's UV space (formats/avatar.md).

Float maps (z, canonical) are stored as float16 when that is lossless enough (`half_if_lossless`),
else float32; readers always return float32.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, excerpts
from dlacli.io.body import body_from_dict, body_to_dict
from dlacli.io.validate import (
    as_str,
    check_finite,
    check_format,
    check_log_scales,
    check_shape,
    load_npz,
    parse_json,
    save_npz,
)
from dlacli.types import F_CHANNELS, F_LOG_SCALE, Avatar

# z and canonical together: a 14 x 2048^2 float32 map (the largest --resolution) is 235 MB, the
# paper's Z (256 x 64^2) 4 MB; an avatar.npz unpacking to more is refused unread.
MAX_UNPACKED = 320 * 2**20

FORMAT = "dla.avatar/1"
KEYS = ("format", "z", "encoder", "decoder", "checkpoint", "body", "uv_layout")
OPTIONAL_KEYS = ("canonical", "extra")
LOG_SCALES = f"channels {F_LOG_SCALE.start}-{F_LOG_SCALE.stop - 1}, log scale"  # F's, as messages name them
MAP_DECODERS = ("identity", "view-cosine")  # decoders whose z holds F's channels 0-13 (formats/avatar.md)
# float16 storage rule: max |float16(a) - a| <= FLOAT16_RTOL * max |a|, and nothing overflows.
FLOAT16_RTOL = 1e-3
_SHA256 = re.compile(r"[0-9a-f]{64}")


def half_if_lossless(a: np.ndarray, rtol: float = FLOAT16_RTOL) -> np.ndarray:
    """`a` (finite float) as float16 if max |f16(a) - a| <= rtol * max |a| and no value overflows,
    else as float32.

    float16 keeps ~11 significant bits (relative error <= 2^-11 ~ 4.9e-4) for |a| in its normal
    range [6.1e-5, 65504]; the rule sends to float32 any array with a value that overflows float16
    (|a| > 65504) or whose small values lose more than rtol of the array's largest magnitude
    (e.g. an array whose every value is below ~1e-5).
    """
    a32 = np.asarray(a, dtype=np.float32)
    with np.errstate(over="ignore"):
        a16 = a32.astype(np.float16)
    if not np.all(np.isfinite(a16)):
        return a32
    if a32.size == 0:
        return a16
    err = float(np.max(np.abs(a16.astype(np.float32) - a32)))
    return a16 if err <= rtol * float(np.max(np.abs(a32))) else a32


def avatar_from_arrays(data: dict[str, Any], where: Any) -> Avatar:
    """Validate the arrays of an avatar.npz (as loaded by np.load) and build an Avatar."""
    check_format(as_str(data["format"], where, "format") if "format" in data else None, FORMAT, where)
    missing = [k for k in KEYS if k not in data]
    if missing:
        raise DlaInputError(where, f"missing array{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}")
    unknown = sorted(set(data) - set(KEYS) - set(OPTIONAL_KEYS))
    if unknown:
        raise DlaInputError(
            where, f"unknown array{'s' if len(unknown) > 1 else ''} {excerpts(unknown)} (put project data in 'extra')"
        )

    z = _float_map(data["z"], where, "z")
    check_shape(z, (None, None, None), where, "z")
    if 0 in z.shape:
        raise DlaInputError(where, f"z has an empty shape {z.shape}")
    if z.shape[1] != z.shape[2]:
        raise DlaInputError(where, f"z has shape {z.shape}; a UV map is square (C, R, R)")
    encoder = as_str(data["encoder"], where, "encoder")
    decoder = as_str(data["decoder"], where, "decoder")
    if decoder in MAP_DECODERS:  # z is the Gaussian map F itself: its log-scales are read as such
        check_log_scales(z[F_LOG_SCALE], where, f"z ({LOG_SCALES})")
    uv_layout = as_str(data["uv_layout"], where, "uv_layout")
    checkpoint = as_str(data["checkpoint"], where, "checkpoint", allow_empty=True)
    if checkpoint and not _SHA256.fullmatch(checkpoint):
        raise DlaInputError(where, f"checkpoint {excerpt(checkpoint)} is neither '' nor a lower-case sha256 hex digest")
    body = body_from_dict(_json_object(data["body"], where, "body"), f"{where}:body")

    canonical = None
    if "canonical" in data:
        canonical = _float_map(data["canonical"], where, "canonical")
        check_shape(canonical, (F_CHANNELS, None, None), where, "canonical")
        if 0 in canonical.shape:
            raise DlaInputError(where, f"canonical has an empty shape {canonical.shape}")
        if canonical.shape[1] != canonical.shape[2]:
            raise DlaInputError(
                where, f"canonical has shape {canonical.shape}; a UV map is square ({F_CHANNELS}, R, R)"
            )
        check_log_scales(canonical[F_LOG_SCALE], where, f"canonical ({LOG_SCALES})")
    extra = _json_object(data["extra"], where, "extra") if "extra" in data else {}
    return Avatar(z, encoder, decoder, body, uv_layout, checkpoint, canonical, extra)


def _float_map(value: Any, where: Any, name: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind != "f":
        raise DlaInputError(where, f"{name} must be float16 or float32, found dtype {arr.dtype}")
    with np.errstate(over="ignore"):
        arr = arr.astype(np.float32)  # a float64 beyond float32's range becomes inf: refused here
    check_finite(arr, where, name)
    return arr


def _json_object(value: Any, where: Any, name: str) -> dict[str, Any]:
    obj = parse_json(as_str(value, where, name), where, name)
    if not isinstance(obj, dict):
        raise DlaInputError(where, f"{name} must be a JSON object, found {type(obj).__name__}")
    return obj


def read_avatar(path: str | os.PathLike) -> Avatar:
    """Read and validate an avatar.npz; z and canonical come back float32."""
    return avatar_from_arrays(load_npz(path, MAX_UNPACKED), Path(path))


def avatar_to_arrays(avatar: Avatar) -> dict[str, np.ndarray]:
    """The arrays written to avatar.npz (float maps already through `half_if_lossless`)."""
    z = np.asarray(avatar.z)  # [C, H, W]
    if z.dtype.kind not in "fiu":
        raise DlaInputError("avatar.z", f"must be numeric, found dtype {z.dtype}")
    check_finite(z.astype(np.float64), "avatar", "z")  # before the cast, so float32 overflow is caught too
    arrays = {
        "format": np.array(FORMAT),
        "z": half_if_lossless(z),
        "encoder": np.array(str(avatar.encoder)),
        "decoder": np.array(str(avatar.decoder)),
        "checkpoint": np.array(str(avatar.checkpoint or "")),
        "body": np.array(json.dumps(body_to_dict(avatar.body), separators=(",", ":"))),
        "uv_layout": np.array(str(avatar.uv_layout)),
    }
    if avatar.canonical is not None:
        canonical = np.asarray(avatar.canonical)  # [14, H', W']
        if canonical.dtype.kind not in "fiu":
            raise DlaInputError("avatar.canonical", f"must be numeric, found dtype {canonical.dtype}")
        check_finite(canonical.astype(np.float64), "avatar", "canonical")
        arrays["canonical"] = half_if_lossless(canonical)
    if avatar.extra:
        try:
            arrays["extra"] = np.array(json.dumps(avatar.extra, allow_nan=False, separators=(",", ":")))
        except (TypeError, ValueError) as err:
            raise DlaInputError("avatar.extra", f"is not JSON-serialisable ({err})") from None
    return arrays


def write_avatar(avatar: Avatar, path: str | os.PathLike) -> None:
    """Write `avatar` as avatar.npz (compressed, atomic); an invalid avatar raises DlaInputError."""
    arrays = avatar_to_arrays(avatar)
    avatar_from_arrays(arrays, "avatar")  # the writer never produces a file its reader rejects
    save_npz(arrays, path)


def summarize_avatar(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of an avatar.npz."""
    data = load_npz(path, MAX_UNPACKED)
    a = avatar_from_arrays(data, Path(path))
    z64 = a.z.astype(np.float64)
    out = {
        "kind": "avatar",
        "format": FORMAT,
        "z_shape": list(a.z.shape),
        "z_stored_dtype": str(data["z"].dtype),
        "z_min": float(z64.min()),
        "z_max": float(z64.max()),
        "z_mean": float(z64.mean()),
        "z_std": float(z64.std()),  # float64: a finite float32 z up to 3.4e38 squares without overflow
        "encoder": a.encoder,
        "decoder": a.decoder,
        "checkpoint": a.checkpoint,
        "uv_layout": a.uv_layout,
        "body_phenotype": dict(a.body.phenotype),
        "posed_bones": len(a.body.pose),
        "canonical_shape": None if a.canonical is None else list(a.canonical.shape),
        "extra_keys": sorted(a.extra),
        "file_bytes": Path(path).stat().st_size,
    }
    return out
