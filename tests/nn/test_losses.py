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


# ------------------------------------------------------------------------ perceptual terms


def test_ms_ssim_is_one_minus_mean_ssim_over_dyadic_scales():
    from dlacli.nn.losses import ms_ssim_loss

    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.random((1, 48, 48, 3)))
    y = torch.from_numpy(np.clip(rng.random((1, 48, 48, 3)) * 0.3 + x.numpy() * 0.7, 0, 1))
    want, a, b = [], x.numpy()[0], y.numpy()[0]
    for _ in range(3):  # 48, 24, 12 pixels: each at least the 11-pixel window
        want.append(np.mean([_ssim_direct(a[..., c], b[..., c]).mean() for c in range(3)]))
        a = a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2, 3).mean(axis=(1, 3))
        b = b.reshape(b.shape[0] // 2, 2, b.shape[1] // 2, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(float(ms_ssim_loss(x, y)), 1.0 - np.mean(want), atol=1e-10)
    assert float(ms_ssim_loss(x, x)) == 0.0


def test_ms_ssim_mask_ignores_pixels_far_outside_it():
    from dlacli.nn.losses import ms_ssim_loss

    rng = np.random.default_rng(2)
    x = torch.from_numpy(rng.random((48, 160, 3)))
    y = x.clone()
    y[:, 120:] = torch.from_numpy(rng.random((48, 40, 3)))  # differs only on the right
    mask = torch.zeros(48, 160, dtype=torch.float64)
    mask[:, 20:40] = 1.0  # inside windows at all 3 scales; the coarsest (4 px per pixel, 11-pixel
    # windows: +-20 px) reach column 60 at most, far left of column 120
    assert float(ms_ssim_loss(x, y, mask)) == 0.0
    assert float(ms_ssim_loss(x, y)) > 0.05
    right = torch.zeros_like(mask)
    right[:, 130:] = 1.0
    assert float(ms_ssim_loss(x, y, right)) > 0.5
    assert float(ms_ssim_loss(x, y, torch.zeros_like(mask))) == 0.0  # nothing inside: no loss


def _random_alexnet_state(seed: int = 0) -> dict[str, torch.Tensor]:
    from dlacli.nn.losses import AlexNetFeatures

    torch.manual_seed(seed)
    return {k: v.clone() for k, v in AlexNetFeatures().state_dict().items()}


def test_alexnet_weights_load_from_safetensors_and_state_dict(tmp_path):
    from safetensors.torch import save_file

    from dlacli.nn.losses import AlexNetFeatures, alexnet_loss, load_alexnet, perceptual_loss

    state = _random_alexnet_state(3)
    save_file(state, str(tmp_path / "alex.safetensors"))
    # torchvision's own layout: features.* plus a classifier the loss does not use
    torch.save({**state, "classifier.1.weight": torch.zeros(2, 2)}, tmp_path / "alex.pth")
    ref = AlexNetFeatures()
    ref.load_state_dict(state)
    x, y = torch.rand(2, 67, 67, 3), torch.rand(2, 67, 67, 3)
    mask = (torch.rand(2, 67, 67) > 0.3).float()
    want = 0.0
    for a, b in zip(ref(x.permute(0, 3, 1, 2)), ref(y.permute(0, 3, 1, 2))):  # direct LPIPS-style sum
        a = a / a.norm(dim=1, keepdim=True).clamp_min(1e-10)
        b = b / b.norm(dim=1, keepdim=True).clamp_min(1e-10)
        d = ((a - b) ** 2).sum(dim=1, keepdim=True)
        w = torch.nn.functional.adaptive_avg_pool2d(mask[:, None], d.shape[-2:])
        want += float((d * w).sum().detach() / w.sum())
    for name in ("alex.safetensors", "alex.pth"):
        net = load_alexnet(tmp_path / name)
        got = float(alexnet_loss(net, x, y, mask))
        assert abs(got - want) <= 1e-5 * max(1.0, abs(want))
        assert float(perceptual_loss(x, y, mask, net)) == got
        assert not any(p.requires_grad for p in net.parameters())


def test_alexnet_weights_bad_files_are_input_errors(tmp_path):
    import pytest
    from safetensors.torch import save_file

    from dlacli.errors import DlaInputError
    from dlacli.nn.losses import load_alexnet

    with pytest.raises(DlaInputError):
        load_alexnet(tmp_path / "missing.safetensors")
    (tmp_path / "junk.pth").write_bytes(b"not a state dict")
    with pytest.raises(DlaInputError):
        load_alexnet(tmp_path / "junk.pth")
    state = _random_alexnet_state()
    state.pop("features.3.weight")
    save_file(state, str(tmp_path / "short.safetensors"))
    with pytest.raises(DlaInputError, match="features.3.weight"):
        load_alexnet(tmp_path / "short.safetensors")


def test_perceptual_loss_without_weights_is_ms_ssim():
    from dlacli.nn.losses import ms_ssim_loss, perceptual_loss

    x, y = torch.rand(1, 32, 32, 3, requires_grad=True), torch.rand(1, 32, 32, 3)
    m = torch.ones(1, 32, 32)
    loss = perceptual_loss(x, y, m)
    assert float(loss.detach()) == float(ms_ssim_loss(x, y, m).detach())
    loss.backward()
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
