"""Observation features: what the input views say about each texel of an unprojected map F.

The residual lift (stages/lift/residual.py) hands these to its network beside F itself, so the net can
tell where unprojection had good evidence and where it guessed. Numpy, no network; computed once
per lift at the map's resolution R (docs/lift.md "Observation features" says what each means):

    0      coverage          1 on texels the UV layout covers, 0 elsewhere
    1      seen              fraction of the views that see the texel (`bake.texel_views`)
    2      best_cos          the most frontal viewing cosine among them (0: none sees it)
    3      colour_std        spread of the views' colours at the texel (std over the views that
                             see it, mean over r, g, b; 0 when fewer than 2 see it)
    4      mask_sdf          the masks' signed distance at the texel's projection, mean over the
                             views it faces unoccluded (mask or not), in units of SDF_UNIT of the
                             image height, clipped to [-1, 1]; > 0 inside the silhouette
    5      hull_gap          visual-hull depth minus body depth along the best view's ray there
                             (metres, clipped to +-HULL_GAP_MAX; < 0: the person stands in
                             front of the body, e.g. hair or loose clothing); 0 where unknown
    6..8   normal            the body's unit normal at the texel, input pose (world frame)
    9..19  part              one-hot UV segmentation over body/regions.py PARTS
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import distance_transform_edt

from dlacli.geometry import project_points
from dlacli.types import ViewSet

if TYPE_CHECKING:
    from dlacli.stages.lift.bake import TexelViews

SDF_UNIT = 0.1  # the mask SDF is measured in tenths of the image height
HULL_GAP_MAX = 0.3  # metres
NAMES = ("coverage", "seen", "best_cos", "colour_std", "mask_sdf", "hull_gap", "normal_x", "normal_y", "normal_z")


def feature_count() -> int:
    from dlacli.body.regions import PARTS

    return len(NAMES) + len(PARTS)


def _mask_sdf(mask: np.ndarray) -> np.ndarray:
    """Signed distance [H, W] in pixels to the edge of mask > 0.5, positive inside."""
    inside = mask > 0.5
    return distance_transform_edt(inside) - distance_transform_edt(~inside)


def _lookup(image: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-pixel values of image [H, W] at pixel coordinates px [M, 2] -> (values [M], inside [M])."""
    h, w = image.shape
    col, row = np.floor(px[:, 0]).astype(np.int64), np.floor(px[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return image[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)], inside


def observation_features(texels: TexelViews, views: ViewSet, depth: np.ndarray, hull) -> np.ndarray:
    """Features [feature_count(), R, R] float32 of an unprojected map F (module doc) from what the
    views show of its texels (`bake.texel_views`: F's texel points on the body in the views'
    pose), the views, the body's depth in them (depth [V, H, W], `bake.body_depth_maps`) and
    step a's hull depths (`hull.HullDepth`)."""
    from dlacli.body.regions import segmentation_onehot
    from dlacli.stages.lift.bake import VISIBLE_DEPTH

    valid, points, normals = texels.valid, texels.points, texels.normals
    res = valid.shape[-1]
    m, n_views = len(points), len(views)
    h = views.masks.shape[1]
    seen = texels.seen
    seen_n = seen.sum(axis=0).astype(np.float64)
    cos_seen = np.where(seen, texels.cosine, 0.0)
    best_view = np.where(seen.any(axis=0), np.argmax(cos_seen, axis=0), -1)
    best_cos = cos_seen.max(axis=0).clip(0.0, None)
    colour = np.where(seen[..., None], texels.rgb, 0.0)
    two = seen_n >= 2
    mean = colour.sum(axis=0) / np.maximum(seen_n, 1)[:, None]
    var = (colour * colour).sum(axis=0) / np.maximum(seen_n, 1)[:, None] - mean * mean
    colour_std = np.where(two, np.sqrt(np.clip(var, 0.0, None)).mean(axis=1), 0.0)

    sdf_sum, sdf_n, gap = np.zeros(m), np.zeros(m), np.zeros(m)
    w2cs = views.cameras.viewmats.double().numpy()
    ks = views.cameras.Ks.double().numpy()
    hull_w2c = hull.cameras.viewmats.double().numpy()
    hull_ks = hull.cameras.Ks.double().numpy()
    for v in range(n_views):
        px, z = project_points(points, w2cs[v], ks[v])
        to_eye = np.linalg.inv(w2cs[v])[:3, 3] - points
        facing = np.einsum("mc,mc->m", to_eye, normals) > 0.05 * np.linalg.norm(to_eye, axis=1)
        body_z, inside = _lookup(depth[v], px)
        visible = inside & facing & (z > 0) & (z <= body_z + VISIBLE_DEPTH)
        sdf, _ = _lookup(_mask_sdf(views.masks[v]), px)
        sdf_sum += np.where(visible, np.clip(sdf / (SDF_UNIT * h), -1.0, 1.0), 0.0)
        sdf_n += visible
        mine = best_view == v
        if mine.any():
            gpx, _ = project_points(points[mine], hull_w2c[v], hull_ks[v])
            hz, in_h = _lookup(hull.hull[v], gpx)
            bz, in_b = _lookup(hull.body[v], gpx)
            ok = in_h & in_b & np.isfinite(hz) & np.isfinite(bz)
            diff = np.zeros(len(ok))
            diff[ok] = np.clip(hz[ok] - bz[ok], -HULL_GAP_MAX, HULL_GAP_MAX)
            gap[mine] = diff

    per_texel = [
        np.ones(m),
        seen_n / n_views,
        best_cos,
        colour_std,
        sdf_sum / np.maximum(sdf_n, 1),
        gap,
        *normals.T,
    ]
    out = np.zeros((len(per_texel), res, res), np.float32)
    out[:, valid] = np.stack(per_texel)
    return np.concatenate([out, segmentation_onehot(res)])
