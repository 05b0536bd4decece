"""Lift: a view folder -> unstructured pose-space Gaussians -> avatar code Z (docs/architecture.md, "The method").

The non-learned path (paper ablation A.i, "mesh unprojection"), made as accurate as optimisation
allows:
a. `unstructured_gaussians`: one Gaussian per (block of) masked pixel, placed along its ray at the
   depth of the fitted body (slightly in front of it, for clothing) or, where the body is not
   seen (hair, loose clothing), at the front of the silhouettes' visual hull, rounded for true
   views (stages/lift/hull.py); colour from the pixel.
b. `unproject_to_uv`: each Gaussian goes to the nearest body texel that faces its camera; texels
   average what they receive (opacity, offset along the tangent frame), and texels no view saw
   take the values of the nearest seen texel in 3D. The result is the Gaussian map F = Z
   (identity decoder; avatar/gaussian_map.py). `stages/lift/bake.bake_colours` then gives every texel the colour
   the views show at its own 3D point (projective texturing, the most frontal view dominating).
c. `refine`: optimise F's geometry (opacity, normal offset, rotation, scale) through sampling +
   skinning + splatting against the input views (L1 + mask + D-SSIM) at the views' own size, up
   to 512 px, `steps` Adam steps; colours are held at their baked values while the geometry
   moves and re-baked from the refined geometry at the end. docs/lift.md "Why colours are baked"
   says what this buys on novel views and why letting Adam move colours loses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from dlacli.avatar import gaussian_map as gm
from dlacli.errors import DlaInputError
from dlacli.limits import MAX_VIEWS, MIN_VIEW_FALLOFF
from dlacli.stages.lift.bake import (
    VIEW_SHARPNESS,
    TexelViews,
    bake_colours,
    body_depth_maps,
    fill_outside_charts,
    texel_views,
    view_falloff,
)
from dlacli.stages.lift.hull import HullDepth, Silhouettes, hull_depth
from dlacli.stages.lift.sheet import contact_sheet as contact_sheet  # re-exported: the sheet lift writes
from dlacli.stages.lift.sheet import sheet_and_novel_view
from dlacli.types import Avatar, Cameras, Gaussians, ViewSet, rgb_to_sh0

ENCODER = "unproject"
DECODER = "identity"
VIEW_DECODER = "view-cosine"  # when the views' colours depend on the view (`view_falloff`)
CLOTH_MARGIN = 0.003  # metres in front of the body surface where the body is seen (tight clothing)
MAX_OFFSET = 0.08  # metres: farther Gaussians are not attached to a texel (loose clothing stays)
MIN_FALLOFF = MIN_VIEW_FALLOFF  # |k| below this: the identity decoder (colour does not depend on the view)


# ------------------------------------------------------------------------------ a. unstructured


def _block_mean(x: np.ndarray, s: int) -> np.ndarray:
    """[H, W, ...] -> [H // s, W // s, ...] mean over s x s blocks (crops the remainder)."""
    h, w = x.shape[0] // s * s, x.shape[1] // s * s
    x = x[:h, :w]
    return x.reshape(h // s, s, w // s, s, *x.shape[2:]).mean(axis=(1, 3))


def unstructured_gaussians(views: ViewSet, vertices: np.ndarray, grid: int = 128, hull: str | None = None):
    """Pixel-aligned Gaussians in the input pose.

    views: the view folder; vertices [V, 3] the fitted body in the input pose; hull: where rays
    off the body stop, "round" (the rounded hull), "box" (the silhouettes' intersection) or None
    (as `hull_shape` chooses for these views).
    -> (Gaussians, view index per Gaussian [N] int64, camera centre per Gaussian [N, 3]).
    """
    return _unstructured(views, vertices, grid, hull_shape(hull, views))[:3]


def _unstructured(views: ViewSet, vertices: np.ndarray, grid: int, shape: str):
    """`unstructured_gaussians` plus the HullDepth it measured on the way."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import rasterize

    faces = get_body_model().faces
    h, w = views.masks.shape[1:]
    stride = max(1, int(round(max(h, w) / grid)))
    gh, gw = h // stride, w // stride
    cams = views.cameras.resized(gw, gh, scale=1.0 / stride)  # blocks of stride pixels, the remainder cropped
    body = rasterize(vertices, faces, cams)
    centre = vertices.mean(axis=0)
    radius = float(np.linalg.norm(vertices - centre, axis=1).max()) + 0.4
    out_means, out_rgb, out_alpha, out_scale, out_view, out_eye = [], [], [], [], [], []
    hulls = np.full((len(views), gh, gw), np.inf)
    silhouettes = Silhouettes(views)
    for v in range(len(views)):
        alpha = _block_mean(views.masks[v], stride)  # [gh, gw]
        rgb = _block_mean(views.images[v] * views.masks[v][..., None], stride)
        rgb = rgb / np.maximum(alpha[..., None], 1e-6)
        keep = alpha > 0.5  # low-opacity filtering
        rows, cols = np.nonzero(keep)
        if rows.size == 0:
            continue
        k = cams.Ks[v].numpy().astype(np.float64)
        c2w = np.linalg.inv(cams.viewmats[v].numpy().astype(np.float64))
        xc = (cols + 0.5 - k[0, 2]) / k[0, 0]
        yc = (rows + 0.5 - k[1, 2]) / k[1, 1]
        dirs = np.stack([xc, yc, np.ones_like(xc)], -1) @ c2w[:3, :3].T  # camera z = 1 per unit
        origin = c2w[:3, 3]
        hull, off_body = hull_depth(origin, dirs, silhouettes, v, centre, radius, rounded=shape == "round")
        hulls[v][rows, cols] = hull
        bdepth = body.depth[v][rows, cols].astype(np.float64)
        # on the body: the body, unless the silhouettes' intersection says it lies farther; off
        # it (hair, loose clothing): the rounded hull (stages/lift/hull.py) or, for "box", the intersection
        depth = np.where(np.isfinite(bdepth), np.maximum(hull, bdepth - CLOTH_MARGIN), off_body)
        if not np.isfinite(hull).all():  # rays that miss the hull (inconsistent masks): use the body
            depth = np.where(np.isfinite(depth), depth, bdepth)
        ok = np.isfinite(depth)
        means = origin + dirs[ok] * depth[ok, None]
        footprint = depth[ok] / k[0, 0]  # metres per grid pixel at that depth
        out_means.append(means)
        out_rgb.append(rgb[rows[ok], cols[ok]])
        out_alpha.append(alpha[rows[ok], cols[ok]])
        out_scale.append(0.5 * footprint)
        out_view.append(np.full(ok.sum(), v))
        out_eye.append(np.broadcast_to(origin, means.shape))
    if not out_means:
        raise DlaInputError("views", "no masked pixels in any view")
    means = torch.from_numpy(np.concatenate(out_means)).float()
    n = means.shape[0]
    scales = torch.from_numpy(np.concatenate(out_scale)).float()[:, None].expand(n, 3).contiguous()
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    gaussians = Gaussians.from_rgb(
        means,
        quats,
        scales,
        torch.from_numpy(np.concatenate(out_alpha)).float().clamp(0.0, 1.0),
        torch.from_numpy(np.concatenate(out_rgb)).float().clamp(0.0, 1.0),
    )
    return gaussians, np.concatenate(out_view), np.concatenate(out_eye), HullDepth(hulls, body.depth, cams)


# --------------------------------------------------------------------------- b. unprojection


def unproject_to_uv(gaussians: Gaussians, eyes: np.ndarray, vertices: np.ndarray, resolution: int) -> np.ndarray:
    """The Gaussian map F [14, R, R] from unstructured Gaussians (means [N, 3] seen from camera
    centres eyes [N, 3]) and the body in the same pose (vertices [V, 3])."""
    from dlacli.body.uv import FRAME_RESOLUTION, texel_frames, uv_raster

    valid = uv_raster(resolution).mask
    verts = torch.from_numpy(np.asarray(vertices, dtype=np.float64))
    t_map, r_map, _ = texel_frames(verts, resolution, FRAME_RESOLUTION)
    pos, rot = t_map.numpy()[valid], r_map.numpy()[valid]  # [M, 3], [M, 3, 3]
    normals = rot[:, :, 2]
    x = gaussians.means.double().numpy()
    rgb = gaussians.rgb.double().numpy()
    alpha = gaussians.opacities.double().numpy()

    # nearest texels that face the Gaussian's camera
    tree = cKDTree(pos)
    k = 8
    dist, idx = tree.query(x, k=k)  # [N, k]
    to_eye = eyes[:, None, :] - pos[idx]  # [N, k, 3]
    facing = np.einsum("nkc,nkc->nk", to_eye, normals[idx]) > 0
    pick = np.where(facing.any(axis=1), np.argmax(facing, axis=1), 0)
    tex = idx[np.arange(len(x)), pick]  # [N]
    cosine = np.einsum("nc,nc->n", eyes - pos[tex], normals[tex])
    cosine /= np.linalg.norm(eyes - pos[tex], axis=1) + 1e-12
    near = np.linalg.norm(x - pos[tex], axis=1) < MAX_OFFSET
    # the most frontal view dominates a texel: averaging views that disagree by a few pixels blurs
    weight = alpha * np.clip(cosine, 0.05, 1.0) ** VIEW_SHARPNESS * near

    m = pos.shape[0]
    wsum = np.bincount(tex, weight, minlength=m)
    local = np.einsum("nji,nj->ni", rot[tex], x - pos[tex])  # R^T (x - T): offsets in the frame
    acc = np.zeros((m, 7))
    for c, values in enumerate((*rgb.T, *local.T, alpha)):
        acc[:, c] = np.bincount(tex, weight * values, minlength=m)
    seen = wsum > 0
    if not seen.any():
        raise DlaInputError("views", "no Gaussian lands on the body: check body.json against the views")
    acc[seen] /= wsum[seen, None]
    if not seen.all():  # texels no view saw: colour and opacity of the nearest seen texel in 3D;
        # no offset (an offset is only meaningful in the frame of the texel that measured it)
        _, nearest = cKDTree(pos[seen]).query(pos[~seen])
        acc[~seen] = acc[seen][nearest]
        acc[~seen, 3:6] = 0.0

    fmap = np.zeros((gm.CHANNELS, resolution, resolution), dtype=np.float64)
    opacity = np.clip(acc[:, 6], 0.05, 0.99)
    fmap[0][valid] = np.log(opacity / (1.0 - opacity))
    fmap[gm.RGB][:, valid] = acc[:, 0:3].T
    fmap[gm.OFFSET][:, valid] = acc[:, 3:6].T
    fmap[7][valid] = 1.0  # identity rotation (w = 1)
    fmap[gm.LOG_SCALE][:, valid] = np.log([[0.6], [0.6], [0.2]])  # flat surfels about as wide as the sample spacing
    return fill_outside_charts(fmap, valid).astype(np.float32)


_CHANNEL_STEP = torch.tensor([5.0, 0, 0, 0, 0, 0, 0.1, 1, 1, 1, 1, 1, 1, 1])


def fixed_order_mean(x: torch.Tensor, rows: int = 1024) -> torch.Tensor:
    """Mean whose value does not depend on the thread count: torch splits a reduction to one
    number of more than 32,768 elements over its threads, but sums each row of a [rows, -1]
    view on one thread and the `rows` row sums serially. Same gradient as x.mean()."""
    flat = x.reshape(-1)
    pad = (-flat.numel()) % rows
    if pad:
        flat = torch.nn.functional.pad(flat, (0, pad))
    return flat.view(rows, -1).sum(dim=1).sum() / x.numel()


def lifted_posed(fmap: np.ndarray, falloff: float, vertices: np.ndarray, cameras: Cameras, samples: gm.Samples):
    """The avatar lift writes for F [14, R, R] and view falloff k (identity decoder, or the
    view-cosine one when k != 0) placed on the body in one pose (vertices [V, 3]) and seen from
    cameras: avatar/posed.PosedAvatar, what `dla render` draws of it."""
    from dlacli.avatar.codec import Decoded, IdentityDecoder, ViewCosineDecoder
    from dlacli.avatar.posed import PosedAvatar

    z = torch.as_tensor(fmap, dtype=torch.float32)  # a tensor stays differentiable (training renders through it)
    decoder = IdentityDecoder()
    if falloff:
        z, decoder = torch.cat([z, torch.full((1, *fmap.shape[1:]), float(falloff))]), ViewCosineDecoder()
    verts = torch.as_tensor(vertices, dtype=torch.float32, device=z.device)  # z's device (training may use CUDA)
    # the view-cosine decoder reads the posed normals alone: the posed body stands in for the rest pose
    decoded = Decoded.of(decoder, z, rest_vertices=verts.cpu().numpy())
    return PosedAvatar(decoded, samples, verts[None], cameras)


def view_colours(
    fmap: np.ndarray, falloff: float, vertices: np.ndarray, cameras: Cameras, samples: gm.Samples
) -> torch.Tensor | None:
    """The samples' colours [C, N, 3] as each camera sees F [14, R, R] with a view falloff k on
    the body in one pose (vertices [V, 3]): what the view-cosine decoder (avatar/codec.py) makes
    of them, so lift refines what `dla render` draws. None for k = 0."""
    if not falloff:
        return None
    posed = lifted_posed(fmap, falloff, vertices, cameras, samples)
    return torch.cat([posed.placed(0, c).rgb for c in range(len(cameras))])


def _render(g: Gaussians, cams: Cameras, colours: torch.Tensor | None):
    """Render g from cams -> (rgb [C, H, W, 3], alpha [C, H, W]); with per-camera colours
    [C, N, 3], each camera sees the Gaussians in its own colours."""
    from dlacli.avatar.posed import render_set

    sh = None if colours is None else rgb_to_sh0(colours)[..., None, :]
    out = render_set(g, cams, sh=sh)
    return out.rgb, out.alpha


def refine(
    fmap: np.ndarray,
    views: ViewSet,
    vertices: np.ndarray,
    cfg,
    progress=None,
    samples: gm.Samples | None = None,
    falloff: float = 0.0,
) -> tuple[np.ndarray, list[float]]:
    """Optimise the geometry of the Gaussian map F [14, R, R] (the channels `_CHANNEL_STEP` moves)
    so that its Gaussians, placed on the body in the input pose (vertices [V, 3]) and coloured as
    each view sees them (view falloff `falloff`, `view_colours`), re-render the input views:
    L1 + w_mask * mask L1 + w_ssim * (1 - SSIM), Adam for cfg.steps steps.
    `progress(step, loss)` is called per step. Returns the refined map and the loss of every step."""
    from dlacli.nn.losses import SSIM_WINDOW, ssim_map
    from dlacli.stages.lift.refine import adam_refine, crop, subject_crops

    cfg = cfg.resolved()
    samples = samples or gm.make_samples(cfg.gaussians, cfg.seed)
    # F itself is optimised (the identity decoder's F = Z): its Gaussians are placed straight by
    # gaussian_map (as avatar/posed.py places any F), the body's frames computed once
    frames = gm.sample_frames(torch.from_numpy(np.asarray(vertices, dtype=np.float32))[None], samples)
    target_rgb, target_mask, cams = views.targets(cfg.render_size)
    base = torch.from_numpy(fmap).float()
    # the views are compared only in a window around the subject (subject_crops): outside it
    # target and render are black, so every term below equals its whole-image value
    full = (len(cams), cams.height, cams.width)
    with torch.no_grad():
        (start,) = gm.gaussians_at_frames(base, samples, frames)
    x0s, y0s, cw, ch = subject_crops(target_mask, start.means.numpy().astype(np.float64), cams)
    target_rgb, target_mask = crop(target_rgb, x0s, y0s, cw, ch), crop(target_mask, x0s, y0s, cw, ch)
    cams = cams.cropped(x0s, y0s, cw, ch)
    colours = view_colours(fmap, falloff, vertices, cams, samples)  # colours are held: once
    delta = torch.zeros_like(base, requires_grad=True)
    step_scale = _CHANNEL_STEP.to(base)[:, None, None]
    n_pixels = full[0] * full[1] * full[2]
    win = min(SSIM_WINDOW, full[1], full[2]) | 1  # as ssim_map sizes its window
    n_ssim = full[0] * (full[1] - win + 1) * (full[2] - win + 1) * 3  # ssim_map's 'valid' values

    w_smooth = smoothness(cfg, views)
    pairs = _neighbour_pairs(fmap.shape[-1]) if w_smooth else None

    def loss() -> torch.Tensor:
        f = base + delta * step_scale
        (g,) = gm.gaussians_at_frames(f, samples, frames)
        rgb, alpha = _render(g, cams, colours)
        value = fixed_order_mean((rgb - target_rgb).abs()) * (rgb.numel() / (3 * n_pixels))
        value = value + cfg.w_mask * fixed_order_mean((alpha - target_mask).abs()) * (alpha.numel() / n_pixels)
        if cfg.w_ssim:
            s = ssim_map(rgb, target_rgb)  # 1 - SSIM is 0 on the black outside the windows
            value = value + cfg.w_ssim * fixed_order_mean(1.0 - s) * (s.numel() / n_ssim)
        if w_smooth:
            value = value + w_smooth * _roughness(f[gm.OFFSET][2], pairs)
        return value

    history = adam_refine([delta], loss, cfg.steps, cfg.lr, progress)
    return (base + delta.detach() * step_scale).numpy(), history


ROUGHNESS_UNIT = 0.01  # metres: the normal offsets' neighbour differences are measured in cm
# The roughness weight for dreamed views (docs/lift.md, "The surface's roughness"): their views
# 1-3 are renders of a smooth body, so a rough surface explains no detail there, and on the
# single-photo benchmark the weight costs 0.03 dB on novel views while it removes the cracks a
# rough surface shows when reposed. Four true views keep 0: there it costs 0.15-0.22 dB.
DREAM_W_SMOOTH = 0.1


def smoothness(cfg, views: ViewSet) -> float:
    """The roughness weight the refinement uses: cfg.w_smooth when set, else DREAM_W_SMOOTH for a
    view folder `dla dream` wrote (its transforms.json holds `dla.dream`) and 0 for others."""
    if cfg.w_smooth is not None:
        return float(cfg.w_smooth)
    return DREAM_W_SMOOTH if dreamed(views) else 0.0


def hull_shape(hull: str | None, views: ViewSet) -> str:
    """Where the lift's rays off the body stop: `hull` when set, else "round" for true views and
    "box" for a view folder `dla dream` wrote. Its side and back silhouettes are renders of the
    fitted body already, so rounding them again buys nothing: on the single-photo benchmark
    rounding cost 0.02 dB on novel views after 40 steps (0.10 dB unrefined) where four true views
    gained 0.09-0.13 dB (docs/lift.md, "Loose clothing")."""
    if hull is not None:
        return hull
    return "box" if dreamed(views) else "round"


def dreamed(views: ViewSet) -> bool:
    """Whether `dla dream` wrote the view folder (its transforms.json holds `dla.dream`)."""
    return "dream" in (views.extra or {})


def _neighbour_pairs(resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Masks (float64) of the horizontally [R, R - 1] and vertically [R - 1, R] adjacent texel
    pairs that the UV layout both covers."""
    from dlacli.body.uv import uv_raster

    valid = torch.from_numpy(uv_raster(resolution).mask)
    return (valid[:, 1:] & valid[:, :-1]).double(), (valid[1:, :] & valid[:-1, :]).double()


def _roughness(normal_offset: torch.Tensor, pairs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Mean squared difference of the normal offsets [R, R] of adjacent covered texels
    (`_neighbour_pairs`), in ROUGHNESS_UNIT: 0 on a surface the offsets move as a whole. Slices,
    not gathers, so that its gradient has no scatter whose order could follow the thread count."""
    right, down = (m.to(normal_offset.dtype) for m in pairs)
    dr = (normal_offset[:, 1:] - normal_offset[:, :-1]) / ROUGHNESS_UNIT
    dd = (normal_offset[1:, :] - normal_offset[:-1, :]) / ROUGHNESS_UNIT
    total = fixed_order_mean(dr * dr * right) * dr.numel() + fixed_order_mean(dd * dd * down) * dd.numel()
    return total / float(right.sum() + down.sum())


# ------------------------------------------------------------------------------------ driver


@dataclass
class LiftResult:
    avatar: Avatar
    unstructured: Gaussians  # the pose-space Gaussians of step a (for the .ply)
    contact_sheet: np.ndarray  # [H, W, 3] uint8: inputs (top) vs re-renders of the avatar (bottom)
    novel_view: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # render, truth, mask of the first novel view


def render_views(fmap: np.ndarray, vertices: np.ndarray, cameras: Cameras, samples: gm.Samples, falloff: float = 0.0):
    """Render the avatar F (view falloff k) placed on one posed body (vertices [V, 3]) from
    cameras, as `dla render` draws it (`lifted_posed`) -> (rgb [C, H, W, 3], alpha [C, H, W])."""
    with torch.no_grad():
        out = lifted_posed(fmap, falloff, vertices, cameras, samples).render()
    return out.rgb, out.alpha


@dataclass
class Unprojected:
    """What mesh unprojection makes of a view folder: the lift with 0 steps (a, b and the bake)."""

    vertices: np.ndarray  # [V, 3] the body in the input pose
    unstructured: Gaussians  # step a's pose-space Gaussians
    depth: np.ndarray  # [V, H, W] the body's camera depth in the views (inf off it)
    hull: HullDepth  # step a's visual-hull depths
    texels: TexelViews  # what the views show of F's texels (its geometry is the bake's)
    fmap: np.ndarray  # [14, R, R] float32: F, colours baked
    falloff: float  # the views' view falloff k (0: the identity decoder)


def unprojection(views: ViewSet, cfg) -> Unprojected:
    """Steps a and b and the colour bake: everything `lift` does before refining."""
    from dlacli.body.model import get_body_model

    cfg = cfg.resolved()

    if views.body is None:
        raise DlaInputError("views", "lift needs body.json beside transforms.json")
    if len(views) > MAX_VIEWS:
        raise DlaInputError("views", f"has {len(views)} views; lift takes at most {MAX_VIEWS} (the method uses 4)")
    vertices = get_body_model().forward_body(views.body).vertices[0].numpy()
    unstructured, _, eyes, hull = _unstructured(views, vertices, cfg.grid, hull_shape(cfg.hull, views))
    depth = body_depth_maps(vertices, views)  # for the bakes and the falloff
    fmap = unproject_to_uv(unstructured, eyes, vertices, cfg.resolution)
    texels = texel_views(fmap, vertices, views, depth)
    falloff = view_falloff(texels) if cfg.view_colour else 0.0
    falloff = falloff if abs(falloff) >= MIN_FALLOFF else 0.0
    fmap = bake_colours(fmap, texels, falloff)
    return Unprojected(vertices, unstructured, depth, hull, texels, fmap, falloff)


def lift(views: ViewSet, cfg, progress=None, novel: ViewSet | None = None) -> LiftResult:
    """A view folder (with body.json) -> avatar (Z = the Gaussian map F), the unstructured
    Gaussians and a contact sheet. `cfg`: the unproject method's config (UnprojectConfig, as
    every `cfg` here; stages/lift/methods/unproject.py). `novel`: ground-truth views of the same
    pose that lift does not see (synth's novel_views/); the first one joins the contact sheet as a
    fifth column and is returned rendered (`LiftResult.novel_view`) for scoring."""
    cfg = cfg.resolved()
    base = unprojection(views, cfg)
    return finish_lift(views, cfg, base, base.fmap, progress, novel)


def finish_lift(
    views: ViewSet,
    cfg,
    base: Unprojected,
    fmap: np.ndarray,
    progress=None,
    novel: ViewSet | None = None,
    encoder: str = ENCODER,
    extra: dict | None = None,
    code=None,
    recolour=None,
) -> LiftResult:
    """The lift's end from a Gaussian map F [14, R, R] on the body of `base`: cfg.steps of
    refinement (colours re-baked after it, then passed through `recolour(F) -> F` when given:
    a correction of the baked colours), the contact sheet, and the avatar
    that records `encoder` and `extra` beside the lift's own. Its decoder is identity or
    view-cosine (z = F, or F and the falloff), unless `code(F)` -> (z, decoder name, checkpoint
    hash, render(cameras) -> rgb [C, H, W, 3] numpy) says otherwise."""
    from dlacli.body.uv import UV_LAYOUT

    cfg = cfg.resolved()
    vertices, depth, falloff = base.vertices, base.depth, base.falloff
    samples = gm.make_samples(cfg.gaussians, cfg.seed)  # the Gaussians refined and shown
    history: list[float] = []
    if cfg.steps > 0:
        fmap, history = refine(fmap, views, vertices, cfg, progress, samples, falloff)
        fmap = bake_colours(fmap, texel_views(fmap, vertices, views, depth), falloff)  # where refinement put them
        if recolour is not None:
            fmap = recolour(fmap)
    if code is None:
        z, decoder, checkpoint = fmap, DECODER, ""
        if falloff:  # colour depends on the view: the view-cosine decoder, k in z's last channel
            z, decoder = np.concatenate([fmap, np.full((1, *fmap.shape[1:]), falloff, np.float32)]), VIEW_DECODER
        render = lambda cams: render_views(fmap, vertices, cams, samples, falloff)[0].numpy()  # noqa: E731
    else:
        z, decoder, checkpoint, render = code(fmap)
    sheet, novel_view = sheet_and_novel_view(views, novel, render)
    extra = {
        **(extra or {}),
        "lift": {
            "steps": cfg.steps,
            "lr": cfg.lr,
            "grid": cfg.grid,
            "gaussians": cfg.gaussians,
            "final_loss": history[-1] if history else None,
            "w_smooth": smoothness(cfg, views) if cfg.steps > 0 else 0.0,  # the weight refinement used
            "view_falloff": falloff,
        },
        "samples": {"count": cfg.gaussians, "seed": cfg.seed},
    }  # what render/animate draw by default
    avatar = Avatar(z, encoder, decoder, views.body, UV_LAYOUT, checkpoint, extra=extra)
    return LiftResult(avatar, base.unstructured, sheet, novel_view)
