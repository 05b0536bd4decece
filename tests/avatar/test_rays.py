"""UV rays by the numba kernel (avatar/ray_kernels.py) against geometry.py's torch Plücker rays."""

import numpy as np
import pytest
import torch

from dlacli.avatar.codec import uv_rays
from dlacli.body import uv as U
from dlacli.geometry import plucker_rays_uv

EPS = float(np.finfo(np.float32).eps)


@pytest.mark.parametrize("resolution", [16, 64])
def test_kernel_rays_match_torch(resolution):
    from dlacli.body.model import get_body_model

    verts = torch.as_tensor(get_body_model().rest_vertices(None), dtype=torch.float32)
    pos = U.position_map(verts, resolution)
    eye = torch.tensor([0.4, -2.7, 1.1])
    pos[0, 0] = eye  # a texel at the camera centre itself: zeros, as plucker gives
    fast = uv_rays(verts, eye, resolution, pos)
    ref = plucker_rays_uv(pos.double(), eye.double()).permute(2, 0, 1).float()  # float64 reference
    assert fast.shape == (6, resolution, resolution) and fast.dtype == torch.float32
    assert torch.equal(fast[:, 0, 0], torch.zeros(6))
    # each element within a few float32 roundings of its magnitude (|d| = 1, |o x d| <= |o|)
    scale = torch.tensor([1.0] * 3 + [float(eye.norm())] * 3)[:, None, None]
    assert ((fast - ref).abs() <= 8 * EPS * scale).all()
    # the torch path (taken with a gradient) agrees the same way
    grad = pos.clone().requires_grad_(True)
    slow = uv_rays(verts, eye, resolution, grad).detach()
    assert ((fast - slow).abs() <= 8 * EPS * scale).all()
    # unit directions, moments perpendicular to them
    d, m = fast[:3, 1:, 1:], fast[3:, 1:, 1:]
    assert ((d.norm(dim=0) - 1).abs() <= 4 * EPS).all()
    assert ((d * m).sum(dim=0).abs() <= 16 * EPS * scale[3]).all()


def test_view_cosine_kernel_matches_torch():
    """The view-cosine decoder's colour F_delta and its cosine by the numba kernels (no gradient,
    float32 CPU) against the formula in float64: within float32 rounding of rgb (1 + |k|) (torch's
    own float32 sqrt is not correctly rounded either); texels with a zero normal (off the body) and
    a zero ray (at the camera) included. The fused kernel equals `view_cosine` then codec.py's
    torch shading bit for bit (what a decoder with a gain of exactly 1 computes), and with a
    gradient asked for the decoder is the torch formula, differentiable in z."""
    from dlacli.avatar.codec import PoseConditioning, ViewCosineDecoder, shading, view_cosine

    g = torch.Generator().manual_seed(4)
    r = 48
    z = torch.rand((15, r, r), generator=g)
    z[14] = torch.rand((r, r), generator=g) * 1.6 - 0.4  # falloffs k, some < 0, some > 1
    normals = torch.randn((3, r, r), generator=g)
    normals = normals / normals.norm(dim=0, keepdim=True)
    normals[:, :4] = 0.0  # texels off the body (rows 0-3)
    rays = torch.randn((6, r, r), generator=g)
    rays[:3] = rays[:3] / rays[:3].norm(dim=0, keepdim=True)
    rays[:, 5, 5] = 0.0  # a texel at the camera centre
    d = rays[:3].double()
    cos64 = (-(normals.double() * d / d.norm(dim=0).clamp_min(1e-12)).sum(0)).clamp(0.0, 1.0)
    want = z[1:4].double() * (shading(z[14].double(), cos64) - 1.0)
    decoder, pose = ViewCosineDecoder(), PoseConditioning(normals=normals)
    cos = view_cosine(normals, rays)
    assert cos.dtype == torch.float32 and ((cos.double() - cos64).abs() <= 4 * EPS).all()
    fast = decoder.delta(z, pose, rays)
    assert fast.shape == (14, r, r) and fast.dtype == torch.float32
    assert torch.equal(fast[:1], torch.zeros(1, r, r)) and torch.equal(fast[4:], torch.zeros(10, r, r))
    assert ((fast[1:4].double() - want).abs() <= 16 * EPS * (1 + z[14].abs()) * z[1:4]).all()
    assert torch.equal(fast[1:4], z[1:4] * (shading(z[14], cos) * torch.ones(3, r, r) - 1.0))
    zg = z.clone().requires_grad_(True)
    slow = decoder.delta(zg, pose, rays)
    slow.sum().backward()
    assert ((slow.detach()[1:4].double() - want).abs() <= 16 * EPS * (1 + z[14].abs()) * z[1:4]).all()
    assert zg.grad[14].abs().sum() > 0
