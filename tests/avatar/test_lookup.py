"""gaussian_map.lookup: bilinear lookup of a UV map at surface points, and its sparse gradient
(avatar/lookup_kernels.py) against torch's grid_sample in float64 and analytic texel centres."""

from __future__ import annotations

import numba
import numpy as np
import torch
import torch.nn.functional as nnf

from dlacli.avatar import gaussian_map as gm

R = 32


def _grid_sample64(fmap: torch.Tensor, uv: np.ndarray) -> torch.Tensor:
    """The same lookup as gm.lookup, in fmap's dtype (float64 for a reference), by grid_sample
    with its own backward."""
    u = torch.from_numpy(uv).to(fmap.dtype)
    grid = torch.stack([2.0 * u[:, 0] - 1.0, 1.0 - 2.0 * u[:, 1]], dim=-1)[None, None]
    maps = fmap.reshape(-1, *fmap.shape[-3:])
    grid = grid.expand(maps.shape[0], 1, -1, 2)
    out = nnf.grid_sample(maps, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].transpose(1, 2).reshape(*fmap.shape[:-3], -1, fmap.shape[-3])


def _points(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-0.05, 1.05, size=(n, 2))  # some beyond the map's edge: border padding
    uv[:8] = (np.array([[3, 5], [0, 0], [R - 1, R - 1], [7, 30], [12, 0], [0, 9], [31, 2], [16, 16]]) + 0.5) / R
    return uv.astype(np.float32)


def test_texel_centres_give_the_texel_and_the_border_is_clamped():
    fmap = torch.arange(2 * R * R, dtype=torch.float32).reshape(2, R, R)
    rows = np.array([4, 0, 31, 9])
    cols = np.array([3, 0, 31, 30])
    uv = np.stack([(cols + 0.5) / R, 1.0 - (rows + 0.5) / R], axis=1).astype(np.float32)  # u right, v up
    got = gm.lookup(fmap, uv)
    assert torch.equal(got, fmap[:, rows, cols].T)
    far = gm.lookup(fmap, np.array([[-0.3, 1.4]], np.float32))  # beyond the top-left corner
    assert torch.equal(far[0], fmap[:, 0, 0])


def test_the_lookup_without_a_gradient_is_the_float64_lookup_rounded():
    """The numba gather: each value is the float64 lookup rounded once to float32, for a batch of
    maps and for a channel slice (a strided view) alike."""
    g = torch.Generator().manual_seed(3)
    for shape in ((gm.CHANNELS, R, R), (3, gm.CHANNELS, R, R)):
        uv = _points(5000, 4)
        fmap = torch.randn(*shape, generator=g)
        with torch.no_grad():
            got = gm.lookup(fmap, uv)
            part = gm.lookup(fmap[..., 1:5, :, :], uv)
        want = _grid_sample64(fmap.double(), uv)
        assert got.dtype == torch.float32 and got.shape == want.shape
        assert ((got.double() - want).abs() <= 2.0**-24 * want.abs() + 2.0**-40 * float(fmap.abs().max())).all()
        assert torch.equal(part, got[..., 1:5])
    # a map that asks for a gradient, read where none is recorded, takes the gather too
    x = fmap.clone().requires_grad_(True)
    with torch.no_grad():
        assert torch.equal(gm.lookup(x, uv), got)


def test_the_sparse_gradient_is_grid_samples_and_the_values_the_gathers():
    g = torch.Generator().manual_seed(1)
    for shape in ((gm.CHANNELS, R, R), (3, gm.CHANNELS, R, R)):
        uv = _points(5000, 2)
        fmap = torch.randn(*shape, generator=g)
        weights = torch.randn(*shape[:-3], len(uv), shape[-3], generator=g)
        x = fmap.clone().requires_grad_(True)
        out = gm.lookup(x, uv)
        (grad,) = torch.autograd.grad((out * weights).sum(), x)
        with torch.no_grad():  # the same values as the lookup without a gradient
            assert torch.equal(out.detach(), gm.lookup(fmap, uv))
        x64 = fmap.double().requires_grad_(True)
        (want,) = torch.autograd.grad((_grid_sample64(x64, uv) * weights.double()).sum(), x64)
        # each texel sums about 4 N / R^2 (~20) products in float64, stored as float32
        assert torch.allclose(grad.double(), want, rtol=2 * 2.0**-24, atol=2.0**-24 * float(want.abs().max()))


def test_the_sparse_gradient_does_not_depend_on_the_thread_count():
    uv = _points(20000, 3)
    fmap = torch.randn(gm.CHANNELS, R, R, generator=torch.Generator().manual_seed(4), requires_grad=True)
    weights = torch.randn(len(uv), gm.CHANNELS, generator=torch.Generator().manual_seed(5))
    grads = []
    before = numba.get_num_threads()
    try:
        for threads in (1, before):
            numba.set_num_threads(threads)
            (gr,) = torch.autograd.grad((gm.lookup(fmap, uv) * weights).sum(), fmap)
            grads.append(gr)
    finally:
        numba.set_num_threads(before)
    assert torch.equal(grads[0], grads[1])
