"""The fast forward pass of the CPU Gaussian rasteriser (`raster_forward_fast`), for renders
without gradients that ask for it (`render_gaussians(exact=False)`: the animation preview's
playback): the exact kernel's rules and order (splat_kernels.py, whose `raster_forward` stays the
reference), in float32, branch-free and vectorised across the pixels of a tile's row, with a
polynomial exponential of bounded error. All float32; fastmath off.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dlacli.render.binning_kernels import NPARAM, TILE
from dlacli.render.splat_kernels import ALPHA_MAX, ALPHA_MIN, BATCH, T_MIN, load_batch, tile_box

# The exponential: exp(-sigma) = q^16, q = exp(-sigma / 16) by its Taylor polynomial of degree 6
# (sigma / 16 <= 0.35 where alpha >= 1/255), in float32. Its relative error is below
# FAST_EXP_REL_ERROR for 0 <= sigma <= 5.6 (1/255 = opacity exp(-sigma) needs sigma <= 5.54),
# measured against float64 exp on 2 million points (tests/render/test_splat_fast.py).
FAST_EXP_REL_ERROR = 5e-6
FAST_SIGMA_MAX = 8.0  # sigma is clamped to [0, 8] before the polynomial (exp(-8) < 1/255 / 0.999)


@njit(cache=True, inline="always")
def _exp_neg_fast(s):
    """exp(-s) for float32 s in [0, FAST_SIGMA_MAX], branch-free (vectorises)."""
    one = np.float32(1.0)
    u = s * np.float32(0.0625)
    q = one - u * (
        one
        - u
        * (
            np.float32(0.5)
            - u
            * (
                np.float32(1.0 / 6.0)
                - u * (np.float32(1.0 / 24.0) - u * (np.float32(1.0 / 120.0) - u * np.float32(1.0 / 720.0)))
            )
        )
    )
    q = q * q
    q = q * q
    q = q * q
    return q * q


HALF = TILE // 2  # pixels a row of a narrow box is evaluated at: half the vector work of a tile row


@njit(cache=True, inline="always")
def _composite_row(st, base, n, dmx, hca, bdy, ry, op, c0, c1, c2, c3):
    """One Gaussian over pixels base .. base + n - 1 of the tile state `st` (n a constant where
    inlined, so that the loop is one vector's width), without branches."""
    f32 = np.float32
    zero = f32(0.0)
    for i in range(n):
        p = np.uint64(base + i)
        dx = dmx - f32(i)
        sigma = (hca * dx + bdy) * dx + ry  # 0.5 (a dx^2 + c dy^2) + b dx dy
        alpha = min(f32(ALPHA_MAX), op * _exp_neg_fast(min(max(sigma, zero), f32(FAST_SIGMA_MAX))))
        t = st[0, p]
        nt = t * (f32(1.0) - alpha)
        ok = (sigma >= zero) & (alpha >= f32(ALPHA_MIN)) & (st[5, p] > zero)
        use = ok & (nt > f32(T_MIN))
        w = alpha * t if use else zero
        st[1, p] += w * c0
        st[2, p] += w * c1
        st[3, p] += w * c2
        st[4, p] += w * c3
        st[0, p] = nt if use else t
        st[5, p] = zero if (ok & (nt <= f32(T_MIN))) else st[5, p]


@njit(parallel=True, cache=True)
def raster_forward_fast(params, tile_offsets, lists, wptr, wtiles, ncam, width, height, out_acc, out_t, out_work):
    """`raster_forward` for renders without gradients, in float32 and vectorised across the pixels
    of a tile's row: each row of a Gaussian's box is evaluated at once (`_composite_row`: the
    whole row, or HALF of it where the box is narrower, as most are), without branches (the tests
    become selects), with `_exp_neg_fast`. The rules are the exact kernel's (alpha = min(0.999,
    opacity exp(-sigma)), skipped when sigma < 0 or alpha < 1/255, a pixel stops before the
    Gaussian whose T (1 - alpha) would be <= 1e-4), the order the same; out_acc [C, H, W, 4],
    out_t [C, H, W] (float64, from float32), out_work [C*TH*TW] the pixel evaluations. Each tile is
    one worker's, walked in a fixed order: the same bits for any thread count. No `last` (the
    backward pass uses the exact kernel's)."""
    tw = (width + TILE - 1) // TILE
    th = (height + TILE - 1) // TILE
    ntiles = tw * th
    nworkers = wptr.shape[0] - 1
    f32 = np.float32
    zero = f32(0.0)
    for wk in prange(nworkers):
        # one array for the tile's state (rows: T, acc rgb + depth, live), indexed unsigned, so that
        # LLVM vectorises the pixel loop (separate arrays or signed indices keep it scalar)
        st = np.empty((6, TILE * TILE), dtype=np.float32)
        rowlive = np.empty(TILE, dtype=np.float32)
        buf = np.empty((BATCH, NPARAM), dtype=params.dtype)
        for it in range(wptr[wk], wptr[wk + 1]):
            tid = wtiles[it]
            c, x0, y0, x1, y1 = tile_box(tid, ntiles, tw, width, height)
            nx = x1 - x0
            for r in range(TILE):
                for i in range(TILE):
                    p = r * TILE + i
                    st[0, p] = 1.0
                    st[1, p] = 0.0
                    st[2, p] = 0.0
                    st[3, p] = 0.0
                    st[4, p] = 0.0
                    st[5, p] = 1.0 if (i < nx and y0 + r < y1) else 0.0
            work = 0
            kend = tile_offsets[tid + 1]
            for kb in range(tile_offsets[tid], kend, BATCH):
                total = zero
                for r in range(TILE):
                    live = zero
                    for i in range(TILE):
                        live += st[5, r * TILE + i]
                    rowlive[r] = live
                    total += live
                if total == zero:
                    break
                nb = min(BATCH, kend - kb)
                load_batch(params, lists, kb, nb, buf)
                for j in range(nb):
                    by0 = max(int(buf[j, 9]), y0)
                    by1 = min(int(buf[j, 10]), y1 - 1)
                    bx0 = max(int(buf[j, 7]), x0) - x0
                    bx1 = min(int(buf[j, 8]), x1 - 1) - x0
                    if bx0 > bx1 or by0 > by1:
                        continue
                    mx = f32(buf[j, 0])
                    my = f32(buf[j, 1])
                    hca = f32(0.5) * f32(buf[j, 2])
                    cb = f32(buf[j, 3])
                    hcc = f32(0.5) * f32(buf[j, 4])
                    op = f32(buf[j, 5])
                    c0 = f32(buf[j, 12])
                    c1 = f32(buf[j, 13])
                    c2 = f32(buf[j, 14])
                    c3 = f32(buf[j, 15])
                    # the pixels of a row evaluated: HALF of them from the box's first (shifted
                    # left to stay in the tile) where the box is that narrow, else the whole row;
                    # the others lie outside the box, where alpha < 1/255 for certain
                    narrow = bx1 - bx0 < HALF
                    s0 = min(bx0, HALF) if narrow else 0
                    dmx = mx - f32(x0 + s0 + 0.5)
                    for y in range(by0, by1 + 1):
                        r = y - y0
                        if rowlive[r] == zero:
                            continue
                        work += HALF if narrow else TILE
                        dy = my - f32(y + 0.5)
                        ry = hcc * dy * dy
                        bdy = cb * dy
                        base = r * TILE + s0
                        if narrow:
                            _composite_row(st, base, HALF, dmx, hca, bdy, ry, op, c0, c1, c2, c3)
                        else:
                            _composite_row(st, base, TILE, dmx, hca, bdy, ry, op, c0, c1, c2, c3)
            out_work[tid] = work
            for y in range(y0, y1):
                for x in range(x0, x1):
                    p = (y - y0) * TILE + (x - x0)
                    out_acc[c, y, x, 0] = st[1, p]
                    out_acc[c, y, x, 1] = st[2, p]
                    out_acc[c, y, x, 2] = st[3, p]
                    out_acc[c, y, x, 3] = st[4, p]
                    out_t[c, y, x] = st[0, p]
