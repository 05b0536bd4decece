"""`gaussian_map.lookup` at fixed points on the CPU (numba): the values and their gradient.

Refinement and training look F up at the same surface samples every step, and posing looks
the colour channels up every frame. Each set of points is reduced once to where its points fall
(`corners`: the top-left texel and the fractions; float64 weights from them, `taps`), and the
lookup is a gather of the four texels per point from a channels-last copy of the map (`gather`:
grid_sample read one cache line per channel and tap, and rounded its weights in float32).
The gradient: torch's grid_sample backward scatters each point's four weights into the map
serially (about 20 ms a step for 32,768 points x 14 channels on 2 cores); here the weights are
gathered into the transpose of the lookup, row by texel (`transpose`), and the gradient of the
map is that matrix times the gradient of the points (`texel_grads`): one thread per texel, each
summing its entries in a fixed order in float64, so the result does not depend on the thread
count (docs/rendering.md "Determinism"). The bilinear weights are grid_sample's (align_corners
False, border padding; docs/conventions.md "UV space"), in float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


def corners(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each point uv [N, 2] (u right, v up) falls in an H x W map: its top-left texel
    (x0, y0) [N, 2] int32 and the fractions (wx, wy) [N, 2] float64 toward the next column and
    row (grid_sample's bilinear, align_corners False, border padding)."""
    u = np.asarray(uv[:, 0], np.float64)
    v = np.asarray(uv[:, 1], np.float64)
    ix = np.clip(u * width - 0.5, 0.0, width - 1)  # grid x = 2u - 1, unnormalised as grid_sample does
    iy = np.clip((1.0 - v) * height - 0.5, 0.0, height - 1)  # grid y = 1 - 2v
    x0, y0 = np.floor(ix), np.floor(iy)
    return np.stack([x0, y0], axis=1).astype(np.int32), np.stack([ix - x0, iy - y0], axis=1)


def taps(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The four texels of each point uv [N, 2] and their bilinear weights (`corners`):
    (texels [N, 4] row-major indices, weights [N, 4] float64), in the order (x0, y0), (x1, y0),
    (x0, y1), (x1, y1)."""
    xy, frac = corners(uv, height, width)
    x0, y0 = xy[:, 0].astype(np.int64), xy[:, 1].astype(np.int64)
    wx, wy = frac[:, 0], frac[:, 1]
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    texels = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], axis=1)
    weights = np.stack([(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy], axis=1)
    return texels, weights


def transpose(uv: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lookup of an H x W map at points uv [N, 2] (u right, v up) as its transpose in CSR form:
    (indptr [H W + 1], points [4 N], weights [4 N] float64), texel t's entries at
    indptr[t]:indptr[t + 1], in point order."""
    t4, w4 = taps(uv, height, width)
    n = t4.shape[0]
    texels, weights = t4.T.reshape(-1), w4.T.reshape(-1)  # tap by tap, each in point order
    points = np.tile(np.arange(n, dtype=np.int64), 4)
    order = np.argsort(texels * n + points, kind="stable")  # by texel, then point
    indptr = np.zeros(height * width + 1, np.int64)
    np.cumsum(np.bincount(texels, minlength=height * width), out=indptr[1:])
    return indptr, points[order], weights[order]


@njit(parallel=True, cache=True)
def gather(maps, xy, frac, height, width, out):
    """The lookup without a gradient: out [B, N, C] (float32) = for each point its four texels
    of maps [B, H W, C] (channels last: one texel's channels share a cache line) weighed as
    `taps` weighs them (from `corners`' xy, frac), summed in float64."""
    nb, nc = maps.shape[0], maps.shape[2]
    for n in prange(xy.shape[0]):
        x0, y0 = np.int64(xy[n, 0]), np.int64(xy[n, 1])
        wx, wy = frac[n, 0], frac[n, 1]
        x1, y1 = min(x0 + 1, width - 1), min(y0 + 1, height - 1)
        t0, t1, t2, t3 = y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1
        w0, w1, w2, w3 = (1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy
        for b in range(nb):
            for c in range(nc):
                out[b, n, c] = w0 * maps[b, t0, c] + w1 * maps[b, t1, c] + w2 * maps[b, t2, c] + w3 * maps[b, t3, c]


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
