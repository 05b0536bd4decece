"""Tile binning of the CPU Gaussian rasteriser (the layout and conventions in splat_kernels.py's
docstring): per (camera, Gaussian) packed rows, pixel boxes and tile rectangles (`_prepare`), the
visible pairs in (camera, depth) order (`_depth_order`, a stable radix sort), the per-tile lists
(`_tile_lists`), the backward pass's per-(pair, tile) gradient rows (`isect_rows`) and the split
of tiles over threads (`assign_workers`). Every output is the same for any thread count.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from dlacli.render import camera_kernels
from dlacli.render.radix_sort import radix_argsort_u32

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
    route's, without its [C, N] intermediates. opacities [N], rgb [C, N, 3] (colour per camera;
    depth is the fourth channel) -> params [C * N, 16], trect [C * N, 4], radii [C, N] int32,
    keys [C, N] float32 (the depth rounded to params' dtype, then float32; 1 where culled: the
    sort keys of `_depth_order`, as bits)."""
    ncam, n = rot.shape[0], means.shape[0]
    ft = params.dtype.type
    for g in prange(n):
        m = camera_kernels._scaled_rotation(quats, scales, g)
        mu0 = np.float64(means[g, 0])
        mu1 = np.float64(means[g, 1])
        mu2 = np.float64(means[g, 2])
        op = np.float64(ft(opacities[g]))
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
                op,
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


@njit(cache=True, nogil=True)
def _depth_order(radii, depth_keys):
    """Flat indices c * N + g of the visible pairs, sorted by camera then depth (stable)."""
    ncam, n = radii.shape[0], radii.shape[1]
    nvis = 0
    for c in range(ncam):
        for g in range(n):
            if radii[c, g] > 0:
                nvis += 1
    out = np.empty(nvis, dtype=np.int64)
    s = 0
    vis = np.empty(n, dtype=np.int64)
    for c in range(ncam):
        m = 0
        for g in range(n):
            if radii[c, g] > 0:
                vis[m] = g
                m += 1
        keys = np.empty(m, dtype=np.uint32)
        for i in range(m):
            keys[i] = depth_keys[c, vis[i]]
        order = radix_argsort_u32(keys)
        for i in range(m):
            out[s] = c * n + vis[order[i]]
            s += 1
    return out


@njit(parallel=True, cache=True)
def _tile_lists(src, trect, n, ncam, width, height, nthreads):
    """Per-tile lists of the sorted pairs `src` (each tile's list front to back) in three parallel
    passes: the tile rectangles gathered in depth order, per-thread tile counts (summed), then
    each thread fills the lists of its own band of tile rows (camera-major rows c * TH + ty, split
    so the bands hold about equal numbers of entries), walking all pairs in depth order. Every
    list slot has one writer and its value does not depend on the split: the same lists for any
    thread count."""
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    ntiles = tw * th
    nrows = ncam * th
    m = src.shape[0]
    nparts = max(1, min(nthreads, nrows))
    rect = np.empty((m, 4), dtype=np.int32)  # tx0, tx1, camera-major row y0, y1 (ends exclusive)
    cam_end = np.searchsorted(src, np.arange(1, ncam + 1) * n)  # src is sorted by camera
    for c in range(ncam):
        r0 = c * th
        for s in prange(0 if c == 0 else cam_end[c - 1], cam_end[c]):
            i = src[s]
            rect[s, 0] = trect[i, 0]
            rect[s, 1] = trect[i, 1]
            rect[s, 2] = r0 + trect[i, 2]
            rect[s, 3] = r0 + trect[i, 3]
    chunk = (m + nparts - 1) // nparts
    part_counts = np.zeros((nparts, nrows * tw), dtype=np.int64)
    for k in prange(nparts):
        _count_tiles(rect, k * chunk, min(m, (k + 1) * chunk), tw, part_counts[k])
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
    for k in prange(nparts):
        _fill_band(src, rect, bands[k], bands[k + 1], tw, fill, lists)
    return counts, lists


@njit(cache=True, nogil=True)
def _count_tiles(rect, s0, s1, tw, cnt):
    """cnt[row * tw + tx] += 1 for every tile of the rectangles rect[s0:s1] (`_tile_lists`)."""
    for s in range(s0, s1):
        for r in range(rect[s, 2], rect[s, 3]):
            for tx in range(rect[s, 0], rect[s, 1]):
                cnt[r * tw + tx] += 1


@njit(cache=True, nogil=True)
def _fill_band(src, rect, b0, b1, tw, fill, lists):
    """Append every pair, in depth order, to the lists of its tiles in rows b0 .. b1 - 1."""
    for s in range(src.shape[0]):
        r0 = max(rect[s, 2], b0)
        r1 = min(rect[s, 3], b1)
        if r0 >= r1:
            continue
        i = src[s]
        for r in range(r0, r1):
            for tx in range(rect[s, 0], rect[s, 1]):
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
    """Sort visible Gaussians by (camera, depth) and build per-tile lists.

    means2d [C, N, 2], conics [C, N, 3], opacities [C, N], colors [C, N, 4], radii [C, N] int,
    depth_keys [C, N] uint32 (float32 bits of positive depths, same order as the depths).
    Returns params [C * N, 16], src [S], tile_offsets [C*TH*TW + 1], lists [n_isects] (rows
    c * N + g) and the tile rectangles trect [C * N, 4] int32 (tx0, tx1, ty0, ty1; ends exclusive),
    all rows in input order (module docstring).
    """
    ncam, n = radii.shape
    params = np.empty((ncam * n, NPARAM), dtype=means2d.dtype)
    trect = np.empty((ncam * n, 4), dtype=np.int32)
    _prepare(means2d, conics, opacities, colors, radii, width, height, params, trect)
    src, offsets, lists = sort_and_list(radii, depth_keys, trect, width, height)
    return params, src, offsets, lists, trect


def sort_and_list(radii, depth_keys, trect, width, height):
    """The visible pairs in (camera, depth) order and the per-tile lists (`bin_gaussians`'s
    src, tile_offsets and lists) from radii [C, N], depth_keys [C, N] uint32 and trect."""
    ncam, n = radii.shape
    src = _depth_order(radii, depth_keys)
    offsets, lists = _tile_lists(src, trect, n, ncam, width, height, numba.get_num_threads())
    return src, offsets, lists


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
