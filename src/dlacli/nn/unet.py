"""Model G: the pose-space reconstruction U-Net (LGM-style, with cross-view self-attention).

`ReconstructionUNet` takes V views of one person, each an image with its Plücker ray map
(rgb 3 + ray 6 = 9 channels, docs/architecture.md "The method", Lift part 1), and predicts one 3D Gaussian per pixel
of a half-resolution map per view (256 px in -> 128 px out: the decoder has one level fewer than
the encoder), plus per-pixel features for the encoder of Z. Residual blocks use GroupNorm (no
BatchNorm: DDP gives the same result as one process); at the attention levels the tokens of all
views of an item form one sequence, so the views exchange information.

The 14 raw Gaussian channels (per pixel; activations in `pixel_gaussians`):

    0..2   position offset    mean = ray origin + ref_depth * ray dir + POSITION_SCALE * raw  (metres, world axes)
    3      opacity logit      opacity = sigmoid(raw)                       (0 -> 0.5)
    4..6   log scale          scale = SCALE_BASE * exp(clamp(raw, LOG_SCALE_MIN, LOG_SCALE_MAX))
    7..10  quaternion offset  quat = normalise(raw + (1, 0, 0, 0)), (w, x, y, z)   (0 -> identity)
    11..13 colour logit       rgb = sigmoid(raw)                           (0 -> grey)

So an all-zero output is a grey, half-opaque, axis-aligned 1 cm Gaussian on each pixel's ray at
the reference depth; the head starts near that (weights scaled by HEAD_INIT_GAIN, zero biases).
The Gaussians of an item are ordered view-major, then row-major: index n = (v * h + i) * w + j.
`dlacli.types.Gaussians.from_rgb(*pixel_gaussians(...))` turns them into the toolkit's Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dlacli.nn import named_preset

GAUSSIAN_CHANNELS = 14
POSITION_SCALE = 0.1  # metres per unit of raw position offset
SCALE_BASE = 0.01  # metres: the scale of a zero raw log-scale
LOG_SCALE_MIN, LOG_SCALE_MAX = -6.0, 3.0  # raw log-scale clamp: scales in [2.5e-5, 0.2] m
HEAD_INIT_GAIN = 0.1  # the Gaussian rows of the head start at this fraction of PyTorch's default init
QUAT_EPS = 1e-8  # smallest quaternion norm divided by (below it the identity is returned)
RESIDUAL_SCALE = 1.0 / math.sqrt(2.0)  # keeps the variance of residual sums ~constant


@dataclass
class UNetConfig:
    """Defaults are the paper's model (LGM's big U-Net, 6 down / 5 up levels)."""

    in_channels: int = 9  # per view: rgb (3) + Plücker ray (6: d, o x d)
    image_size: int = 256  # the input side S the network is trained at (square); out side S / 2
    feature_channels: int = 32  # per-pixel features out, for the encoder (Cf)
    down_channels: tuple[int, ...] = (64, 128, 256, 512, 1024, 1024)  # one per encoder level
    up_channels: tuple[int, ...] = (1024, 1024, 512, 256, 128)  # one level fewer: out side = S / 2
    attention: tuple[bool, ...] = (False, False, False, True, True, True)  # per down level; up levels mirror
    mid_attention: bool = True  # cross-view attention in the bottleneck
    layers_per_block: int = 2  # residual blocks per down level (up levels have one more)
    head_dim: int = 64  # channels per attention head (heads = channels / head_dim)
    norm_groups: int = 32  # GroupNorm groups (the gcd with each width is used)

    def __post_init__(self) -> None:
        self.down_channels = tuple(self.down_channels)
        self.up_channels = tuple(self.up_channels)
        self.attention = tuple(self.attention)
        n = len(self.down_channels)
        if n < 2 or len(self.up_channels) != n - 1:
            raise ValueError(
                f"need >= 2 down levels and exactly one up level fewer, got {n} down, {len(self.up_channels)} up"
            )
        if len(self.attention) != n:
            raise ValueError(f"attention has {len(self.attention)} entries for {n} down levels")
        ints = (
            self.in_channels,
            self.image_size,
            self.feature_channels,
            self.layers_per_block,
            self.head_dim,
            self.norm_groups,
            *self.down_channels,
            *self.up_channels,
        )
        if any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in ints):
            raise ValueError("channel counts, sizes and layer counts must be positive ints")
        if self.image_size % 2 ** (n - 1):
            raise ValueError(f"image_size {self.image_size} is not divisible by 2^{n - 1} ({n} down levels)")
        for c in self.attended_channels():
            if c % self.head_dim:
                raise ValueError(f"attention width {c} is not a multiple of head_dim {self.head_dim}")

    @property
    def up_attention(self) -> tuple[bool, ...]:
        """Up level k mirrors down level n - 1 - k (the deepest first)."""
        return tuple(reversed(self.attention))[: len(self.up_channels)]

    @property
    def output_size(self) -> int:
        return self.image_size // 2

    def attended_channels(self) -> list[int]:
        mid = [self.down_channels[-1]] if self.mid_attention else []
        down = [c for c, a in zip(self.down_channels, self.attention) if a]
        return down + mid + [c for c, a in zip(self.up_channels, self.up_attention) if a]


PRESETS: dict[str, UNetConfig] = {
    # 64 px in, 32 px out; 861,446 parameters; trains on 2 CPU cores
    "tiny": UNetConfig(
        image_size=64,
        feature_channels=8,
        down_channels=(16, 32, 64, 64),
        up_channels=(64, 32, 32),
        attention=(False, False, True, True),
        layers_per_block=1,
        head_dim=16,
        norm_groups=8,
    ),
    # 128 px in, 64 px out; 25,506,878 parameters
    "small": UNetConfig(
        image_size=128,
        feature_channels=16,
        down_channels=(32, 64, 128, 256, 256),
        up_channels=(256, 256, 128, 64),
        attention=(False, False, False, True, True),
        layers_per_block=2,
        head_dim=32,
        norm_groups=16,
    ),
    # the paper's 256 px in, 128 px out (LGM big); 415,032,430 parameters (the paper states 419 M: -0.95 %)
    "paper": UNetConfig(),
}


def preset(name: str) -> UNetConfig:
    """A copy of the named U-Net preset ("tiny", "small", "paper")."""
    return named_preset(PRESETS, name, "U-Net")


# --------------------------------------------------------------------------------------------
# building blocks


def _norm(channels: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(channels, groups), channels)


class ResBlock(nn.Module):
    """GroupNorm, SiLU, 3x3 conv, twice, plus a (1x1 conv where the width changes) shortcut."""

    def __init__(self, cin: int, cout: int, groups: int):
        super().__init__()
        self.norm1, self.conv1 = _norm(cin, groups), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = _norm(cout, groups), nn.Conv2d(cout, cout, 3, padding=1)
        self.shortcut = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return (self.shortcut(x) + h) * RESIDUAL_SCALE


class CrossViewAttention(nn.Module):
    """Residual multi-head self-attention over the tokens of all V views of an item together:
    x [B*V, C, h, w] -> the same shape, attending over a (B, V*h*w, C) sequence."""

    def __init__(self, channels: int, head_dim: int, groups: int):
        super().__init__()
        self.heads = channels // head_dim
        self.norm = _norm(channels, groups)
        self.qkv = nn.Linear(channels, 3 * channels, bias=False)
        self.proj = nn.Linear(channels, channels)

    def forward(self, x: Tensor, views: int) -> Tensor:
        bv, c, h, w = x.shape
        b = bv // views
        t = self.norm(x).reshape(b, views, c, h * w).permute(0, 1, 3, 2).reshape(b, views * h * w, c)
        q, k, v = self.qkv(t).reshape(b, -1, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v)  # [B, heads, V*h*w, head_dim]
        a = self.proj(a.transpose(1, 2).reshape(b, views * h * w, c))
        a = a.reshape(b, views, h * w, c).permute(0, 1, 3, 2).reshape(bv, c, h, w)
        return (x + a) * RESIDUAL_SCALE


class Level(nn.Module):
    """Residual blocks, each optionally followed by cross-view attention."""

    def __init__(self, cins: list[int], cout: int, attend: bool, cfg: UNetConfig):
        super().__init__()
        self.blocks = nn.ModuleList(ResBlock(c, cout, cfg.norm_groups) for c in cins)
        attn = (CrossViewAttention(cout, cfg.head_dim, cfg.norm_groups) for _ in cins) if attend else ()
        self.attn = nn.ModuleList(attn)

    def step(self, i: int, x: Tensor, views: int) -> Tensor:
        x = self.blocks[i](x)
        return self.attn[i](x, views) if len(self.attn) else x


class Upsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


# --------------------------------------------------------------------------------------------
# the network


class ReconstructionUNet(nn.Module):
    """views [B, V, in_channels, S, S] -> (raw [B, V, 14, S/2, S/2], features [B, V, Cf, S/2, S/2]).

    Encoder: a 3x3 conv, then per level `layers_per_block` blocks and a stride-2 conv (not after
    the last); every block output and every downsampled map is a skip. Bottleneck: block,
    attention, block. Decoder (one level fewer): per level `layers_per_block + 1` blocks on
    [h, skip] (the deepest skips first), nearest x2 + 3x3 conv between levels. The shallowest
    skips (full resolution) are not used. Head: GroupNorm, SiLU, 1x1 conv to 14 + Cf channels.
    S may be any multiple of 2^(levels - 1); `config.image_size` is the size it is trained at."""

    def __init__(self, config: UNetConfig):
        super().__init__()
        self.config = cfg = config
        c0, lpb = cfg.down_channels[0], cfg.layers_per_block
        self.conv_in = nn.Conv2d(cfg.in_channels, c0, 3, padding=1)
        skips, prev = [c0], c0
        self.down, self.downsample = nn.ModuleList(), nn.ModuleList()
        for k, (c, attend) in enumerate(zip(cfg.down_channels, cfg.attention)):
            self.down.append(Level([prev] + [c] * (lpb - 1), c, attend, cfg))
            skips += [c] * lpb
            if k < len(cfg.down_channels) - 1:
                self.downsample.append(nn.Conv2d(c, c, 3, stride=2, padding=1))
                skips.append(c)
            prev = c
        self.mid = Level([prev, prev], prev, False, cfg)
        self.mid_attn = CrossViewAttention(prev, cfg.head_dim, cfg.norm_groups) if cfg.mid_attention else None
        self.up, self.upsample = nn.ModuleList(), nn.ModuleList()
        for k, (c, attend) in enumerate(zip(cfg.up_channels, cfg.up_attention)):
            cins = []
            for _ in range(lpb + 1):
                cins.append(prev + skips.pop())
                prev = c
            self.up.append(Level(cins, c, attend, cfg))
            if k < len(cfg.up_channels) - 1:
                self.upsample.append(Upsample(c))
        self.norm_out = _norm(prev, cfg.norm_groups)
        self.head = nn.Conv2d(prev, GAUSSIAN_CHANNELS + cfg.feature_channels, 1)
        self.reset_head()

    def reset_head(self) -> None:
        """Start near the all-zero output (module docstring): small Gaussian weights, zero biases."""
        self.head.reset_parameters()
        with torch.no_grad():
            self.head.weight[:GAUSSIAN_CHANNELS].mul_(HEAD_INIT_GAIN)
            self.head.bias[:GAUSSIAN_CHANNELS].zero_()

    def forward(self, views: Tensor) -> tuple[Tensor, Tensor]:
        cfg = self.config
        assert views.ndim == 5 and views.shape[2] == cfg.in_channels, (
            f"views must be [B, V, {cfg.in_channels}, S, S], got {tuple(views.shape)}"
        )
        b, v, _, s, s2 = views.shape
        step = 2 ** (len(cfg.down_channels) - 1)
        assert s == s2 and s % step == 0, f"views must be square with side divisible by {step}, got {s}x{s2}"
        x = self.conv_in(views.reshape(b * v, cfg.in_channels, s, s))
        skips = [x]
        for k, level in enumerate(self.down):
            for i in range(len(level.blocks)):
                x = level.step(i, x, v)
                skips.append(x)
            if k < len(self.downsample):
                x = self.downsample[k](x)
                skips.append(x)
        x = self.mid.blocks[0](x)
        if self.mid_attn is not None:
            x = self.mid_attn(x, v)
        x = self.mid.blocks[1](x)
        for k, level in enumerate(self.up):
            for i in range(len(level.blocks)):
                x = level.step(i, torch.cat([x, skips.pop()], dim=1), v)
            if k < len(self.upsample):
                x = self.upsample[k](x)
        out = self.head(F.silu(self.norm_out(x)))
        out = out.reshape(b, v, out.shape[1], out.shape[2], out.shape[3])
        return out[:, :, :GAUSSIAN_CHANNELS], out[:, :, GAUSSIAN_CHANNELS:]


# --------------------------------------------------------------------------------------------
# pixel-aligned Gaussians


class PixelGaussians(NamedTuple):
    means: Tensor  # [B, N, 3] world, metres (N = V * h * w, view-major, then row-major)
    quats: Tensor  # [B, N, 4] (w, x, y, z) unit
    scales: Tensor  # [B, N, 3] metres, > 0
    opacities: Tensor  # [B, N] in (0, 1)
    rgb: Tensor  # [B, N, 3] in [0, 1]


def _flat(x: Tensor) -> Tensor:
    """[B, V, h, w, K] -> [B, V*h*w, K]."""
    return x.reshape(x.shape[0], -1, x.shape[-1])


def pixel_gaussians(raw: Tensor, origins: Tensor, dirs: Tensor, ref_depth: Tensor) -> PixelGaussians:
    """raw [B, V, 14, h, w]; origins, dirs [B, V, h, w, 3] the world rays through the output pixels'
    centres (unit dirs); ref_depth [B, V] metres: camera-to-subject distance. Activations as in the
    module docstring; differentiable everywhere (no NaN, also for a zero quaternion)."""
    assert raw.ndim == 5 and raw.shape[2] == GAUSSIAN_CHANNELS, f"raw must be [B, V, 14, h, w], got {tuple(raw.shape)}"
    b, v, _, h, w = raw.shape
    assert origins.shape == dirs.shape == (b, v, h, w, 3), (tuple(origins.shape), tuple(dirs.shape), (b, v, h, w, 3))
    assert ref_depth.shape == (b, v), (tuple(ref_depth.shape), (b, v))
    r = raw.permute(0, 1, 3, 4, 2)  # [B, V, h, w, 14]
    means = origins + dirs * ref_depth[:, :, None, None, None] + POSITION_SCALE * r[..., 0:3]
    opacities = torch.sigmoid(r[..., 3])
    scales = SCALE_BASE * torch.exp(r[..., 4:7].clamp(LOG_SCALE_MIN, LOG_SCALE_MAX))
    q = r[..., 7:11] + r.new_tensor([1.0, 0.0, 0.0, 0.0])
    norm = q.norm(dim=-1, keepdim=True)
    quats = torch.where(norm > QUAT_EPS, q / norm.clamp_min(QUAT_EPS), r.new_tensor([1.0, 0.0, 0.0, 0.0]))
    rgb = torch.sigmoid(r[..., 11:14])
    return PixelGaussians(_flat(means), _flat(quats), _flat(scales), opacities.reshape(b, -1), _flat(rgb))


def raw_parameters(g: PixelGaussians) -> Tensor:
    """[B, N, 14] the Gaussians as the encoder's input: means (3), opacity logit (1), log scales (3),
    quats (4), rgb (3): one row per Gaussian (the 3DGS PLY's activation spaces)."""
    eps = torch.finfo(g.opacities.dtype).eps
    logit = torch.logit(g.opacities, eps=eps)
    return torch.cat([g.means, logit[..., None], torch.log(g.scales), g.quats, g.rgb], dim=-1)


def parameter_count(config: UNetConfig) -> int:
    """Parameters of the network `config` builds, counted on the meta device (no memory)."""
    with torch.device("meta"):
        return sum(p.numel() for p in ReconstructionUNet(config).parameters())
