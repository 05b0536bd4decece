"""Compact time samples for dla's USD files (formats/usd.md "Compaction"); numpy, no pxr.

Two reductions, each checked against the full animation at every frame:

1. **Rigid parts** (`split_parts`, `dlacli.geometry.rigid_motion`): the Gaussians are grouped by
   how they move (k-means over their trajectories, then rigid reassignment); each part gets one
   rigid transform per frame (a Kabsch fit), stored exactly at every frame as the part prim's
   `xformOp:transform`, and its Gaussians are stored in the part's own frame, where a limb's
   Gaussians barely move.
2. **Keyframe reduction** (`keep_frames`): a time sample of a part's positions, orientations or
   sizes is left out when USD's interpolation between the kept neighbouring samples (linear for
   points and floats, slerp for quaternions (`dlacli.geometry.quat_slerp`),
   `Usd.InterpolationTypeLinear`) reproduces every Gaussian of the part within the tolerance at
   that frame. The first and last frames are kept.
   A track whose every frame is within tolerance of frame 0 is written once, not time-sampled.

Tolerance (one number, `tol` metres, 0 = exact): the 1-sigma ellipsoid of every Gaussian moves
by at most `tol`: its centre (|dx| <= tol), its surface under rotation (angle * max sigma <= tol);
sizes (scales or widths) stay within SIZE_REL of their value, per axis. The rigid transforms
only re-express positions (an isometry), so errors measured in a part's frame are world errors.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dlacli.geometry import (
    matrix_to_quat,
    quat_conjugate,
    quat_continuous_signs,
    quat_multiply,
    quat_slerp,
    rigid_motion,
)

SIZE_REL = 0.02  # relative tolerance of scales / widths whenever tol > 0
GAUSSIANS_PER_PART = 2048  # parts = clip(N // GAUSSIANS_PER_PART, 1, MAX_PARTS)
MAX_PARTS = 64
KMEANS_ITERATIONS = 12
FEATURE_FRAMES = 32  # trajectories are clustered on at most this many evenly spaced frames
KMEANS_SAMPLE = 16384  # k-means is fitted on at most this many Gaussians
RIGID_ROUNDS = 2  # rounds of rigid reassignment after k-means (more made the demo walk no smaller)
RIGID_FRAMES = 12  # frames the rigid reassignment compares


@dataclass
class Track:
    """One attribute of one part: the kept frames and the values written at them."""

    frames: np.ndarray  # [K] int, ascending frame indices; K = 1 with constant: written once
    values: np.ndarray  # [K, n, d] as stored (quaternions (w, x, y, z), rounded to the stored dtype)
    constant: bool

    def at(self, t: int, kind: str = "linear") -> np.ndarray:
        """[n, d] the value USD returns at frame t (linear or slerp between the kept samples)."""
        if self.constant or t <= self.frames[0]:
            return self.values[0]
        k = int(np.searchsorted(self.frames, t, side="right")) - 1
        if k >= len(self.frames) - 1:
            return self.values[-1]
        t0, t1 = self.frames[k], self.frames[k + 1]
        alpha = (t - t0) / (t1 - t0)
        a, b = self.values[k].astype(np.float64), self.values[k + 1].astype(np.float64)
        return quat_slerp(a, b, alpha) if kind == "slerp" else a + (b - a) * alpha


@dataclass
class Part:
    """Gaussians `indices` [n] (into the full set) in a frame that moves rigidly."""

    indices: np.ndarray  # [n] int64, ascending
    transforms: np.ndarray | None  # [T, 4, 4] float64 local -> world, USD's row-vector form, or None
    positions: Track  # [., n, 3] in the part's frame
    quats: Track | None  # [., n, 4] (w, x, y, z) in the part's frame
    sizes: Track  # [., n, 3] scales, or [., n, 1] widths


# --------------------------------------------------------------------------------------------
# interpolation errors


def _weights(k: int, j: int, dtype=np.float32) -> np.ndarray:
    return ((np.arange(k + 1, j) - k) / (j - k)).astype(dtype)[:, None, None]  # [j-k-1, 1, 1]


def lerp_check(stored: np.ndarray, truth: np.ndarray, tol) -> Callable[[int, int], bool]:
    """ok(k, j): linear interpolation of stored[k], stored[j] [n, 3] (float32) is within tol
    (metres) of truth [T, n, 3] at every frame between (Euclidean distance)."""
    tol2 = np.float32(tol) ** 2

    def ok(k: int, j: int) -> bool:
        a, b = stored[k], stored[j]
        diff = a + (b - a) * _weights(k, j) - truth[k + 1 : j]  # [j-k-1, n, 3]
        return bool(np.all(np.einsum("mnd,mnd->mn", diff, diff) <= tol2))

    return ok


def relative_check(stored: np.ndarray, truth: np.ndarray, rel: float) -> Callable[[int, int], bool]:
    """ok(k, j): linear interpolation within rel * |truth| of truth [T, n, d], per component."""

    def ok(k: int, j: int) -> bool:
        a, b = stored[k], stored[j]
        ref = truth[k + 1 : j]
        return bool(np.all(np.abs(a + (b - a) * _weights(k, j) - ref) <= rel * np.abs(ref)))

    return ok


def slerp_check(stored: np.ndarray, truth: np.ndarray, tol_rad: np.ndarray) -> Callable[[int, int], bool]:
    """ok(k, j): slerp of stored[k], stored[j] (unit [n, 4], float64) within tol_rad [n] of truth
    (unit) at every frame between; never across a sign flip (GfSlerp would go the other way).
    A rotation angle theta between unit quaternions a, b is |<a, b>| = cos(theta / 2)."""
    min_dot = np.cos(np.minimum(tol_rad, np.pi) / 2)  # [n]

    def ok(k: int, j: int) -> bool:
        a, b = stored[k], stored[j]
        if np.any(np.einsum("nd,nd->n", a, b) < 0):
            return False
        mid = quat_slerp(a, b, _weights(k, j, np.float64))  # [j-k-1, n, 4]
        return bool(np.all(np.abs(np.einsum("mnd,mnd->mn", mid, truth[k + 1 : j])) >= min_dot))

    return ok


# --------------------------------------------------------------------------------------------
# keyframe selection


def keep_frames(ok: Callable[[int, int], bool], t: int) -> np.ndarray:
    """[K] frames to keep of 0..t-1 (first and last always): greedy, each kept frame followed by
    the farthest next one found by doubling the span, then bisecting, for which ok(k, j) holds.
    ok(k, k + 1) is true by definition (nothing lies between). Every frame left out lies in a
    span that passed `ok`, whatever `ok`'s shape."""
    kept, k = [0], 0
    while k < t - 1:
        good, bad = k + 1, None
        while good < t - 1:
            cand = min(k + 2 * (good - k), t - 1)
            if ok(k, cand):
                good = cand
            else:
                bad = cand
                break
        while bad is not None and bad - good > 1:
            mid = (good + bad) // 2
            if ok(k, mid):
                good = mid
            else:
                bad = mid
        kept.append(good)
        k = good
    return np.asarray(kept, dtype=np.int64)


