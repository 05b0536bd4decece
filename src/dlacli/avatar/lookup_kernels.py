"""The gradient of `gaussian_map.lookup` at fixed points as a sparse product (numba).

Refinement and training look F up at the same surface samples every step; torch's grid_sample
backward scatters each point's four bilinear weights into the map serially (about 20 ms a step
for 32,768 points x 14 channels on 2 cores). Here the weights are gathered once per set of points
into the transpose of the lookup, row by texel (`transpose`), and the gradient of the map is
that matrix times the gradient of the points (`texel_grads`): one thread per texel, each summing
its entries in a fixed order in float64, so the result does not depend on the thread count
(docs/rendering.md "Determinism"). The bilinear weights are grid_sample's own (align_corners
False, border padding; docs/conventions.md "UV space").
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


def transpose(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lookup of an H x W map at points uv [N, 2] (u right, v up) as its transpose in CSR form:
    (indptr [H W + 1], points [4 N], weights [4 N] float64), texel t's entries at
    indptr[t]:indptr[t + 1], in point order."""
    u = np.asarray(uv[:, 0], np.float64)
    v = np.asarray(uv[:, 1], np.float64)
    ix = np.clip(u * width - 0.5, 0.0, width - 1)  # grid x = 2u - 1, unnormalised as grid_sample does
    iy = np.clip((1.0 - v) * height - 0.5, 0.0, height - 1)  # grid y = 1 - 2v
    x0, y0 = np.floor(ix), np.floor(iy)
    wx, wy = ix - x0, iy - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    texels = np.concatenate([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1])
    weights = np.concatenate([(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy])
    points = np.tile(np.arange(len(u), dtype=np.int64), 4)
    order = np.argsort(texels * len(u) + points, kind="stable")  # by texel, then point
    indptr = np.zeros(height * width + 1, np.int64)
    np.cumsum(np.bincount(texels, minlength=height * width), out=indptr[1:])
    return indptr, points[order], weights[order]


@njit(parallel=True, cache=True)
def texel_grads(indptr, points, weights, grad, out):
    """out [T, C] (float32) = the transpose times grad [N, C]: per texel t, the sum over its
    entries e of weights[e] grad[points[e]], in float64."""
    nt, nc = out.shape
    for t in prange(nt):
        acc = np.zeros(nc, np.float64)
        for e in range(indptr[t], indptr[t + 1]):
            w = weights[e]
            n = points[e]
            for c in range(nc):
                acc[c] += w * grad[n, c]
        for c in range(nc):
            out[t, c] = acc[c]
