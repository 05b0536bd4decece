"""The refinement loop both lifts share: Adam on some tensors against a rendering loss.

`dla lift` refines the geometry of the Gaussian map F (stages/lift.py `refine`), the learned lift
refines the code Z through the frozen decoder (stages/learned.py `lift_learned`); what they
optimise and how they score a render is theirs, the steps are this one loop.
"""

from __future__ import annotations

from collections.abc import Callable

import torch


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
