"""The Gaussian budget: how many Gaussians an avatar needs at a render size (`--gaussians auto`).

Quality is masked PSNR (inside the mask, rgb on black, as dlacli.bench.metrics) of the avatar's
renders with n Gaussians, for n on a ladder (LADDER: 4,096 ... 262,144); the chosen count is the
smallest n within `tolerance_db` (0.2 dB) of the best score (`choose_gaussians`).

- `dla lift --gaussians auto` (`choose_for_views`) measures against ground truth, the input views
  (`measure_budget`), and records the choice in the avatar: `extra.samples.count` (what render and
  animate draw by default) and `extra.budget` (the scores, and the size the person had in those
  views: `subject_px`, the median height in pixels of the body's projection).
- `dla lift` does this by default (`--gaussians N` refines with and records N, no budget); `dla
  render` and `dla animate` then draw the recorded budget by default (`budget_default`, the
  "recorded" rule below), `dla view` and `dla export` (no cameras) its count as recorded.
- `dla render` / `dla animate --gaussians auto` (`auto_gaussians`) have no ground truth. When the
  avatar records a budget, its count is carried to the target cameras by the area the person
  covers: n = recorded count x (target subject_px / recorded subject_px)^2, rounded up to the
  ladder ("recorded"). Otherwise by sampling noise ("self-consistency"): s(n) is half the masked
  mean squared difference between two renders with n Gaussians drawn at different sample seeds
  (the variance of one render's sampling noise), and under the additive-error model (the avatar
  misses the truth by an error of mean square e = 10^(-REFERENCE_PSNR/10), independent of the
  sampling noise) a render with n Gaussians scores -10 log10(e + s(n)) (`predicted_psnr`); the
  choice is made on those scores.

Why not compare with the render at the largest count: the count changes how dense and opaque the
Gaussians lie, not just how noisy, so that render is no reference (measured: a lifted avatar at
256 px scores best on its novel views at 16-32k Gaussians; every smaller count differs from the
262k render by more than 4.7 % of e, which would pick 262k every time). docs/benchmarks.md, "The
Gaussian budget", compares the rules' choices with the ground truth's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.limits import BUDGET_LADDER, BUDGET_TOLERANCE_DB
from dlacli.types import Avatar, Cameras, ViewSet

LADDER = BUDGET_LADDER  # 4,096 ... 262,144 (dlacli.limits: the CLI's help quotes them)
TOLERANCE_DB = BUDGET_TOLERANCE_DB
# the error level e of the additive model, as a masked PSNR: what the CPU lift's avatars score on
# their own input views at 128-512 px (21-22 dB, docs/benchmarks.md "The Gaussian budget"); a
# higher value keeps more Gaussians.
REFERENCE_PSNR = 21.0
AUTO_VIEWS = 4  # cameras of a self-consistency measurement


def choose_gaussians(scores: dict[int, float], tolerance_db: float = TOLERANCE_DB) -> int:
    """The smallest count whose score (dB, higher is better) is within `tolerance_db` of the best.
    NaN and -inf (a failed render) never win; +inf is a perfect score (only other perfect scores
    are within any tolerance of it)."""
    if not scores:
        raise ValueError("choose_gaussians: no scores")
    if not (math.isfinite(tolerance_db) and tolerance_db >= 0):
        raise ValueError(f"choose_gaussians: tolerance {tolerance_db!r} is not a finite number >= 0")
    ok = {int(n): float(s) for n, s in scores.items() if not math.isnan(s) and s != -math.inf}
    if not ok:
        raise ValueError("choose_gaussians: no usable score (all NaN or -inf)")
    best = max(ok.values())
    return min(n for n, s in ok.items() if s >= best - tolerance_db)


def _masked_mse(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, where: str) -> float:
    sel = np.asarray(mask) > 0.5
    if not sel.any():
        raise DlaInputError(where, "nothing to score the Gaussian budget on: the person covers no pixel")
    diff = np.asarray(pred, np.float64)[sel] - np.asarray(gt, np.float64)[sel]
    return float(np.mean(diff**2))


def _db(mse: float) -> float:
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def _renders(
    avatar: Avatar, cameras: Cameras, n: int, seed: int | None, times=None, motion=None, checkpoint: str | None = None
) -> np.ndarray:
    """RGBA [C, H, W, 4] of the avatar drawn with n Gaussians, in camera order."""
    from dlacli.stages.render import render_avatar

    times = [None] * len(cameras) if times is None else list(times)
    shots = render_avatar(avatar, cameras, times, motion, n_gaussians=n, seed=seed, checkpoint=checkpoint)
    return np.stack([s.rgba for s in sorted(shots, key=lambda s: s.camera)])


def _check_counts(counts) -> list[int]:
    from dlacli.limits import MAX_GAUSSIANS

    out = sorted({int(n) for n in counts})
    if not out or out[0] < 2 or out[-1] > MAX_GAUSSIANS:
        raise DlaInputError(
            "--gaussians", f"the counts to compare must lie in [2, {MAX_GAUSSIANS}], got {list(counts)!r}"
        )
    return out


def _scaled_views(views: ViewSet, render_size: int | None):
    """(ground truth rgb on black [V, h, w, 3], masks [V, h, w], cameras) with the long side at
    most render_size (None: the views' own size; never scaled up)."""
    h, w = views.masks.shape[1:]
    rgb, mask, cams = views.targets(max(h, w) if render_size is None else int(render_size))
    return rgb.numpy(), mask.numpy(), cams


def measure_budget(
    avatar: Avatar,
    views: ViewSet,
    counts=LADDER,
    render_size: int | None = None,
    motion=None,
    seed: int | None = None,
    checkpoint: str | None = None,
) -> dict[int, float]:
    """Masked PSNR of the avatar's renders with each count against the views' ground truth, the
    views scaled down so their long side is at most `render_size` (None: their own size).
    `motion`: what the views' `time`s index (None: the avatar's own pose). Seed: the avatar's own."""
    gt, mask, cams = _scaled_views(views, render_size)
    return {
        n: _db(
            _masked_mse(_renders(avatar, cams, n, seed, views.times, motion, checkpoint)[..., :3], gt, mask, "views")
        )
        for n in _check_counts(counts)
    }


def sampling_noise(
    avatar: Avatar, cameras: Cameras, counts=LADDER, seed: int | None = None, checkpoint: str | None = None
) -> dict[int, float]:
    """s(n): half the masked mean squared difference between the renders with n Gaussians at sample
    seeds `seed` (default: the avatar's) and seed + 1, own pose (mask: either alpha > 0.5)."""
    from dlacli.avatar.posed import sample_settings

    _, seed = sample_settings(avatar, None, seed)
    other = (seed + 1) % 2**32
    out = {}
    for n in _check_counts(counts):
        a = _renders(avatar, cameras, n, seed, checkpoint=checkpoint)
        b = _renders(avatar, cameras, n, other, checkpoint=checkpoint)
        out[n] = 0.5 * _masked_mse(a[..., :3], b[..., :3], np.maximum(a[..., 3], b[..., 3]), "avatar")
    return out


def predicted_psnr(noise: dict[int, float], reference_psnr: float = REFERENCE_PSNR) -> dict[int, float]:
    """Scores under the additive-error model (module doc): -10 log10(e + s(n)), e = 10^(-P/10)."""
    if not math.isfinite(reference_psnr):
        raise ValueError(f"predicted_psnr: reference PSNR {reference_psnr!r} is not finite")
    e = 10.0 ** (-reference_psnr / 10.0)
    return {n: -10.0 * math.log10(e + s) for n, s in noise.items()}


def subject_pixels(avatar: Avatar, cameras: Cameras) -> float:
    """Median over the cameras of the height in pixels of the avatar's body (own pose) projected
    into them (its vertices' vertical extent)."""
    from dlacli.body.model import get_body_model
    from dlacli.geometry import project_points

    verts = get_body_model().forward_body(avatar.body).vertices[0].double().numpy()
    heights = []
    for c in range(len(cameras)):
        px, z = project_points(verts, cameras.viewmats[c].double().numpy(), cameras.Ks[c].double().numpy())
        px = px[z > 0]
        heights.append(float(np.ptp(px[:, 1])) if len(px) else 0.0)
    return float(np.median(heights))


def scaled_count(count: int, from_px: float, to_px: float, counts=LADDER) -> int:
    """The smallest ladder count >= count x (to_px / from_px)^2 (the ladder's largest when none)."""
    counts = _check_counts(counts)
    if not (from_px > 0 and math.isfinite(from_px) and math.isfinite(to_px) and to_px >= 0):
        raise ValueError(f"scaled_count: subject sizes {from_px!r} -> {to_px!r} px")
    # the sizes are float64 projections: a person exactly half as tall can measure 0.5 + 1e-16 as
    # tall, which must not round 4x the count up to the next rung (a relative slack of 1e-9 is far
    # above float64 rounding and far below any real difference in size)
    need = count * (to_px / from_px) ** 2 * (1.0 - 1e-9)
    return next((n for n in counts if n >= need), counts[-1])


def recorded_budget(avatar: Avatar) -> dict | None:
    """The avatar's `extra.budget` when it holds a usable measurement (count and subject_px)."""
    budget = avatar.extra.get("budget")
    if not isinstance(budget, dict):
        return None
    count, px = budget.get("count"), budget.get("subject_px")
    ok = (
        isinstance(count, int)
        and not isinstance(count, bool)
        and count >= 2
        and isinstance(px, (int, float))
        and not isinstance(px, bool)
        and math.isfinite(px)
        and px > 0
    )
    return budget if ok else None


@dataclass
class BudgetChoice:
    count: int
    rule: str  # "measured", "recorded" or "self-consistency"
    scores: dict[int, float] = field(default_factory=dict)  # dB per count (measured or predicted)
    subject_px: float | None = None  # the person's height in pixels where the choice applies
    noise: dict[int, float] = field(default_factory=dict)  # s(n) (self-consistency)


def auto_cameras(cameras: Cameras, k: int = AUTO_VIEWS) -> Cameras:
    """At most k of the cameras, evenly spread over their order."""
    idx = np.unique(np.linspace(0, len(cameras) - 1, min(k, len(cameras))).round().astype(np.int64))
    return cameras.select(idx)


def budget_default(avatar: Avatar, cameras: Cameras, counts=LADDER) -> BudgetChoice | None:
    """What render and animate draw when no --gaussians is given: the avatar's recorded budget
    carried to the person's size in `cameras` (the "recorded" rule, no render), or None when the
    avatar records no budget (an avatar lifted before budgets or with --gaussians N: then
    `sample_settings`, its extra.samples.count, else DEFAULT_GAUSSIANS)."""
    recorded = recorded_budget(avatar)
    if recorded is None:
        return None
    px = subject_pixels(avatar, cameras)
    return BudgetChoice(scaled_count(recorded["count"], recorded["subject_px"], px, counts), "recorded", subject_px=px)


def auto_gaussians(
    avatar: Avatar,
    cameras: Cameras,
    counts=LADDER,
    tolerance_db: float = TOLERANCE_DB,
    seed: int | None = None,
    checkpoint: str | None = None,
) -> BudgetChoice:
    """`--gaussians auto` for rendering at `cameras` (module doc): the recorded budget carried to
    the person's size in these cameras, else self-consistency by sampling noise."""
    choice = budget_default(avatar, cameras, counts)
    if choice is not None:
        return choice
    px = subject_pixels(avatar, cameras)
    noise = sampling_noise(avatar, cameras, counts, seed, checkpoint)
    scores = predicted_psnr(noise)
    return BudgetChoice(choose_gaussians(scores, tolerance_db), "self-consistency", scores, px, noise)


def choose_for_views(
    avatar: Avatar,
    views: ViewSet,
    counts=LADDER,
    render_size: int | None = None,
    tolerance_db: float = TOLERANCE_DB,
    checkpoint: str | None = None,
) -> tuple[Avatar, BudgetChoice]:
    """`dla lift --gaussians auto`: measure on the (input) views at `render_size` (None: their own
    size), choose, and return the avatar recording the choice: `extra.samples.count` and
    `extra.budget` = {count, tolerance_db, render_size, subject_px, measured_on, psnr_masked:
    {count: dB}} (non-finite scores as null), with the choice itself. `checkpoint`: a learned
    avatar's network (folder or hash), before it is installed in the cache."""
    from dlacli.avatar.posed import sample_settings

    _, seed = sample_settings(avatar)
    scores = measure_budget(avatar, views, counts, render_size, seed=seed, checkpoint=checkpoint)
    count = choose_gaussians(scores, tolerance_db)
    _, _, cams = _scaled_views(views, render_size)
    px = subject_pixels(avatar, cams)
    extra = dict(avatar.extra)
    samples = extra.get("samples") if isinstance(extra.get("samples"), dict) else {}
    extra["samples"] = {**samples, "count": count, "seed": seed}
    extra["budget"] = {
        "count": count,
        "tolerance_db": tolerance_db,
        "render_size": max(cams.width, cams.height),
        "subject_px": px,
        "measured_on": "input views",
        "psnr_masked": {str(n): (s if math.isfinite(s) else None) for n, s in scores.items()},
    }
    return replace(avatar, extra=extra), BudgetChoice(count, "measured", scores, px)
