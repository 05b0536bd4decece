"""The residual lift's network: a small UV-space ConvNet that corrects mesh unprojection.

    [F (the unprojected Gaussian map, 14 x R x R) ; observation features (stages/observations.py)]
        --resize to `internal` x `internal`--> U-shaped ConvNet (GroupNorm, SiLU; two downsamplings)
        --> t = tanh(head) [10, internal, internal] --bilinear to R--> bounded corrections of F:

    opacity logit  + max_opacity * t0
    rgb            + t * (1 - rgb) where t > 0, + t * rgb where t < 0   (stays in [0, 1])
    offset         + max_offset * t  (metres, in the texel's tangent frame)
    rotation       untouched
    log scale      + max_log_scale * t

The head is initialised to zero, so the untrained network returns F bit for bit (x + 0 = x):
the residual lift starts exactly at unprojection and training can only move it from there.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import nn

from dlacli.avatar import gaussian_map as gm

CORRECTIONS = 10  # opacity 1, rgb 3, offset 3, log scale 3
_IN_F = (0, 1, 2, 3, 4, 5, 6, 11, 12, 13)  # F's channels the net reads (rotation is identity after unprojection)


@dataclass
class ResidualNetConfig:
    features: int = 20  # observation feature channels (stages/observations.feature_count)
    width: int = 32  # channels at the internal resolution; x2 and x4 below it
    internal: int = 128  # the UV resolution the net works at (the data's measured need)
    groups: int = 8  # GroupNorm groups
    max_opacity: float = 4.0  # logit units
    max_offset: float = 0.04  # metres
    max_log_scale: float = 1.0
    resolution: int = 128  # the map resolution it was trained at (the lift's default)
    gaussians: int = 32_768  # the Gaussians it was trained with (the lift's default)


class _Block(nn.Module):
    def __init__(self, c: int, groups: int):
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(min(groups, c), c), nn.Conv2d(c, c, 3, padding=1)
        self.n2, self.c2 = nn.GroupNorm(min(groups, c), c), nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.c2(nnf.silu(self.n2(self.c1(nnf.silu(self.n1(x))))))


def _resize(x: torch.Tensor, size: int) -> torch.Tensor:
    """[B, C, r, r] -> [B, C, size, size]: area when shrinking, bilinear when growing."""
    if x.shape[-1] == size:
        return x
    if x.shape[-1] > size:
        return nnf.interpolate(x, size=(size, size), mode="area")
    return nnf.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)


class ResidualNet(nn.Module):
    """F [B, 14, R, R] + features [B, features, R, R] -> corrected F (module doc)."""

    def __init__(self, config: ResidualNetConfig):
        super().__init__()
        self.config = c = config
        w, g = c.width, c.groups
        self.stem = nn.Conv2d(len(_IN_F) + c.features, w, 3, padding=1)
        self.enc1 = _Block(w, g)
        self.down1 = nn.Conv2d(w, 2 * w, 3, stride=2, padding=1)
        self.enc2 = _Block(2 * w, g)
        self.down2 = nn.Conv2d(2 * w, 4 * w, 3, stride=2, padding=1)
        self.mid = nn.Sequential(_Block(4 * w, g), _Block(4 * w, g))
        self.up2 = nn.Conv2d(4 * w, 2 * w, 3, padding=1)
        self.dec2 = _Block(2 * w, g)
        self.up1 = nn.Conv2d(2 * w, w, 3, padding=1)
        self.dec1 = _Block(w, g)
        self.norm_out = nn.GroupNorm(min(g, w), w)
        self.head = nn.Conv2d(w, CORRECTIONS, 3, padding=1)
        nn.init.zeros_(self.head.weight)  # the untrained net is unprojection, bit for bit
        nn.init.zeros_(self.head.bias)

    @staticmethod
    def _normalised(fmap: torch.Tensor) -> torch.Tensor:
        """F's channels the net reads, scaled to about unit range."""
        x = fmap[:, list(_IN_F)]
        shift = torch.tensor([0.0, 0.5, 0.5, 0.5, 0, 0, 0, -0.5, -0.5, -1.6], dtype=x.dtype, device=x.device)
        scale = torch.tensor([0.25, 2, 2, 2, 20, 20, 20, 1, 1, 1], dtype=x.dtype, device=x.device)
        return (x - shift[:, None, None]) * scale[:, None, None]

    def corrections(self, fmap: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """t in (-1, 1) [B, 10, R, R]: the bounded corrections before scaling (module doc)."""
        assert fmap.ndim == 4 and fmap.shape[1] == gm.CHANNELS, f"fmap [B, 14, R, R], got {tuple(fmap.shape)}"
        assert features.shape[0] == fmap.shape[0] and features.shape[1] == self.config.features, (
            f"features [B, {self.config.features}, R, R], got {tuple(features.shape)}"
        )
        res, n = fmap.shape[-1], self.config.internal
        x = torch.cat([_resize(self._normalised(fmap), n), _resize(features.to(fmap), n)], dim=1)
        e1 = self.enc1(self.stem(x))
        e2 = self.enc2(self.down1(e1))
        m = self.mid(self.down2(e2))
        d2 = self.dec2(self.up2(nnf.interpolate(m, scale_factor=2.0, mode="nearest")) + e2)
        d1 = self.dec1(self.up1(nnf.interpolate(d2, scale_factor=2.0, mode="nearest")) + e1)
        t = torch.tanh(self.head(nnf.silu(self.norm_out(d1))))
        return _resize(t, res) if res != n else t

    def apply_corrections(self, fmap: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """F [B, 14, R, R] moved by t [B, 10, R, R] within the config's bounds (module doc)."""
        c = self.config
        rgb = fmap[:, gm.RGB]
        t_rgb = t[:, 1:4]
        parts = [
            fmap[:, gm.OPACITY] + c.max_opacity * t[:, 0:1],
            rgb + t_rgb * torch.where(t_rgb > 0, 1.0 - rgb, rgb),
            fmap[:, gm.OFFSET] + c.max_offset * t[:, 4:7],
            fmap[:, gm.ROTATION],
            fmap[:, gm.LOG_SCALE] + c.max_log_scale * t[:, 7:10],
        ]
        return torch.cat(parts, dim=1)

    def forward(self, fmap: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (corrected F [B, 14, R, R], t [B, 10, R, R])."""
        t = self.corrections(fmap, features)
        return self.apply_corrections(fmap, t), t
