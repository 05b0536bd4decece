"""SSIM against a direct per-window evaluation of Wang et al.'s formula."""

from __future__ import annotations

import numpy as np
import torch

from dlacli.nn.losses import ssim, ssim_map


def _ssim_direct(x: np.ndarray, y: np.ndarray, size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Per-window SSIM of one channel [H, W] with explicit loops (valid windows only)."""
    ax = np.arange(size) - (size - 1) / 2
    w = np.exp(-(ax[:, None] ** 2 + ax[None] ** 2) / (2 * sigma**2))
    w /= w.sum()
    c1, c2 = 0.01**2, 0.03**2
    h, wd = x.shape
    out = np.zeros((h - size + 1, wd - size + 1))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            px, py = x[i : i + size, j : j + size], y[i : i + size, j : j + size]
            mx, my = (w * px).sum(), (w * py).sum()
            vx, vy = (w * (px - mx) ** 2).sum(), (w * (py - my) ** 2).sum()
            cxy = (w * (px - mx) * (py - my)).sum()
            out[i, j] = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return out


def test_ssim_matches_direct_formula():
    rng = np.random.default_rng(0)
    x = rng.random((20, 17, 2))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    got = ssim_map(torch.from_numpy(x), torch.from_numpy(y)).numpy()
    for c in range(2):
        np.testing.assert_allclose(got[..., c], _ssim_direct(x[..., c], y[..., c]), atol=1e-10)


def test_ssim_identity_and_gradient():
    x = torch.rand(1, 12, 12, 1, dtype=torch.float64)
    assert float(ssim(x, x)) == 1.0
    y = x.clone().requires_grad_(True)
    torch.autograd.gradcheck(lambda t: ssim(t, x * 0.9 + 0.05), (y,))
