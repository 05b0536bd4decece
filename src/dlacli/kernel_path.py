"""The one rule for when a numba kernel serves a computation in place of its torch twin
(docs/architecture.md, "numba kernels and their torch twins")."""

from __future__ import annotations

import torch


def takes_kernels(*tensors: torch.Tensor, held: tuple | None = None, dtype: torch.dtype | None = torch.float32) -> bool:
    """Whether the numba kernels serve these tensors: all on the CPU, all of `dtype` (None: any),
    and no gradient asked for of the tensors in `held` (default: all of them). The torch twin
    keeps the gradients; `held` names fewer where the kernel carries its own backward for the
    rest (the projection's for the Gaussians, the lookup's for the maps: held=())."""
    if any(t.device.type != "cpu" or (dtype is not None and t.dtype != dtype) for t in tensors):
        return False
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in (tensors if held is None else held)))
