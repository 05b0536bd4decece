"""Accuracy against cost of the CPU pipeline on synthetic subjects (synth -> lift -> render).

For each seed and each number of refinement steps: lift the 4 input views, then score renders of
the avatar against ground truth on the subject's novel views (same pose, other cameras) and novel
poses (other poses from the motion, fixed cameras): PSNR over the whole image on black, PSNR
inside the person's mask, SSIM, alpha IoU; with the lift wall time. Also times `animate` for a
120-frame motion (posing + USD). Seeds should be ones that appear in no test.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dlacli.bench.score import METRICS, score_split

_score = score_split  # the name tests/stages score lifts with


def run(
    seeds: list[int],
    steps: list[int],
    res: int = 512,
    novel_views: int = 12,
    novel_poses: int = 8,
    animate_frames: int = 120,
    log: Callable[[str], None] = print,
) -> dict:
    from dlacli.body.builtin_motions import builtin_motion
    from dlacli.data.synth import synth
    from dlacli.io.motion import read_motion
    from dlacli.io.views import read_views
    from dlacli.stages.animate import pose_avatar, write_animation
    from dlacli.stages.lift.methods import make_spec

    rows = []
    animate_s = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            folder = synth(seed, Path(tmp) / f"s{seed}", res=res, novel_views=novel_views, novel_poses=novel_poses)
            views = read_views(folder)
            nv = read_views(folder / "novel_views", require_body=False)
            npose = read_views(folder / "novel_poses", require_body=False)
            motion = read_motion(folder / "novel_poses" / "motion.npz")
            for n_steps in steps:
                t0 = time.perf_counter()
                avatar = make_spec("unproject", steps=n_steps).lift(views).avatar
                lift_s = time.perf_counter() - t0
                row = {
                    "seed": seed,
                    "steps": n_steps,
                    "lift_s": lift_s,
                    "novel_views": score_split(avatar, nv),
                    "novel_poses": score_split(avatar, npose, motion),
                }
                rows.append(row)
                log(
                    f"seed {seed} steps {n_steps}: lift {lift_s:.1f} s, novel views {row['novel_views']}, novel "
                    f"poses {row['novel_poses']}"
                )
            walk = builtin_motion("walk")
            idx = np.arange(animate_frames) % walk.num_frames
            from dlacli.types import Motion

            clip = Motion(
                walk.bone_labels, walk.rotations[idx], walk.root_rotation[idx], walk.root_translation[idx], walk.fps
            )
            t0 = time.perf_counter()
            anim = pose_avatar(avatar, clip)
            write_animation(anim, Path(tmp) / "anim.usdc")
            animate_s.append(time.perf_counter() - t0)
            log(f"seed {seed}: animate {animate_frames} frames + USD {animate_s[-1]:.1f} s")
    summary = {}
    for n_steps in steps:
        sel = [r for r in rows if r["steps"] == n_steps]
        summary[str(n_steps)] = {
            "lift_s_median": statistics.median(r["lift_s"] for r in sel),
            **{
                f"{split}_{k}_mean": float(np.mean([r[split][k] for r in sel]))
                for split in ("novel_views", "novel_poses")
                for k in METRICS
            },
        }
    return {
        "rows": rows,
        "summary": summary,
        "animate_s_median": statistics.median(animate_s),
        "animate_frames": animate_frames,
        "res": res,
    }


def markdown_table(result: dict) -> str:
    """The summary as a markdown table (one row per number of steps)."""
    head = (
        "| steps | lift s (median) | novel views PSNR / masked / SSIM / IoU | novel poses PSNR / masked / SSIM / "
        "IoU |\n"
        "|---|---|---|---|"
    )
    lines = [head]
    for steps, s in result["summary"].items():
        nv = " / ".join(f"{s[f'novel_views_{k}_mean']:.{2 if k.startswith('psnr') else 3}f}" for k in METRICS)
        npose = " / ".join(f"{s[f'novel_poses_{k}_mean']:.{2 if k.startswith('psnr') else 3}f}" for k in METRICS)
        lines.append(f"| {steps} | {s['lift_s_median']:.1f} | {nv} | {npose} |")
    return "\n".join(lines)


def result_rows(result: dict) -> list[dict]:
    """The run as `dla.bench/1` rows (dlacli.bench.rows): one per subject, steps setting and
    split; method "unproject" (stages.methods) with its steps."""
    from dlacli.bench.rows import make_row

    rows = []
    for r in result["rows"]:
        for split in ("novel_views", "novel_poses"):
            rows.append(
                make_row(
                    "unproject",
                    {"steps": r["steps"], "res": result["res"]},
                    split,
                    r["lift_s"],
                    None,
                    r[split],
                    subject=r["seed"],
                )
            )
    return rows
