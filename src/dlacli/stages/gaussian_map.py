"""The UV Gaussian map F and the Gaussians drawn from it (DESIGN.md §1 "Animate").

F is a [14, R, R] map over the body's UV space (docs/conventions.md "UV space"), channels:

    0       opacity, as a logit
    1..3    colour, rgb (rendered clamped to [0, 1])
    4..6    position offset dxyz in the texel's tangent frame, metres
    7..10   rotation dR in the tangent frame, quaternion (w, x, y, z), normalised at use
    11..13  log of the scale multiplier ds (texel units: ds = 1 is about one texel of a 256 map)

Gaussians are sampled from F at fixed surface samples (half uniform in UV, half uniform on the
mesh surface, as in the paper) by bilinear lookup, then placed with the posed body's tangent frames:
x = T + R dxyz, R_g = R dR, s = S ds (dlacli.body.skinning). The non-learned decoder is the identity
(F = Z); a learned GPD produces F from Z and plugs in at `decode`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as nnf

from dlacli.errors import DlaInputError
from dlacli.types import Avatar, Gaussians, rgb_to_sh0

CHANNELS = 14
OPACITY, RGB, OFFSET, ROTATION, LOG_SCALE = (
    slice(0, 1), slice(1, 4), slice(4, 7), slice(7, 11), slice(11, 14),
)  # fmt: skip
DEFAULT_GAUSSIANS = 131_072  # 65,536 uniform in UV + 65,536 uniform on the surface


@dataclass
class Samples:
    """Fixed surface sample points that carry one Gaussian each."""

    face_id: np.ndarray  # [N] int64 triangle of the body mesh
    bary: np.ndarray  # [N, 3] float32 barycentrics
    uv: np.ndarray  # [N, 2] float32 UV coordinates (u right, v up)

    def __len__(self) -> int:
        return self.face_id.shape[0]


def make_samples(n: int = DEFAULT_GAUSSIANS, seed: int = 0) -> Samples:
    """n samples: n // 2 uniform over the covered UV texels, the rest uniform by surface area."""
    from dlacli.body.uv import sample_surface, sample_uv, sample_uv_points

    if n < 2:
        raise DlaInputError("--gaussians", f"needs at least 2 Gaussians, got {n}")
    f_uv, b_uv = sample_uv(n // 2, seed=seed)
    f_s, b_s = sample_surface(n - n // 2, seed=seed + 1)
    face_id = np.concatenate([f_uv, f_s])
    bary = np.concatenate([b_uv, b_s]).astype(np.float32)
    return Samples(face_id, bary, sample_uv_points(face_id, bary).astype(np.float32))


def lookup(fmap: torch.Tensor, uv: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of a map [C, R, R] at UV points [N, 2] -> [N, C] (differentiable in fmap).

    Texel centres follow docs/conventions.md: u = (j + 0.5) / R, v = 1 - (i + 0.5) / R.
    """
    uv = torch.as_tensor(uv, dtype=fmap.dtype, device=fmap.device)
    grid = torch.stack([2.0 * uv[:, 0] - 1.0, 1.0 - 2.0 * uv[:, 1]], dim=-1)  # [N, 2] in [-1, 1]
    out = nnf.grid_sample(
        fmap[None], grid[None, None], mode="bilinear", padding_mode="border", align_corners=False
    )  # [1, C, 1, N]
    return out[0, :, 0].T


def skinned_params(
    fmap: torch.Tensor,  # [14, R, R] the Gaussian map F
    samples: Samples,
    frames: tuple[torch.Tensor, ...],  # T [P,N,3], R [P,N,3,3], S [P,N], Q [P,N,4] (`sample_frames`)
):
    """Gaussian parameters for P posed frames (tangent frames precomputed at the samples):
    means [P, N, 3], quats [P, N, 4] (w, x, y, z), scales [P, N, 3], opacities [N], rgb [N, 3]."""
    from dlacli.body.skinning import skin_gaussians

    params = lookup(fmap, samples.uv)  # [N, 14]
    frames_T, frames_R, frames_S, frames_Q = frames
    dquat = params[:, ROTATION]
    dquat = dquat / dquat.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    ds = params[:, LOG_SCALE].exp()
    means, quats, scales = skin_gaussians(frames_T, frames_R, frames_S, params[:, OFFSET], dquat, ds, frames_Q)
    return means, quats, scales, torch.sigmoid(params[:, 0]), params[:, RGB].clamp(0.0, 1.0)


def gaussians_at_frames(fmap: torch.Tensor, samples: Samples, frames) -> list[Gaussians]:
    """World Gaussians for each of P posed frames (see `skinned_params`)."""
    means, quats, scales, opacity, rgb = skinned_params(fmap, samples, frames)
    sh = rgb_to_sh0(rgb)[:, None, :]
    return [Gaussians(means[p], quats[p], scales[p], opacity, sh) for p in range(means.shape[0])]


def sample_frames(vertices: torch.Tensor, samples: Samples):
    """Tangent frames of posed vertices [P, V, 3] at the samples: positions T [P, N, 3],
    rotations R [P, N, 3, 3] and the same as quaternions Q [P, N, 4], scales S [P, N]."""
    from dlacli.body.rotations import matrix_to_quat
    from dlacli.body.uv import tangent_frames

    frames_T, frames_R, frames_S = tangent_frames(vertices, samples.face_id, samples.bary)
    return frames_T, frames_R, frames_S, matrix_to_quat(frames_R)


def decode(avatar: Avatar, where: str = "avatar") -> torch.Tensor:
    """The Gaussian map F [14, R, R] of an avatar (float32 tensor); the identity decoder has
    F = z, so it needs no canonical cache."""
    if avatar.decoder != "identity":
        raise DlaInputError(
            where, f"decoder {avatar.decoder!r} is not available in this version (known: identity)"
        )
    if avatar.z.shape[0] != CHANNELS:
        raise DlaInputError(where, f"identity decoder needs z with {CHANNELS} channels, got {avatar.z.shape}")
    return torch.from_numpy(np.ascontiguousarray(avatar.z, dtype=np.float32))
