"""The Gaussian budget on synthetic subjects (`dla bench budget`): quality against the number of
Gaussians and the UV resolution at a target render size, with the render time and USD size each
count costs, and what `--gaussians auto`'s rules choose (dlacli.stages.budget).

Per seed: a synth subject with its views at the render size; per UV resolution, one avatar
(a method spec of dlacli.stages.lift.methods, lifted with that `resolution`); per count on the
ladder: masked PSNR, PSNR, SSIM and IoU of the renders on the input views ("inputs": what lift
--gaussians auto measures), the novel views and the novel poses; the median time to render one
image; the size and write time of a `usd_frames`-frame walk as USD (animate's default schema and
tolerance); the sampling noise s(n) at AUTO_VIEWS turntable cameras of the render size (what the
self-consistency rule sees).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dlacli.limits import DEFAULT_GAUSSIANS
from dlacli.stages.lift.methods import MethodSpec

DEFAULT_COUNT = DEFAULT_GAUSSIANS  # the count lift refines at and an avatar without a budget draws (the baseline)


def _timed_split(avatar, views, n: int, motion=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(RGBA renders [C, H, W, 4], ground truth on black, seconds per image: the split's render
    time, drawing the n samples once included, over its images)."""
    from dlacli.stages.render import render_avatar

    t0 = time.perf_counter()
    shots = sorted(render_avatar(avatar, views.cameras, views.times, motion, n_gaussians=n), key=lambda s: s.camera)
    per_image = (time.perf_counter() - t0) / max(len(shots), 1)
    return np.stack([s.rgba for s in shots]), views.images * views.masks[..., None], per_image


def _usd_cost(avatar, n: int, frames: int, folder: Path) -> tuple[float, float]:
    """(MiB, seconds) of a `frames`-frame walk with n Gaussians written as animate writes it."""
    from dlacli.body.builtin_motions import builtin_motion
    from dlacli.stages.animate import pose_avatar, write_animation
    from dlacli.types import Motion

    walk = builtin_motion("walk")
    idx = np.arange(frames) % walk.num_frames
    clip = Motion(walk.bone_labels, walk.rotations[idx], walk.root_rotation[idx], walk.root_translation[idx], walk.fps)
    anim = pose_avatar(avatar, clip, n)
    path = folder / f"budget_{n}.usdc"
    t0 = time.perf_counter()
    write_animation(anim, path, "points", 0.001)
    seconds = time.perf_counter() - t0
    size = path.stat().st_size / 2**20
    path.unlink()
    return size, seconds


def run(
    seeds: list[int],
    counts: list[int],
    uv_resolutions: list[int],
    render_size: int = 512,
    method: MethodSpec | None = None,
    novel_views: int = 4,
    novel_poses: int = 2,
    usd_frames: int = 8,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Budget rows (dlacli.bench.rows "budget") for every seed x UV resolution x count x split;
    `method`: a stages.methods spec that takes `resolution` (default: unproject)."""
    from dlacli.bench.rows import budget_row, default_device
    from dlacli.bench.score import scores
    from dlacli.bench.stability import make_subject
    from dlacli.stages.budget import AUTO_VIEWS, sampling_noise
    from dlacli.stages.lift.methods import make_spec
    from dlacli.stages.render import turntable_cameras

    spec = method or make_spec("unproject")
    cfg = spec.options()
    device = default_device()
    counts = sorted(set(counts))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            subject = make_subject(seed, render_size, novel_views, novel_poses)
            splits = (
                ("inputs", subject.views, None),
                ("novel_views", subject.novel_views, None),
                ("novel_poses", subject.novel_poses, subject.motion),
            )
            for res in uv_resolutions:
                t0 = time.perf_counter()
                avatar = spec.with_options(resolution=res).lift(subject.views).avatar
                lift_s = time.perf_counter() - t0
                noise = sampling_noise(avatar, turntable_cameras(avatar, AUTO_VIEWS, render_size), counts)
                for n in counts:
                    usd_mib, usd_s = _usd_cost(avatar, n, usd_frames, Path(tmp)) if usd_frames else (None, None)
                    line = []
                    for split, views, motion in splits:
                        pred, gt, per_image = _timed_split(avatar, views, n, motion)
                        metrics = scores(pred, gt, views.masks)
                        rows.append(
                            budget_row(
                                spec.name,
                                {**cfg, "uv_resolution": res, "usd_frames": usd_frames},
                                split,
                                lift_s,
                                metrics,
                                n,
                                render_size,
                                per_image * 1e3,
                                usd_mib,
                                usd_s,
                                noise[n],
                                subject=seed,
                                device=device,
                            )
                        )
                        line.append(f"{split} {metrics['psnr_masked']:.2f}")
                    usd = f", USD {usd_mib:.1f} MiB" if usd_mib is not None else ""
                    log(
                        f"seed {seed} uv {res} n {n}: masked PSNR {', '.join(line)}; {per_image * 1e3:.0f} "
                        f"ms/image{usd}"
                    )
    return rows


# ------------------------------------------------------------------------------ summary


def curve(rows: list[dict], split: str, metric: str = "psnr_masked") -> dict[tuple[str, int], dict[int, dict]]:
    """{(method and setting, uv_resolution): {count: {value (mean over subjects), render_ms,
    usd_mib (medians), noise (mean)}}} of the budget rows on `split`."""
    from dlacli.bench.rows import label

    groups: dict[tuple[str, int], dict[int, list[dict]]] = {}
    for r in rows:
        if r.get("kind") == "budget" and r["split"] == split:
            key = (label(r, ("uv_resolution", "usd_frames")), int(r["config"].get("uv_resolution", 0)))
            groups.setdefault(key, {}).setdefault(r["gaussians"], []).append(r)
    out = {}
    for key, by_n in sorted(groups.items()):
        out[key] = {}
        for n, rs in sorted(by_n.items()):
            usd = [r["usd_mib"] for r in rs if r["usd_mib"] is not None]
            noise = [r["noise"] for r in rs if r["noise"] is not None]
            out[key][n] = {
                "value": statistics.fmean(r["metrics"][metric] for r in rs),
                "render_ms": statistics.median(r["render_ms"] for r in rs),
                "usd_mib": statistics.median(usd) if usd else None,
                "noise": statistics.fmean(noise) if noise else None,
                "subjects": len(rs),
            }
    return out


def choices(rows: list[dict], tolerance_db: float | None = None) -> dict[tuple[str, int], dict[str, int]]:
    """Per (method and setting, uv_resolution): the count each rule picks from the rows' means: "novel views"
    and "novel poses" (ground truth the method never saw: the oracle), "inputs" (lift --gaussians
    auto), "self-consistency" (sampling noise, stages.budget.predicted_psnr)."""
    from dlacli.stages.budget import TOLERANCE_DB, choose_gaussians, predicted_psnr

    tol = TOLERANCE_DB if tolerance_db is None else tolerance_db
    out: dict[tuple[str, int], dict[str, int]] = {}
    for split, name in (("novel_views", "novel views"), ("novel_poses", "novel poses"), ("inputs", "inputs")):
        for key, by_n in curve(rows, split).items():
            out.setdefault(key, {})[name] = choose_gaussians({n: p["value"] for n, p in by_n.items()}, tol)
            if split == "inputs" and all(p["noise"] is not None for p in by_n.values()):
                out[key]["self-consistency"] = choose_gaussians(
                    predicted_psnr({n: p["noise"] for n, p in by_n.items()}), tol
                )
    return out
