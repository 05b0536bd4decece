"""The learned lift (`dla lift --method learned`): the network of nn/learned.py run on a view
folder, U-Net -> encoder -> Z (the posterior mean), optionally refined through the frozen decoder.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.nn.learned import DECODER, ENCODER, LearnedAvatarNet, subject_depth

# checkpoints written before the network moved to nn/ name dlacli.stages.lift.learned.LearnedAvatarNet
# and .LearnedConfig: both stay importable from here (avatar/checkpoint.py rebuilds by dotted name)
from dlacli.nn.learned import LearnedConfig as LearnedConfig
from dlacli.types import Cameras, Gaussians, ViewSet

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
    return x[:, :3].contiguous(), x[:, 3:].contiguous(), views.cameras.resized(size, size)


def load_learned(checkpoint: str, where: str = "--checkpoint"):
    """(LearnedAvatarNet in eval mode, its hash) from a checkpoint folder or hash."""
    from dlacli.avatar.checkpoint import load_checkpoint, resolve_checkpoint

    loaded = load_checkpoint(resolve_checkpoint(checkpoint))
    if not isinstance(loaded.module, LearnedAvatarNet):
        raise DlaInputError(where, f"holds a {type(loaded.module).__name__}, not a learned avatar network (dla train)")
    return loaded.module.eval(), loaded.hash


def render_targets(net: LearnedAvatarNet, z: torch.Tensor, vertices: torch.Tensor, rest, cameras: Cameras):
    """Render the avatar z [C, r, r] (differentiable in z) on one posed body (vertices [V, 3];
    rest [V, 3] its zero pose) from C cameras, with the F of each camera when the GPD is
    view-conditioned (avatar/posed.py) -> rgb [C, H, W, 3], alpha [C, H, W]."""
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar

    out = PosedAvatar(Decoded.of(net, z, rest), net.samples, vertices[None].float().to(z.device), cameras).render()
    return out.rgb, out.alpha


def lift_learned(
    views: ViewSet,
    checkpoint: str,
    steps: int = 0,
    lr: float = 0.02,
    render_size: int = 256,
    progress=None,
    novel: ViewSet | None = None,
):
    """`dla lift --method learned`: U-Net -> encoder -> Z (the posterior mean), then `steps` of
    refining Z alone through the frozen decoder against the input views (L1 + mask at
    render_size) -> stages.lift.LiftResult (avatar, the U-Net's pixel Gaussians, contact sheet)."""
    from dlacli.body.model import get_body_model
    from dlacli.body.uv import UV_LAYOUT
    from dlacli.stages.lift.refine import adam_refine
    from dlacli.stages.lift.unproject import MAX_VIEWS, LiftResult, sheet_and_novel_view
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
    rgb, mask, cams = input_tensors(views, net.input_size)
    t0 = time.perf_counter()
    with torch.no_grad():
        g, feats = net.reconstruct(rgb[None], [cams], subject_depth(cams, verts)[None])
        mean, _ = net.encode(g, feats, net.uv_positions(verts[None]), mask=mask[None])
    z = mean[0].clone()
    history: list[float] = []
    if steps > 0:
        t_rgb, t_mask, t_cams = views.targets(render_size)
        z.requires_grad_(True)

        def loss() -> torch.Tensor:
            pred, alpha = render_targets(net, z, verts, rest, t_cams)
            return (pred - t_rgb).abs().mean() + (alpha - t_mask).abs().mean()

        history = adam_refine([z], loss, steps, lr, progress)
        z = z.detach()
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        f_c = net.canonical(z)
        sheet, novel_view = sheet_and_novel_view(
            views, novel, lambda c: render_targets(net, z, verts, rest, c)[0].numpy()
        )
    unstructured = Gaussians.from_rgb(g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.rgb[0])
    extra = {
        "lift": {
            "steps": steps,
            "final_loss": history[-1] if history else None,
            "seconds": seconds,
            "preset": net.config.preset,
            "variant": net.config.variant,
        },
        "samples": {"count": net.config.gaussians, "seed": net.config.sample_seed},
    }
    avatar = Avatar(
        z=z.numpy().astype(np.float32),
        encoder=ENCODER,
        decoder=DECODER,
        body=views.body,
        uv_layout=UV_LAYOUT,
        checkpoint=digest,
        canonical=f_c.numpy().astype(np.float32),
        extra=extra,
    )
    return LiftResult(avatar, unstructured, sheet, novel_view)
