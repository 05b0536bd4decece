"""The completion prior's network (nn/completion.py): zero-initialised head, bounded output, the
checkpoint round trip, shape checks."""

from __future__ import annotations

import pytest
import torch


def _net(width: int = 8, resolution: int = 32):
    from dlacli.nn.completion import CompletionConfig, CompletionNet

    torch.manual_seed(0)
    return CompletionNet(CompletionConfig(width=width, resolution=resolution))


def test_untrained_network_is_zero_and_a_trained_one_is_bounded():
    from dlacli.nn.completion import INPUTS, corrected_colour

    net = _net()
    x = torch.randn(2, INPUTS, 32, 32)
    assert torch.equal(net(x), torch.zeros(2, 3, 32, 32))
    torch.nn.init.normal_(net.head.weight, std=0.3)
    t = net(x)
    assert t.abs().max() <= 1.0 and t.abs().max() > 0.1
    rgb = torch.rand(2, 3, 32, 32)
    out = corrected_colour(rgb, t)
    assert out.min() >= 0.0 and out.max() <= 1.0
    assert torch.equal(corrected_colour(rgb, torch.zeros_like(rgb)), rgb)  # t == 0: the rule exactly


def test_checkpoint_round_trip_keeps_the_outputs(tmp_path):
    from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
    from dlacli.nn.completion import INPUTS

    net = _net()
    torch.nn.init.normal_(net.head.weight, std=0.1)
    digest = save_checkpoint(tmp_path / "prior", net, net.config, step=3)
    loaded = load_checkpoint(tmp_path / "prior")
    x = torch.randn(1, INPUTS, 32, 32)
    assert loaded.hash == digest and loaded.step == 3 and loaded.config == net.config
    assert torch.equal(loaded.module(x), net.eval()(x))


def test_shapes_are_checked():
    from dlacli.nn.completion import INPUTS, CompletionConfig, CompletionNet

    with pytest.raises(AssertionError, match=r"\[B, 22, 32, 32\]"):
        _net()(torch.zeros(1, INPUTS, 16, 16))
    with pytest.raises(ValueError, match="multiple of 8"):
        CompletionNet(CompletionConfig(resolution=36))
