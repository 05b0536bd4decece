"""Where a splatted frame's compositing time goes: per tile, how many Gaussians its list holds and
how many pixel evaluations the exact kernel made (its own count); per pixel, how many Gaussians
cover it (within the cutoff where alpha >= 1/255 at full transmittance) and how many it composited
before its transmittance ran out. `dla bench speed --suite render` reports them and draws them as
heat maps (docs/rendering.md "Where the time goes").

The per-pixel counts come from a compositing written out again in numpy, tile by tile, from the
same binned lists the kernels read (`splat.binned_plain`); its colour sum equals the exact kernel's
to round-off (tests/render/test_splat_stats.py), which is what makes its counts trustworthy.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from dlacli.render import splat_kernels as K
from dlacli.render.splat import TILE, binned_plain, check_render_inputs, composite_lists
from dlacli.types import Cameras, Gaussians

CHUNK = 2048  # list entries composited at once (memory: CHUNK x 256 pixels x a few float64 arrays)


class CompositeStats(NamedTuple):
    listed: np.ndarray  # [C, TH, TW] int64 entries in each tile's list
    evaluations: np.ndarray  # [C, TH, TW] float64 pixel evaluations of the exact kernel in each tile
    covering: np.ndarray  # [C, H, W] int32 Gaussians whose cutoff ellipse holds the pixel
    contributing: np.ndarray  # [C, H, W] int32 Gaussians composited into the pixel
    acc: np.ndarray  # [C, H, W, 4] float64 the premultiplied colour and depth sums of that compositing

    def summary(self) -> dict[str, float]:
        """What a frame costs where it draws: the share of pixels some Gaussian covers; over the
        tiles with a list, its mean length and the kernel's evaluations per pixel; over the covered
        pixels, the means and 99th percentiles of the Gaussians covering and composited."""
        used = self.listed > 0
        covered = self.covering > 0
        if not covered.any():
            return {"covered_share": 0.0}
        cov, con = self.covering[covered], self.contributing[covered]
        return {
            "covered_share": float(covered.mean()),
            "listed_per_tile": float(self.listed[used].mean()),
            "evaluations_per_pixel": float(self.evaluations[used].sum() / (used.sum() * TILE * TILE)),
            "covering_per_pixel": float(cov.mean()),
            "covering_p99": float(np.percentile(cov, 99)),
            "contributing_per_pixel": float(con.mean()),
            "contributing_p99": float(np.percentile(con, 99)),
        }


def composite_stats(gaussians: Gaussians, cameras: Cameras, *, sh_degree: int | None = None) -> CompositeStats:
    """The counts of a render of `gaussians` (no batch dimensions) by `cameras` on the CPU, as
    `render_gaussians` would composite it with the exact kernel."""
    degree, _ = check_render_inputs(gaussians, cameras, None, sh_degree)
    g = gaussians.to(torch.device("cpu"))
    dtype = g.means.dtype
    viewmats, Ks = cameras.viewmats.to(dtype=dtype), cameras.Ks.to(dtype=dtype)
    w, h, ncam = int(cameras.width), int(cameras.height), len(cameras)
    with torch.no_grad():
        params, offsets, lists = binned_plain(g, viewmats, Ks, w, h, degree)
    _, _, (_, _, work) = composite_lists(params, offsets, lists, ncam, w, h)
    tw, th = (w + TILE - 1) // TILE, (h + TILE - 1) // TILE
    covering = np.zeros((ncam, h, w), np.int32)
    contributing = np.zeros((ncam, h, w), np.int32)
    acc = np.zeros((ncam, h, w, 4))
    for tid in range(ncam * th * tw):
        c, t = divmod(tid, th * tw)
        ty, tx = divmod(t, tw)
        y0, x0 = ty * TILE, tx * TILE
        y1, x1 = min(y0 + TILE, h), min(x0 + TILE, w)
        entries = lists[offsets[tid] : offsets[tid + 1]]
        if not len(entries):
            continue
        cov, con, col = _tile(params[entries].astype(np.float64), x0, x1, y0, y1)
        covering[c, y0:y1, x0:x1] = cov
        contributing[c, y0:y1, x0:x1] = con
        acc[c, y0:y1, x0:x1] = col
    listed = np.diff(offsets).reshape(ncam, th, tw)
    return CompositeStats(listed, work.reshape(ncam, th, tw), covering, contributing, acc)


def _tile(p: np.ndarray, x0: int, x1: int, y0: int, y1: int):
    """One tile's entries p [E, NPARAM] (front to back) composited as `K.raster_forward` does ->
    (covering, contributing [y1 - y0, x1 - x0], acc [.., .., 4])."""
    ys, xs = np.mgrid[y0:y1, x0:x1]
    px, py = xs.ravel(), ys.ravel()
    npix = px.size
    trans = np.ones(npix)
    alive = np.ones(npix, bool)
    cov = np.zeros(npix, np.int32)
    con = np.zeros(npix, np.int32)
    col = np.zeros((npix, 4))
    for k0 in range(0, len(p), CHUNK):
        q = p[k0 : k0 + CHUNK]
        inbox = (px >= q[:, 7:8]) & (px <= q[:, 8:9]) & (py >= q[:, 9:10]) & (py <= q[:, 10:11])  # [E, P]
        dx = q[:, 0:1] - (px + 0.5)
        dy = q[:, 1:2] - (py + 0.5)
        sigma = 0.5 * (q[:, 2:3] * dx * dx + q[:, 4:5] * dy * dy) + q[:, 3:4] * dx * dy
        inside = inbox & (sigma >= 0.0) & (sigma <= q[:, 6:7])
        alpha = np.where(inside, np.minimum(K.ALPHA_MAX, q[:, 5:6] * np.exp(-np.where(inside, sigma, 0.0))), 0.0)
        use = inside & (alpha >= K.ALPHA_MIN)
        cov += inside.sum(0, dtype=np.int32)
        if not alive.any():
            continue  # every pixel finished: the rest only counts as covering
        # front to back: the transmittance before each entry, and the first entry that would end it
        factor = np.where(use, 1.0 - alpha, 1.0)
        before = trans * np.concatenate([np.ones((1, npix)), np.cumprod(factor, axis=0)[:-1]])
        ends = use & (before * (1.0 - alpha) <= K.T_MIN)
        first_end = np.where(ends.any(0), ends.argmax(0), len(q))
        counted = use & (np.arange(len(q))[:, None] < first_end) & alive
        con += counted.sum(0, dtype=np.int32)
        wgt = np.where(counted, alpha * before, 0.0)
        col += wgt.T @ q[:, 12:16]
        last = np.where(counted, np.arange(len(q))[:, None], -1).max(0)
        at = (np.maximum(last, 0), np.arange(npix))
        trans = np.where(last >= 0, before[at] * factor[at], trans)
        alive &= first_end == len(q)
    shape = (y1 - y0, x1 - x0)
    return cov.reshape(shape), con.reshape(shape), col.reshape(*shape, 4)
