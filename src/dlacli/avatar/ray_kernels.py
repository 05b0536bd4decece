"""UV-space Plücker rays without gradients (numba): what a view-conditioned decoder reads of a
camera, once per posed body and camera (`codec.uv_rays`). The same float32 operations as
geometry.py's `plucker_rays_uv` (direction p - o, its length as the square root of the sum of
squares, floored at 1e-12, the moment o x d), element by element, written channels first; and
the cosine of the view-cosine decoder and its colour F_delta from them (`view_cosine_map`,
`view_cosine_rgb`), the same float32 steps as codec.py's `view_cosine` and `shading`. These
agree with torch to float32 rounding, not bit for bit: torch's CPU sqrt is not correctly rounded
(it differs from IEEE sqrt in the last bit for about a sixth of inputs). Torch stays the
reference and the path for gradients (tests/avatar/test_rays.py)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def uv_plucker(positions, eye, out):
    """positions [H, W, 3] float32 (a point per texel), eye [3] float32 (the camera centre) ->
    out [6, H, W] float32: the unit direction d from eye to each point, then eye x d."""
    o0, o1, o2 = eye[0], eye[1], eye[2]
    tiny = np.float32(1e-12)
    for i in prange(positions.shape[0]):
        for j in range(positions.shape[1]):
            d0 = positions[i, j, 0] - o0
            d1 = positions[i, j, 1] - o1
            d2 = positions[i, j, 2] - o2
            n = max(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), tiny)
            d0, d1, d2 = d0 / n, d1 / n, d2 / n
            out[0, i, j] = d0
            out[1, i, j] = d1
            out[2, i, j] = d2
            out[3, i, j] = o1 * d2 - o2 * d1
            out[4, i, j] = o2 * d0 - o0 * d2
            out[5, i, j] = o0 * d1 - o1 * d0


@njit(cache=True, inline="always")
def _cosine(normals, rays, i, j):
    """cos = -n . (d / |d|) clamped to [0, 1] at texel (i, j), in codec.py `view_cosine`'s order
    of float32 operations: |d| as the square root of ((d0 d0 + d1 d1) + d2 d2) floored at 1e-12,
    the dot product summed in channel order."""
    d0, d1, d2 = rays[0, i, j], rays[1, i, j], rays[2, i, j]
    n = max(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2), np.float32(1e-12))
    c = -(normals[0, i, j] * (d0 / n) + normals[1, i, j] * (d1 / n) + normals[2, i, j] * (d2 / n))
    return min(max(c, np.float32(0.0)), np.float32(1.0))


@njit(parallel=True, cache=True)
def view_cosine_map(normals, rays, out):
    """codec.py `view_cosine`: unit normals [3, H, W], rays [6, H, W] (float32) -> out [H, W]."""
    for i in prange(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = _cosine(normals, rays, i, j)


@njit(parallel=True, cache=True)
def view_cosine_rgb(rgb, falloff, normals, rays, out):
    """The view-cosine decoder's colour F_delta (codec.py `ViewCosineDecoder.delta`): rgb [3, H, W],
    falloff k [H, W], unit normals [3, H, W], rays [6, H, W] (float32) -> out [3, H, W] = rgb
    (shading(k, cos) - 1) with `_cosine`'s cos and shading = 1 - k + k cos, in codec.py's order
    of float32 operations (so the same bits as `view_cosine_map` followed by codec.py's torch
    shading: a decoder that multiplies the shading by a gain of exactly 1 agrees bit for bit)."""
    one = np.float32(1.0)
    for i in prange(rgb.shape[1]):
        for j in range(rgb.shape[2]):
            k = falloff[i, j]
            g = (one - k + k * _cosine(normals, rays, i, j)) - one
            out[0, i, j] = rgb[0, i, j] * g
            out[1, i, j] = rgb[1, i, j] * g
            out[2, i, j] = rgb[2, i, j] * g
