"""The colour bake of the lift (stages/lift/unproject.py): projective texturing of the Gaussian map F from
the views, and the views' view-dependent falloff k.

Each texel's 3D point on the body in the input pose is projected into every view; a view sees it
when the point lies no deeper than VISIBLE_DEPTH behind the body's depth there (`body_depth_maps`)
and faces the camera. `bake_colours` gives each texel the views' colours weighted by
cos(view angle) ** VIEW_SHARPNESS (the most frontal view dominating); `view_falloff` measures k,
how colour falls off with the viewing angle (the view-cosine decoder, avatar/codec.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from dlacli.avatar import gaussian_map as gm
from dlacli.avatar.codec import shading
from dlacli.geometry import project_points as _project  # points [..., 3] -> (pixels [..., 2], z [...])
from dlacli.types import ViewSet

VIEW_SHARPNESS = 4.0  # texel colour weight ~ cos(view angle) ** VIEW_SHARPNESS
VISIBLE_DEPTH = 0.03  # metres: a texel point up to this far behind the body's depth still counts as seen
FALLOFF_RANGE = (-0.5, 0.95)  # the view falloffs k `view_falloff` considers (1 - k + k cos > 0 for cos >= 0)


def fill_outside_charts(fmap: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Copy each empty texel's nearest valid texel (in UV) so bilinear lookups at chart borders
    do not blend in zeros. fmap [C, R, R], valid [R, R]."""
    _, (ri, ci) = distance_transform_edt(~valid, return_indices=True)
    return fmap[:, ri, ci]


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """image [H, W, C] at continuous pixel coordinates (x, y) [M] (pixel centres at +0.5), clamped
    to the image -> [M, C]."""
    h, w = image.shape[:2]
    x = np.clip(x - 0.5, 0.0, w - 1.0)
    y = np.clip(y - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (
        image[y0, x0] * (1 - fx) * (1 - fy)
        + image[y0, x1] * fx * (1 - fy)
        + image[y1, x0] * (1 - fx) * fy
        + image[y1, x1] * fx * fy
    )


def body_depth_maps(vertices: np.ndarray, views: ViewSet) -> np.ndarray:
    """Camera depth [V, H, W] of the body (vertices [V, 3]) in every view, inf off the body."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import rasterize

    return rasterize(vertices, get_body_model().faces, views.cameras).depth


@dataclass
class TexelViews:
    """What the views show of each covered texel's point on the body in the input pose (T + R dx,
    the texel's own offset): computed once per map geometry (`texel_views`) and read by the
    falloff, the bake and the residual lift's observation features."""

    valid: np.ndarray  # [R, R] bool: the texels the UV layout covers
    points: np.ndarray  # [M, 3] float64: their points
    normals: np.ndarray  # [M, 3] float64: the body's unit normal there
    rgb: np.ndarray  # [V, M, 3] straight colour per view
    mask: np.ndarray  # [V, M] the view's mask there
    cosine: np.ndarray  # [V, M] cosine toward the camera
    seen: np.ndarray  # [V, M] bool: the view sees the point


def texel_views(fmap: np.ndarray, vertices: np.ndarray, views: ViewSet, body_depth: np.ndarray) -> TexelViews:
    """Each covered texel's point of the map F [14, R, R] on the body (vertices [V, 3]) and what
    every view shows of it. A view sees a point that falls inside its image and mask (> 0.5) and
    its colour trust (> 0.5, `ViewSet.trust`: not where a limb the body does not place there
    covers it), faces it (cos > 0.05) and is not hidden by the body (camera depth at most
    VISIBLE_DEPTH behind the body's depth there, `body_depth` [V, H, W] from `body_depth_maps`)."""
    from dlacli.body.uv import FRAME_RESOLUTION, texel_frames, uv_raster

    res = fmap.shape[-1]
    valid = uv_raster(res).mask
    t_map, r_map, _ = texel_frames(torch.from_numpy(np.asarray(vertices, dtype=np.float64)), res, FRAME_RESOLUTION)
    pos, rot = t_map.numpy()[valid], r_map.numpy()[valid]  # [M, 3], [M, 3, 3]
    points = pos + np.einsum("mij,mj->mi", rot, fmap[gm.OFFSET][:, valid].T.astype(np.float64))
    normals = rot[:, :, 2]
    h, w = views.masks.shape[1:]
    per_view = []
    for v in range(len(views)):
        w2c = views.cameras.viewmats[v].double().numpy()
        px, z = _project(points, w2c, views.cameras.Ks[v].double().numpy())
        to_eye = np.linalg.inv(w2c)[:3, 3] - points
        cosine = np.einsum("mc,mc->m", to_eye, normals) / (np.linalg.norm(to_eye, axis=1) + 1e-12)
        rgba = np.concatenate([views.images[v] * views.masks[v][..., None], views.masks[v][..., None]], -1)
        sampled = _bilinear(rgba, px[:, 0], px[:, 1])  # premultiplied rgb, mask
        mask = sampled[:, 3]
        col = np.clip(np.floor(px[:, 0]).astype(np.int64), 0, w - 1)
        row = np.clip(np.floor(px[:, 1]).astype(np.int64), 0, h - 1)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h) & (z > 0)
        seen = inside & (z <= body_depth[v][row, col] + VISIBLE_DEPTH) & (cosine > 0.05) & (mask > 0.5)
        if views.trust is not None:
            seen &= _bilinear(views.trust[v][..., None], px[:, 0], px[:, 1])[:, 0] > 0.5
        per_view.append((sampled[:, :3] / np.maximum(mask, 1e-6)[:, None], mask, cosine, seen))
    rgb, mask, cosine, seen = (np.stack(parts) for parts in zip(*per_view))
    return TexelViews(valid, points, normals, rgb, mask, cosine, seen)


