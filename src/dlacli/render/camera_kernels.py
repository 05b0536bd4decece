"""Numba kernels of the splatter's camera transform (render/splat.py `_CameraPoints`): the
Gaussians' means in each camera's frame and the gradient back to the means, each output element
written by one thread in a fixed order of operations, so the results do not depend on the thread
count (docs/rendering.md "Determinism")."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def camera_points(rot, trans, means, out):
    """out[c, n] = rot[c] @ means[n] + trans[c]: rot [C, 3, 3], trans [C, 3], means [N, 3],
    out [C, N, 3]. One thread per Gaussian, a fixed order of operations (float64)."""
    ncam, n = rot.shape[0], means.shape[0]
    for g in prange(n):
        m0 = np.float64(means[g, 0])
        m1 = np.float64(means[g, 1])
        m2 = np.float64(means[g, 2])
        for c in range(ncam):
            for i in range(3):
                out[c, g, i] = (
                    np.float64(rot[c, i, 0]) * m0
                    + np.float64(rot[c, i, 1]) * m1
                    + np.float64(rot[c, i, 2]) * m2
                    + np.float64(trans[c, i])
                )


@njit(parallel=True, cache=True)
def camera_points_grad(rot, grad, out):
    """out[n, j] = sum over c, i (in that order) of grad[c, n, i] rot[c, i, j]: the gradient of
    `camera_points` w.r.t. the means. rot [C, 3, 3], grad [C, N, 3], out [N, 3]."""
    ncam, n = grad.shape[0], grad.shape[1]
    for g in prange(n):
        for j in range(3):
            v = 0.0
            for c in range(ncam):
                for i in range(3):
                    v += np.float64(grad[c, g, i]) * np.float64(rot[c, i, j])
            out[g, j] = v