def make_track(stored: np.ndarray, ok: Callable[[int, int], bool], still: Callable[[], bool]) -> Track:
    """A Track of stored [T, n, d]: written once when still() (every frame within tolerance of
    frame 0), else at keep_frames(ok)."""
    t = stored.shape[0]
    if t == 1 or still():
        return Track(np.zeros(1, np.int64), stored[:1], True)
    frames = keep_frames(ok, t)
    return Track(frames, stored[frames], False)


def exact_track(stored: np.ndarray) -> Track:
    """Every frame (or once, when every frame is identical)."""
    if np.all(stored == stored[:1]):
        return Track(np.zeros(1, np.int64), stored[:1], True)
    return Track(np.arange(stored.shape[0]), stored, False)


# --------------------------------------------------------------------------------------------
# rigid parts


def split_parts(positions: np.ndarray, n_parts: int, seed: int = 0) -> np.ndarray:
    """[N] part label in 0..P-1 of each Gaussian, P <= n_parts.

    Fitted on <= KMEANS_SAMPLE Gaussians (fixed seed): k-means (Lloyd) over trajectories (the
    positions [T, N, 3] at <= FEATURE_FRAMES evenly spaced frames); then, since k-means groups by
    where the Gaussians are as much as by how they move, RIGID_ROUNDS rounds of the rigid step of
    skinning decomposition: fit each part's rigid motion (`rigid_motion`), move each Gaussian to
    the part whose motion carries its frame-0 position closest to where it is (least squares over
    <= RIGID_FRAMES frames). Every Gaussian then goes to its best part; empty parts are dropped
    and parts are numbered by their first Gaussian."""
    t, n = positions.shape[:2]
    if n_parts <= 1 or n < 2:
        return np.zeros(n, np.int64)
    pick = np.unique(np.linspace(0, t - 1, min(t, FEATURE_FRAMES)).round().astype(np.int64))
    rng = np.random.default_rng(seed)
    fit_index = np.sort(rng.choice(n, min(n, KMEANS_SAMPLE), replace=False))
    fit = np.ascontiguousarray(positions[pick][:, fit_index].transpose(1, 0, 2).reshape(len(fit_index), -1), np.float32)
    centres = fit[rng.choice(len(fit), min(n_parts, len(fit)), replace=False)]
    for _ in range(KMEANS_ITERATIONS):
        d2 = np.einsum("kd,kd->k", centres, centres)[None] - 2 * fit @ centres.T  # + |x|^2, same for all k
        labels = np.argmin(d2, axis=1)
        counts = np.bincount(labels, minlength=len(centres))
        sums = np.stack([np.bincount(labels, fit[:, d], minlength=len(centres)) for d in range(fit.shape[1])], 1)
        centres = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], centres).astype(np.float32)
    frames = positions[np.unique(np.linspace(0, t - 1, min(t, RIGID_FRAMES)).round().astype(np.int64))]  # frame 0 first
    fit_frames = frames[:, fit_index]
    for _ in range(RIGID_ROUNDS):
        labels = _best_rigid_part(fit_frames, _part_motions(fit_frames, labels, len(centres)))
    labels = _best_rigid_part(frames, _part_motions(fit_frames, labels, len(centres)))
    used, first = np.unique(labels, return_index=True)
    remap = np.empty(len(centres), np.int64)
    remap[used[np.argsort(first)]] = np.arange(len(used))
    return remap[labels]


