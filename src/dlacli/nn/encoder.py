"""The encoder E: unstructured Gaussians -> the avatar code Z on the body's UV space
(docs/architecture.md "The method", Lift part 2).

The U-Net's pixel-aligned Gaussians of one item (N of them, flattened over its views) become tokens:
a linear projection of their raw parameters and U-Net features, plus a projection of a Fourier
encoding of their world positions. Gaussians with opacity above a threshold are the candidates
(the most opaque ones when too few pass), and P of them are chosen by farthest point sampling on
their positions. One multi-head cross-attention lets the r x r UV texels (queries) read those P
tokens: in the paper's variant ("body") a query is the encoded world position of its texel on the
posed body (`dlacli.body.uv.position_map`); the ablation ("learned", paper A.ii) uses a learned
table instead. A residual MLP and an output layer give the mean and log-variance of Z [C, r, r].
Empty texels (outside the UV charts) get outputs too; the decoder sees the segmentation.

Inputs, per item b: params [N, 14] (means 3, opacity logit 1, log scales 3, quats 4, rgb 3: the U-Net's
`raw_parameters`), features [N, Cf], positions [N, 3] world metres, opacities [N] in (0, 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import Tensor, nn

from dlacli.nn import named_preset

QUERIES = ("body", "learned")


@dataclass
class EncoderConfig:
    gaussian_channels: int = 14  # raw parameters per Gaussian
    feature_channels: int = 32  # Cf: the U-Net's per-pixel features (must match UNetConfig.feature_channels)
    width: int = 1024  # attention width
    heads: int = 16
    points: int = 2048  # P: farthest-point-sampled keys
    opacity_threshold: float = 0.05
    uv_resolution: int = 64  # Z's side r
    latent_channels: int = 256  # Z's channels C
    pe_frequencies: int = 10  # Fourier frequencies 2^k pi, k < L, of world positions in metres
    query: str = "body"  # "body": encoded posed-body UV position map; "learned": a learned [r*r, width] table
    token_hidden: int = 2816  # hidden width of the per-token residual MLP (0: none)
    mlp_hidden: int = 4096  # hidden width of the residual MLP after the cross-attention
    # locality (issue 22's diagnosis: untrained attention stays uniform over all tokens): with body
    # queries, each texel's attention logits get -d^2 / (2 locality^2), d = the distance in metres
    # from its posed-body point to the token's Gaussian, so a texel starts by reading the Gaussians
    # near it. 0: off (checkpoints made before it existed)
    locality: float = 0.0
    # the log-variance of Z at initialisation: the head's log-variance half starts with zero weights
    # and this bias (None: the default init, std ~1, far above the spread of Z's mean)
    logvar_init: float | None = None

    @staticmethod
    def from_older(config: dict) -> dict:
        """A config saved before locality and logvar_init existed: both off (its network as it was)."""
        config.setdefault("locality", 0.0)
        config.setdefault("logvar_init", None)
        return config

    def __post_init__(self):
        if self.query not in QUERIES:
            raise ValueError(f"query must be one of {QUERIES}, got {self.query!r}")
        if self.width < 1 or self.heads < 1 or self.width % self.heads:
            raise ValueError(f"width {self.width} must be a positive multiple of heads {self.heads}")
        for name in ("gaussian_channels", "points", "uv_resolution", "latent_channels", "mlp_hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("feature_channels", "pe_frequencies", "token_hidden", "locality"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


LOCALITY = 0.1  # metres: about a limb's radius
LOGVAR_INIT = -5.0  # std 0.08 at initialisation, below the ~0.3 spread of Z's mean measured untrained

PRESETS: dict[str, EncoderConfig] = {
    "tiny": EncoderConfig(
        width=64,
        heads=4,
        points=256,
        uv_resolution=16,
        latent_channels=16,
        pe_frequencies=6,
        token_hidden=128,
        mlp_hidden=128,
        locality=LOCALITY,
        logvar_init=LOGVAR_INIT,
    ),
    "small": EncoderConfig(
        width=256,
        heads=8,
        points=1024,
        uv_resolution=32,
        latent_channels=64,
        pe_frequencies=8,
        token_hidden=512,
        mlp_hidden=1024,
        locality=LOCALITY,
        logvar_init=LOGVAR_INIT,
    ),
    # 19,077,376 parameters (paper: 19 M); feature_channels 32 = the U-Net's default Cf
    "paper": EncoderConfig(locality=LOCALITY, logvar_init=LOGVAR_INIT),
}


def preset(name: str) -> EncoderConfig:
    """A copy of the named encoder preset ("tiny", "small", "paper")."""
    return named_preset(PRESETS, name, "encoder")


# ------------------------------------------------------------------------------------ functions


def fourier_features(x: Tensor, frequencies: int) -> Tensor:
    """x [..., D] -> [..., D (1 + 2 L)]: x, sin(2^k pi x), cos(2^k pi x) for k < L (NeRF's encoding)."""
    if frequencies == 0:
        return x
    scales = math.pi * 2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)  # [L]
    arg = (x[..., None] * scales).flatten(-2)  # [..., D L]
    return torch.cat([x, torch.sin(arg), torch.cos(arg)], dim=-1)


