"""The reconstruction U-Net (model G): shapes, gradients, cross-view mixing, batch independence,
the pixel-aligned Gaussian activations against hand-written per-pixel oracles, parameter counts
on the meta device, and a checkpoint round trip; all at the tiny preset."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from dlacli.avatar.checkpoint import config_from_dict, load_checkpoint, save_checkpoint
from dlacli.errors import DlaInputError
from dlacli.nn import unet as U

F32 = torch.float32
DEPTH = 40  # ~rounding steps from input to output of the tiny net (its layers), for tolerances


def _tiny(**changes) -> U.ReconstructionUNet:
    torch.manual_seed(0)
    return U.ReconstructionUNet(dataclasses.replace(U.preset("tiny"), **changes))


def _views(b: int = 2, v: int = 4, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    s = U.preset("tiny").image_size
    return torch.randn(b, v, 9, s, s, generator=g)


def _differ(a: torch.Tensor, b: torch.Tensor, tol) -> float:
    """Largest difference relative to the tolerance of a float32 result of a's size."""
    return float((a - b).abs().max()) / tol(F32, float(a.abs().max()), ops=DEPTH)


NO_ATTENTION = {"attention": (False,) * 4, "mid_attention": False}


@pytest.fixture(scope="module")
def tiny():
    return _tiny()


# ------------------------------------------------------------------------------- the network


def test_shapes(tiny):
    cfg = tiny.config
    raw, feats = tiny(_views(2, 4))
    side = cfg.image_size // 2
    assert raw.shape == (2, 4, U.GAUSSIAN_CHANNELS, side, side)
    assert feats.shape == (2, 4, cfg.feature_channels, side, side)
    raw3, _ = tiny(_views(1, 3))  # any number of views
    assert raw3.shape == (1, 3, U.GAUSSIAN_CHANNELS, side, side)


