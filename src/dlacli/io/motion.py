"""motion.npz: a motion clip on the body model's rig (formats/motion.md).

Strings are stored as numpy unicode arrays and read with allow_pickle=False: no pickles.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, excerpts
from dlacli.io.validate import (
    MAX_ANGLE,
    MAX_DISTANCE,
    as_float,
    as_str,
    check_finite,
    check_format,
    check_magnitude,
    check_shape,
    load_npz,
    save_npz,
)
from dlacli.types import MAX_FPS, MAX_FRAMES, MIN_FPS, Motion  # the limits every motion reader shares

FORMAT = "dla.motion/1"
MODELS = ("anny",)
KEYS = ("format", "model", "bone_labels", "rotations", "root_rotation", "root_translation", "fps")


def motion_from_arrays(data: dict[str, Any], where: Any) -> Motion:
    """Validate the arrays of a motion.npz (as loaded by np.load) and build a Motion."""
    check_format(as_str(data["format"], where, "format") if "format" in data else None, FORMAT, where)
    missing = [k for k in KEYS if k not in data]
    if missing:
        raise DlaInputError(where, f"missing array{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}")
    model = as_str(data["model"], where, "model")
    if model not in MODELS:
        raise DlaInputError(where, f"model {excerpt(model)} is not supported (supported: {', '.join(MODELS)})")

    labels = np.asarray(data["bone_labels"])
    if labels.shape == (0,):
        labels = labels.astype(np.str_)  # an empty list saved by numpy defaults to float64
    if labels.dtype.kind != "U":
        raise DlaInputError(where, f"bone_labels must be a unicode string array, found dtype {labels.dtype}")
    check_shape(labels, (None,), where, "bone_labels")
    bone_labels = [str(s) for s in labels]
    if any(not s for s in bone_labels):
        raise DlaInputError(where, "bone_labels holds an empty label")
    if len(set(bone_labels)) != len(bone_labels):
        from collections import Counter

        dup = sorted(s for s, n in Counter(bone_labels).items() if n > 1)
        raise DlaInputError(where, f"bone_labels repeats {excerpts(dup)}")
    j = len(bone_labels)

    rotations = _float_array(data["rotations"], where, "rotations")
    check_shape(rotations, (None, j, 3), where, "rotations")
    t = rotations.shape[0]
    if t < 1:
        raise DlaInputError(where, "rotations has no frames (T = 0); a motion needs at least one")
    if t > MAX_FRAMES:
        raise DlaInputError(where, f"rotations has {t:,} frames; at most {MAX_FRAMES:,} are supported")
    root_rotation = _float_array(data["root_rotation"], where, "root_rotation")
    check_shape(root_rotation, (t, 3), where, "root_rotation")
    root_translation = _float_array(data["root_translation"], where, "root_translation")
    check_shape(root_translation, (t, 3), where, "root_translation")
    for name, arr in (
        ("rotations", rotations),
        ("root_rotation", root_rotation),
        ("root_translation", root_translation),
    ):
        check_finite(arr, where, name)
    check_magnitude(rotations, MAX_ANGLE, where, "rotations", "rad")
    check_magnitude(root_rotation, MAX_ANGLE, where, "root_rotation", "rad")
    check_magnitude(root_translation, MAX_DISTANCE, where, "root_translation", "m")

    fps_arr = np.asarray(data["fps"])
    if fps_arr.shape != ():
        raise DlaInputError(where, f"fps has shape {fps_arr.shape}, expected a scalar ()")
    fps = as_float(fps_arr, where, "fps")
    if fps <= 0:
        raise DlaInputError(where, f"fps = {fps} must be > 0")
    if fps < MIN_FPS:
        raise DlaInputError(where, f"fps = {fps:g} is below {MIN_FPS:g} (not a frame rate a motion has)")
    if fps > MAX_FPS:
        raise DlaInputError(where, f"fps = {fps:g} is above {MAX_FPS:g} (not supported)")
    return Motion(bone_labels, rotations, root_rotation, root_translation, fps, model)


def _float_array(value: Any, where: Any, name: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise DlaInputError(where, f"{name} must be a numeric array, found dtype {arr.dtype}")
    with np.errstate(over="ignore"):
        return arr.astype(np.float32)  # beyond float32's range: inf, refused by the caller's check_finite


def read_motion(path: str | os.PathLike) -> Motion:
    """Read and validate a motion.npz file; arrays come back float32."""
    return motion_from_arrays(load_npz(path), Path(path))


def write_motion(motion: Motion, path: str | os.PathLike) -> None:
    """Write `motion` as a compressed motion.npz (atomic); an invalid motion raises DlaInputError."""
    arrays = {
        "format": np.array(FORMAT),
        "model": np.array(motion.model),
        "bone_labels": np.array([str(s) for s in motion.bone_labels], dtype=np.str_).reshape(-1),
        "rotations": np.asarray(motion.rotations, dtype=np.float32),
        "root_rotation": np.asarray(motion.root_rotation, dtype=np.float32),
        "root_translation": np.asarray(motion.root_translation, dtype=np.float32),
        "fps": np.array(motion.fps, dtype=np.float64),
    }
    motion_from_arrays(arrays, path)  # the writer never produces a file its reader rejects
    save_npz(arrays, path)


def summarize_motion(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of a motion.npz."""
    m = read_motion(path)
    angles = np.linalg.norm(m.rotations, axis=-1)  # [T, J]
    moving = (
        [m.bone_labels[i] for i in np.flatnonzero(np.ptp(m.rotations, axis=0).max(axis=-1) > 1e-6)]
        if m.rotations.shape[1]
        else []
    )
    return {
        "kind": "motion",
        "format": FORMAT,
        "model": m.model,
        "frames": m.num_frames,
        "fps": m.fps,
        "duration_s": (m.num_frames - 1) / m.fps,
        "bones": len(m.bone_labels),
        "bone_labels": m.bone_labels,
        "moving_bones": len(moving),
        "max_rotation_deg": float(np.degrees(angles.max())) if angles.size else 0.0,
        "root_translation_min": m.root_translation.min(axis=0).tolist(),
        "root_translation_max": m.root_translation.max(axis=0).tolist(),
    }
