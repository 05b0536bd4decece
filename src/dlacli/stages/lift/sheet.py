"""The contact sheet `dla lift` writes beside an avatar: the input views above the avatar's
renders of them, plus the first novel view (ground truth the avatar never saw) when there is one."""

from __future__ import annotations

import numpy as np

from dlacli.types import ViewSet


def contact_sheet(inputs: np.ndarray, renders: np.ndarray, tile: int = 256) -> np.ndarray:
    """Inputs [V, H, W, 3] above renders [V, H, W, 3] (floats in [0, 1]) -> uint8 image; tiles
    are framed by a 1-pixel grey line so that columns stay apart on a black background."""
    from PIL import Image

    def row(images):
        tiles = []
        for im in images:
            pil = Image.fromarray((np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8))
            pil.thumbnail((tile, tile))
            canvas = Image.new("RGB", (tile, tile))
            canvas.paste(pil, ((tile - pil.width) // 2, (tile - pil.height) // 2))
            framed = np.asarray(canvas).copy()
            framed[[0, -1], :] = framed[:, [0, -1]] = 64
            tiles.append(framed)
        return np.concatenate(tiles, axis=1)

    return np.concatenate([row(inputs), row(renders)], axis=0)


def sheet_and_novel_view(views: ViewSet, novel: ViewSet | None, render):
    """The contact sheet of an avatar shown by `render(cameras) -> rgb [C, H, W, 3]` (numpy):
    the views at <= 512 px above its renders of them, plus the first novel view (ground truth
    the avatar never saw) as a fifth column when `novel` has one -> (sheet, (render, truth,
    mask) of that novel view or None)."""
    rgb, _, cams = views.targets(512)
    inputs, renders, novel_view = rgb.numpy(), render(cams), None
    if novel is not None and len(novel):
        n_rgb, n_mask, n_cams = novel.targets(512)
        n_out = render(n_cams.select(0))
        novel_view = (n_out[0], n_rgb[0].numpy(), n_mask[0].numpy())
        inputs, renders = np.concatenate([inputs, n_rgb[:1].numpy()]), np.concatenate([renders, n_out])
    return contact_sheet(inputs, renders), novel_view