def view_falloff(texels: TexelViews) -> float:
    """How much the views' colours depend on the angle they see the surface at: the falloff k of
    colour = albedo (1 - k + k cos) that best explains the texels two views see at different
    angles (cos differing by > 0.2, both > 0.35, well inside both masks; at more grazing angles
    a point misplaced by a pixel lands on a more frontal patch, which biases k low). Each such pair gives
    log(L_i / L_j) = log(shading(k, cos_i) / shading(k, cos_j)) for the luminances L; k is the
    value in FALLOFF_RANGE (steps of 0.01) with the least median absolute residual, robust to
    the pairs a geometry error misregisters. 0 when fewer than 200 pairs exist (too few texels
    seen twice to tell). `texels`: what the views show of the map's texels (`texel_views`)."""
    obs = [
        (rgb.mean(axis=1), cos, seen & (mask > 0.95))
        for rgb, mask, cos, seen in zip(texels.rgb, texels.mask, texels.cosine, texels.seen)
    ]
    ratios, ci, cj = [], [], []
    for i in range(len(obs)):
        for j in range(i + 1, len(obs)):
            (li, cos_i, si), (lj, cos_j, sj) = obs[i], obs[j]
            pair = si & sj & (cos_i > 0.35) & (cos_j > 0.35) & (np.abs(cos_i - cos_j) > 0.2) & (li > 0.04) & (lj > 0.04)
            ratios.append(np.log(li[pair] / lj[pair]))
            ci.append(cos_i[pair])
            cj.append(cos_j[pair])
    ratio, ci, cj = (np.concatenate(a) if a else np.zeros(0) for a in (ratios, ci, cj))
    if ratio.size < 200:
        return 0.0
    ks = np.round(np.arange(FALLOFF_RANGE[0], FALLOFF_RANGE[1] + 1e-9, 0.01), 2)
    cost = [np.median(np.abs(ratio - np.log(shading(k, ci) / shading(k, cj)))) for k in ks]
    return float(ks[int(np.argmin(cost))])


def bake_colours(fmap: np.ndarray, texels: TexelViews, falloff: float = 0.0) -> np.ndarray:
    """F [14, R, R] with its colour channels baked from the views: each texel's point on the body
    in the input pose (T + R dx, its own offset) is projected into every view that sees it
    (`texels`, from `texel_views` of this F's geometry); the texel takes the bilinear colour of
    those views weighted by cos ** VIEW_SHARPNESS x mask, each divided by the view's shading
    (`shading(falloff, cos)`, so the texel holds the colour seen head-on). Texels no view sees
    keep their colour. Gathering at the texel's own point keeps colour and geometry aligned to
    the pixel, where scattering pixel Gaussians to their nearest texel (step b) leaves holes and
    shifts of up to a texel."""
    valid = texels.valid
    if valid.shape != fmap.shape[-2:]:
        raise ValueError(f"bake_colours: texels of a {valid.shape} map for a {fmap.shape[-2:]} map")
    res = fmap.shape[-1]
    weight = np.where(texels.seen, np.clip(texels.cosine, 0.05, 1.0) ** VIEW_SHARPNESS * texels.mask, 0.0)  # [V, M]
    acc = np.einsum("vm,vmc->mc", weight / shading(falloff, texels.cosine), texels.rgb)
    wsum = weight.sum(axis=0)
    out = fmap.copy()
    rgb = out[gm.RGB][:, valid].T.astype(np.float64)  # [M, 3]
    got = wsum > 0
    rgb[got] = np.clip(acc[got] / wsum[got, None], 0.0, 1.0)
    full = np.zeros((3, res, res))
    full[:, valid] = rgb.T
    out[gm.RGB] = fill_outside_charts(full, valid)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------- c. refinement

# Adam steps move F by about lr * scale per channel: opacity logit, rgb, offset (metres),
# rotation (quaternion), log scale. Colours and the tangential offsets are held (0): colours are
# baked from the views, and a tangential offset would slide a texel off the colour baked for it.
