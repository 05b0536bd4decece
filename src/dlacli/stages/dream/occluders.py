"""Occluders in the photo for dream's body backend (docs/dream.md "Backend body", step 2): which
baked texels show a limb in front of them rather than themselves, so `texture.bake` leaves them
to the completion."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

OCCLUDER_DIV = 16  # a limb in front (a hand, an arm, a knee) may really cover res / OCCLUDER_DIV px beyond its fit
OCCLUDER_DEPTH = -0.02  # metres: a limb within this behind a texel may still rest on it (hands on knees)
OCCLUDERS = {  # the limbs that rest on or cross in front of other parts, and the parts they never cover
    # here: the part they continue (no occluding edge between them) and their mirror, which is
    # dressed alike (crossed legs, one glove over the other), so colour cannot tell the two apart
    # and the covered one's colour is right either way
    "left_arm": ("left_hand", "right_arm"),
    "right_arm": ("right_hand", "left_arm"),
    "left_hand": ("left_arm", "right_hand"),
    "right_hand": ("right_arm", "left_hand"),
    "left_leg": ("left_foot", "right_leg"),
    "right_leg": ("right_foot", "left_leg"),
    "left_foot": ("left_leg", "right_foot"),
    "right_foot": ("right_leg", "left_foot"),
}
COLOUR_SAMPLES = 2000  # photo colours per part that decide whether a pixel shows a limb in front of it
MIN_SAMPLES = 200  # a part with fewer pixels seen out of the limb's reach gives no evidence
COLOUR_TOL = 0.06  # a pixel shows the limb when its colour is nearer to the limb's than its part's by this (RGB)


def covered_pixels(rgb, pimg, pure, inside, depth) -> np.ndarray:
    """[H, W] bool: photo pixels that show a part in front of the fitted part there, not that part
    itself (a hand on a thigh, crossed arms, a raised knee). The fit places an occluding limb only roughly (a hand's
    fingers and turn are not fitted at all), so geometry proposes and the photo's colours decide.
    For each limb q (`OCCLUDERS`), a pixel of another part P is covered by q when it lies within
    res / OCCLUDER_DIV px of q's fitted silhouette, q's nearest pixel is not behind it by more than
    -OCCLUDER_DEPTH (a hand resting on a knee may sink into the fitted knee), and its colour (the
    photo smoothed over 3 x 3 px) is nearer to q's own pixels than to P's pixels out of that reach
    (at least MIN_SAMPLES of them), by more than COLOUR_TOL (RGB; the nearest of up to
    COLOUR_SAMPLES each).
    Where the fit is right the pixels beside the limb look like their own part; where the real
    limb reaches past the fitted one they look like the limb. Where the two look alike the texel
    keeps its colour, which is then right either way. rgb [H, W, 3]; pimg [H, W] the part seen at
    each pixel (-1: none); pure [H, W] bool, away from a part border; inside [H, W] bool, the
    person mask; depth [H, W] the z-buffer."""
    from dlacli.body.regions import PARTS

    h, w = pimg.shape
    reach = max(1, w // OCCLUDER_DIV)
    smooth = ndimage.uniform_filter(rgb.astype(np.float64), size=(3, 3, 1), mode="nearest")
    rng = np.random.default_rng(0)
    covered = np.zeros((h, w), bool)
    for name, spared in OCCLUDERS.items():
        q = PARTS.index(name)
        ys, xs = np.nonzero(pimg == q)
        if not len(ys):
            continue
        pad = reach + 1
        crop = (slice(max(ys.min() - pad, 0), ys.max() + pad + 1), slice(max(xs.min() - pad, 0), xs.max() + pad + 1))
        pc, ins = pimg[crop], inside[crop]
        own = (pc == q) & pure[crop] & ins
        if not own.any():
            continue
        dist, (ny, nx) = ndimage.distance_transform_edt(~own, return_indices=True)
        never = [PARTS.index(n) for n in spared]
        other = (pc >= 0) & (pc != q) & ~np.isin(pc, never) & ins
        zone = other & (dist < reach) & (depth[crop][ny, nx] < depth[crop] - OCCLUDER_DEPTH)  # q not behind
        if not zone.any():
            continue
        sc = smooth[crop]
        q_tree = _colour_tree(sc[own], rng)
        beyond = inside & pure
        beyond[crop] &= dist >= reach  # the other parts as they look out of q's reach
        looks = np.zeros(zone.shape, bool)
        for p in np.unique(pc[zone]):
            samples = smooth[beyond & (pimg == p)]
            if len(samples) < MIN_SAMPLES:
                continue  # too little of P seen beyond the limb's reach: no evidence either way
            at = zone & (pc == p)
            d_q = q_tree.query(sc[at], k=1)[0]
            d_p = _colour_tree(samples, rng).query(sc[at], k=1)[0]
            looks[at] = d_p > d_q + COLOUR_TOL
        covered[crop] |= looks
    return covered


def _colour_tree(colours: np.ndarray, rng) -> cKDTree:
    """A k-d tree over at most COLOUR_SAMPLES of colours [M, 3] (a fixed random subset)."""
    if len(colours) > COLOUR_SAMPLES:
        colours = colours[np.sort(rng.choice(len(colours), size=COLOUR_SAMPLES, replace=False))]
    return cKDTree(np.asarray(colours, np.float64))
