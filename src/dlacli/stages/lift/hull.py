"""The views' visual hull, rounded: where a ray through a view's silhouette meets the person.

Four silhouettes at 90 degrees bound a round skirt by a square: the intersection of the views'
silhouettes (the visual hull) has corners where the person has none, and a ray near the edge of
one silhouette enters it at a face of that square, in front of the true surface. Every input view
agrees with either shape, so the refinement cannot tell; the corners show in the views between
(docs/lift.md, "Loose clothing").

So the hull here is the part of the silhouettes' intersection that is also inside the ellipse
their extents describe. A point p projects into view v inside a run of silhouette pixels along
its image row; its place there, t_v = (x - centre) / half-width in [-1, 1], is, for a round
cross-section of radius r, (a_v . q) / r with a_v the camera's x-axis in the world and q the
point's offset from the axis. The least-squares q / r over the views (`Silhouettes.spread`, a
pseudo-inverse of the a_v) has length 1 on the ellipse that touches every silhouette's edges; the
rounded hull keeps |q / r| <= 1. Where the ray never enters the rounded hull (views that disagree,
the very edge of a silhouette) the intersection alone gives the depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlacli.geometry import project_points
from dlacli.types import Cameras, ViewSet

HULL_STEPS = 128  # ray-marching samples through the body's bounding sphere
HULL_BISECT = 6


@dataclass
class HullDepth:
    """What the lift's step a measured along the rays of a grid x grid downsampling of every
    view: the camera depth [V, gh, gw] where each masked pixel's ray enters the other views'
    silhouettes' intersection, not rounded (inf off the mask or where it never does), and the
    body's depth there (inf off the body), for the cameras of that grid."""

    hull: np.ndarray
    body: np.ndarray
    cameras: Cameras


def row_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[H, W] bool -> (centre, half) [H, W] float64: the centre and half width, in pixel
    coordinates (pixel c spans [c, c + 1)), of the run of mask pixels along its row that holds
    each pixel; meaningless off the mask."""
    h, w = mask.shape
    idx = np.broadcast_to(np.arange(w), (h, w))
    start = np.maximum.accumulate(np.where(mask, -1, idx), axis=1) + 1  # after the last gap on the left
    last_gap = np.maximum.accumulate(np.where(mask[:, ::-1], -1, idx), axis=1)[:, ::-1]  # reversed index
    end = w - 1 - last_gap  # the first gap on the right, or w
    return 0.5 * (start + end), 0.5 * (end - start)


class Silhouettes:
    """The views' masks, cameras and row runs, set up once for the many points a lift tests."""

    def __init__(self, views: ViewSet):
        self.masks = views.masks > 0.5
        self.w2cs = views.cameras.viewmats.numpy().astype(np.float64)
        self.ks = views.cameras.Ks.numpy().astype(np.float64)
        self.runs = [row_runs(m) for m in self.masks]
        axes = self.w2cs[:, 0, :3]  # [V, 3] each camera's x-axis (image columns) in the world
        self.spread = np.linalg.pinv(axes)  # [3, V]: t [.., V] -> q / r [.., 3] (least squares)

    def inside(self, points: np.ndarray, skip: int, rounded: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """points [..., 3] -> (in the intersection of every view's silhouette but view `skip`'s,
        in the rounded hull as well; None unless `rounded`) [...] bool. View folders frame the
        whole person, so a point outside a view's image (or behind its camera) is outside the
        hull. View `skip` (the ray's own) counts for the rounding only, at the edge of its
        silhouette where it misses it."""
        shape = points.shape[:-1]
        inside = np.ones(shape, dtype=bool)
        t = np.ones((*shape, len(self.masks))) if rounded else None
        h, w = self.masks.shape[1:]
        for v, (mask, (centre, half)) in enumerate(zip(self.masks, self.runs)):
            px, z = project_points(points, self.w2cs[v], self.ks[v])
            col, row = np.floor(px[..., 0]).astype(np.int64), np.floor(px[..., 1]).astype(np.int64)
            in_img = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            on = np.zeros(shape, dtype=bool)
            on[in_img] = mask[row[in_img], col[in_img]]
            if rounded:
                r, c = row[on], col[on]
                t[..., v][on] = (px[..., 0][on] - centre[r, c]) / np.maximum(half[r, c], 0.5)
            if v != skip:
                inside &= on
        if not rounded:
            return inside, None
        q = t @ self.spread.T  # [..., 3]
        return inside, inside & (np.einsum("...i,...i->...", q, q) <= 1.0)


def hull_depth(
    origin, dirs, silhouettes: Silhouettes, v: int, centre, radius, rounded: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-z depths [N] where rays of view v (origin [3], dirs [N, 3] with unit camera-z
    component) first enter the views' silhouettes' intersection and their rounded hull; the
    rounded one is the intersection's where the ray never enters the rounded hull (and
    everywhere unless `rounded`: then the rounding is not computed), and both are inf where the
    ray never enters the intersection."""
    oc = origin - centre
    d0 = max(float(np.linalg.norm(oc)) - radius, 1e-3)
    ts = np.linspace(d0, d0 + 2.0 * radius, HULL_STEPS)  # [S]
    pts = origin + dirs[:, None, :] * ts[None, :, None]  # [N, S, 3]
    box, in_round = silhouettes.inside(pts, v, rounded)
    n = len(dirs)
    if not rounded:  # one shape: rows [N] of the intersection only
        in_round, use_round = box[:0], np.zeros(0, dtype=bool)
    else:
        use_round = in_round.any(axis=1)  # [N]
        in_round = np.where(use_round[:, None], in_round, box)
    inside = np.concatenate([box, in_round])  # [N or 2N, S]: both shapes bisected together
    hit = inside.any(axis=1)
    first = np.argmax(inside, axis=1)
    lo = ts[np.maximum(first - 1, 0)]
    hi = ts[first]
    which = np.concatenate([np.zeros(n, dtype=bool), use_round])  # rows bisected in the rounded hull
    ray_dirs = np.concatenate([dirs, dirs[: len(use_round)]])
    for _ in range(HULL_BISECT):
        mid = 0.5 * (lo + hi)
        m_box, m_round = silhouettes.inside(origin + ray_dirs * mid[:, None], v, rounded)
        m_in = np.where(which, m_round, m_box) if rounded else m_box
        hi = np.where(m_in, mid, hi)
        lo = np.where(m_in, lo, mid)
    depth = np.where(hit, hi, np.inf)
    return depth[:n], (depth[n:] if rounded else depth[:n])
