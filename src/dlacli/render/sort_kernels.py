"""A stable sort of uint32 keys in numba: each tile list of the CPU rasteriser front to back
(`binning_kernels._tile_lists` sorts every list by its pairs' float32 depth bits, ties kept in pair
order: the order gsplat's (tile, depth) radix sort gives)."""

from __future__ import annotations

from numba import njit

SMALL = 24  # segments up to this long are sorted by insertion


@njit(cache=True, inline="always")
def sort_segment(values, o0, o1, keys, kb, kb2, ib, ib2, cnt):
    """Sort values[o0:o1] (int64 indices into keys, uint32) by their keys, stably, in place.
    Scratch: kb, kb2 (uint32) and ib, ib2 (int64) of at least o1 - o0 entries, cnt [256] int64.
    Short segments by insertion; longer ones by an LSD radix sort in four passes of 8 bits, each
    skipped where every key has the same digit (the depths of one tile share their top bits)."""
    n = o1 - o0
    if n < 2:
        return
    for j in range(n):
        i = values[o0 + j]
        ib[j] = i
        kb[j] = keys[i]
    if n <= SMALL:
        for j in range(1, n):
            k, i = kb[j], ib[j]
            q = j - 1
            while q >= 0 and kb[q] > k:
                kb[q + 1] = kb[q]
                ib[q + 1] = ib[q]
                q -= 1
            kb[q + 1] = k
            ib[q + 1] = i
        for j in range(n):
            values[o0 + j] = ib[j]
        return
    sk, si, dk, di = kb, ib, kb2, ib2
    for p in range(4):
        shift = 8 * p
        cnt[:] = 0
        for j in range(n):
            cnt[(sk[j] >> shift) & 255] += 1
        same = False
        start = 0
        for d in range(256):  # counts -> each digit's first slot
            c = cnt[d]
            same = same or c == n
            cnt[d] = start
            start += c
        if same:
            continue
        for j in range(n):
            k = sk[j]
            d = (k >> shift) & 255
            q = cnt[d]
            dk[q] = k
            di[q] = si[j]
            cnt[d] = q + 1
        sk, dk = dk, sk
        si, di = di, si
    for j in range(n):
        values[o0 + j] = si[j]
