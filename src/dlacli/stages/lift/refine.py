"""The refinement loop both lifts share: Adam on some tensors against a rendering loss; and the
window around the subject that refinement renders and compares (`subject_crops`, `crop`).

`dla lift` refines the geometry of the Gaussian map F (stages/lift/unproject.py `refine`), the learned lift
refines the code Z through the frozen decoder (stages/lift/learned.py `lift_learned`); what they
optimise and how they score a render is theirs, the steps are this one loop.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from dlacli.geometry import project_points
from dlacli.types import Cameras


def adam_refine(
    params: list[torch.Tensor],
    loss: Callable[[], torch.Tensor],
    steps: int,
    lr: float,
    progress: Callable[[int, float], None] | None = None,
) -> list[float]:
    """`steps` Adam steps (learning rate lr) on params (leaf tensors that require grad) against
    loss() (a scalar tensor, recomputed every step) -> the loss of every step, before its update.
    `progress(step, loss)` is called after each step."""
    opt = torch.optim.Adam(params, lr=lr)
    history: list[float] = []
    for step in range(steps):
        opt.zero_grad(set_to_none=True)
        value = loss()
        value.backward()
        opt.step()
        history.append(float(value.detach()))
        if progress is not None:
            progress(step, history[-1])
    return history


CROP_MARGIN = 0.05  # of the long side: the refinement's crops reach this far beyond the subject


def subject_crops(target_mask: torch.Tensor, points: np.ndarray, cameras: Cameras, margin: float = CROP_MARGIN):
    """One window size for all views that holds, in each view, every pixel of its target mask
    [V, h, w] and the projection of every point [N, 3] in front of it, plus `margin` x the long
    side on every side (clipped to the image): (x0 [V], y0 [V], width, height) for
    `Cameras.cropped`. What lies outside a view's window is background in the target and, while
    the Gaussians stay within the margin of where they started, in the render too."""
    from dlacli.nn.losses import SSIM_WINDOW

    v, h, w = target_mask.shape
    pad = max(int(np.ceil(margin * max(h, w))), SSIM_WINDOW)  # SSIM's windows at the edge see only black
    boxes = []
    for i in range(v):
        rows, cols = np.nonzero(target_mask[i].numpy() > 0)
        px, z = project_points(
            points, cameras.viewmats[i].numpy().astype(np.float64), cameras.Ks[i].numpy().astype(np.float64)
        )
        px = px[z > 0]
        xs = np.concatenate([cols + 0.5, px[:, 0]]) if px.size else cols + 0.5
        ys = np.concatenate([rows + 0.5, px[:, 1]]) if px.size else rows + 0.5
        if xs.size == 0:
            boxes.append((0, 0, w, h))
            continue
        x0, x1 = int(np.floor(xs.min())) - pad, int(np.ceil(xs.max())) + pad
        y0, y1 = int(np.floor(ys.min())) - pad, int(np.ceil(ys.max())) + pad
        boxes.append((max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)))
    cw = min(w, max(2 * SSIM_WINDOW, *(b[2] - b[0] for b in boxes)))
    ch = min(h, max(2 * SSIM_WINDOW, *(b[3] - b[1] for b in boxes)))
    x0s = [int(np.clip((b[0] + b[2] - cw) // 2, 0, w - cw)) for b in boxes]
    y0s = [int(np.clip((b[1] + b[3] - ch) // 2, 0, h - ch)) for b in boxes]
    return np.array(x0s), np.array(y0s), cw, ch


def crop(images: torch.Tensor, x0s, y0s, width: int, height: int) -> torch.Tensor:
    """[V, h, w, ...] -> [V, height, width, ...]: view i's window at (x0s[i], y0s[i])."""
    return torch.stack(
        [images[i, y : y + height, x : x + width] for i, (x, y) in enumerate(zip(x0s, y0s))]
    ).contiguous()