@torch.no_grad()
def farthest_point_sample(points: Tensor, k: int, valid: Tensor | None = None, start: Tensor | None = None) -> Tensor:
    """points [B, N, 3], valid [B, N] bool -> indices [B, k] (long), greedy farthest point sampling
    restricted to valid points (if fewer than k are valid, repeat valid ones; if none, use all).

    Starts at `start` [B] (taken as valid), by default the first valid point; each next point is the
    valid unselected one with the largest squared distance to the selected set (ties: the lowest
    index). With m < k valid points the m distinct picks repeat in order: out[j] = out[j mod m]."""
    assert points.ndim == 3 and points.shape[-1] == 3, f"points must be [B, N, 3], got {tuple(points.shape)}"
    b, n, _ = points.shape
    if k < 1 or n < 1:
        raise ValueError(f"farthest_point_sample needs k >= 1 and N >= 1, got k={k}, N={n}")
    pts = points.detach()
    dev = pts.device
    if valid is None:
        valid = torch.ones(b, n, dtype=torch.bool, device=dev)
    else:
        assert valid.shape == (b, n), f"valid must be [{b}, {n}], got {tuple(valid.shape)}"
        valid = valid.to(device=dev, dtype=torch.bool)
        valid = valid | ~valid.any(dim=1, keepdim=True)  # none valid: all are
    if start is None:
        start = valid.to(torch.uint8).argmax(dim=1)  # the first valid point
    else:
        assert start.shape == (b,), f"start must be [{b}], got {tuple(start.shape)}"
        start = start.to(device=dev, dtype=torch.long)
        valid = valid.clone()
        valid[torch.arange(b, device=dev), start] = True
    rows = torch.arange(b, device=dev)
    # running min squared distance to the selected set; -inf never wins (invalid), -1 marks selected
    best = torch.full((b, n), math.inf, dtype=pts.dtype, device=dev).masked_fill(~valid, -math.inf)
    out = torch.empty(b, k, dtype=torch.long, device=dev)
    idx = start
    for i in range(k):
        out[:, i] = idx
        if i == k - 1:
            break
        d = (pts - pts[rows, idx][:, None]).square().sum(dim=-1)  # [B, N]
        best = torch.minimum(best, d)
        best[rows, idx] = -1.0
        idx = best.argmax(dim=1)
    m = valid.sum(dim=1).clamp(max=k)  # [B] distinct picks
    order = torch.arange(k, device=dev)[None] % m[:, None]
    return out.gather(1, order)


