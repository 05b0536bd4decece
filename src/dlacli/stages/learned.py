"""The learned method (DESIGN.md §1; the paper's contribution) as one network and one lift.

    views (4 x RGB + Plücker rays)  --U-Net G-->  pixel-aligned Gaussians in the input pose (+ features)
        --encoder F (cross-attention, queries on the posed body's UV map)-->  latent Z [C, r, r]
        --GPD-->  F = F_c(Z) + F_delta(Z, target pose maps, target camera rays)  [14, R, R]
        --gaussian_map (skinning, tangent frames)-->  Gaussians  --splat-->  images

`LearnedAvatarNet` holds the three networks (nn/unet.py, nn/encoder.py, nn/gpd.py) and is the
codec's decoder "gpd" (stages/codec.py): one checkpoint (nn/checkpoint.py) holds all three, its
hash is what a learned avatar records, and `dla animate` / `render` / `edit` decode the avatar's
Z through it. The training loop (dlacli.train) and `lift_learned` (`dla lift --method learned`)
call the same batched pieces: `reconstruct`, `encode`, `decode`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import nn

from dlacli.errors import DlaInputError
from dlacli.nn.encoder import EncoderConfig, UVEncoder
from dlacli.nn.encoder import preset as encoder_preset
from dlacli.nn.gpd import GaussianParameterDecoder, GPDConfig
from dlacli.nn.gpd import preset as gpd_preset
from dlacli.nn.unet import PixelGaussians, ReconstructionUNet, UNetConfig, pixel_gaussians
from dlacli.nn.unet import preset as unet_preset
from dlacli.stages import gaussian_map as gm
from dlacli.stages.codec import Decoder, PoseConditioning
from dlacli.types import Cameras, Gaussians, ViewSet

ENCODER, DECODER = "learned", "gpd"
PRESET_NAMES = ("tiny", "small", "paper")
# ablations of the paper's Table 4 that are trained networks (A.i, mesh unprojection, is
# `dla lift --method unproject`): A.ii replaces the body queries by a learned table, B turns
# the GPD's pose and view conditioning off.
VARIANTS = ("full", "learned-query", "no-conditioning")
GAUSSIANS = {"tiny": 16_384, "small": 65_536, "paper": 131_072}  # sampled from F per render


@dataclass
class LearnedConfig:
    unet: UNetConfig = field(default_factory=UNetConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    gpd: GPDConfig = field(default_factory=GPDConfig)
    gaussians: int = 131_072  # Gaussians sampled from F when the avatar is rendered
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
    e = replace(e, feature_channels=u.feature_channels, gaussian_channels=14,
                query="learned" if variant == "learned-query" else "body")  # fmt: skip
    g = replace(g, latent_channels=e.latent_channels, latent_resolution=e.uv_resolution)
    if variant == "no-conditioning":
        g = replace(g, pose_conditioned=False, view_conditioned=False)
    return LearnedConfig(u, e, g, gaussians=GAUSSIANS[preset], preset=preset, variant=variant)


def scaled_cameras(cameras: Cameras, size: int) -> Cameras:
    """The same cameras for size x size images (square views: intrinsics scale by size / width)."""
    f = size / cameras.width
    ks = cameras.Ks.clone()
    ks[:, :2, :] *= f
    return Cameras(cameras.viewmats.clone(), ks, size, size)


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

    return pixel_rays(scaled_cameras(cameras.to(dtype=torch.float32), side))


def conditioning(vertices: torch.Tensor, rest_vertices, eye, resolution: int, pose=None) -> torch.Tensor:
    """[12, R, R] what the GPD's pose/view branch sees of one target: the posed body's relative
    vertex positions (3) and normals (3) and the camera's Plücker rays (6) in UV space. `pose`:
    the body's codec.PoseConditioning when already computed (several cameras, one body)."""
    from dlacli.stages.codec import pose_conditioning, uv_rays

    v = torch.as_tensor(vertices, dtype=torch.float32)
    pose = pose if pose is not None else pose_conditioning(v, np.asarray(rest_vertices), resolution)
    rays = uv_rays(v, torch.as_tensor(eye, dtype=torch.float32), resolution)
    return torch.cat([pose.relative_positions, pose.normals, rays], dim=0)


