"""Colour of Gaussians from real spherical harmonics (degree 0-3): the basis in the 3DGS / gsplat
sign convention and the per-camera colour `eval_sh_colors` that the splatter composites (the
conventions in docs/rendering.md, "Colour")."""

from __future__ import annotations

import torch

# Real SH constants (the 3DGS / gsplat sign convention, Condon-Shortley phase included).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """[..., 3] unit directions -> [..., (degree + 1)^2] real SH basis (3DGS convention)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz, _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh_colors(
    sh: torch.Tensor,  # [N, K, 3], or [C, N, K, 3]: each camera's own coefficients
    means: torch.Tensor,  # [N, 3]
    viewmats: torch.Tensor,  # [C, 4, 4]
    degree: int,
) -> torch.Tensor:
    """[C, N, 3] colour = sum_k basis_k(normalised mean - camera centre) sh_k + 0.5, >= 0."""
    ncam = viewmats.shape[0]
    if degree == 0:
        col = (_C0 * sh[..., 0, :] + 0.5).clamp(min=0.0)
        return col if sh.ndim == 4 else col[None].expand(ncam, -1, -1)
    R = viewmats[:, :3, :3]
    centres = -torch.einsum("cji,cj->ci", R, viewmats[:, :3, 3])  # [C, 3] = -R^T t
    dirs = torch.nn.functional.normalize(means[None] - centres[:, None], dim=-1)  # [C, N, 3]
    basis = sh_basis(degree, dirs)  # [C, N, B]
    kb = basis.shape[-1]
    if sh.ndim == 4:
        col = torch.einsum("cnk,cnkd->cnd", basis, sh[:, :, :kb, :]) + 0.5
    else:
        col = torch.einsum("cnk,nkd->cnd", basis, sh[:, :kb, :]) + 0.5
    return col.clamp(min=0.0)
