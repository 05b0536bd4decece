"""The compositing counts (dlacli.render.splat_stats) against the exact kernel and analytic cases.

Oracles: the exact kernel's own colour sums (`splat.composite_lists`; the numpy compositing that counts
must reproduce them to round-off, or its counts would not be the kernel's), its list lengths, and
stacks of identical Gaussians on one pixel, where the stop rule (transmittance <= 1e-4 ends a
pixel) gives the number composited in closed form.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from tests.render.test_splat import look_at_cameras, random_gaussians

from dlacli.render.splat import TILE, binned_plain, composite_lists
from dlacli.render.splat_stats import composite_stats
from dlacli.types import Gaussians


def test_the_counting_compositing_is_the_exact_kernels():
    g = random_gaussians(4000, 0, seed=5, extent=1.2, scale=(0.005, 0.08))
    cams = look_at_cameras([(0.5, -2.6, 0.6), (-2.4, 0.9, -0.2)], 97, 75, 80.0)  # not a multiple of the tile
    stats = composite_stats(g, cams)
    params, offsets, lists = binned_plain(g, cams.viewmats, cams.Ks, 97, 75, 0)
    acc, _, (_, _, work) = composite_lists(params, offsets, lists, 2, 97, 75)
    np.testing.assert_allclose(stats.acc, acc, rtol=0, atol=1e-9)
    assert stats.listed.shape == (2, math.ceil(75 / TILE), math.ceil(97 / TILE))
    assert stats.listed.sum() == len(lists)
    np.testing.assert_array_equal(stats.evaluations.ravel(), work)
    # what the kernel evaluates includes every composited Gaussian; what covers a pixel includes them too
    assert (stats.covering >= stats.contributing).all() and stats.contributing.max() > 20
    tiles = stats.contributing.reshape(2, -1).sum(1)
    assert (stats.evaluations.reshape(2, -1).sum(1) >= tiles).all()
    s = stats.summary()
    assert 0 < s["covered_share"] < 1 and s["covering_per_pixel"] >= s["contributing_per_pixel"] > 1
    assert s["listed_per_tile"] >= s["covering_p99"]  # a pixel's Gaussians are all in its tile's list


def _stack(opacity: float, count: int) -> Gaussians:
    """`count` identical round Gaussians on the camera's axis, one behind the other."""
    means = torch.zeros(count, 3, dtype=torch.float64)
    means[:, 1] = torch.linspace(-0.2, 0.2, count, dtype=torch.float64)  # along the view axis (+Y)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(count, 4).contiguous()
    scales = torch.full((count, 3), 0.05, dtype=torch.float64)
    opac = torch.full((count,), opacity, dtype=torch.float64)
    return Gaussians(means, quats, scales, opac, torch.full((count, 1, 3), 0.3, dtype=torch.float64))


def test_the_stop_rule_counts_in_closed_form_on_a_stack():
    cams = look_at_cameras([(0.0, -3.0, 0.0)], 33, 33, 60.0, cx=16.5, cy=16.5)  # the axis at pixel (16, 16)'s centre
    # alpha 0.5 at the centre pixel: the transmittance after k is 2^-k, and the Gaussian that would
    # take it to <= 1e-4 (k = 14) ends the pixel uncounted: 13 composited of the 20 that cover it
    stats = composite_stats(_stack(0.5, 20), cams)
    assert stats.covering[0, 16, 16] == 20
    assert stats.contributing[0, 16, 16] == math.floor(math.log(1e-4) / math.log(0.5))
    # alpha capped at 0.999: the first leaves 1e-3, the second would leave 1e-6: one composited
    stats = composite_stats(_stack(1.0, 3), cams)
    assert (stats.covering[0, 16, 16], stats.contributing[0, 16, 16]) == (3, 1)
    # away from the centre every Gaussian's alpha is lower, so more of them are composited, and
    # where none reaches 1/255 none covers the pixel and none is composited
    assert stats.contributing[0, 16, 16] <= stats.contributing[0, 16, 20]
    assert stats.covering[0, 0, 0] == stats.contributing[0, 0, 0] == 0