class LearnedAvatarNet(nn.Module, Decoder):
    """U-Net G + encoder F + GPD, built from a LearnedConfig; the codec's decoder "gpd"."""

    name = DECODER
    linear = False

    def __init__(self, config: LearnedConfig):
        nn.Module.__init__(self)
        if config.unet.feature_channels != config.encoder.feature_channels:
            raise ValueError("LearnedConfig: the U-Net's features and the encoder's input differ")
        if (config.encoder.latent_channels, config.encoder.uv_resolution) != (
                config.gpd.latent_channels, config.gpd.latent_resolution):  # fmt: skip
            raise ValueError("LearnedConfig: the encoder's Z and the GPD's input differ")
        self.config = config
        self.unet = ReconstructionUNet(config.unet)
        self.encoder = UVEncoder(config.encoder)
        self.gpd = GaussianParameterDecoder(config.gpd)
        with torch.no_grad():  # the neutral scale covers the body with the default 131,072 Gaussians
            self.gpd.canonical_head.bias[gm.LOG_SCALE] += 0.5 * math.log(gm.DEFAULT_GAUSSIANS / config.gaussians)
        self.pose_conditioned = bool(config.gpd.pose_conditioned)
        self.view_conditioned = bool(config.gpd.view_conditioned)
        self.resolution = int(config.gpd.out_resolution)
        self._samples: gm.Samples | None = None
        self._trunk_cache: tuple | None = None

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

    def encode(self, g: PixelGaussians, features: torch.Tensor, uv_positions: torch.Tensor, generator=None):
        """-> (mean, logvar) of Z [B, C, r, r]; uv_positions [B, 3, r, r] the posed body's map."""
        from dlacli.nn.unet import raw_parameters

        return self.encoder(raw_parameters(g), features, g.means, g.opacities, uv_positions, generator=generator)

    def uv_positions(self, vertices: torch.Tensor) -> torch.Tensor:
        """[B, V, 3] posed body vertices -> the encoder's queries' positions [B, 3, r, r]."""
        from dlacli.body.uv import position_map

        r = self.config.encoder.uv_resolution
        return torch.stack([position_map(v.float(), r).permute(2, 0, 1) for v in vertices])

    def decode(self, z: torch.Tensor, cond: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """z [B, C, r, r], cond [B, 12, R, R] or None -> (F [B, 14, R, R], F_delta [B, 14, R, R])."""
        trunk = self.gpd.trunk(z)
        f_c = self.gpd.canonical(z, trunk=trunk)
        if cond is None or not self.conditioned:
            return f_c, torch.zeros_like(f_c)
        d = self.gpd.delta(z, cond, trunk=trunk)
        return f_c + d, d

    def gaussians(self, fmap: torch.Tensor, vertices: torch.Tensor) -> Gaussians:
        """World Gaussians of maps F [P, 14, R, R] on posed bodies [P, V, 3] (batch [P, N])."""
        frames = gm.sample_frames(vertices.float(), self.samples)
        return gm.posed_gaussians(fmap, self.samples, frames)

    # ------------------------------------------------------------------ the codec's Decoder
    def _trunk(self, z: torch.Tensor):
        """The GPD trunk of one avatar's z [C, r, r], cached while z is unchanged and grad is off."""
        key = (z.data_ptr(), z._version, tuple(z.shape))
        if torch.is_grad_enabled() or self._trunk_cache is None or self._trunk_cache[0] != key:
            trunk = self.gpd.trunk(z[None])
            if torch.is_grad_enabled():
                return trunk
            self._trunk_cache = (key, trunk)
        return self._trunk_cache[1]

    def canonical(self, z: torch.Tensor) -> torch.Tensor:
        self._check_z(z)
        return self.gpd.canonical(z[None], trunk=self._trunk(z))[0]

    def delta(self, z: torch.Tensor, pose: PoseConditioning | None, rays: torch.Tensor | None) -> torch.Tensor | None:
        if not self.conditioned:
            return None
        r = self.resolution
        zeros3 = torch.zeros(3, r, r, dtype=z.dtype, device=z.device)
        rel = pose.relative_positions if pose is not None else zeros3
        nrm = pose.normals if pose is not None else zeros3
        ray = rays if rays is not None else torch.zeros(6, r, r, dtype=z.dtype, device=z.device)
        cond = torch.cat([rel, nrm, ray], dim=0).to(z)[None]
        return self.gpd.delta(z[None], cond, trunk=self._trunk(z))[0]

    def _check_z(self, z: torch.Tensor) -> None:
        want = (self.config.encoder.latent_channels, self.config.encoder.uv_resolution, self.config.encoder.uv_resolution)
        if tuple(z.shape) != want:
            raise DlaInputError("avatar", f"z is {tuple(z.shape)}; this checkpoint's GPD decodes {want}")


# ------------------------------------------------------------------------------ the lift


def input_tensors(views: ViewSet, size: int) -> tuple[torch.Tensor, torch.Tensor, Cameras]:
    """A view folder at the U-Net's size: (rgb [V, 3, S, S] on black, mask [V, 1, S, S], cameras)."""
    import torch.nn.functional as nnf

    h, w = views.masks.shape[1:]
    if h != w:
        raise DlaInputError("views", f"the learned lift takes square views, got {w}x{h}")
    rgba = np.concatenate([views.images * views.masks[..., None], views.masks[..., None]], -1)
    x = torch.from_numpy(np.ascontiguousarray(rgba)).float().permute(0, 3, 1, 2)
    if h != size:
        x = nnf.interpolate(x, size=(size, size), mode="area" if h > size else "bilinear")
    x = x.clamp(0.0, 1.0)
    return x[:, :3].contiguous(), x[:, 3:].contiguous(), scaled_cameras(views.cameras, size)


def load_learned(checkpoint: str, where: str = "--checkpoint"):
    """(LearnedAvatarNet in eval mode, its hash) from a checkpoint folder or hash."""
    from dlacli.nn.checkpoint import load_checkpoint, resolve_checkpoint

    loaded = load_checkpoint(resolve_checkpoint(checkpoint))
    if not isinstance(loaded.module, LearnedAvatarNet):
        raise DlaInputError(where, f"holds a {type(loaded.module).__name__}, not a learned avatar network (dla train)")
    return loaded.module.eval(), loaded.hash


def render_targets(net: LearnedAvatarNet, z: torch.Tensor, vertices: torch.Tensor, rest, cameras: Cameras):
    """Render the avatar z [C, r, r] on one posed body (vertices [V, 3]) from each camera, with
    the F of that camera (a view-conditioned GPD decodes per camera) -> rgb [C, H, W, 3], alpha."""
    from dlacli.geometry import camera_centers
    from dlacli.render.splat import render_gaussians

    from dlacli.stages.codec import pose_conditioning

    eyes = camera_centers(cameras.viewmats.float())
    rgbs, alphas = [], []
    trunk = net.gpd.trunk(z[None])
    f_c = net.gpd.canonical(z[None], trunk=trunk)
    pose = pose_conditioning(vertices.float(), np.asarray(rest), net.resolution) if net.conditioned else None
    for c in range(len(cameras)):
        fmap = f_c
        if net.conditioned:
            cond = conditioning(vertices, rest, eyes[c], net.resolution, pose)[None]
            fmap = f_c + net.gpd.delta(z[None], cond, trunk=trunk)
        g = net.gaussians(fmap, vertices[None]).item(0)
        cam = Cameras(cameras.viewmats[c:c + 1], cameras.Ks[c:c + 1], cameras.width, cameras.height)
        out = render_gaussians(g, cam)
        rgbs.append(out.rgb[0])
        alphas.append(out.alpha[0])
    return torch.stack(rgbs), torch.stack(alphas)


def lift_learned(views: ViewSet, checkpoint: str, steps: int = 0, lr: float = 0.02, render_size: int = 256,
                 progress=None, novel: ViewSet | None = None):  # fmt: skip
    """`dla lift --method learned`: U-Net -> encoder -> Z (the posterior mean), then `steps` of
    refining Z alone through the frozen decoder against the input views (L1 + mask at
    render_size) -> stages.lift.LiftResult (avatar, the U-Net's pixel Gaussians, contact sheet)."""
    from dlacli.body.model import get_body_model
    from dlacli.body.uv import UV_LAYOUT
    from dlacli.stages.lift import MAX_VIEWS, LiftResult, _resized_targets, sheet_and_novel_view
    from dlacli.types import Avatar

    if views.body is None:
        raise DlaInputError("views", "lift needs body.json beside transforms.json")
    if len(views) > MAX_VIEWS:
        raise DlaInputError("views", f"has {len(views)} views; lift takes at most {MAX_VIEWS} (the method uses 4)")
    net, digest = load_learned(checkpoint)
    net.requires_grad_(False)
    model = get_body_model()
    verts = model.forward_body(views.body).vertices[0].float()
    rest = model.rest_vertices(views.body.phenotype)
    rgb, _, cams = input_tensors(views, net.input_size)
    t0 = time.perf_counter()
    with torch.no_grad():
        g, feats = net.reconstruct(rgb[None], [cams], subject_depth(cams, verts)[None])
        mean, _ = net.encode(g, feats, net.uv_positions(verts[None]))
    z = mean[0].clone()
    history: list[float] = []
    if steps > 0:
        t_rgb, t_mask, t_cams = _resized_targets(views, render_size)
        z.requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        for i in range(steps):
            opt.zero_grad(set_to_none=True)
            pred, alpha = render_targets(net, z, verts, rest, t_cams)
            loss = (pred - t_rgb).abs().mean() + (alpha - t_mask).abs().mean()
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
            if progress is not None:
                progress(i, history[-1])
        z = z.detach()
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        f_c = net.canonical(z)
        sheet, novel_view = sheet_and_novel_view(views, novel, lambda c: render_targets(net, z, verts, rest, c)[0].numpy())
    unstructured = Gaussians.from_rgb(g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.rgb[0])
    extra = {"lift": {"steps": steps, "final_loss": history[-1] if history else None, "seconds": seconds,
                      "preset": net.config.preset, "variant": net.config.variant},
             "samples": {"count": net.config.gaussians, "seed": net.config.sample_seed}}  # fmt: skip
    avatar = Avatar(z=z.numpy().astype(np.float32), encoder=ENCODER, decoder=DECODER, body=views.body,
                    uv_layout=UV_LAYOUT, checkpoint=digest, canonical=f_c.numpy().astype(np.float32),
                    extra=extra)  # fmt: skip
    return LiftResult(avatar, unstructured, sheet, novel_view)
