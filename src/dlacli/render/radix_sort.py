"""A stable argsort of uint32 keys in numba: the depth order of the CPU rasteriser's tile lists
(`splat_binning._depth_order` sorts each camera's float32 depth bits with it, as gsplat's radix sort
orders its (tile, depth) keys)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def radix_argsort_u32(keys):
    """keys [M] uint32 -> [M] int64 indices that sort them, stable (equal keys keep their order):
    an LSD radix sort in three passes of 11 bits."""
    m = keys.shape[0]
    order = np.arange(m)
    tmp = np.empty(m, dtype=np.int64)
    counts = np.empty(2049, dtype=np.int64)
    for shift in (0, 11, 22):
        counts[:] = 0
        for i in range(m):
            counts[((keys[order[i]] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            counts[d + 1] += counts[d]
        for i in range(m):
            o = order[i]
            d = (keys[o] >> shift) & 2047
            tmp[counts[d]] = o
            counts[d] += 1
        order, tmp = tmp, order
    return order
