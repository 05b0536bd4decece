"""The adversarial critic of training: a PatchGAN discriminator with least-squares losses.

pix2pix's N-layer PatchGAN (Isola et al. 2017): `layers` 4x4 stride-2 convs (the first without a
norm), one 4x4 stride-1 conv with a norm, and a 4x4 stride-1 conv to one score per patch; LeakyReLU
0.2 between them. Affine InstanceNorm replaces BatchNorm, so DDP gives the same result as one
process with the combined batch. `layers=3` is the classic 70x70 receptive field; the paper preset
uses 4 (142x142 patches) to reach the paper's 7 M parameters. The losses are LSGAN's (Mao et al.
2017) with targets real = 1, fake = 0 (docs/architecture.md "The method", Training).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from dlacli.nn import named_preset

KERNEL, PADDING, SLOPE = 4, 1, 0.2


@dataclass
class DiscriminatorConfig:
    in_channels: int = 3  # rgb
    base_channels: int = 64  # width of the first conv; doubles per layer up to max_channels
    layers: int = 3  # stride-2 convs (pix2pix n_layers); side / 2^layers, minus 2, scores per side
    max_channels: int = 512

    def __post_init__(self) -> None:
        vals = (self.in_channels, self.base_channels, self.layers, self.max_channels)
        if any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in vals):
            raise ValueError("in_channels, base_channels, layers and max_channels must be positive ints")
        if self.layers > 16:  # each halves the image: 16 already leaves 1 px of a 65,536 px side
            raise ValueError(f"layers = {self.layers}: at most 16")

    def widths(self) -> list[int]:
        """Output channels of the layers + 1 feature convs (the stride-2 ones, then the stride-1 one)."""
        return [min(self.base_channels * 2**k, self.max_channels) for k in range(self.layers + 1)]


PRESETS: dict[str, DiscriminatorConfig] = {
    "tiny": DiscriminatorConfig(base_channels=16, layers=2, max_channels=64),  # 42,961 parameters
    "small": DiscriminatorConfig(base_channels=32, layers=3, max_channels=256),  # 694,689 parameters
    "paper": DiscriminatorConfig(base_channels=64, layers=4),  # 6,960,961 parameters (the paper states 7 M: -0.6 %)
}


def preset(name: str) -> DiscriminatorConfig:
    """A copy of the named discriminator preset ("tiny", "small", "paper")."""
    return named_preset(PRESETS, name, "discriminator")


class PatchDiscriminator(nn.Module):
    """images [B, in_channels, H, W] in [0, 1] -> scores [B, 1, h, w], one per overlapping patch
    (h = H / 2^layers - 2 for H divisible by 2^layers). Higher means "looks real"."""

    def __init__(self, config: DiscriminatorConfig):
        super().__init__()
        self.config = config
        widths = config.widths()
        layers: list[nn.Module] = [nn.Conv2d(config.in_channels, widths[0], KERNEL, 2, PADDING), nn.LeakyReLU(SLOPE)]
        for k in range(1, len(widths)):
            stride = 2 if k < config.layers else 1
            layers += [
                nn.Conv2d(widths[k - 1], widths[k], KERNEL, stride, PADDING, bias=False),  # the norm has the bias
                nn.InstanceNorm2d(widths[k], affine=True),
                nn.LeakyReLU(SLOPE),
            ]
        layers.append(nn.Conv2d(widths[-1], 1, KERNEL, 1, PADDING))
        self.net = nn.Sequential(*layers)

    def forward(self, images: Tensor) -> Tensor:
        assert images.ndim == 4 and images.shape[1] == self.config.in_channels, (
            f"images must be [B, {self.config.in_channels}, H, W], got {tuple(images.shape)}"
        )
        return self.net(images * 2.0 - 1.0)  # [0, 1] -> [-1, 1], pix2pix's input range


def lsgan_discriminator_loss(real_scores: Tensor, fake_scores: Tensor) -> Tensor:
    """0.5 * (mean (D(x) - 1)^2 + mean D(G)^2): the critic pushes real scores to 1, fake ones to 0."""
    return 0.5 * ((real_scores - 1.0).square().mean() + fake_scores.square().mean())


def lsgan_generator_loss(fake_scores: Tensor) -> Tensor:
    """0.5 * mean (D(G) - 1)^2: the generator pushes the scores of its images to 1."""
    return 0.5 * (fake_scores - 1.0).square().mean()


def parameter_count(config: DiscriminatorConfig) -> int:
    """Parameters of the network `config` builds, counted on the meta device (no memory)."""
    with torch.device("meta"):
        return sum(p.numel() for p in PatchDiscriminator(config).parameters())