def sample_latent(mean: Tensor, logvar: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """The reparameterised z = mean + exp(logvar / 2) * eps, eps ~ N(0, 1) (from `generator`)."""
    eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
    return mean + torch.exp(0.5 * logvar) * eps


def kl_divergence(mean: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mean, exp(logvar)) || N(0, 1)) per element, averaged over all elements (a scalar)."""
    return 0.5 * (mean.square() + torch.exp(logvar) - 1.0 - logvar).mean()


# ------------------------------------------------------------------------------------ network


class _MLP(nn.Sequential):
    def __init__(self, width: int, hidden: int):
        super().__init__(nn.LayerNorm(width), nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, width))


class UVEncoder(nn.Module):
    """Gaussians -> (mean, logvar) of Z [B, C, r, r] by one cross-attention from the UV texels."""

    def __init__(self, config: EncoderConfig):
        super().__init__()
        self.config = c = config
        pe = 3 * (1 + 2 * c.pe_frequencies)
        self.token_in = nn.Linear(c.gaussian_channels + c.feature_channels, c.width)
        self.token_pe = nn.Linear(pe, c.width)
        self.token_mlp = _MLP(c.width, c.token_hidden) if c.token_hidden else None
        if c.query == "body":
            self.query_pe = nn.Linear(pe, c.width)
        else:
            self.query_table = nn.Parameter(torch.randn(c.uv_resolution**2, c.width) * 0.02)
        self.norm_q, self.norm_kv = nn.LayerNorm(c.width), nn.LayerNorm(c.width)
        self.to_q = nn.Linear(c.width, c.width)
        self.to_kv = nn.Linear(c.width, 2 * c.width)
        self.to_out = nn.Linear(c.width, c.width)
        self.mlp = _MLP(c.width, c.mlp_hidden)
        self.norm_out = nn.LayerNorm(c.width)
        self.head = nn.Linear(c.width, 2 * c.latent_channels)
        if c.logvar_init is not None:
            with torch.no_grad():
                self.head.weight[c.latent_channels :].zero_()
                self.head.bias[c.latent_channels :].fill_(c.logvar_init)

    def select(self, positions: Tensor, opacities: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """The P key Gaussians [B, P] (long): farthest points among those with opacity > threshold
        (the P most opaque when fewer pass), starting at the most opaque one, or at a random
        candidate drawn from `generator` (on the inputs' device; training-time variety)."""
        c = self.config
        with torch.no_grad():
            op = opacities.detach()
            valid = op > c.opacity_threshold
            few = valid.sum(dim=1) < c.points  # [B]
            if bool(few.any()):
                order = torch.sort(op, dim=1, descending=True, stable=True).indices[:, : c.points]
                top = torch.zeros_like(valid).scatter_(1, order, True)
                valid = torch.where(few[:, None], top, valid)
            if generator is None:
                score = op
            else:
                score = torch.rand(op.shape, generator=generator, dtype=op.dtype, device=op.device)
            start = score.masked_fill(~valid, -math.inf).argmax(dim=1)
            return farthest_point_sample(positions, c.points, valid, start)

    def forward(
        self,
        params: Tensor,
        features: Tensor,
        positions: Tensor,
        opacities: Tensor,
        uv_positions: Tensor | None,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """params [B,N,14], features [B,N,Cf], positions [B,N,3], opacities [B,N],
        uv_positions [B, 3, r, r] (posed body position map at r; unused, may be None, for "learned") ->
        (mean [B, C, r, r], logvar [B, C, r, r])"""
        c = self.config
        b, n = positions.shape[:2]
        shapes = {
            "positions": (positions, (b, n, 3)),
            "params": (params, (b, n, c.gaussian_channels)),
            "features": (features, (b, n, c.feature_channels)),
            "opacities": (opacities, (b, n)),
        }
        for name, (x, want) in shapes.items():
            assert x.shape == want, f"{name} must be {list(want)}, got {list(x.shape)}"
        r = c.uv_resolution
        idx = self.select(positions, opacities, generator)  # [B, P]

        def take(x: Tensor) -> Tensor:  # [B, N, D] -> [B, P, D], with gradient
            return x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))

        tokens = self.token_in(torch.cat([take(params), take(features)], dim=-1))
        tokens = tokens + self.token_pe(fourier_features(take(positions), c.pe_frequencies))  # [B, P, W]
        if self.token_mlp is not None:
            tokens = tokens + self.token_mlp(tokens)
        if c.query == "body":
            got = None if uv_positions is None else list(uv_positions.shape)
            assert got == [b, 3, r, r], f"uv_positions must be [{b}, 3, {r}, {r}], got {got}"
            uv = uv_positions.flatten(2).transpose(1, 2)  # [B, r*r, 3], row-major texels
            query = self.query_pe(fourier_features(uv, c.pe_frequencies))
        else:
            query = self.query_table[None].expand(b, -1, -1)
        h = c.heads

        def split(x: Tensor) -> Tensor:  # [B, L, W] -> [B, heads, L, W / heads]
            return x.unflatten(-1, (h, -1)).transpose(1, 2)

        q = split(self.to_q(self.norm_q(query)))
        k, v = self.to_kv(self.norm_kv(tokens)).chunk(2, dim=-1)
        bias = None
        if c.query == "body" and c.locality > 0:  # [B, 1, r*r, P]: texels read the Gaussians near them first
            d2 = torch.cdist(uv, take(positions).to(uv)).square()
            bias = (-d2 / (2.0 * c.locality**2)).to(q.dtype)[:, None]
        att = nnf.scaled_dot_product_attention(q, split(k), split(v), attn_mask=bias)  # [B, heads, r*r, W / heads]
        x = query + self.to_out(att.transpose(1, 2).flatten(2))
        x = x + self.mlp(x)
        out = self.head(self.norm_out(x))  # [B, r*r, 2C]
        out = out.transpose(1, 2).unflatten(-1, (r, r))  # [B, 2C, r, r]
        mean, logvar = out.chunk(2, dim=1)
        return mean, logvar
