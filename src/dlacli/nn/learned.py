"""The learned avatar network (docs/architecture.md, "The method"; the paper's contribution) as one module.

    views (4 x RGB + Plücker rays)  --U-Net G-->  pixel-aligned Gaussians in the input pose (+ features)
        --encoder F (cross-attention, queries on the posed body's UV map)-->  latent Z [C, r, r]
        --GPD-->  F = F_c(Z) + F_delta(Z, target pose maps, target camera rays)  [14, R, R]
        --avatar.posed (skinning on tangent frames, avatar/gaussian_map)-->  Gaussians  --splat-->  images

`LearnedAvatarNet` holds the three networks (nn/unet.py, nn/encoder.py, nn/gpd.py) and is the
codec's decoder "gpd" (avatar/codec.py): one checkpoint (avatar/checkpoint.py) holds all three, its
hash is what a learned avatar records, and `dla animate` / `render` / `edit` decode the avatar's
Z through it. The training loop (dlacli.train) and the learned lift (stages/lift/learned.py) call the
same batched pieces, `reconstruct` and `encode`, and decode Z as every avatar is decoded: the
codec's `Decoded.of(net, z)` placed by avatar/posed.py (`prepare` shares the GPD trunk between
F_c and every F_delta).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import nn

from dlacli.avatar import gaussian_map as gm
from dlacli.avatar.codec import Decoder, PoseConditioning
from dlacli.errors import DlaInputError
from dlacli.limits import DEFAULT_GAUSSIANS
from dlacli.nn.encoder import EncoderConfig, UVEncoder
from dlacli.nn.encoder import preset as encoder_preset
from dlacli.nn.gpd import GaussianParameterDecoder, GPDConfig
from dlacli.nn.gpd import preset as gpd_preset
from dlacli.nn.unet import PixelGaussians, ReconstructionUNet, UNetConfig, pixel_gaussians
from dlacli.nn.unet import preset as unet_preset
from dlacli.types import Cameras

ENCODER, DECODER = "learned", "gpd"
PRESET_NAMES = ("tiny", "small", "paper")
# ablations of the paper's Table 4 that are trained networks (A.i, mesh unprojection, is
# `dla lift --method unproject`): A.ii replaces the body queries by a learned table, B turns
# the GPD's pose and view conditioning off.
VARIANTS = ("full", "learned-query", "no-conditioning")
GAUSSIANS = {"tiny": 16_384, "small": 65_536, "paper": DEFAULT_GAUSSIANS}  # sampled from F per render


@dataclass
class LearnedConfig:
    unet: UNetConfig = field(default_factory=UNetConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    gpd: GPDConfig = field(default_factory=GPDConfig)
    gaussians: int = DEFAULT_GAUSSIANS  # Gaussians sampled from F when the avatar is rendered
    sample_seed: int = 0  # seed of their sample points (gaussian_map.make_samples)
    preset: str = "paper"
    variant: str = "full"


def learned_config(preset: str = "tiny", variant: str = "full") -> LearnedConfig:
    """The networks of a preset, made to agree (feature and latent sizes), with a variant applied."""
    if preset not in PRESET_NAMES:
        raise DlaInputError("--preset", f"unknown preset {preset!r} (available: {', '.join(PRESET_NAMES)})")
    if variant not in VARIANTS:
        raise DlaInputError("--variant", f"unknown variant {variant!r} (available: {', '.join(VARIANTS)})")
    u, e, g = unet_preset(preset), encoder_preset(preset), gpd_preset(preset)
    e = replace(
        e,
        feature_channels=u.feature_channels,
        gaussian_channels=14,
        query="learned" if variant == "learned-query" else "body",
    )
    g = replace(g, latent_channels=e.latent_channels, latent_resolution=e.uv_resolution)
    if variant == "no-conditioning":
        g = replace(g, pose_conditioned=False, view_conditioned=False)
    return LearnedConfig(u, e, g, gaussians=GAUSSIANS[preset], preset=preset, variant=variant)


def pixel_mask(mask: torch.Tensor, n: int) -> torch.Tensor:
    """Person masks [B, V, 1, S, S] at the U-Net's output pixels, flattened as its Gaussians are
    (view-major, row-major) -> [B, n], n = V h h (area-averaged to h x h)."""
    import torch.nn.functional as nnf

    b, v = mask.shape[:2]
    h = math.isqrt(n // v)
    assert v * h * h == n, f"{n} Gaussians are not {v} square maps"
    m = mask.reshape(b * v, 1, *mask.shape[-2:]).float()
    if m.shape[-1] != h:
        m = nnf.interpolate(m, size=(h, h), mode="area" if m.shape[-1] > h else "bilinear", align_corners=None)
    return m.reshape(b, v * h * h)


def subject_depth(cameras: Cameras, vertices: torch.Tensor) -> torch.Tensor:
    """[C] distance from each camera centre to the centre of the body's bounding box (metres)."""
    from dlacli.geometry import camera_centers

    v = torch.as_tensor(vertices, dtype=torch.float32)
    centre = 0.5 * (v.min(dim=0).values + v.max(dim=0).values)
    return (camera_centers(cameras.viewmats.float()) - centre).norm(dim=-1)


