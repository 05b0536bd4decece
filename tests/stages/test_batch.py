"""The batch axis through the differentiable path: maps [B, 14, R, R] -> sampling -> skinning ->
`render_gaussians` with leading batch dimensions gives, item by item, what each map gives alone:
the same images and the same gradients."""

from __future__ import annotations

import numpy as np
import torch

from dlacli.avatar import gaussian_map as gm
from dlacli.render.splat import render_gaussians
from dlacli.types import BodyParams, Gaussians

R = 24
N = 3000


def _maps(b: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(11)
    z = torch.zeros(b, gm.CHANNELS, R, R)
    z[:, gm.OPACITY] = 1.0 + torch.rand(b, 1, R, R, generator=g)
    z[:, gm.RGB] = torch.rand(b, 3, R, R, generator=g)
    z[:, gm.OFFSET] = 0.01 * torch.randn(b, 3, R, R, generator=g)
    z[:, gm.ROTATION] = torch.tensor([1.0, 0.0, 0.0, 0.0])[None, :, None, None] + 0.1 * torch.randn(
        b, 4, R, R, generator=g
    )
    z[:, gm.LOG_SCALE] = np.log(3.0) + 0.2 * torch.randn(b, 3, R, R, generator=g)
    return z


def _two_poses() -> torch.Tensor:
    from dlacli.body.model import get_body_model

    model = get_body_model()
    rest = model.forward_body(BodyParams()).vertices  # [1, V, 3]
    bent = model.forward_body(
        BodyParams(pose={"upperarm01.L": np.array([0.0, 0.0, 0.8]), "upperleg01.R": np.array([0.6, 0.0, 0.0])})
    ).vertices
    return torch.cat([rest, bent])  # [2, V, 3]


def _cameras():
    from dlacli.geometry import look_at_orbit_cameras

    return look_at_orbit_cameras(np.array([0.0, 0.0, -0.2]), 3.0, np.array([0.0, 120.0]), 5.0, 40.0, 32)


def test_batched_render_equals_per_item_render_values_and_gradients():
    samples = gm.make_samples(N, seed=2)
    verts = _two_poses()
    frames = gm.sample_frames(verts, samples)
    cams = _cameras()
    weights = torch.randn(2, 2, 32, 32, 3, generator=torch.Generator().manual_seed(5))

    maps = _maps(2).requires_grad_(True)
    batch = gm.posed_gaussians(maps, samples, frames)
    assert batch.batch_shape == (2,) and len(batch) == N
    out = render_gaussians(batch, cams)
    assert out.rgb.shape == (2, 2, 32, 32, 3) and out.alpha.shape == (2, 2, 32, 32)
    (grad_batch,) = torch.autograd.grad((out.rgb * weights).sum() + out.alpha.sum(), maps)

    for b in range(2):
        one_map = _maps(2)[b].requires_grad_(True)
        one_frames = tuple(f[b : b + 1] for f in frames)
        (g,) = gm.gaussians_at_frames(one_map, samples, one_frames)
        single = render_gaussians(g, cams)
        # the same kernels on the same numbers: float32 results agree to the last bits (the
        # batched grid_sample and einsum may block differently: a few ulps of values ~1)
        atol = 64 * torch.finfo(torch.float32).eps
        torch.testing.assert_close(out.rgb[b], single.rgb, rtol=0, atol=atol)
        torch.testing.assert_close(out.alpha[b], single.alpha, rtol=0, atol=atol)
        (grad_one,) = torch.autograd.grad((single.rgb * weights[b]).sum() + single.alpha.sum(), one_map)
        scale = float(grad_one.abs().max())
        assert scale > 0
        torch.testing.assert_close(grad_batch[b], grad_one, rtol=0, atol=1e-4 * scale)


def test_leading_dimensions_of_any_shape():
    """[2, 3] sets of Gaussians render to [2, 3, C, H, W]: item (i, j) is set (i, j) alone."""
    g = torch.Generator().manual_seed(1)
    n = 50
    means = 0.3 * torch.randn(2, 3, n, 3, generator=g)
    quats = torch.nn.functional.normalize(torch.randn(2, 3, n, 4, generator=g), dim=-1)
    scales = 0.02 + 0.05 * torch.rand(2, 3, n, 3, generator=g)
    opac = torch.rand(2, 3, n, generator=g)
    rgb = torch.rand(2, 3, n, 3, generator=g)
    sets = Gaussians.from_rgb(means, quats, scales, opac, rgb)
    cams = _cameras()
    out = render_gaussians(sets, cams)
    assert out.rgb.shape == (2, 3, 2, 32, 32, 3)
    for i in range(2):
        for j in range(3):
            alone = render_gaussians(
                Gaussians.from_rgb(means[i, j], quats[i, j], scales[i, j], opac[i, j], rgb[i, j]), cams
            )
            assert torch.equal(out.rgb[i, j], alone.rgb) and torch.equal(out.depth[i, j], alone.depth)
