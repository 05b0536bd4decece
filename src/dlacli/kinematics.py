"""Skeleton kinematics in numpy: Euler-angle rotations, forward kinematics, rest poses.

Bottom layer (next to `dlacli.geometry`): plain maths on `dlacli.types.SkeletonMotion`, used by
the motion readers in `dlacli.io` (BVH, ASF/AMC) and by the retargeting in `dlacli.body`. The
convention of a `SkeletonMotion` (docs/motion.md):

- joint j sits at its parent's position plus `offsets[j]` rotated by the parent's world rotation;
- `rotations[t, j]` is joint j's *local* rotation matrix: its world rotation is
  G_j = G_parent @ rotations[t, j], and G_j rotates everything below j about j's position.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dlacli.types import SkeletonMotion


def euler_matrices(angles: np.ndarray, axes: str) -> np.ndarray:
    """Rotation matrices R = R_axes[0] @ R_axes[1] @ ... (first listed is outermost).

    angles [T, K] radians, axes a string of K letters from "xyz" -> [T, 3, 3] float64.
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), (angles.shape[0], 3, 3)).copy()
    for k, axis in enumerate(axes):
        out = out @ axis_rotation(axis, angles[:, k])
    return out


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """Right-handed rotations about a coordinate axis: angle [T] radians -> [T, 3, 3]."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(angle.shape + (3, 3))
    i = "xyz".index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    m[..., i, i] = 1.0
    m[..., j, j] = c
    m[..., k, k] = c
    m[..., j, k] = -s
    m[..., k, j] = s
    return m


def forward_kinematics(skel: SkeletonMotion, frames: np.ndarray | None = None):
    """World rotations [T, J, 3, 3] and positions [T, J, 3] (file units) of every joint.

    A plain loop over joints; `frames` [T'] selects frames (all by default).
    """
    idx = np.arange(skel.num_frames) if frames is None else np.asarray(frames)
    local = skel.rotations[idx]  # [T, J, 3, 3]
    t, j = local.shape[:2]
    glob = np.empty_like(local)
    pos = np.empty((t, j, 3))
    for k in range(j):
        p = skel.parents[k]
        if p < 0:
            glob[:, k] = local[:, k]
            pos[:, k] = skel.root_positions[idx]
        else:
            glob[:, k] = glob[:, p] @ local[:, k]
            pos[:, k] = pos[:, p] + glob[:, p] @ skel.offsets[k]
    return glob, pos


def rest_positions(skel: SkeletonMotion) -> np.ndarray:
    """[J, 3] joint positions in the rest pose with the root at the origin (file units)."""
    pos = np.zeros((skel.num_joints, 3))
    for k in range(skel.num_joints):
        p = skel.parents[k]
        if p >= 0:
            pos[k] = pos[p] + skel.offsets[k]
    return pos


def rest_height(skel: SkeletonMotion) -> float:
    """Extent of the rest skeleton (joints and End Sites) along its up axis, file units."""
    rest = rest_positions(skel)
    ends = [rest[k] + e for k, e in skel.end_sites.items()]
    return float(np.ptp(np.vstack([rest, *ends])[:, "xyz".index(skel.up)]))
