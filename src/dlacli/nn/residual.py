"""The residual lift's network: a small UV-space ConvNet that corrects mesh unprojection.

    [F (the unprojected Gaussian map, 14 x R x R) ; observation features (stages/lift/observations.py)]
        --resize to `internal` x `internal`--> U-shaped ConvNet (GroupNorm, SiLU; two downsamplings)
        --> t = tanh(head) [10, internal, internal] --bilinear to R--> bounded corrections of F:

    opacity logit  + max_opacity * t0
    rgb            + t * (1 - rgb) where t > 0, + t * rgb where t < 0   (stays in [0, 1])
    offset         + max_offset * t  (metres, in the texel's tangent frame)
    rotation       untouched
    log scale      + max_log_scale * t

The head is initialised to zero, so the untrained network returns F bit for bit (x + 0 = x):
the residual lift starts exactly at unprojection and training can only move it from there.

F_delta, the colour gain (config.gain): the network is then also the codec's decoder
"residual-gain" (found by its checkpoint hash, like the learned method's "gpd"). Its avatar
code is z = [F' (14) ; view falloff k (1) ; lighting code (light_channels)] [15 + L, R, R]: the
lighting code is pooled from the trunk's bottleneck over the input views' evidence, constant
over the map. F_c = F'; F_delta changes colour only:

    rgb -> rgb * shading(k, cos) * gain,   gain = exp(max_log_gain * tanh(head(...))) [3, R, R]

from a small ConvNet on the target pose's normals and relative positions, the target rays'
directions, the lighting code and F_c's colour. Its head starts at zero: gain == 1 exactly, and
the decoder is the view-cosine decoder bit for bit; without pose or rays (conditioning off) it
is F_c itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import nn

from dlacli.avatar import gaussian_map as gm
from dlacli.avatar.codec import Decoder, PoseConditioning, shading, view_cosine
from dlacli.errors import DlaInputError

CORRECTIONS = 10  # opacity 1, rgb 3, offset 3, log scale 3
T_RGB = slice(1, 4)  # the colour's corrections among them
GAIN_MODULES = ("light", "gain_net", "gain_head")  # F_delta's submodules of ResidualNet (config.gain)


def corrected_colour(rgb: torch.Tensor, t_rgb: torch.Tensor) -> torch.Tensor:
    """Colours in [0, 1] moved by t in (-1, 1): toward 1 where t > 0, toward 0 where t < 0."""
    return rgb + t_rgb * torch.where(t_rgb > 0, 1.0 - rgb, rgb)


_IN_F = (0, 1, 2, 3, 4, 5, 6, 11, 12, 13)  # F's channels the net reads (rotation is identity after unprojection)


@dataclass
class ResidualNetConfig:
    features: int = 20  # observation feature channels (stages/lift/observations.feature_count)
    width: int = 32  # channels at the internal resolution; x2 and x4 below it
    internal: int = 128  # the UV resolution the net works at (the data's measured need)
    groups: int = 8  # GroupNorm groups
    max_opacity: float = 4.0  # logit units
    max_offset: float = 0.04  # metres
    max_log_scale: float = 1.0
    resolution: int = 128  # the map resolution it was trained at (the lift's default)
    gaussians: int = 32_768  # the Gaussians it was trained with (the lift's default)
    gain: bool = False  # F_delta: a pose- and view-conditioned colour gain (module doc)
    light_channels: int = 8
    gain_width: int = 16
    max_log_gain: float = 0.7  # the gain stays in [1/2, 2]

    @staticmethod
    def from_older(config: dict) -> dict:
        """A config saved before the gain existed (the first residual runs): no gain."""
        for key, value in (("gain", False), ("light_channels", 8), ("gain_width", 16), ("max_log_gain", 0.7)):
            config.setdefault(key, value)
        return config


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


class ResidualNet(nn.Module, Decoder):
    """F [B, 14, R, R] + features [B, features, R, R] -> corrected F (module doc); with
    config.gain also the codec's decoder "residual-gain"."""

    name = "residual-gain"
    linear = False
    delta_geometry = False  # F_delta: colour only (the gain and the view falloff)

    def __init__(self, config: ResidualNetConfig):
        nn.Module.__init__(self)
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
        self.pose_conditioned = self.view_conditioned = bool(c.gain)
        if c.gain:
            gw = c.gain_width
            self.light = nn.Linear(4 * w, c.light_channels)
            self.gain_net = nn.Sequential(
                nn.Conv2d(3 + 3 + 3 + 3 + c.light_channels, gw, 3, padding=1),
                nn.SiLU(),
                nn.Conv2d(gw, gw, 3, padding=1),
                nn.SiLU(),
            )
            self.gain_head = nn.Conv2d(gw, 3, 3, padding=1)
            nn.init.zeros_(self.gain_head.weight)  # gain == 1 exactly until trained
            nn.init.zeros_(self.gain_head.bias)

    @staticmethod
    def _normalised(fmap: torch.Tensor) -> torch.Tensor:
        """F's channels the net reads, scaled to about unit range."""
        x = fmap[:, list(_IN_F)]
        shift = torch.tensor([0.0, 0.5, 0.5, 0.5, 0, 0, 0, -0.5, -0.5, -1.6], dtype=x.dtype, device=x.device)
        scale = torch.tensor([0.25, 2, 2, 2, 20, 20, 20, 1, 1, 1], dtype=x.dtype, device=x.device)
        return (x - shift[:, None, None]) * scale[:, None, None]

    def _trunk(self, fmap: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (t in (-1, 1) [B, 10, R, R], the bottleneck [B, 4 width, n / 4, n / 4])."""
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
        return (_resize(t, res) if res != n else t), m

    def corrections(self, fmap: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """t in (-1, 1) [B, 10, R, R]: the bounded corrections before scaling (module doc)."""
        return self._trunk(fmap, features)[0]

    def apply_corrections(self, fmap: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """F [B, 14, R, R] moved by t [B, 10, R, R] within the config's bounds (module doc)."""
        c = self.config
        rgb = fmap[:, gm.RGB]
        t_rgb = t[:, T_RGB]
        parts = [
            fmap[:, gm.OPACITY] + c.max_opacity * t[:, 0:1],
            corrected_colour(rgb, t_rgb),
            fmap[:, gm.OFFSET] + c.max_offset * t[:, 4:7],
            fmap[:, gm.ROTATION],
            fmap[:, gm.LOG_SCALE] + c.max_log_scale * t[:, 7:10],
        ]
        return torch.cat(parts, dim=1)

    def forward(self, fmap: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (corrected F [B, 14, R, R], t [B, 10, R, R])."""
        t = self.corrections(fmap, features)
        return self.apply_corrections(fmap, t), t

    def encode(self, fmap: torch.Tensor, features: torch.Tensor, falloff) -> tuple[torch.Tensor, torch.Tensor]:
        """The "residual-gain" avatar code z [B, 15 + L, R, R] (module doc) for F, its features
        and the views' falloff k (a number or [B]) -> (z, t)."""
        assert self.config.gain, "encode: this network has no gain branch (config.gain is off)"
        t, m = self._trunk(fmap, features)
        b, res = fmap.shape[0], fmap.shape[-1]
        light = torch.tanh(self.light(m.mean(dim=(2, 3))))  # [B, L]
        k = torch.as_tensor(falloff, dtype=fmap.dtype, device=fmap.device).reshape(-1)
        k = k.expand(b)[:, None, None, None].expand(b, 1, res, res)
        maps = light[:, :, None, None].expand(b, light.shape[1], res, res)
        return torch.cat([self.apply_corrections(fmap, t), k, maps], dim=1), t

    # ------------------------------------------------------------------ the codec's Decoder
    def _check_z(self, z: torch.Tensor) -> None:
        want = gm.CHANNELS + 1 + self.config.light_channels
        if not self.config.gain or z.ndim != 3 or z.shape[0] != want:
            have = "no gain branch" if not self.config.gain else f"codes of {want} channels"
            raise DlaInputError("avatar", f"z is {tuple(z.shape)}; this residual-gain checkpoint decodes {have}")

    def canonical(self, z: torch.Tensor) -> torch.Tensor:
        self._check_z(z)
        return z[: gm.CHANNELS]

    def gain(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None) -> torch.Tensor:
        """The colour gain [3, R, R] of code z for one target pose and camera; exactly 1 without
        either (conditioning off)."""
        self._check_z(z)
        if pose is None or rays is None:
            return torch.ones((3, *z.shape[1:]), dtype=z.dtype, device=z.device)
        d = rays[:3] / rays[:3].norm(dim=0, keepdim=True).clamp_min(1e-12)
        light = z[gm.CHANNELS + 1 :]
        x = torch.cat([pose.normals.to(z), pose.relative_positions.to(z), d.to(z), z[gm.RGB], light])[None]
        return torch.exp(self.config.max_log_gain * torch.tanh(self.gain_head(self.gain_net(x))))[0]

    def delta(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None):
        """F_delta: colour only, rgb (shading(k, cos) gain - 1) (module doc); None without pose or rays."""
        self._check_z(z)
        if pose is None or rays is None:
            return None
        cos = view_cosine(pose.normals.to(z), rays.to(z))
        factor = shading(z[gm.CHANNELS], cos) * self.gain(z, pose, rays)  # [3, R, R]
        out = torch.zeros((gm.CHANNELS, *z.shape[1:]), dtype=z.dtype, device=z.device)
        out[gm.RGB] = z[gm.RGB] * (factor - 1.0)
        return out
