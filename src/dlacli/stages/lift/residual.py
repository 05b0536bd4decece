"""The residual lift (`dla lift --method residual`): mesh unprojection, then a small trained
UV-space network (nn/residual.py) that corrects its Gaussian map from observation features
(stages/lift/observations.py), then optionally `steps` of the lift's own refinement.

    views --stages/lift/unproject.unprojection--> F, body, depths --observation_features--> features
        --ResidualNet--> F' = F + bounded corrections --(steps > 0: refine the geometry, re-bake
        the colours, the network's colour correction again)--> avatar (identity or view-cosine
        decoder: F' is a Gaussian map like any unprojected one)

The untrained network returns F bit for bit, so with an untrained checkpoint this lift writes
the same avatar z as `unproject` (tests/nn/test_residual.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.types import ViewSet

ENCODER = "residual"
SHIPPED = Path(__file__).resolve().parents[2] / "assets" / "weights" / "residual"


@dataclass
class ResidualInputs:
    """What the network reads of one view folder, and the unprojection it corrects."""

    base: object  # stages/lift.Unprojected
    features: np.ndarray  # [feature_count, R, R] float32


def residual_inputs(views: ViewSet, cfg) -> ResidualInputs:
    """Unprojection of `views` with the unproject method's config cfg (UnprojectConfig) and its
    observation features: everything the network does not change, computed once."""
    from dlacli.stages.lift.observations import observation_features
    from dlacli.stages.lift.unproject import unprojection

    base = unprojection(views, cfg)
    return ResidualInputs(base, observation_features(base.texels, views, base.depth, base.hull))


def load_residual(checkpoint: str | None, where: str = "--method residual"):
    """(ResidualNet in eval mode, its hash) from a checkpoint folder or hash; None: the shipped
    weights (assets/weights/residual/), a one-line error when none ship."""
    from dlacli.avatar.checkpoint import CONFIG, load_checkpoint, resolve_checkpoint
    from dlacli.nn.residual import ResidualNet

    if checkpoint is None:
        if not (SHIPPED / CONFIG).is_file():
            raise DlaInputError(
                where,
                "no residual weights ship with this version; pass checkpoint=PATH "
                "(a `dla train --method residual` run's RUN/ckpt-N/generator)",
            )
        path = SHIPPED
    else:
        path = resolve_checkpoint(checkpoint)
    loaded = load_checkpoint(path)
    if not isinstance(loaded.module, ResidualNet):
        raise DlaInputError(where, f"{path} holds a {type(loaded.module).__name__}, not a residual lift network")
    return loaded.module.eval(), loaded.hash


def corrected_map(net, inputs: ResidualInputs) -> tuple[np.ndarray, torch.Tensor]:
    """The network's F' [14, R, R] float32 for one view folder's inputs and its corrections t
    [1, 10, R, R] (no gradient)."""
    with torch.no_grad():
        out, t = net(torch.from_numpy(inputs.base.fmap)[None], torch.from_numpy(inputs.features)[None])
    return out[0].numpy(), t


def colour_correction(t: torch.Tensor):
    """F -> F with the colour part of the network's corrections t [1, 10, R, R] applied to F's
    colours, the rest of F as it is: what the lift does to colours re-baked after refinement
    (opacity, offset and scale are refinement's to change)."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.nn.residual import T_RGB, corrected_colour

    t_rgb = t[0, T_RGB]

    def recolour(fmap: np.ndarray) -> np.ndarray:
        corrected = fmap.copy()
        with torch.no_grad():
            corrected[gm.RGB] = corrected_colour(torch.from_numpy(fmap[gm.RGB]), t_rgb).numpy()
        return corrected

    return recolour


def lift_residual(views: ViewSet, config, progress=None, novel: ViewSet | None = None):
    """views -> LiftResult with the residual method's config (ResidualConfig,
    stages/lift/methods/residual.py): unprojection at the network's resolution and
    Gaussian count (unless the config sets resolution / gaussians), the network's corrections,
    `steps` of refinement of the geometry, then the colours re-baked where the refined geometry
    puts the Gaussians and corrected by the network again (`colour_correction`)."""
    import dataclasses

    from dlacli.stages.lift.unproject import finish_lift

    net, digest = load_residual(config.checkpoint)
    cfg = config.unprojection()
    cfg = dataclasses.replace(
        cfg, resolution=cfg.resolution or net.config.resolution, gaussians=cfg.gaussians or net.config.gaussians
    ).resolved()
    inputs = residual_inputs(views, cfg)
    extra = {"residual": {"checkpoint": digest, "gain": bool(net.config.gain)}}
    if not net.config.gain:
        fmap, t = corrected_map(net, inputs)
        recolour = colour_correction(t)
        return finish_lift(
            views, cfg, inputs.base, fmap, progress, novel, encoder=ENCODER, extra=extra, recolour=recolour
        )
    with torch.no_grad():
        z, t = net.encode(
            torch.from_numpy(inputs.base.fmap)[None], torch.from_numpy(inputs.features)[None], inputs.base.falloff
        )
    recolour = colour_correction(t)
    z = z[0].numpy()
    fmap = z[:14].copy()

    def code(final: np.ndarray):
        """The residual-gain avatar code around the (refined) map: F_delta is the gain decoder's."""
        out = np.concatenate([final, z[14:]])
        render = lambda cams: render_code(net, out, inputs.base.vertices, views.body, cams, cfg)  # noqa: E731
        return out, net.name, digest, render

    return finish_lift(
        views, cfg, inputs.base, fmap, progress, novel, encoder=ENCODER, extra=extra, code=code, recolour=recolour
    )


def render_code(net, z: np.ndarray, vertices: np.ndarray, body, cameras, cfg) -> np.ndarray:
    """The residual-gain code z on the body in the input pose (vertices [V, 3]) from cameras, as
    `dla render` draws it -> rgb [C, H, W, 3] numpy."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar
    from dlacli.body.model import get_body_model

    rest = get_body_model().rest_vertices(body.phenotype)
    verts = torch.from_numpy(np.asarray(vertices, np.float32))[None]
    with torch.no_grad():
        decoded = Decoded.of(net, torch.from_numpy(z), rest)
        return PosedAvatar(decoded, gm.make_samples(cfg.gaussians, cfg.seed), verts, cameras).render().rgb.numpy()