def _part_motions(frames: np.ndarray, labels: np.ndarray, k: int) -> list:
    """[(R [F, 3, 3], c [F, 3], mean_0 [3])] rigid motion of each part's members (None: empty)."""
    out = []
    for label in range(k):
        members = frames[:, labels == label]
        if members.shape[1] == 0:
            out.append(None)
            continue
        r, c = rigid_motion(members)
        out.append((r.astype(np.float32), c.astype(np.float32), c[0].astype(np.float32)))
    return out


def _best_rigid_part(frames: np.ndarray, motions: list) -> np.ndarray:
    """[n] the part whose rigid motion best explains each trajectory (frames [F, n, 3]):
    argmin over parts of sum_f |R_f^T (p_f - c_f) - (p_0 - c_0)|^2, expanded into dot products
    so that all parts are scored by a few matrix products (float64; the per-frame centroid of all
    points is taken out first, which changes no cost and keeps the numbers small)."""
    f, n = frames.shape[:2]
    centre = frames.astype(np.float64).mean(axis=1)  # [F, 3]
    p = frames.astype(np.float64) - centre[:, None]  # [F, n, 3]
    p0 = p[0]  # [n, 3]
    live = [k for k, m in enumerate(motions) if m is not None]
    r = np.stack([motions[k][0] for k in live]).astype(np.float64)  # [K, F, 3, 3]
    c = np.stack([motions[k][1] for k in live]).astype(np.float64) - centre  # [K, F, 3]
    c0 = c[:, 0]  # [K, 3]
    flat = p.transpose(1, 0, 2).reshape(n, 3 * f)  # [n, 3F]
    outer = np.einsum("fni,nj->nfij", p, p0).reshape(n, 9 * f)  # [n, 9F] p_f,i p_0,j
    cost = (
        -2 * flat @ c.reshape(len(live), 3 * f).T  # -2 sum_f p_f . c_f
        + np.einsum("kfd,kfd->k", c, c)[None]  # + sum_f |c_f|^2
        + f * (np.einsum("kd,kd->k", c0, c0)[None] - 2 * p0 @ c0.T)  # + F |p_0 - c_0|^2 (less |p_0|^2)
        - 2 * outer @ r.reshape(len(live), 9 * f).T  # cross term: sum_f p_f^T R_f p_0
        + 2 * flat @ np.einsum("kfij,kj->kfi", r, c0).reshape(len(live), 3 * f).T  # + sum_f p_f . R_f c_0
        + 2 * p0 @ np.einsum("kfij,kfi->kj", r, c).T  # + p_0 . sum_f R_f^T c_f
        - 2 * np.einsum("kfi,kfij,kj->k", c, r, c0)[None]  # - sum_f c_f^T R_f c_0
    )  # [n, K], up to terms that are the same for every part
    return np.asarray(live, np.int64)[np.argmin(cost, axis=1)]


