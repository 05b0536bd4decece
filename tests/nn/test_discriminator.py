"""The PatchGAN discriminator and the LSGAN losses: score-map sizes from conv arithmetic,
gradients, batch independence (InstanceNorm, no BatchNorm), analytic loss values, parameter
counts on the meta device, and a checkpoint round trip."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
from dlacli.errors import DlaInputError
from dlacli.nn import discriminator as D

F32 = torch.float32


def _tiny(**changes) -> D.PatchDiscriminator:
    torch.manual_seed(0)
    return D.PatchDiscriminator(dataclasses.replace(D.preset("tiny"), **changes))


def _images(b: int, side: int, seed: int = 1, channels: int = 3) -> torch.Tensor:
    return torch.rand(b, channels, side, side, generator=torch.Generator().manual_seed(seed))


def _conv_side(side: int, kernel: int, stride: int, padding: int) -> int:
    return (side + 2 * padding - kernel) // stride + 1


@pytest.mark.parametrize("layers, side", [(2, 32), (2, 40), (3, 64), (3, 70)])
def test_score_map_size(layers, side):
    net = _tiny(layers=layers)
    expect = side
    for _ in range(layers):
        expect = _conv_side(expect, 4, 2, 1)
    expect = _conv_side(_conv_side(expect, 4, 1, 1), 4, 1, 1)
    with torch.no_grad():
        scores = net(_images(2, side))
    assert scores.shape == (2, 1, expect, expect)


def test_pix2pix_layout():
    """layers=3 is pix2pix's 70x70 PatchGAN: widths 64-128-256 (stride 2), 512 (stride 1), 1."""
    net = D.PatchDiscriminator(D.DiscriminatorConfig())
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.stride[0]) for c in convs] == [
        (3, 64, 2),
        (64, 128, 2),
        (128, 256, 2),
        (256, 512, 1),
        (512, 1, 1),
    ]
    assert all(c.kernel_size == (4, 4) for c in convs)
    norms = [m for m in net.modules() if isinstance(m, torch.nn.InstanceNorm2d)]
    assert len(norms) == 3 and all(n.affine for n in norms)
    assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in net.modules())
    assert all(
        isinstance(m, torch.nn.LeakyReLU) and m.negative_slope == 0.2
        for m in net.modules()
        if isinstance(m, (torch.nn.LeakyReLU, torch.nn.ReLU))
    )


def test_gradients_reach_every_parameter_and_the_input():
    net = _tiny()
    x = _images(2, 32).requires_grad_(True)
    D.lsgan_generator_loss(net(x)).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().max() > 0, f"{name} gets no gradient"
    assert torch.isfinite(x.grad).all() and x.grad.abs().max() > 0


def test_batch_items_are_independent(tol):
    net = _tiny()
    x = _images(2, 32)
    y = x.clone()
    y[1] = _images(1, 32, seed=5)[0]
    with torch.no_grad():
        a, b, alone = net(x), net(y), net(x[:1])
    atol = tol(F32, float(a.abs().max()), ops=20)  # ~20 rounding steps per score (5 convs, norms)
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=atol)
    torch.testing.assert_close(a[0], alone[0], rtol=0, atol=atol)
    assert float((a[1] - b[1]).abs().max()) > 1e3 * atol


# ------------------------------------------------------------------------------- losses


def test_lsgan_losses_on_constant_maps(tol):
    ones, zeros = torch.ones(2, 1, 6, 6), torch.zeros(2, 1, 6, 6)
    assert D.lsgan_discriminator_loss(ones, zeros) == 0  # the perfect critic
    assert D.lsgan_discriminator_loss(zeros, ones) == 1  # 0.5 (1 + 1)
    assert D.lsgan_generator_loss(ones) == 0
    assert D.lsgan_generator_loss(zeros) == 0.5
    # constant maps of different sizes: each term is its own mean
    a, b = 0.3, -1.7
    real, fake = torch.full((2, 1, 3, 3), a), torch.full((1, 1, 5, 4), b)
    want_d, want_g = 0.5 * ((a - 1) ** 2 + b**2), 0.5 * (b - 1) ** 2
    assert abs(float(D.lsgan_discriminator_loss(real, fake)) - want_d) <= tol(F32, want_d, ops=4)
    assert abs(float(D.lsgan_generator_loss(fake)) - want_g) <= tol(F32, want_g, ops=4)


def test_lsgan_losses_match_a_per_element_sum(tol):
    g = torch.Generator().manual_seed(2)
    real, fake = torch.randn(3, 1, 4, 5, generator=g), torch.randn(3, 1, 4, 5, generator=g)
    r, f = real.double().flatten().tolist(), fake.double().flatten().tolist()
    want_d = 0.5 * (sum((x - 1) ** 2 for x in r) / len(r) + sum(x * x for x in f) / len(f))
    want_g = 0.5 * sum((x - 1) ** 2 for x in f) / len(f)
    assert abs(float(D.lsgan_discriminator_loss(real, fake)) - want_d) <= tol(F32, want_d, ops=len(r))
    assert abs(float(D.lsgan_generator_loss(fake)) - want_g) <= tol(F32, want_g, ops=len(f))


# ------------------------------------------------------------------------------- sizes, checkpoints


def test_parameter_counts():
    counts = {name: D.parameter_count(D.preset(name)) for name in ("tiny", "small", "paper")}
    assert abs(counts["paper"] / 7e6 - 1) < 0.05, counts  # the paper's discriminator: 7 M
    assert counts["tiny"] < counts["small"] < counts["paper"]
    assert counts["tiny"] == sum(p.numel() for p in _tiny().parameters())


def test_presets_and_config_errors():
    with pytest.raises(DlaInputError, match="--preset"):
        D.preset("huge")
    assert D.preset("tiny") == D.PRESETS["tiny"] and D.preset("tiny") is not D.PRESETS["tiny"]
    with pytest.raises(ValueError, match="positive"):
        D.DiscriminatorConfig(layers=0)


def test_checkpoint_round_trip(tmp_path):
    net = _tiny()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))  # move the norms' affine weights off their init
    x = _images(2, 32)
    with torch.no_grad():
        before = net(x)
    save_checkpoint(tmp_path / "disc", net, net.config)
    loaded = load_checkpoint(tmp_path / "disc")
    assert isinstance(loaded.module, D.PatchDiscriminator) and loaded.config == net.config
    with torch.no_grad():
        torch.testing.assert_close(loaded.module(x), before, rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    net = _tiny()
    x = _images(2, 32)
    with torch.no_grad():
        cpu = net(x)
        gpu = net.to("cuda")(x.to("cuda"))
    assert gpu.device.type == "cuda" and gpu.dtype == F32
    # cuDNN convolutions may run in TF32 (PyTorch's default): a 10-bit mantissa, ~20 steps per score
    assert float((cpu - gpu.cpu()).abs().max()) <= 20 * 2.0**-10 * float(cpu.abs().max())
