"""Small, differentiable rotation helpers in torch (no anny import).

Conventions (docs/conventions.md, docs/body.md):
- axis-angle: a vector whose direction is the rotation axis and whose length is the angle, radians;
- matrices rotate column vectors: x' = R x;
- quaternions are (w, x, y, z), unit length; `matrix_to_quat` and `axis_angle_to_quat` return the
  representative with w >= 0.

Every function works on any leading batch shape, keeps the input's dtype and device, and has
finite gradients everywhere, including at the zero rotation (series expansions near 0) and
near a half turn (the log map goes through quaternions, which are well conditioned there).
"""

from __future__ import annotations

import torch

_SMALL = 1e-6  # below this angle (squared: _SMALL**2) the closed forms switch to Taylor series


def skew(v: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> [..., 3, 3] cross-product matrix: skew(v) @ x == cross(v, x)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: [..., 3] axis-angle -> [..., 3, 3] rotation matrix."""
    theta2 = (aa * aa).sum(-1)  # [...]
    small = theta2 < _SMALL**2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    # a = sin(t) / t, b = (1 - cos(t)) / t^2, with series near t = 0
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = skew(aa)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z) -> [..., 3, 3]; q need not be normalised (it is, first)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    m = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return m.reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation -> [..., 4] unit (w, x, y, z) with w >= 0.

    Shepperd's method: of the four ways to read the quaternion off the matrix, use the one whose
    pivot component (|w|, |x|, |y| or |z|) is largest, so no division by a small number happens.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * squared components: [..., 4] for (w, x, y, z)
    sq = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    pivot = sq.clamp_min(0.1).sqrt()  # [..., 4] 2|q_i|, only used where it is the largest (>= 1)
    # candidate quaternions (times 2 * pivot), one per pivot: [..., 4 candidates, 4 components]
    cand = torch.stack(
        [
            torch.stack([pivot[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, pivot[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, pivot[..., 2] ** 2, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, pivot[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    )
    cand = cand / (2.0 * pivot[..., None])
    best = sq.argmax(dim=-1)  # [...]
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def axis_angle_to_quat(aa: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle -> [..., 4] unit (w, x, y, z)."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    small = theta2 < _SMALL**2
    theta = torch.where(small, torch.ones_like(theta2), theta2).sqrt()
    half_sinc = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(0.5 * theta) / theta)
    w = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(0.5 * theta))
    q = torch.cat([w, aa * half_sinc], dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z) -> [..., 3] axis-angle with angle in [0, pi].

    Uses angle = 2 atan2(|v|, w) after flipping q to w >= 0, which is accurate near 0 and near pi.
    """
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < _SMALL**2
    n = torch.where(small, torch.ones_like(n2), n2).sqrt()
    angle = 2.0 * torch.atan2(n, w)
    # angle / |v|; near |v| = 0 (then w ~ 1): 2 / w * (1 - |v|^2 / (3 w^2))
    scale = torch.where(small, 2.0 / w * (1.0 - n2 / (3.0 * w * w)), angle / n)
    return v * scale


def matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    """Log map: [..., 3, 3] rotation -> [..., 3] axis-angle, angle in [0, pi] (robust near pi)."""
    return quat_to_axis_angle(matrix_to_quat(m))


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of [..., 4] (w, x, y, z) quaternions (rotation b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] -> [..., 4] conjugate (the inverse for unit quaternions)."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """[..., 4] -> [..., 4] unit quaternion."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)
