"""The one scorer of every benchmark: an avatar's renders against a split's ground truth, as the
metric dict {psnr, psnr_masked, ssim, iou} (METRICS) that result rows hold (bench/metrics.py has
the metrics themselves). Renders and truth are composited on black, as the paper reports.
"""

from __future__ import annotations

import numpy as np

METRICS = ("psnr", "psnr_masked", "ssim", "iou")  # a row's metrics, in this order (LPIPS: absent)


def scores(rgba: np.ndarray, gt: np.ndarray, masks: np.ndarray) -> dict[str, float]:
    """Renders rgba [C, H, W, 4] against ground truth gt [C, H, W, 3] (on black) and its masks
    [C, H, W] -> {psnr, psnr_masked, ssim, iou}."""
    from dlacli.bench.metrics import alpha_iou, masked_psnr, psnr, ssim

    rgb = rgba[..., :3]
    out = {
        "psnr": psnr(rgb, gt),
        "psnr_masked": masked_psnr(rgb, gt, masks),
        "ssim": ssim(rgb, gt),
        "iou": alpha_iou(rgba[..., 3], masks),
    }
    assert tuple(out) == METRICS
    return out


def render_split(avatar, views, motion=None) -> tuple[np.ndarray, np.ndarray]:
    """The avatar rendered at a split's cameras (and motion frames) -> (RGBA [C, H, W, 4] in the
    views' order, ground truth [C, H, W, 3] on black)."""
    from dlacli.stages.render import render_avatar

    shots = sorted(render_avatar(avatar, views.cameras, views.times, motion), key=lambda s: s.camera)
    return np.stack([s.rgba for s in shots]), views.images * views.masks[..., None]


def score_split(avatar, views, motion=None) -> dict[str, float]:
    """`scores` of the avatar's renders of a split (views, and the motion its times index)."""
    rgba, gt = render_split(avatar, views, motion)
    return scores(rgba, gt, views.masks)
