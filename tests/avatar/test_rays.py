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