def usd_matrix(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(R [T, 3, 3], c [T, 3]) -> [T, 4, 4] in USD's row-vector form: p_world = (p_local, 1) M."""
    m = np.zeros((r.shape[0], 4, 4))
    m[:, :3, :3] = np.swapaxes(r, 1, 2)
    m[:, 3, :3] = c
    m[:, 3, 3] = 1
    return m


def compact(
    positions: np.ndarray,  # [T, N, 3] metres
    quats: np.ndarray | None,  # [T, N, 4] (w, x, y, z) unit, or None (points: no orientations)
    sizes: np.ndarray,  # [T, N, d] scales (d = 3) or widths (d = 1), > 0
    sigma_max: np.ndarray,  # [T, N] largest standard deviation (orientation tolerance)
    tol: float,  # metres, > 0
    *,
    quat_dtype=np.float16,
    parts: bool = True,
) -> list[Part]:
    """The compact tracks of one schema's prim(s); `parts=False` keeps one world-space part."""
    t, n = positions.shape[:2]
    n_parts = int(np.clip(n // GAUSSIANS_PER_PART, 1, MAX_PARTS)) if parts else 1
    labels = split_parts(positions, n_parts) if n_parts > 1 else np.zeros(n, np.int64)
    out = []
    for label in range(int(labels.max()) + 1 if n else 0):
        idx = np.flatnonzero(labels == label)
        pos, size = positions[:, idx].astype(np.float64), sizes[:, idx]
        transforms = None
        if parts:
            r, c = rigid_motion(pos)
            pos = np.einsum("tni,tij->tnj", pos - c[:, None], r)  # R^T (p - c), row vectors
            transforms = usd_matrix(r, c)
        pos32 = pos.astype(np.float32)
        # the checks' closures run inside make_track, in this iteration: B023 does not apply
        pos_track = make_track(
            pos32,
            lerp_check(pos32, pos32, tol),
            lambda: bool(np.all(np.linalg.norm(pos32 - pos32[:1], axis=-1) <= tol)),  # noqa: B023
        )
        size_track = make_track(
            size,
            relative_check(size, size, SIZE_REL),
            lambda: bool(np.all(np.abs(size - size[:1]) <= SIZE_REL * size)),  # noqa: B023
        )
        quat_track = None
        if quats is not None:
            q = quats[:, idx].astype(np.float64)
            if parts:
                q_part = matrix_to_quat(r)  # [T, 4]
                q = quat_multiply(np.broadcast_to(quat_conjugate(q_part)[:, None], q.shape), q)
            written = quat_continuous_signs(q.astype(quat_dtype))  # [T, n, 4] as the file holds them
            unit = written.astype(np.float64)
            unit /= np.linalg.norm(unit, axis=-1, keepdims=True)
            tol_rad = tol / np.maximum(sigma_max[:, idx].max(axis=0), 1e-12)  # [n], the largest sigma over time
            min_dot = np.cos(np.minimum(tol_rad, np.pi) / 2)
            quat_track = make_track(
                written,
                slerp_check(unit, unit, tol_rad),
                lambda: bool(np.all(np.abs(np.einsum("tnd,nd->tn", unit, unit[0])) >= min_dot)),  # noqa: B023
            )
        out.append(Part(idx, transforms, pos_track, quat_track, size_track))
    return out
