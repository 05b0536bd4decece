"""The rasteriser's depth sort (render/sort_kernels.py: insertion for short lists, radix passes for long
ones) against numpy's stable argsort."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from dlacli.render.sort_kernels import sort_segment


@njit
def radix_argsort_u32(keys):
    """keys [M] uint32 -> the int64 indices that sort them: `sort_segment` of 0 .. M - 1."""
    m = keys.shape[0]
    order = np.arange(m)
    kb, kb2 = np.empty(m, np.uint32), np.empty(m, np.uint32)
    ib, ib2 = np.empty(m, np.int64), np.empty(m, np.int64)
    sort_segment(order, 0, m, keys, kb, kb2, ib, ib2, np.empty(256, np.int64))
    return order


def _cases():
    rng = np.random.default_rng(11)
    depths = rng.uniform(0.5, 40.0, 5000).astype(np.float32)
    return {
        "empty": np.zeros(0, np.uint32),
        "one": np.array([7], np.uint32),
        "all equal": np.full(300, 12345, np.uint32),
        "full range": rng.integers(0, 2**32, 20000, dtype=np.uint64).astype(np.uint32),
        "extremes": np.array([2**32 - 1, 0, 2**32 - 1, 1, 0, 2**31], np.uint32),
        # the longest list sorted by insertion, and the shortest by radix passes
        "24 with ties": rng.integers(0, 6, 24).astype(np.uint32),
        "25 with ties": rng.integers(0, 6, 25).astype(np.uint32) << 9,
        "many ties": rng.integers(0, 40, 20000).astype(np.uint32),
        # the rasteriser's keys: bits of positive float32 depths, with repeats
        "depth bits": np.concatenate([depths, depths[::7]]).view(np.uint32),
        "ties across digits": (rng.integers(0, 4, 5000).astype(np.uint32) << 22) | 2047,
    }


@pytest.mark.parametrize("name", list(_cases()))
def test_radix_argsort_is_numpy_stable_argsort(name):
    keys = _cases()[name]
    got = radix_argsort_u32(keys)
    assert got.dtype == np.int64
    assert np.array_equal(got, np.argsort(keys, kind="stable"))


def test_float_bits_sort_as_the_depths():
    """The bits of positive float32 values sort in the order of the values (what the tile lists'
    depth sort relies on), ties kept in input order."""
    rng = np.random.default_rng(5)
    z = rng.choice(np.float32([0.01, 0.5, 1.0, 1.5, 3.0, 1e3]), 2000)
    assert np.array_equal(radix_argsort_u32(z.view(np.uint32)), np.argsort(z, kind="stable"))
