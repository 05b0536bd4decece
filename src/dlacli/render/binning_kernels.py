"""Tile binning of the CPU Gaussian rasteriser (the layout and conventions in splat_kernels.py's
docstring): per (camera, Gaussian) packed rows, pixel boxes and tile rectangles (`_prepare`), the
per-tile lists, each sorted front to back by depth (`_tile_lists`, a stable radix sort per list),
the backward pass's per-(pair, tile) gradient rows (`isect_rows`) and the split of tiles over
threads (`assign_workers`). Every output is the same for any thread count.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from dlacli.render import camera_kernels
from dlacli.render.sort_kernels import sort_segment

TILE = 16
# Extra room on the sigma cut-off used for the pixel bounding boxes, far above float32 rounding
# of sigma, so that the boxes never drop a pixel where alpha >= 1/255.
SIGMA_MARGIN = 0.05
NPARAM = 16


@njit(cache=True, inline="always")
def _no_tiles(trect, i):
    """Pair i is in no tile's list (culled, or its pixel box is empty)."""
    for k in range(4):
        trect[i, k] = 0


@njit(cache=True, inline="always")
def _pack_pair(i, mx, my, a, b, cc, op, c0, c1, c2, c3, r, width, height, params, trect):
    """Row i of params (packed parameters, pixel box) and of trect (tile rectangle) of one
    (camera, Gaussian) pair with radius r > 0, from its values as stored (float64 of them)."""
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    _no_tiles(trect, i)
    params[i, 0] = mx
    params[i, 1] = my
    params[i, 2] = a
    params[i, 3] = b
    params[i, 4] = cc
    params[i, 5] = op
    params[i, 11] = 0.0
    params[i, 12] = c0
    params[i, 13] = c1
    params[i, 14] = c2
    params[i, 15] = c3
    # gsplat's tile rectangle from the integer radius (this decides membership)
    tx0 = int(min(max(np.floor(mx / TILE - r / TILE), 0.0), tw))
    tx1 = int(min(max(np.ceil(mx / TILE + r / TILE), 0.0), tw))
    ty0 = int(min(max(np.floor(my / TILE - r / TILE), 0.0), th))
    ty1 = int(min(max(np.ceil(my / TILE + r / TILE), 0.0), th))
    # pixel box outside of which sigma > log(255 opacity): alpha < 1/255 there
    det = a * cc - b * b
    ok = np.isfinite(mx) and np.isfinite(my) and det > 0.0 and a > 0.0 and cc > 0.0
    if not ok or not (op * 255.0 >= 1.0):
        thr = -1.0
        bx0, bx1, by0, by1 = 0, -1, 0, -1
    else:
        thr = math.log(op * 255.0) + SIGMA_MARGIN
        ex = math.sqrt(2.0 * thr * cc / det)  # sqrt(2 thr cov_xx)
        ey = math.sqrt(2.0 * thr * a / det)
        if not (np.isfinite(ex) and np.isfinite(ey)):
            ex = 1e30
            ey = 1e30
        bx0 = int(min(max(np.ceil(mx - ex - 0.5), 0.0), width))
        bx1 = int(min(max(np.floor(mx + ex - 0.5), -1.0), width - 1))
        by0 = int(min(max(np.ceil(my - ey - 0.5), 0.0), height))
        by1 = int(min(max(np.floor(my + ey - 0.5), -1.0), height - 1))
    params[i, 6] = thr
    params[i, 7] = bx0
    params[i, 8] = bx1
    params[i, 9] = by0
    params[i, 10] = by1
    if bx0 > bx1 or by0 > by1:
        return
    trect[i, 0] = max(tx0, bx0 // TILE)
    trect[i, 1] = max(min(tx1, bx1 // TILE + 1), trect[i, 0])
    trect[i, 2] = max(ty0, by0 // TILE)
    trect[i, 3] = max(min(ty1, by1 // TILE + 1), trect[i, 2])


@njit(parallel=True, cache=True)
def _prepare(means2d, conics, opacities, colors, radii, width, height, params, trect):
    """Per (camera, Gaussian) in input order: packed parameters, pixel box, tile rectangle (the
    kernels read them in place through the tile lists: no gather into depth order)."""
    ncam, n = radii.shape[0], radii.shape[1]
    for c in range(ncam):  # no integer division per pair
        for g in prange(n):
            i = c * n + g
            if radii[c, g] <= 0:
                _no_tiles(trect, i)
                continue
            _pack_pair(
                i,
                np.float64(means2d[c, g, 0]),
                np.float64(means2d[c, g, 1]),
                np.float64(conics[c, g, 0]),
                np.float64(conics[c, g, 1]),
                np.float64(conics[c, g, 2]),
                np.float64(opacities[c, g]),
                np.float64(colors[c, g, 0]),
                np.float64(colors[c, g, 1]),
                np.float64(colors[c, g, 2]),
                np.float64(colors[c, g, 3]),
                np.float64(radii[c, g]),
                width,
                height,
                params,
                trect,
            )


@njit(parallel=True, cache=True)
def project_and_pack(
    means, quats, scales, opacities, rgb, rot, trans, intr, width, height, eps2d, near, far, params, trect, radii, keys
):
    """`camera_kernels.project_fused` and `_prepare` in one pass, for renders without autograd:
    the projected values are rounded to params' dtype (what the two-pass route stores between
    them) before they are packed, so params, trect and radii are bit for bit the two-pass
    route's, without its [C, N] intermediates. opacities [C, N], rgb [C, N, 3] (per camera;
    depth is the fourth channel) -> params [C * N, 16], trect [C * N, 4], radii [C, N] int32,
    keys [C, N] float32 (the depth rounded to params' dtype, then float32; 1 where culled: the
    sort keys of `_tile_lists`, as bits)."""
    ncam, n = rot.shape[0], means.shape[0]
    ft = params.dtype.type
    for g in prange(n):
        m = camera_kernels._scaled_rotation(quats, scales, g)
        mu0 = np.float64(means[g, 0])
        mu1 = np.float64(means[g, 1])
        mu2 = np.float64(means[g, 2])
        for c in range(ncam):
            i = c * n + g
            mx, my, ca, cb, cc, z, r = camera_kernels._project_one(
                m, mu0, mu1, mu2, rot, trans, intr, c, width, height, eps2d, near, far
            )
            radii[c, g] = r
            if r <= 0:
                keys[c, g] = 1.0
                _no_tiles(trect, i)
                continue
            zr = np.float64(ft(z))
            keys[c, g] = np.float32(zr)
            _pack_pair(
                i,
                np.float64(ft(mx)),
                np.float64(ft(my)),
                np.float64(ft(ca)),
                np.float64(ft(cb)),
                np.float64(ft(cc)),
                np.float64(ft(opacities[c, g])),
                np.float64(ft(rgb[c, g, 0])),
                np.float64(ft(rgb[c, g, 1])),
                np.float64(ft(rgb[c, g, 2])),
                zr,
                np.float64(r),
                width,
                height,
                params,
                trect,
            )


@njit(parallel=True, cache=True)
def _tile_lists(depth_keys, trect, width, height, nthreads):
    """Per-tile lists of the (camera, Gaussian) pairs, each front to back (depth_keys [C, N]
    uint32 ascending, ties in pair order c * N + g: the order of a stable sort by depth), in three
    parallel passes: per-thread tile counts over slices of the pairs (summed), then each thread
    fills the lists of its own band of tile rows (camera-major rows c * TH + ty, split so the
    bands hold about equal numbers of entries), walking all pairs in index order, and sorts those
    lists by depth (`sort_kernels.sort_segment`). Culled pairs have empty tile rectangles and are
    in no list. Every list slot has one writer and its value does not depend on the split: the
    same lists for any thread count."""
    ncam, n = depth_keys.shape
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    ntiles = tw * th
    nrows = ncam * th
    m = ncam * n
    nparts = max(1, min(nthreads, nrows))
    chunk = (m + nparts - 1) // nparts
    part_counts = np.zeros((nparts, ncam * ntiles), dtype=np.int64)
    for k in prange(nparts):
        cnt = part_counts[k]
        for i in range(k * chunk, min(m, (k + 1) * chunk)):
            base = (i // n) * ntiles
            for ty in range(trect[i, 2], trect[i, 3]):
                for tx in range(trect[i, 0], trect[i, 1]):
                    cnt[base + ty * tw + tx] += 1
    counts = np.zeros(ncam * ntiles + 1, dtype=np.int64)
    for k in range(nparts):
        for t in range(ncam * ntiles):
            counts[t + 1] += part_counts[k, t]
    for t in range(ncam * ntiles):
        counts[t + 1] += counts[t]
    total = counts[ncam * ntiles]
    lists = np.empty(total, dtype=np.int64)
    # bands of rows with about total / nparts entries each
    bands = np.empty(nparts + 1, dtype=np.int64)
    bands[0] = 0
    r = 0
    for k in range(1, nparts):
        while r < nrows and counts[(r + 1) * tw] * nparts < total * k:
            r += 1
        bands[k] = max(r, bands[k - 1])
    bands[nparts] = nrows
    fill = counts[:-1].copy()
    keys = depth_keys.reshape(-1)
    for k in prange(nparts):
        _fill_band(trect, n, th, tw, bands[k], bands[k + 1], fill, lists)
        longest = 0
        for t in range(bands[k] * tw, bands[k + 1] * tw):
            longest = max(longest, counts[t + 1] - counts[t])
        kb, kb2 = np.empty(longest, np.uint32), np.empty(longest, np.uint32)
        ib, ib2 = np.empty(longest, np.int64), np.empty(longest, np.int64)
        cnt = np.empty(256, np.int64)
        for t in range(bands[k] * tw, bands[k + 1] * tw):
            sort_segment(lists, counts[t], counts[t + 1], keys, kb, kb2, ib, ib2, cnt)
    return counts, lists


@njit(cache=True, nogil=True)
def _fill_band(trect, n, th, tw, b0, b1, fill, lists):
    """Append every pair, in index order, to the lists of its tiles in camera-major rows b0 .. b1 - 1."""
    for i in range(trect.shape[0]):
        r0 = (i // n) * th
        lo = max(r0 + trect[i, 2], b0)
        hi = min(r0 + trect[i, 3], b1)
        for r in range(lo, hi):
            for tx in range(trect[i, 0], trect[i, 1]):
                t = r * tw + tx
                lists[fill[t]] = i
                fill[t] += 1


@njit(cache=True, nogil=True)
def isect_rows(trect):
    """Row offsets [S + 1] of a per-(Gaussian, tile) array laid out Gaussian by Gaussian: pair s owns
    rows sptr[s] .. sptr[s + 1] - 1, one per tile of its rectangle trect[s] in row-major order."""
    m = trect.shape[0]
    sptr = np.empty(m + 1, dtype=np.int64)
    sptr[0] = 0
    for s in range(m):
        sptr[s + 1] = sptr[s] + (trect[s, 1] - trect[s, 0]) * (trect[s, 3] - trect[s, 2])
    return sptr


def bin_gaussians(means2d, conics, opacities, colors, radii, depth_keys, width, height):
    """Pack the (camera, Gaussian) pairs and list them per tile, front to back.

    means2d [C, N, 2], conics [C, N, 3], opacities [C, N], colors [C, N, 4], radii [C, N] int,
    depth_keys [C, N] uint32 (float32 bits of positive depths, same order as the depths).
    Returns params [C * N, 16], tile_offsets [C*TH*TW + 1], lists [n_isects] (rows c * N + g)
    and the tile rectangles trect [C * N, 4] int32 (tx0, tx1, ty0, ty1; ends exclusive), all
    rows in input order (module docstring).
    """
    ncam, n = radii.shape
    params = np.empty((ncam * n, NPARAM), dtype=means2d.dtype)
    trect = np.empty((ncam * n, 4), dtype=np.int32)
    _prepare(means2d, conics, opacities, colors, radii, width, height, params, trect)
    offsets, lists = tile_lists(depth_keys, trect, width, height)
    return params, offsets, lists, trect


def tile_lists(depth_keys, trect, width, height):
    """The per-tile lists (`bin_gaussians`'s tile_offsets and lists) from depth_keys [C, N]
    uint32 and the tile rectangles trect [C * N, 4] (culled pairs: empty)."""
    return _tile_lists(np.ascontiguousarray(depth_keys), trect, width, height, numba.get_num_threads())


@njit(cache=True, nogil=True)
def assign_workers(cost, nworkers):
    """Greedy longest-first split of tiles over workers. cost [T] -> (ptr [W+1], tiles [T])."""
    nt = cost.shape[0]
    order = np.argsort(-cost, kind="mergesort")
    load = np.zeros(nworkers, dtype=np.float64)
    owner = np.empty(nt, dtype=np.int64)
    for i in range(nt):
        t = order[i]
        w = np.argmin(load)
        owner[t] = w
        load[w] += cost[t] + 1.0
    ptr = np.zeros(nworkers + 1, dtype=np.int64)
    for t in range(nt):
        ptr[owner[t] + 1] += 1
    for w in range(nworkers):
        ptr[w + 1] += ptr[w]
    fill = ptr[:-1].copy()
    tiles = np.empty(nt, dtype=np.int64)
    for i in range(nt):
        t = order[i]
        tiles[fill[owner[t]]] = t
        fill[owner[t]] += 1
    return ptr, tiles
