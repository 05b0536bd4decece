"""AMASS motion .npz files (SMPL-H / SMPL-X / SMPL poses), read into a `SkeletonMotion`.

Keys: `poses` [T, 156] (SMPL-H: root + 21 body + 2 x 15 hand joints), [T, 165] (SMPL-X: root +
21 body + jaw + 2 eyes + 2 x 15 hand joints) or [T, 72] (SMPL: root + 23 joints), axis-angles in
radians; `trans` [T, 3] metres; `mocap_framerate` or `mocap_frame_rate`; optional `betas`,
`gender`. Only the 22 body joints are read (hands, jaw and eyes have no counterpart that this
toolkit animates). A `poses` of 3 x J values with J <= 22 is read as the first J body joints
(the retargeting then refuses the bones it lacks unless missing joints are allowed). Frame rates
above 1000 fps, poses beyond 1e4 rad and trans beyond 1e5 m are refused. AMASS worlds are Z-up
and ground-registered.

No SMPL model files are needed: the skeleton's rest pose is `SMPL_REST_JOINTS`, rounded joint
locations of an average SMPL body in its canonical frame (metres, +Y up, facing +Z, the body's
left on +X). They serve for bone directions and leg length only; `betas` are ignored. The world
position of the pelvis is `trans` + the rest pelvis location (SMPL rotates about the pelvis).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.bvh import check_motion_size, clean_fps
from dlacli.io.validate import MAX_ANGLE, MAX_DISTANCE
from dlacli.types import MAX_FPS, MIN_FPS, SkeletonMotion

SMPL_JOINTS = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
)
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

# [22, 3] rounded rest joint locations of an average SMPL body (canonical frame, metres)
SMPL_REST_JOINTS = np.array(
    [
        [0.00, -0.22, 0.03],
        [0.07, -0.31, 0.02],
        [-0.07, -0.31, 0.02],
        [0.00, -0.10, 0.01],
        [0.10, -0.68, 0.02],
        [-0.10, -0.68, 0.02],
        [0.00, 0.03, 0.03],
        [0.09, -1.10, -0.02],
        [-0.09, -1.10, -0.02],
        [0.00, 0.08, 0.03],
        [0.12, -1.16, 0.10],
        [-0.12, -1.16, 0.10],
        [0.00, 0.29, -0.01],
        [0.08, 0.20, -0.01],
        [-0.08, 0.20, -0.01],
        [0.00, 0.39, 0.03],
        [0.17, 0.22, -0.02],
        [-0.17, 0.22, -0.02],
        [0.43, 0.21, -0.04],
        [-0.43, 0.21, -0.04],
        [0.69, 0.22, -0.04],
        [-0.69, 0.22, -0.04],
    ]
)
# end sites: toe tips, head top, hand middles (offsets from their joints)
SMPL_END_SITES = {
    10: np.array([0.0, -0.02, 0.08]),
    11: np.array([0.0, -0.02, 0.08]),
    15: np.array([0.0, 0.15, 0.0]),
    20: np.array([0.09, 0.0, 0.0]),
    21: np.array([-0.09, 0.0, 0.0]),
}

LAYOUTS = {156: "smplh", 165: "smplx", 72: "smpl"}
FRAMERATE_KEYS = ("mocap_framerate", "mocap_frame_rate")


def axis_angle_matrices(aa: np.ndarray) -> np.ndarray:
    """Rodrigues: [..., 3] axis-angles (radians) -> [..., 3, 3] rotation matrices (float64)."""
    aa = np.asarray(aa, dtype=np.float64)
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)  # [..., 1]
    small = theta < 1e-12
    axis = aa / np.where(small, 1.0, theta)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(aa.shape[:-1] + (3, 3))
    s = np.sin(theta)[..., None]
    c = np.cos(theta)[..., None]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + s * k + (1.0 - c) * (k @ k)


def _load(path: Path) -> dict[str, np.ndarray]:
    """All arrays, through the shared npz loader: regular files only, no pickles, zip members and
    .npy headers checked against a cap before numpy allocates anything (`dlacli.io.npz_bounds`)."""
    from dlacli.io.validate import load_npz

    return load_npz(path)


def _layout(width: int) -> tuple[str, int]:
    """(layout name, number of SMPL body joints read) for `poses` of `width` values per frame."""
    if width in LAYOUTS:
        return LAYOUTS[width], len(SMPL_JOINTS)
    if 0 < width <= 3 * len(SMPL_JOINTS) and width % 3 == 0:
        return f"smpl body, first {width // 3} joints", width // 3
    raise ValueError(width)


def read_amass(path: str | os.PathLike) -> SkeletonMotion:
    """Read an AMASS npz (see the module docstring); bad content raises DlaInputError."""
    path = Path(path)
    data = _load(path)
    if "poses" not in data:
        raise DlaInputError(path, "no 'poses' array (not an AMASS motion)")
    poses = np.asarray(data["poses"])
    if poses.dtype.kind not in "fiu" or poses.ndim != 2:
        raise DlaInputError(path, f"poses must be a numeric [T, 156|165|72] array, got {poses.dtype} {poses.shape}")
    try:
        _, joints = _layout(poses.shape[1])
    except ValueError:
        raise DlaInputError(
            path,
            f"poses has {poses.shape[1]} values per frame; supported: 156 (SMPL-H), 165 (SMPL-X), 72 (SMPL), "
            "or 3 x J for the first J <= 22 SMPL body joints",
        ) from None
    t = poses.shape[0]
    if t == 0:
        raise DlaInputError(path, "poses has no frames (T = 0)")
    check_motion_size(path, t, joints)
    if "trans" not in data:
        raise DlaInputError(path, "no 'trans' array (root translation [T, 3])")
    trans = np.asarray(data["trans"])
    if trans.dtype.kind not in "fiu" or trans.shape != (t, 3):
        raise DlaInputError(path, f"trans has shape {trans.shape}, expected ({t}, 3)")
    for name, arr, most in (("poses", poses, MAX_ANGLE), ("trans", trans, MAX_DISTANCE)):  # radians, metres
        if not np.all(np.isfinite(arr)):
            raise DlaInputError(
                path, f"{name} holds non-finite values (first at frame {np.argwhere(~np.isfinite(arr))[0][0]})"
            )
        largest = float(np.abs(arr.astype(np.float64)).max()) if arr.size else 0.0  # float16: no overflow on compare
        if largest > most:
            raise DlaInputError(path, f"{name} holds values beyond +-{most:g} (largest {largest:g}): not a motion")
    key = next((k for k in FRAMERATE_KEYS if k in data), None)
    if key is None:
        raise DlaInputError(path, f"no frame rate ({' or '.join(FRAMERATE_KEYS)})")
    try:
        fps = float(np.asarray(data[key]).reshape(()))
    except (TypeError, ValueError):
        raise DlaInputError(path, f"{key} must be one number, got shape {np.shape(data[key])}") from None
    if not np.isfinite(fps) or fps <= 0:
        raise DlaInputError(path, f"{key} = {fps} must be > 0")
    if fps < MIN_FPS:
        raise DlaInputError(path, f"{key} = {fps:g} is below {MIN_FPS:g} fps (not supported)")
    if fps > MAX_FPS:
        raise DlaInputError(path, f"{key} = {fps:g} is above {MAX_FPS:g} fps (not supported)")

    # fewer joints than the 22 body joints (a cut layout): the first ones, in SMPL order; the
    # retargeting then refuses the bones they lack unless told to leave them at rest
    body = poses[:, : 3 * joints].astype(np.float64).reshape(t, joints, 3)
    parents = np.array(SMPL_PARENTS[:joints], dtype=np.int64)
    rest = SMPL_REST_JOINTS[:joints]
    offsets = rest.copy()
    offsets[1:] -= rest[parents[1:]]
    return SkeletonMotion(
        names=list(SMPL_JOINTS[:joints]),
        parents=parents,
        offsets=offsets,
        rotations=axis_angle_matrices(body),
        root_positions=trans.astype(np.float64) + SMPL_REST_JOINTS[0],
        fps=clean_fps(fps),
        up="z",
        metres_per_unit=1.0,
        units="m",
        source=str(path),
        end_sites={k: v.copy() for k, v in SMPL_END_SITES.items() if k < joints},
        dialect="smpl",
    )


def summarize_amass(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of an AMASS npz (for `dla info`)."""
    skel = read_amass(path)
    data = _load(Path(path))
    width = int(np.asarray(data["poses"]).shape[1])
    out = {
        "kind": "amass",
        "format": f"amass ({_layout(width)[0]}, {width} pose values)",
        "frames": skel.num_frames,
        "fps": skel.fps,
        "duration_s": (skel.num_frames - 1) / skel.fps,
        "root_travel_m": float(np.linalg.norm(skel.root_positions[-1] - skel.root_positions[0])),
    }
    if "gender" in data:
        out["gender"] = str(np.asarray(data["gender"]))
    if "betas" in data:
        out["betas"] = int(np.asarray(data["betas"]).size)
    return out