def view_inputs(rgb: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """rgb [V, 3, S, S] on black, cameras at S -> the U-Net's input [V, 9, S, S] (rgb + Plücker)."""
    from dlacli.geometry import plucker_rays

    rays = plucker_rays(cameras.to(dtype=torch.float32)).permute(0, 3, 1, 2)  # [V, 6, S, S]
    return torch.cat([rgb, rays.to(rgb)], dim=1)


def output_rays(cameras: Cameras, side: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through the centres of the U-Net's side x side output pixels: [V, h, w, 3] x 2."""
    from dlacli.geometry import pixel_rays

    return pixel_rays(cameras.to(dtype=torch.float32).resized(side, side))


class LearnedAvatarNet(nn.Module, Decoder):
    """U-Net G + encoder F + GPD, built from a LearnedConfig; the codec's decoder "gpd"."""

    name = DECODER
    linear = False

    def __init__(self, config: LearnedConfig):
        nn.Module.__init__(self)
        if config.unet.feature_channels != config.encoder.feature_channels:
            raise ValueError("LearnedConfig: the U-Net's features and the encoder's input differ")
        if (config.encoder.latent_channels, config.encoder.uv_resolution) != (
            config.gpd.latent_channels,
            config.gpd.latent_resolution,
        ):
            raise ValueError("LearnedConfig: the encoder's Z and the GPD's input differ")
        self.config = config
        self.unet = ReconstructionUNet(config.unet)
        self.encoder = UVEncoder(config.encoder)
        self.gpd = GaussianParameterDecoder(config.gpd)
        with torch.no_grad():  # the neutral scale covers the body with the default 131,072 Gaussians
            self.gpd.canonical_head.bias[gm.LOG_SCALE] += 0.5 * math.log(DEFAULT_GAUSSIANS / config.gaussians)
        self.pose_conditioned = bool(config.gpd.pose_conditioned)
        self.view_conditioned = bool(config.gpd.view_conditioned)
        self.resolution = int(config.gpd.out_resolution)
        self._samples: gm.Samples | None = None

    # ------------------------------------------------------------------ the batched pieces
    @property
    def input_size(self) -> int:
        return int(self.config.unet.image_size)

    @property
    def samples(self) -> gm.Samples:
        if self._samples is None:
            self._samples = gm.make_samples(self.config.gaussians, self.config.sample_seed)
        return self._samples

    def reconstruct(self, rgb: torch.Tensor, cameras: list[Cameras], depth: torch.Tensor):
        """rgb [B, V, 3, S, S] on black, cameras: B sets of V cameras at S, depth [B, V] camera to
        subject (`subject_depth`) -> (PixelGaussians [B, N], features [B, N, Cf]), N = V h w."""
        b, v = rgb.shape[:2]
        x = torch.stack([view_inputs(rgb[i], cameras[i]) for i in range(b)])
        raw, feats = self.unet(x)  # [B, V, 14, h, w], [B, V, Cf, h, w]
        h = raw.shape[-1]
        rays = [output_rays(c, h) for c in cameras]
        origins = torch.stack([r[0] for r in rays]).to(raw)
        dirs = torch.stack([r[1] for r in rays]).to(raw)
        g = pixel_gaussians(raw, origins, dirs, depth.to(raw))
        features = feats.permute(0, 1, 3, 4, 2).reshape(b, v * h * h, -1)
        return g, features

    def encode(self, g: PixelGaussians, features: torch.Tensor, uv_positions: torch.Tensor, generator=None, mask=None):
        """-> (mean, logvar) of Z [B, C, r, r]; uv_positions [B, 3, r, r] the posed body's map.
        mask [B, V, 1, S, S]: the input views' person masks; the encoder's opacity filter then
        keys on opacity x mask at each pixel Gaussian, so an untrained G (opacity ~0.5 everywhere)
        cannot hand it background Gaussians (issue 22's diagnosis)."""
        from dlacli.nn.unet import raw_parameters

        opacities = (
            g.opacities if mask is None else g.opacities * pixel_mask(mask, g.opacities.shape[1]).to(g.opacities)
        )
        return self.encoder(raw_parameters(g), features, g.means, opacities, uv_positions, generator=generator)

    def uv_positions(self, vertices: torch.Tensor) -> torch.Tensor:
        """[B, V, 3] posed body vertices -> the encoder's queries' positions [B, 3, r, r]."""
        from dlacli.body.uv import position_map

        r = self.config.encoder.uv_resolution
        return torch.stack([position_map(v.float(), r).permute(2, 0, 1) for v in vertices])

    # ------------------------------------------------------------------ the codec's Decoder
    def prepare(self, z: torch.Tensor):
        """The GPD trunk of one avatar's z [C, r, r]: F_c and every F_delta start from it."""
        self._check_z(z)
        return self.gpd.trunk(z[None])

    def canonical(self, z: torch.Tensor, prepared=None) -> torch.Tensor:
        self._check_z(z)
        trunk = self.prepare(z) if prepared is None else prepared
        return self.gpd.canonical(z[None], trunk=trunk)[0]

    def delta(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None, prepared=None):
        if not self.conditioned:
            return None
        r = self.resolution
        zeros3 = torch.zeros(3, r, r, dtype=z.dtype, device=z.device)
        rel = pose.relative_positions if pose is not None else zeros3
        nrm = pose.normals if pose is not None else zeros3
        ray = rays if rays is not None else torch.zeros(6, r, r, dtype=z.dtype, device=z.device)
        cond = torch.cat([rel, nrm, ray], dim=0).to(z)[None]
        return self.gpd.delta(z[None], cond, trunk=self.prepare(z) if prepared is None else prepared)[0]

    def _check_z(self, z: torch.Tensor) -> None:
        want = (
            self.config.encoder.latent_channels,
            self.config.encoder.uv_resolution,
            self.config.encoder.uv_resolution,
        )
        if tuple(z.shape) != want:
            raise DlaInputError("avatar", f"z is {tuple(z.shape)}; this checkpoint's GPD decodes {want}")
