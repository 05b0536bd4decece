"""The Gaussian Parameter Decoder (GPD): the avatar code Z -> the UV Gaussian map F
(docs/architecture.md "The method", Animate).

A SPADE ConvNet (Park et al. 2019): residual blocks whose parameter-free instance normalisation is
modulated per texel by gamma / beta predicted from the one-hot UV part segmentation
(`dlacli.body.regions.segmentation_onehot`, resized to each block's resolution). The trunk starts
from Z [C, r, r] and doubles the resolution per stage (nearest + conv) up to F's side R. At R it
splits into
- the canonical head: F_c [14, R, R], computed once per avatar (cacheable with the trunk output);
- the pose/view branch: the trunk's features at R concatenated with the target's conditioning maps
  (relative vertex positions and normals of the target pose, the camera's Plücker rays, all in UV
  space) -> a few convs -> F_delta [14, R, R]; its last conv starts at zero, so a fresh decoder
  has F_delta = 0 exactly.
F = F_c + F_delta. Conditioning channels: 0..2 relative positions, 3..5 normals (the pose
channels), 6.. Plücker rays (d, o x d; the view channels). A decoder with pose_conditioned /
view_conditioned off ignores those channels; with both off it has no branch and F = F_c (paper
ablation B). The segmentation is a non-persistent buffer, so checkpoints hold weights only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import Tensor, nn

from dlacli.avatar.gaussian_map import CHANNELS, OPACITY, RGB, ROTATION
from dlacli.nn import named_preset

POSE_CHANNELS = slice(0, 6)  # conditioning: relative positions (3) + normals (3)
VIEW_START = 6  # conditioning channels from here on: Plücker rays (6)
NEUTRAL_OPACITY_LOGIT = 2.0


def neutral_gaussian_map() -> Tensor:
    """[14] the neutral Gaussian: opacity logit 2, rgb 0.5, offset 0, quaternion (1, 0, 0, 0), log scale 0."""
    f = torch.zeros(CHANNELS)
    f[OPACITY] = NEUTRAL_OPACITY_LOGIT
    f[RGB] = 0.5
    f[ROTATION.start] = 1.0
    return f


@dataclass
class GPDConfig:
    latent_channels: int = 256  # Z's channels C
    latent_resolution: int = 64  # Z's side r
    out_resolution: int = 256  # F's side R (R / r a power of two)
    channels: tuple[int, ...] = (512, 256, 128)  # trunk width per resolution r, 2r, ..., R (log2(R/r) + 1 entries)
    segments: int = 11  # len(PARTS)
    condition_channels: int = 12  # relative positions (3) + normals (3) + Plücker rays (6)
    pose_conditioned: bool = True  # False with view_conditioned False = ablation B (no conditioning)
    view_conditioned: bool = True
    spade_hidden: int = 96  # hidden width of each SPADE's segmentation -> (gamma, beta) convs
    delta_channels: int = 64  # width of the pose/view branch
    head_init_scale: float = 0.01  # the canonical head's initial weights, relative to PyTorch's default

    def __post_init__(self):
        r, big = self.latent_resolution, self.out_resolution
        if r < 1 or big < r or big % r or (big // r) & (big // r - 1):
            raise ValueError(f"out_resolution / latent_resolution must be a power of two, got {big} / {r}")
        stages = (big // r).bit_length() - 1
        if len(self.channels) != stages + 1 or min(self.channels, default=0) < 1:
            raise ValueError(f"channels needs {stages + 1} positive entries (r, 2r, ..., R), got {self.channels}")
        if self.condition_channels <= VIEW_START:
            raise ValueError(f"condition_channels must be > {VIEW_START}, got {self.condition_channels}")
        for name in ("latent_channels", "segments", "spade_hidden", "delta_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


PRESETS: dict[str, GPDConfig] = {
    "tiny": GPDConfig(
        latent_channels=16,
        latent_resolution=16,
        out_resolution=64,
        channels=(32, 24, 16),
        spade_hidden=16,
        delta_channels=16,
    ),
    "small": GPDConfig(
        latent_channels=64,
        latent_resolution=32,
        out_resolution=128,
        channels=(128, 96, 64),
        spade_hidden=32,
        delta_channels=32,
    ),
    # 12,148,764 parameters (paper: 12 M)
    "paper": GPDConfig(),
}


def preset(name: str) -> GPDConfig:
    """A copy of the named GPD preset ("tiny", "small", "paper")."""
    return named_preset(PRESETS, name, "GPD")


def _conv(cin: int, cout: int, kernel: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel, padding=kernel // 2)


class SPADE(nn.Module):
    """Param-free instance norm of x [B, C, h, w], modulated by (gamma, beta) of the segmentation [1, S, h, w]."""

    def __init__(self, channels: int, segments: int, hidden: int):
        super().__init__()
        self.norm = nn.InstanceNorm2d(channels, affine=False)
        self.shared = nn.Sequential(_conv(segments, hidden), nn.ReLU())
        self.gamma, self.beta = _conv(hidden, channels), _conv(hidden, channels)

    def forward(self, x: Tensor, seg: Tensor) -> Tensor:
        a = self.shared(seg)
        return self.norm(x) * (1.0 + self.gamma(a)) + self.beta(a)


class SPADEResBlock(nn.Module):
    def __init__(self, channels: int, segments: int, hidden: int):
        super().__init__()
        # conv0 feeds norm1's instance norm, which removes any per-channel bias: it has none (a
        # bias there gets a zero gradient, and Adam turns the rounding noise into updates)
        self.norm0 = SPADE(channels, segments, hidden)
        self.conv0 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.norm1, self.conv1 = SPADE(channels, segments, hidden), _conv(channels, channels)

    def forward(self, x: Tensor, seg: Tensor) -> Tensor:
        dx = self.conv0(nnf.leaky_relu(self.norm0(x, seg), 0.2))
        dx = self.conv1(nnf.leaky_relu(self.norm1(dx, seg), 0.2))
        return x + dx


class GaussianParameterDecoder(nn.Module):
    """Z [B, C, r, r] -> (F = F_c + F_delta, F_delta), each [B, 14, R, R]."""

    def __init__(self, config: GPDConfig):
        super().__init__()
        from dlacli.body.regions import segmentation_onehot

        self.config = c = config
        with torch.device("cpu"):  # the body model loads on the CPU whatever the caller's default device
            onehot = segmentation_onehot(c.out_resolution)
        seg = torch.as_tensor(onehot, dtype=torch.float32)[None]  # [1, S, R, R]
        if seg.shape[1] != c.segments:
            raise ValueError(f"segments is {c.segments}, the UV segmentation has {seg.shape[1]} parts")
        self.stem = _conv(c.latent_channels, c.channels[0])
        self.ups = nn.ModuleList(_conv(a, b) for a, b in zip(c.channels[:-1], c.channels[1:]))
        self.blocks = nn.ModuleList(SPADEResBlock(ch, c.segments, c.spade_hidden) for ch in c.channels)
        res = c.latent_resolution
        for i in range(len(c.channels)):
            s = seg if res == c.out_resolution else nnf.interpolate(seg, size=(res, res), mode="nearest-exact")
            self.register_buffer(f"segmentation{i}", s, persistent=False)
            res *= 2
        self.canonical_head = _conv(c.channels[-1], CHANNELS)
        with torch.no_grad():
            self.canonical_head.weight.mul_(c.head_init_scale)
            self.canonical_head.bias.copy_(neutral_gaussian_map())
        used = ([*range(POSE_CHANNELS.start, POSE_CHANNELS.stop)] if c.pose_conditioned else []) + (
            [*range(VIEW_START, c.condition_channels)] if c.view_conditioned else []
        )
        self.register_buffer("condition_index", torch.tensor(used, dtype=torch.long), persistent=False)
        self.delta_branch = None
        if used:
            d = c.delta_channels
            self.delta_branch = nn.Sequential(
                _conv(c.channels[-1] + len(used), d), nn.LeakyReLU(0.2), _conv(d, d), nn.LeakyReLU(0.2)
            )
            self.delta_out = _conv(d, CHANNELS)
            nn.init.zeros_(self.delta_out.weight)
            nn.init.zeros_(self.delta_out.bias)

    def _check_z(self, z: Tensor) -> None:
        c = self.config
        r = c.latent_resolution
        assert z.ndim == 4 and z.shape[1:] == (c.latent_channels, r, r), (
            f"z must be [B, {c.latent_channels}, {r}, {r}], got {tuple(z.shape)}"
        )

    def trunk(self, z: Tensor) -> Tensor:
        """Shared features [B, channels[-1], R, R] of z [B, C, r, r]."""
        self._check_z(z)
        x = self.stem(z)
        for i, block in enumerate(self.blocks):
            if i:
                x = self.ups[i - 1](nnf.interpolate(x, scale_factor=2.0, mode="nearest"))
            x = block(x, getattr(self, f"segmentation{i}"))
        return x

    def canonical(self, z: Tensor, trunk: Tensor | None = None) -> Tensor:
        """F_c [B, 14, R, R]; `trunk` = self.trunk(z) if already computed."""
        feats = self.trunk(z) if trunk is None else trunk
        return self.canonical_head(nnf.leaky_relu(feats, 0.2))

    def delta(self, z: Tensor, conditioning: Tensor, trunk: Tensor | None = None) -> Tensor:
        """conditioning [B, condition_channels, R, R]: relative positions, normals, rays (the
        channels a config does not use — pose or view switched off — are ignored; both off: zeros)."""
        c = self.config
        big = c.out_resolution
        b = z.shape[0]
        want = [b, c.condition_channels, big, big]
        assert list(conditioning.shape) == want, f"conditioning must be {want}, got {list(conditioning.shape)}"
        if self.delta_branch is None:
            self._check_z(z)
            return z.new_zeros(b, CHANNELS, big, big)
        feats = self.trunk(z) if trunk is None else trunk
        cond = conditioning.index_select(1, self.condition_index).to(feats.dtype)
        return self.delta_out(self.delta_branch(torch.cat([feats, cond], dim=1)))

    def forward(self, z: Tensor, conditioning: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(F = F_c + F_delta, F_delta); without conditioning F_delta is zero and F = F_c."""
        feats = self.trunk(z)
        f_c = self.canonical(z, feats)
        f_delta = torch.zeros_like(f_c) if conditioning is None else self.delta(z, conditioning, feats)
        return f_c + f_delta, f_delta