def test_gradients_reach_every_parameter_and_the_input():
    net = _tiny()
    x = _views(2, 4).requires_grad_(True)
    raw, feats = net(x)
    (raw.square().mean() + feats.sin().mean()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().max() > 0, f"{name} gets no gradient"
    assert torch.isfinite(x.grad).all() and x.grad.abs().max() > 0


def test_cross_view_attention_mixes_views(tiny, tol):
    x = _views(1, 4)
    y = x.clone()
    y[:, 3] = torch.randn(y[:, 3].shape, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        (ra, fa), (rb, fb) = tiny(x), tiny(y)
    assert _differ(ra[:, 0], rb[:, 0], tol) > 1e3 and _differ(fa[:, 0], fb[:, 0], tol) > 1e3
    # without attention each view is its own image: view 0 does not see view 3
    plain = _tiny(**NO_ATTENTION)
    assert not any(isinstance(m, U.CrossViewAttention) for m in plain.modules())
    with torch.no_grad():
        (ra, fa), (rb, fb) = plain(x), plain(y)
    assert _differ(ra[:, :3], rb[:, :3], tol) <= 1 and _differ(fa[:, :3], fb[:, :3], tol) <= 1
    assert _differ(ra[:, 3], rb[:, 3], tol) > 1e3


def test_batch_items_are_independent(tiny, tol):
    x = _views(2, 4)
    y = x.clone()
    y[1] = torch.randn(y[1].shape, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        (ra, fa), (rb, fb) = tiny(x), tiny(y)
        r0, f0 = tiny(x[:1])  # item 0 alone
    assert _differ(ra[0], rb[0], tol) <= 1 and _differ(fa[0], fb[0], tol) <= 1
    assert _differ(ra[0], r0[0], tol) <= 1 and _differ(fa[0], f0[0], tol) <= 1
    assert _differ(ra[1], rb[1], tol) > 1e3


def test_no_batchnorm_anywhere():
    with torch.device("meta"):
        net = U.ReconstructionUNet(U.preset("paper"))
    assert not any(isinstance(m, torch.nn.modules.batchnorm._NormBase) for m in net.modules())


def test_fresh_network_gives_sane_gaussians(tiny):
    """The head starts near the all-zero output: every raw Gaussian value well inside (-0.5, 0.5),
    which the module docstring maps to Gaussians near each ray's reference point."""
    with torch.no_grad():
        raw, _ = tiny(_views(2, 4))
    assert raw.abs().max() < 0.5
    b, v, _, h, w = raw.shape
    o = torch.zeros(b, v, h, w, 3)
    d = torch.nn.functional.normalize(torch.randn(b, v, h, w, 3), dim=-1)
    g = U.pixel_gaussians(raw, o, d, torch.full((b, v), 2.5))
    assert ((g.means - _flat(d) * 2.5).norm(dim=-1) < 0.5 * U.POSITION_SCALE * math.sqrt(3)).all()
    assert ((g.opacities > 0.3) & (g.opacities < 0.7)).all()
    assert ((g.scales > U.SCALE_BASE / 2) & (g.scales < U.SCALE_BASE * 2)).all()
    assert (g.quats[..., 0] > 0.8).all()
    assert ((g.rgb > 0.3) & (g.rgb < 0.7)).all()


def test_bad_inputs_and_configs():
    net = _tiny()
    with pytest.raises(AssertionError, match="views must be"):
        net(torch.zeros(1, 4, 9, 64, 60))
    with pytest.raises(AssertionError, match="divisible"):
        net(torch.zeros(1, 4, 9, 36, 36))
    with pytest.raises(AssertionError, match="views must be"):
        net(torch.zeros(4, 9, 64, 64))
    with pytest.raises(ValueError, match="one up level fewer"):
        U.UNetConfig(down_channels=(8, 16), up_channels=(16, 8), attention=(False, False))
    with pytest.raises(ValueError, match="head_dim"):
        U.UNetConfig(head_dim=48)
    with pytest.raises(DlaInputError, match="--preset"):
        U.preset("huge")
    raw = json.loads(json.dumps(dataclasses.asdict(U.preset("tiny")))) | {"image_size": 60}
    with pytest.raises(DlaInputError, match="divisible"):
        config_from_dict(U.UNetConfig, raw, "config.json")


# ------------------------------------------------------------------------------- pixel Gaussians


def _rays(b: int, v: int, h: int, w: int, seed: int = 3):
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(b, v, h, w, 3, generator=g) * 2.0
    dirs = torch.nn.functional.normalize(torch.randn(b, v, h, w, 3, generator=g), dim=-1)
    ref = 1.0 + 3.0 * torch.rand(b, v, generator=g)
    return origins, dirs, ref


def _flat(x: torch.Tensor) -> torch.Tensor:
    return x.reshape(x.shape[0], -1, x.shape[-1])


def test_zero_output_is_pixel_aligned(tol):
    b, v, h, w = 2, 3, 4, 5
    origins, dirs, ref = _rays(b, v, h, w)
    g = U.pixel_gaussians(torch.zeros(b, v, 14, h, w), origins, dirs, ref)
    n = v * h * w
    expect = origins + dirs * ref[:, :, None, None, None]  # on each pixel's ray at the reference depth
    atol = tol(F32, float(expect.abs().max()), ops=3)
    torch.testing.assert_close(g.means, expect.reshape(b, n, 3), rtol=0, atol=atol)
    torch.testing.assert_close(g.quats, torch.tensor([1.0, 0, 0, 0]).expand(b, n, 4), rtol=0, atol=0)
    torch.testing.assert_close(g.scales, torch.full((b, n, 3), U.SCALE_BASE), rtol=0, atol=tol(F32, U.SCALE_BASE))
    torch.testing.assert_close(g.opacities, torch.full((b, n), 0.5), rtol=0, atol=0)
    torch.testing.assert_close(g.rgb, torch.full((b, n, 3), 0.5), rtol=0, atol=0)


def test_activations_and_ordering_per_pixel(tol):
    """Each Gaussian n against the raw pixel (v, i, j) with n = (v h + i) w + j, written out
    pixel by pixel with Python scalars."""
    b, v, h, w = 2, 2, 3, 4
    origins, dirs, ref = _rays(b, v, h, w)
    raw = torch.randn(b, v, 14, h, w, generator=torch.Generator().manual_seed(5)) * 2.0
    g = U.pixel_gaussians(raw, origins, dirs, ref)
    assert g.means.shape == (b, v * h * w, 3) and g.opacities.shape == (b, v * h * w)
    for bi in range(b):
        for vi in range(v):
            for i in range(h):
                for j in range(w):
                    n = (vi * h + i) * w + j
                    r = raw[bi, vi, :, i, j].tolist()
                    o, d, t = origins[bi, vi, i, j].tolist(), dirs[bi, vi, i, j].tolist(), float(ref[bi, vi])
                    mean = [o[k] + d[k] * t + U.POSITION_SCALE * r[k] for k in range(3)]
                    q = [r[7] + 1.0, r[8], r[9], r[10]]
                    qn = math.sqrt(sum(c * c for c in q))
                    sig = [1.0 / (1.0 + math.exp(-x)) for x in (r[3], r[11], r[12], r[13])]
                    scale = [U.SCALE_BASE * math.exp(min(max(x, U.LOG_SCALE_MIN), U.LOG_SCALE_MAX)) for x in r[4:7]]
                    close = lambda got, want, m: torch.testing.assert_close(  # noqa: E731
                        got, torch.tensor(want, dtype=F32), rtol=0, atol=tol(F32, m, ops=8)
                    )
                    close(g.means[bi, n], mean, max(map(abs, mean)) + 1)
                    close(g.quats[bi, n], [c / qn for c in q], 1.0)
                    close(g.opacities[bi, n], sig[0], 1.0)
                    close(g.rgb[bi, n], sig[1:], 1.0)
                    close(g.scales[bi, n], scale, max(scale))
    assert torch.allclose(g.quats.norm(dim=-1), torch.ones(()), rtol=0, atol=tol(F32, 1.0, ops=8))
    assert (g.scales > 0).all() and (g.opacities > 0).all() and (g.opacities < 1).all()
    assert (g.rgb >= 0).all() and (g.rgb <= 1).all()


def test_zero_quaternion_is_finite():
    raw = torch.zeros(1, 1, 14, 1, 2)
    raw[0, 0, 7] = -1.0  # raw + identity offset = exactly zero
    raw.requires_grad_(True)
    o, d, ref = _rays(1, 1, 1, 2)
    g = U.pixel_gaussians(raw, o, d, ref)
    assert torch.isfinite(g.quats).all() and torch.allclose(g.quats.norm(dim=-1), torch.ones(()))
    sum(t.sum() for t in g).backward()
    assert torch.isfinite(raw.grad).all()


def test_raw_parameters_invert_the_activations(tol):
    b, v, h, w = 2, 2, 3, 3
    origins, dirs, ref = _rays(b, v, h, w)
    raw = torch.randn(b, v, 14, h, w, generator=torch.Generator().manual_seed(6))  # inside the clamp
    g = U.pixel_gaussians(raw, origins, dirs, ref)
    p = U.raw_parameters(g)
    assert p.shape == (b, v * h * w, 14)
    flat = raw.permute(0, 1, 3, 4, 2).reshape(b, -1, 14)
    torch.testing.assert_close(p[..., 0:3], g.means, rtol=0, atol=0)
    torch.testing.assert_close(p[..., 3], flat[..., 3], rtol=0, atol=tol(F32, 4.0, ops=8))  # logit(sigmoid(x)) = x
    log_s = flat[..., 4:7] + math.log(U.SCALE_BASE)  # log(SCALE_BASE exp(x))
    torch.testing.assert_close(p[..., 4:7], log_s, rtol=0, atol=tol(F32, float(log_s.abs().max()), ops=4))
    torch.testing.assert_close(p[..., 7:11], g.quats, rtol=0, atol=0)
    torch.testing.assert_close(p[..., 11:14], g.rgb, rtol=0, atol=0)
    # and back: the encoder's input rebuilds the activated Gaussians
    torch.testing.assert_close(torch.sigmoid(p[..., 3]), g.opacities, rtol=0, atol=tol(F32, 1.0, ops=4))
    torch.testing.assert_close(torch.exp(p[..., 4:7]), g.scales, rtol=tol(F32, 1.0, ops=4), atol=0)


def test_log_scale_is_clamped():
    raw = torch.zeros(1, 1, 14, 1, 2)
    raw[0, 0, 4:7, 0, 0], raw[0, 0, 4:7, 0, 1] = 50.0, -50.0
    g = U.pixel_gaussians(raw, *_rays(1, 1, 1, 2))
    assert torch.allclose(g.scales[0, 0], torch.tensor(U.SCALE_BASE * math.exp(U.LOG_SCALE_MAX)))
    assert torch.allclose(g.scales[0, 1], torch.tensor(U.SCALE_BASE * math.exp(U.LOG_SCALE_MIN)))


# ------------------------------------------------------------------------------- sizes, checkpoints


def test_parameter_counts():
    counts = {name: U.parameter_count(U.preset(name)) for name in ("tiny", "small", "paper")}
    assert abs(counts["paper"] / 419e6 - 1) < 0.05, counts  # the paper's U-Net: 419 M
    assert 1e5 < counts["tiny"] < 2e6 and 1e7 < counts["small"] < 3e7, counts
    assert counts["tiny"] < counts["small"] < counts["paper"]
    net = _tiny()  # the meta count is the real one
    assert counts["tiny"] == sum(p.numel() for p in net.parameters())


def test_paper_preset_is_lgm_shaped():
    cfg = U.preset("paper")
    assert cfg == U.UNetConfig() and cfg.image_size == 256 and cfg.output_size == 128
    assert cfg.up_attention == (True, True, True, False, False)  # mirrors the deep down levels
    with torch.device("meta"):
        raw, feats = U.ReconstructionUNet(cfg)(torch.empty(1, 4, 9, 256, 256))
    assert raw.shape == (1, 4, 14, 128, 128) and feats.shape == (1, 4, 32, 128, 128)  # 65,536 Gaussians


def test_checkpoint_round_trip(tmp_path):
    net = _tiny()
    with torch.no_grad():
        for p in net.parameters():  # weights a trained net could have, not the fresh init
            p.add_(0.01 * torch.randn_like(p))
    x = _views(1, 4)
    with torch.no_grad():
        before = net(x)
    save_checkpoint(tmp_path / "unet", net, net.config, step=3)
    loaded = load_checkpoint(tmp_path / "unet")
    assert isinstance(loaded.module, U.ReconstructionUNet) and loaded.config == net.config and loaded.step == 3
    with torch.no_grad():
        after = loaded.module(x)
    for a, b in zip(before, after):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(tiny, tol):
    x = _views(2, 4)
    with torch.no_grad():
        cpu = tiny(x)
        gpu = tiny.to("cuda")(x.to("cuda"))
    tiny.to("cpu")
    for a, b in zip(cpu, gpu):
        assert b.device.type == "cuda" and b.dtype == F32
        # cuDNN convolutions may run in TF32 (PyTorch's default): a 10-bit mantissa per step
        assert float((a - b.cpu()).abs().max()) <= DEPTH * 2.0**-10 * float(a.abs().max())
