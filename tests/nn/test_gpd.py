"""The Gaussian Parameter Decoder: shapes and gradients, which conditioning channels the output
depends on under each switch, a fresh decoder's F_delta = 0 and near-neutral F_c, the
segmentation buffers, parameter counts, save/load."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
from dlacli.avatar.gaussian_map import CHANNELS, LOG_SCALE, OFFSET, OPACITY, RGB, ROTATION
from dlacli.body.regions import PARTS, segmentation_onehot
from dlacli.errors import DlaInputError
from dlacli.nn.gpd import (
    PRESETS,
    GaussianParameterDecoder,
    GPDConfig,
    neutral_gaussian_map,
    preset,
)

POSE = slice(0, 6)  # relative positions + normals
VIEW = slice(6, 12)  # Plücker rays


def tiny(**changes) -> GPDConfig:
    return dataclasses.replace(preset("tiny"), **changes)


def make(cfg: GPDConfig, seed: int = 0, trained_delta: bool = False) -> GaussianParameterDecoder:
    """A decoder; `trained_delta` replaces the zero-initialised last conv of the pose/view branch by
    random weights, standing for a trained one (a fresh branch outputs exactly zero)."""
    torch.manual_seed(seed)
    net = GaussianParameterDecoder(cfg).eval()
    if trained_delta:
        for p in net.delta_out.parameters():
            nn.init.normal_(p, std=0.1)
    return net


def inputs(cfg: GPDConfig, b: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, cfg.latent_channels, cfg.latent_resolution, cfg.latent_resolution, generator=g)
    cond = torch.randn(b, cfg.condition_channels, cfg.out_resolution, cfg.out_resolution, generator=g)
    return z, cond


def changed(cond: torch.Tensor, channels: slice) -> torch.Tensor:
    out = cond.clone()
    out[:, channels] = torch.randn(out[:, channels].shape, generator=torch.Generator().manual_seed(9))
    return out


# ------------------------------------------------------------------------------------ shapes, gradients


def test_shapes_and_finite_gradients():
    cfg = tiny()
    net = make(cfg, trained_delta=True)
    z, cond = inputs(cfg)
    z.requires_grad_(True)
    cond.requires_grad_(True)
    f, f_delta = net(z, cond)
    shape = (2, CHANNELS, cfg.out_resolution, cfg.out_resolution)
    assert f.shape == f_delta.shape == shape and f.dtype == torch.float32
    (f.square().mean() + f_delta.square().mean()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().max() > 0, name
    for t in (z, cond):
        assert torch.isfinite(t.grad).all() and t.grad.abs().max() > 0


def test_fresh_decoder_gradients_are_finite():
    net = make(tiny())  # zero-initialised branch end: its inner layers get zero (finite) gradients
    z, cond = inputs(tiny())
    f, _ = net(z, cond)
    f.mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())
    assert net.delta_out.weight.grad.abs().max() > 0  # the zero conv itself learns


def test_trunk_canonical_delta_compose():
    cfg = tiny()
    net = make(cfg, trained_delta=True)
    z, cond = inputs(cfg)
    with torch.no_grad():
        feats = net.trunk(z)
        assert feats.shape == (2, cfg.channels[-1], cfg.out_resolution, cfg.out_resolution)
        f_c, f_d = net.canonical(z), net.delta(z, cond)
        assert torch.equal(net.canonical(z, feats), f_c) and torch.equal(net.delta(z, cond, feats), f_d)
        f, f_delta = net(z, cond)
        assert torch.equal(f_delta, f_d) and torch.equal(f, f_c + f_d)
        f0, d0 = net(z)  # no conditioning: the canonical map alone
        assert torch.equal(f0, f_c) and not d0.any()


# ------------------------------------------------------------------------------------ conditioning switches


def test_output_depends_on_pose_and_view_channels():
    cfg = tiny()
    net = make(cfg, trained_delta=True)
    z, cond = inputs(cfg)
    with torch.no_grad():
        ref, _ = net(z, cond)
        assert not torch.allclose(net(z, changed(cond, POSE))[0], ref)
        assert not torch.allclose(net(z, changed(cond, VIEW))[0], ref)
        assert not torch.allclose(net(z, changed(cond, slice(0, 3)))[0], ref)  # relative positions alone
        assert not torch.allclose(net(z, changed(cond, slice(3, 6)))[0], ref)  # normals alone


@pytest.mark.parametrize("off, on", [("pose", VIEW), ("view", POSE)])
def test_switched_off_channels_are_ignored(off, on):
    cfg = tiny(**{f"{off}_conditioned": False})
    net = make(cfg, trained_delta=True)
    z, cond = inputs(cfg)
    ignored = POSE if off == "pose" else VIEW
    with torch.no_grad():
        ref, _ = net(z, cond)
        assert torch.equal(net(z, changed(cond, ignored))[0], ref)
        assert not torch.allclose(net(z, changed(cond, on))[0], ref)
        nan = cond.clone()
        nan[:, ignored] = float("nan")  # ignored means not read at all
        assert torch.equal(net(z, nan)[0], ref)


def test_no_conditioning_is_the_canonical_map():
    cfg = tiny(pose_conditioned=False, view_conditioned=False)
    torch.manual_seed(0)
    net = GaussianParameterDecoder(cfg).eval()
    assert not hasattr(net, "delta_out") and net.delta_branch is None
    z, cond = inputs(cfg)
    with torch.no_grad():
        f_c = net.canonical(z)
        f, f_delta = net(z, cond)
        assert torch.equal(f, f_c) and not f_delta.any()
        assert torch.equal(net(z, torch.randn_like(cond) * 100)[0], f_c)
        assert not net.delta(z, cond).any()
    full = make(tiny())
    n_full = sum(p.numel() for p in full.parameters())
    assert sum(p.numel() for p in net.parameters()) < n_full  # no branch weights at all


# ------------------------------------------------------------------------------------ initialisation


def test_fresh_delta_is_exactly_zero_and_canonical_near_neutral():
    cfg = tiny()
    net = make(cfg)
    z, cond = inputs(cfg)
    with torch.no_grad():
        f, f_delta = net(z, cond)
    assert torch.count_nonzero(f_delta) == 0
    neutral = neutral_gaussian_map()[None, :, None, None]
    # near: every channel within 0.1 of the neutral Gaussian (opacity 0.88 +- 0.01, colour 0.5 +- 0.1,
    # offsets under 0.1 m, a quaternion within 0.1 of identity, scale within 10 %), for z ~ N(0, 1)
    assert (f - neutral).abs().max() < 0.1


def test_channel_layout_and_neutral_map():
    slices = (OPACITY, RGB, OFFSET, ROTATION, LOG_SCALE)
    covered = [i for s in slices for i in range(CHANNELS)[s]]
    assert CHANNELS == 14 and covered == list(range(14))
    n = neutral_gaussian_map()
    assert n[OPACITY].tolist() == [2.0] and n[RGB].tolist() == [0.5] * 3 and n[OFFSET].tolist() == [0.0] * 3
    assert n[ROTATION].tolist() == [1.0, 0.0, 0.0, 0.0] and n[LOG_SCALE].tolist() == [0.0] * 3


# ------------------------------------------------------------------------------------ segmentation


def test_segmentation_buffers_are_fixed_and_not_saved():
    cfg = tiny()
    net = make(cfg)
    assert not any("segmentation" in k for k in net.state_dict())
    full = segmentation_onehot(cfg.out_resolution)  # [S, R, R]
    assert full.shape[0] == len(PARTS) == cfg.segments
    res = cfg.latent_resolution
    for i in range(len(cfg.channels)):
        buf = getattr(net, f"segmentation{i}")
        f = cfg.out_resolution // res
        rows = np.arange(res) * f + f // 2  # nearest source texel of each target texel's centre
        expect = full[:, rows][:, :, rows] if f > 1 else full
        assert buf.shape == (1, cfg.segments, res, res)
        assert np.array_equal(buf[0].numpy(), expect)
        res *= 2


def test_output_depends_on_the_segmentation():
    cfg = tiny()
    net = make(cfg)
    z, _ = inputs(cfg)
    with torch.no_grad():
        ref = net.canonical(z)
        net.segmentation0 = net.segmentation0.flip(-1)
        assert not torch.allclose(net.canonical(z), ref)


def test_batch_items_are_independent(tol):
    cfg = tiny()
    net = make(cfg, trained_delta=True)
    z, cond = inputs(cfg, seed=0)
    z2, cond2 = inputs(cfg, seed=1)
    with torch.no_grad():
        ref, _ = net(z, cond)
        out, _ = net(torch.cat([z[:1], z2[1:]]), torch.cat([cond[:1], cond2[1:]]))
    fan_in = 9 * max(cfg.channels)  # roundings per conv output, a few layers deep
    torch.testing.assert_close(out[0], ref[0], rtol=0, atol=tol(torch.float32, ref[0].abs().max(), ops=fan_in))
    assert not torch.allclose(out[1], ref[1])


# ------------------------------------------------------------------------------------ presets, checkpoints


def count(cfg: GPDConfig) -> int:
    with torch.device("meta"):
        return sum(p.numel() for p in GaussianParameterDecoder(cfg).parameters())


def test_parameter_counts():
    counts = {name: count(preset(name)) for name in ("tiny", "small", "paper")}
    assert counts["tiny"] < counts["small"] < counts["paper"]
    assert abs(counts["paper"] - 12e6) <= 0.05 * 12e6  # the paper's GPD: 12 M
    p = preset("paper")
    assert (p.latent_channels, p.latent_resolution, p.out_resolution) == (256, 64, 256)
    s = preset("small")
    assert (s.latent_resolution, s.out_resolution) == (32, 128)


def test_presets_and_config_validation():
    assert set(PRESETS) == {"tiny", "small", "paper"}
    with pytest.raises(DlaInputError, match="--preset"):
        preset("huge")
    with pytest.raises(ValueError, match="power of two"):
        GPDConfig(latent_resolution=16, out_resolution=48, channels=(8, 8))
    with pytest.raises(ValueError, match="channels"):
        GPDConfig(latent_resolution=16, out_resolution=64, channels=(8, 8))


@pytest.mark.parametrize("switches", [(True, True), (False, False)])
def test_save_load_keeps_outputs(tmp_path, switches):
    cfg = tiny(pose_conditioned=switches[0], view_conditioned=switches[1])
    net = make(cfg, seed=3)
    if net.delta_branch is not None:
        with torch.no_grad():
            net.delta_out.weight.normal_(std=0.1)
    z, cond = inputs(cfg)
    save_checkpoint(tmp_path / "gpd", net, cfg)
    loaded = load_checkpoint(tmp_path / "gpd")
    assert isinstance(loaded.module, GaussianParameterDecoder) and loaded.config == cfg
    with torch.no_grad():
        for a, b in zip(net(z, cond), loaded.module(z, cond)):
            assert torch.equal(a, b)
