"""Gaussian skinning: Gaussians stored in the body's UV tangent frames -> world Gaussians per pose.

A Gaussian attached to a surface sample point (face id + barycentrics) has its parameters in the
sample's tangent frame (docs/body.md "Tangent frames"): an offset dxyz, a rotation dR (unit
quaternion, w-first) and a scale multiplier ds. With the posed frame (T, R, S) of the sample,

    mean  = T + R dxyz
    R_g   = R dR
    scale = S ds

Offsets `dxyz` are in metres (not texel units), so a decoder's offsets mean the same thing on every
body; scales use S (metres per texel), so ds = 1 is "about one texel" wide.
Everything is vectorised over frames and differentiable (torch).
"""

from __future__ import annotations

import numpy as np
import torch

from dlacli.geometry import matrix_to_quat, quat_multiply, quat_normalize


def skin_gaussians(
    frames_T: torch.Tensor,  # [T, N, 3] sample positions
    frames_R: torch.Tensor,  # [T, N, 3, 3] columns (tangent, bitangent, normal)
    frames_S: torch.Tensor,  # [T, N] metres per texel
    dxyz: torch.Tensor,  # [N, 3] or [T, N, 3] offsets in the tangent frame, metres
    dquat: torch.Tensor,  # [N, 4] or [T, N, 4] rotations in the tangent frame, (w, x, y, z)
    ds: torch.Tensor,  # [N, 3] or [T, N, 3] scale multipliers (texel units)
    frames_q: torch.Tensor | None = None,  # [T, N, 4] matrix_to_quat(frames_R), when reused
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> means [T, N, 3], quats [T, N, 4] (w, x, y, z, unit, w >= 0 not enforced), scales [T, N, 3].

    Pass `frames_q` when the same frames are skinned many times (optimisation, animation).
    """
    if frames_T.ndim != 3 or frames_T.shape[-1] != 3:
        raise ValueError(f"frames_T must be [T, N, 3], got {tuple(frames_T.shape)}")
    t, n = frames_T.shape[:2]
    if frames_R.shape != (t, n, 3, 3):
        raise ValueError(f"frames_R must be [{t}, {n}, 3, 3], got {tuple(frames_R.shape)}")
    if frames_S.shape != (t, n):
        raise ValueError(f"frames_S must be [{t}, {n}], got {tuple(frames_S.shape)}")
    for name, x, k in (("dxyz", dxyz, 3), ("dquat", dquat, 4), ("ds", ds, 3)):
        if x.shape not in ((n, k), (t, n, k)):
            raise ValueError(f"{name} must be [{n}, {k}] or [{t}, {n}, {k}], got {tuple(x.shape)}")
    means = frames_T + (frames_R @ dxyz.expand(t, n, 3)[..., None])[..., 0]
    frame_q = matrix_to_quat(frames_R) if frames_q is None else frames_q  # [T, N, 4]
    quats = quat_normalize(quat_multiply(frame_q, dquat.expand(t, n, 4)))
    scales = frames_S[..., None] * ds.expand(t, n, 3)
    return means, quats, scales


def skin_gaussians_on_body(
    vertices: torch.Tensor,  # [T, V, 3] posed vertices (BodyOutput.vertices)
    face_id: torch.Tensor,  # [N] sample faces
    bary: torch.Tensor,  # [N, 3] sample barycentrics
    dxyz: torch.Tensor,  # [N, 3] or [T, N, 3]
    dquat: torch.Tensor,  # [N, 4] or [T, N, 4]
    ds: torch.Tensor,  # [N, 3] or [T, N, 3]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tangent frames of the posed body at the samples, then `skin_gaussians`."""
    from dlacli.body.uv import tangent_frames

    frames_T, frames_R, frames_S = tangent_frames(vertices, face_id, bary)
    return skin_gaussians(frames_T, frames_R, frames_S, dxyz, dquat, ds)


def skin_gaussians_on_body_fast(
    vertices: torch.Tensor,  # [P, V, 3] posed vertices, float32
    face_id: np.ndarray,  # [N] sample faces
    bary: np.ndarray,  # [N, 3] sample barycentrics
    dxyz: torch.Tensor,  # [N, 3] or [P, N, 3]
    dquat: torch.Tensor,  # [N, 4] or [P, N, 4], unit
    ds: torch.Tensor,  # [N, 3] or [P, N, 3]
    resolution: int | None = None,  # R_ref of the scale S; None: uv.FRAME_RESOLUTION
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`skin_gaussians_on_body` without gradients, as numba kernels (body/skin_kernels.py):
    tangent frames, their quaternions and the skinning fused, float64 inside -> means [P, N, 3],
    quats [P, N, 4], scales [P, N, 3], float32 CPU tensors."""
    from dlacli.body import skin_kernels as sk
    from dlacli.body.uv import FRAME_RESOLUTION, body_face_frames, face_uv_terms

    faces = face_uv_terms()[0]
    verts = np.ascontiguousarray(vertices.detach().cpu().numpy(), np.float32)
    p, n = verts.shape[0], len(face_id)
    fid = np.ascontiguousarray(face_id, np.int64)
    bar = np.ascontiguousarray(bary, np.float32)

    def per_body(x: torch.Tensor, k: int) -> np.ndarray:
        a = np.ascontiguousarray(x.detach().cpu().numpy(), np.float32)
        return a.reshape(-1, n, k) if a.ndim == 3 else a[None]

    dx, dq, dsc = per_body(dxyz, 3), per_body(dquat, 4), per_body(ds, 3)
    means, quats, scales = (np.empty((p, n, k), np.float32) for k in (3, 4, 3))
    res = float(FRAME_RESOLUTION if resolution is None else resolution)
    for b in range(p):
        vn, dpdu, scale = body_face_frames(verts[b])
        m = b if dx.shape[0] > 1 else 0
        sk.skin_samples(
            verts[b], faces, vn, dpdu, scale / res, fid, bar, dx[m], dq[m], dsc[m], means[b], quats[b], scales[b]
        )
    return torch.from_numpy(means), torch.from_numpy(quats), torch.from_numpy(scales)
