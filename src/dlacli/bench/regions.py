"""Where an avatar's error lives: masked PSNR per body region and an error picture.

Each pixel inside the ground-truth mask gets one region: the body part the fitted body shows
there (`dlacli.body.regions.PARTS`, grouped into face, hair, hands, arms, torso, legs, feet), or
"off body" (clothing or hair outside the body's silhouette), except that pixels within `BAND`
pixels of the mask's outline are the "silhouette band" whatever lies under them: there the error
is about where the edge is, not about colour.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

BAND = 3  # pixels
GROUPS = {
    "face": ("face",),
    "hair": ("hair",),
    "hands": ("left_hand", "right_hand"),
    "arms": ("left_arm", "right_arm"),
    "torso": ("torso",),
    "legs": ("left_leg", "right_leg"),
    "feet": ("left_foot", "right_foot"),
}
REGIONS = (*GROUPS, "off body", "silhouette band")


def pixel_regions(vertices: np.ndarray, cameras, masks: np.ndarray, band: int = BAND) -> np.ndarray:
    """vertices [V, 3] (the posed body), cameras [C], masks [C, H, W] -> [C, H, W] int: an index
    into REGIONS inside the mask (> 0.5), -1 outside."""
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import PARTS, face_parts
    from dlacli.render.raster import rasterize

    part_of_face = face_parts()  # [F] index into PARTS
    group_of_part = np.array([next(i for i, g in enumerate(GROUPS.values()) if p in g) for p in PARTS])
    face_id = rasterize(vertices, get_body_model().faces, cameras).face_id  # [C, H, W]
    inside = masks > 0.5
    labels = np.where(face_id >= 0, group_of_part[part_of_face[np.maximum(face_id, 0)]], REGIONS.index("off body"))
    for c in range(len(masks)):
        edge = inside[c] & ~ndimage.binary_erosion(inside[c], iterations=band, border_value=0)
        labels[c][edge] = REGIONS.index("silhouette band")
    return np.where(inside, labels, -1)


def region_psnr(pred: np.ndarray, gt: np.ndarray, labels: np.ndarray) -> dict[str, dict[str, float]]:
    """pred, gt [C, H, W, 3] in [0, 1], labels from `pixel_regions` -> per region: masked PSNR,
    its share of the masked pixels and its share of the masked squared error (regions with no
    pixels are left out). The shares say where improving would pay."""
    se = ((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2).mean(-1)  # [C, H, W]
    inside = labels >= 0
    total_se, total_px = se[inside].sum(), inside.sum()
    out = {}
    for i, name in enumerate(REGIONS):
        sel = labels == i
        if not sel.any():
            continue
        mse = se[sel].mean()
        out[name] = {
            "psnr": float("inf") if mse == 0 else float(-10 * np.log10(mse)),
            "pixels": float(sel.sum() / total_px),
            "error": float(se[sel].sum() / max(total_se, 1e-30)),
        }
    return out


def _heat(x: np.ndarray) -> np.ndarray:
    """[H, W] in [0, 1] -> [H, W, 3]: black -> red -> yellow -> white."""
    x = np.clip(x, 0.0, 1.0)[..., None]
    return np.clip(np.concatenate([3 * x, 3 * x - 1, 3 * x - 2], -1), 0.0, 1.0)


def error_picture(
    gt: np.ndarray, pred: np.ndarray, labels: np.ndarray, scale: float = 4.0, tile: int = 384
) -> np.ndarray:
    """One view: ground truth | render | |error| x scale as a heat map | the regions (each a grey
    level, the silhouette band white), cut to a square around the person (8 px margin) and
    scaled to `tile` pixels (nearest neighbour, so pixels stay visible) -> uint8 [tile, 4 tile, 3]."""
    from PIL import Image

    err = np.abs(np.asarray(pred, np.float64) - gt).mean(-1) * scale
    region = np.where(labels >= 0, (labels + 1) / len(REGIONS), 0.0)
    tiles = [gt, pred, _heat(err), np.repeat(region[..., None], 3, -1)]
    rows, cols = np.nonzero(labels >= 0)
    if rows.size:
        h, w = labels.shape
        side = min(max(np.ptp(rows), np.ptp(cols)) + 17, h, w)
        r0 = int(np.clip((rows.min() + rows.max() - side) // 2, 0, h - side))
        c0 = int(np.clip((cols.min() + cols.max() - side) // 2, 0, w - side))
        tiles = [t[r0 : r0 + side, c0 : c0 + side] for t in tiles]
    tiles = [
        np.asarray(Image.fromarray((np.clip(t, 0, 1) * 255 + 0.5).astype(np.uint8)).resize((tile, tile), Image.NEAREST))
        for t in tiles
    ]
    return np.concatenate(tiles, axis=1)
