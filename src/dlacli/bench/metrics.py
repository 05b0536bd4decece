"""Image metrics for lift/animate accuracy (numpy in, floats out).

Images are [..., H, W, 3] rgb in [0, 1], composited on black (as the paper reports); masks
[..., H, W] in [0, 1]. The whole-image PSNR is flattered by the background (an all-black guess
already scores about 20 dB on a person-sized subject), so `masked_psnr` is reported beside it.
"""

from __future__ import annotations

import numpy as np
import torch


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR in dB over all pixels and channels (peak 1)."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """PSNR over the pixels where the ground-truth mask > 0.5 (all three channels)."""
    sel = np.asarray(mask) > 0.5
    if not sel.any():
        raise ValueError("masked_psnr: empty mask")
    diff = np.asarray(pred, np.float64)[sel] - np.asarray(gt, np.float64)[sel]
    mse = float(np.mean(diff**2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean SSIM (Gaussian window 11, sigma 1.5) over all images, pixels and channels."""
    from dlacli.nn.losses import ssim as ssim_t

    return float(ssim_t(torch.from_numpy(np.asarray(pred, np.float64)), torch.from_numpy(np.asarray(gt, np.float64))))


def alpha_iou(pred_alpha: np.ndarray, gt_alpha: np.ndarray) -> float:
    """Intersection over union of the alpha masks thresholded at 0.5."""
    a, b = np.asarray(pred_alpha) > 0.5, np.asarray(gt_alpha) > 0.5
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
