"""The completion prior: a UV-space ConvNet that corrects the body backend's hand-written fill
where the photo does not see the body (dream's `--prior`, docs/dream.md "The completion prior").

    inputs (dlacli.stages.dream.completion.prior_inputs) [B, INPUTS, R, R] at R = config.resolution:
        the rule's completed colour (3), the photo's baked colour x its confidence a (3), a (1),
        the valid-texel mask (1), the body part one-hot (11), the rest-pose texel point (3)
    --> U-Net (GroupNorm, SiLU; three downsamplings, a global context vector at the bottom)
    --> t = tanh(head) [B, 3, R, R]

The stage applies t where the photo did not see the texel (`corrected_colour` with t (1 - a)):
colours move toward 1 where t > 0 and toward 0 where t < 0, and stay in [0, 1]. The head is
initialised to zero, so an untrained network returns the rule's colours bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import nn

INPUTS = 22  # channels of stages/dream/completion.prior_inputs
OUTPUTS = 3  # the colour correction t


def corrected_colour(rgb: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Colours in [0, 1] moved by t in (-1, 1): toward 1 where t > 0, toward 0 where t < 0
    (t == 0 returns rgb exactly)."""
    return rgb + t * torch.where(t > 0, 1.0 - rgb, rgb)


@dataclass
class CompletionConfig:
    inputs: int = INPUTS
    width: int = 32  # channels at the full resolution; x2, x4, x4 below it
    groups: int = 8  # GroupNorm groups
    resolution: int = 128  # the UV resolution the network reads and writes


class _Block(nn.Module):
    def __init__(self, c: int, groups: int):
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(min(groups, c), c), nn.Conv2d(c, c, 3, padding=1)
        self.n2, self.c2 = nn.GroupNorm(min(groups, c), c), nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.c2(nnf.silu(self.n2(self.c1(nnf.silu(self.n1(x))))))


class CompletionNet(nn.Module):
    """inputs [B, config.inputs, R, R] -> t [B, 3, R, R] in (-1, 1) (module doc)."""

    def __init__(self, config: CompletionConfig):
        super().__init__()
        self.config = c = config
        if c.resolution % 8 or c.resolution < 16:
            raise ValueError(f"resolution must be a multiple of 8 and >= 16, got {c.resolution}")
        w, g = c.width, c.groups
        widths = (w, 2 * w, 4 * w, 4 * w)
        self.stem = nn.Conv2d(c.inputs, w, 3, padding=1)
        self.enc = nn.ModuleList([_Block(k, g) for k in widths[:3]])
        self.down = nn.ModuleList([nn.Conv2d(a, b, 3, stride=2, padding=1) for a, b in zip(widths[:3], widths[1:])])
        self.mid = nn.Sequential(_Block(widths[3], g), _Block(widths[3], g))
        self.context = nn.Linear(widths[3], widths[3])  # the whole map's mean, added back everywhere
        self.up = nn.ModuleList([nn.Conv2d(b + a, a, 3, padding=1) for a, b in zip(widths[:3], widths[1:])])
        self.dec = nn.ModuleList([_Block(k, g) for k in widths[:3]])
        self.norm_out = nn.GroupNorm(min(g, w), w)
        self.head = nn.Conv2d(w, OUTPUTS, 3, padding=1)
        nn.init.zeros_(self.head.weight)  # the untrained network is the rule, bit for bit
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.config
        assert x.dim() == 4 and x.shape[1] == c.inputs and x.shape[-2:] == (c.resolution, c.resolution), (
            f"inputs must be [B, {c.inputs}, {c.resolution}, {c.resolution}], got {tuple(x.shape)}"
        )
        h = self.stem(x)
        skips = []
        for enc, down in zip(self.enc, self.down):
            h = enc(h)
            skips.append(h)
            h = down(h)
        h = self.mid(h)
        h = h + self.context(h.mean(dim=(2, 3)))[..., None, None]
        for k in reversed(range(len(self.up))):
            h = nnf.interpolate(h, scale_factor=2.0, mode="nearest")
            h = self.dec[k](self.up[k](torch.cat([h, skips[k]], dim=1)))
        return torch.tanh(self.head(nnf.silu(self.norm_out(h))))
