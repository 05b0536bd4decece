"""`dla bench accuracy`: every method on held-out synthetic subjects, the paper's protocol.

Each seed becomes a `dla synth` subject (by default lit, in the held-out wardrobe: garments no
training subject wore) at 512² on black. Every method lifts its 4 input views in a fresh process
(wall time of the lift alone, and the child's peak resident memory), then its avatar is scored on
the paper's three splits:

    novel_views      the input pose from 12 other cameras
    novel_poses      8 other poses seen from the front input camera (azimuth 0)
    novel_view_pose  the same 8 poses from azimuths 120 and 240 (no input camera there)

Metrics: PSNR over the whole image, PSNR inside the person's mask, SSIM, alpha IoU
(bench/metrics.py). LPIPS needs AlexNet weights the toolkit does not ship: it is absent, and the
report says so. Method specs (`--methods`, comma-separated):

    unproject                  mesh unprojection (ablation A.i)
    refine:STEPS[@SIZE]        unprojection + STEPS refinement steps at render size SIZE
    learned:CKPT[:STEPS]       the learned encoder + GPD from a checkpoint, + STEPS refinement of Z
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from dlacli.errors import DlaInputError

SPLITS = ("novel_views", "novel_poses", "novel_view_pose")
FRONT_AZIMUTH = 0.0  # the novel-pose camera that coincides with an input camera's direction


@dataclass(frozen=True)
class MethodSpec:
    name: str  # "unproject", "unproject+refine" or "learned" (+refine)
    config: dict
    label: str  # the spec as the user wrote it


def parse_methods(text: str) -> list[MethodSpec]:
    """`--methods` -> specs; one-line errors naming the bad spec."""
    specs = []
    for raw in [t.strip() for t in text.split(",") if t.strip()]:
        kind, _, rest = raw.partition(":")
        try:
            if kind == "unproject" and not rest:
                specs.append(MethodSpec("unproject", {"steps": 0}, raw))
            elif kind == "refine":
                steps, _, size = rest.partition("@")
                cfg = {"steps": int(steps)}
                if size:
                    cfg["render_size"] = int(size)
                if cfg["steps"] < 1 or cfg.get("render_size", 512) < 16:
                    raise ValueError
                specs.append(MethodSpec("unproject+refine", cfg, raw))
            elif kind == "learned" and rest:
                head, _, tail = rest.rpartition(":")
                ckpt, steps = (head, int(tail)) if head and tail.isdigit() else (rest, 0)
                cfg = {"checkpoint": ckpt, "steps": steps}
                specs.append(MethodSpec("learned" if cfg["steps"] == 0 else "learned+refine", cfg, raw))
            else:
                raise ValueError
        except ValueError:
            raise DlaInputError("--methods", f"cannot read {raw!r} (unproject, refine:STEPS[@SIZE], learned:CKPT[:STEPS])") from None
    if not specs:
        raise DlaInputError("--methods", "is empty")
    return specs


def lift_with(spec: MethodSpec, views):
    """The avatar a method makes from the views (in this process)."""
    if spec.name.startswith("learned"):
        from dlacli.stages.learned import lift_learned

        return lift_learned(views, spec.config["checkpoint"], steps=spec.config["steps"]).avatar
    from dlacli.stages.lift import LiftConfig, lift

    return lift(views, LiftConfig(**spec.config)).avatar


def _child(spec: MethodSpec, folder: str, out: str, threads: int) -> tuple[float, float]:
    import torch

    from dlacli.io.avatar import write_avatar
    from dlacli.io.views import read_views

    torch.set_num_threads(threads)
    views = read_views(folder)
    t0 = time.perf_counter()
    avatar = lift_with(spec, views)
    seconds = time.perf_counter() - t0
    write_avatar(avatar, out)
    return seconds, peak_rss_mb()


def peak_rss_mb() -> float:
    """This process's peak resident set in MB: VmHWM of /proc/self/status (the memory map's own
    high-water mark, which starts afresh at exec), else getrusage (on Linux that maximum is kept
    across exec, so a spawned child would report its parent's peak)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def timed_lift(spec: MethodSpec, folder: Path, out: Path) -> tuple[float, float]:
    """Lift in a fresh process: (seconds of the lift, peak resident MB of that process)."""
    import concurrent.futures as cf
    import multiprocessing as mp

    import torch

    with cf.ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        return pool.submit(_child, spec, str(folder), str(out), torch.get_num_threads()).result()


def split_indices(views) -> dict[str, np.ndarray]:
    """Frames of the novel_poses folder by split (camera azimuth from synth's record)."""
    az = np.asarray(views.extra.get("synth", {}).get("azimuths", []), float)
    if az.size == 0:
        raise DlaInputError("novel_poses", "has no synth camera record")
    cam = np.arange(len(views)) % az.size
    front = np.isclose(((az[cam] - FRONT_AZIMUTH + 180.0) % 360.0) - 180.0, 0.0)
    return {"novel_poses": np.flatnonzero(front), "novel_view_pose": np.flatnonzero(~front)}


def scores(pred: np.ndarray, gt: np.ndarray, masks: np.ndarray) -> dict[str, float]:
    from dlacli.bench.metrics import alpha_iou, masked_psnr, psnr, ssim

    return {"psnr": psnr(pred[..., :3], gt), "psnr_masked": masked_psnr(pred[..., :3], gt, masks),
            "ssim": ssim(pred[..., :3], gt), "iou": alpha_iou(pred[..., 3], masks)}  # fmt: skip


def score_avatar(avatar, folder: Path) -> dict[str, dict[str, float]]:
    """The avatar's metrics on the subject's three splits."""
    from dlacli.bench.pipeline import render_split
    from dlacli.io.motion import read_motion
    from dlacli.io.views import read_views

    out = {}
    nv = read_views(folder / "novel_views", require_body=False)
    pred, gt = render_split(avatar, nv)
    out["novel_views"] = scores(pred, gt, nv.masks)
    npose = read_views(folder / "novel_poses", require_body=False)
    pred, gt = render_split(avatar, npose, read_motion(folder / "novel_poses" / "motion.npz"))
    for split, idx in split_indices(npose).items():
        out[split] = scores(pred[idx], gt[idx], npose.masks[idx])
    return out


def run(seeds: list[int], methods: list[MethodSpec], res: int = 512, appearance: str = "lit",
        wardrobe: str = "heldout", novel_views: int = 12, novel_poses: int = 8,
        log: Callable[[str], None] = print) -> list[dict]:  # fmt: skip
    """dla.bench/1 rows: one per seed, method and split."""
    from dlacli.bench.results import make_row
    from dlacli.data.synth import synth
    from dlacli.io.avatar import read_avatar

    from dlacli.avatar.checkpoint import install_checkpoint, resolve_checkpoint

    for spec in methods:  # the renders find a learned avatar's decoder by its hash, as after `dla lift`
        if "checkpoint" in spec.config:
            install_checkpoint(resolve_checkpoint(spec.config["checkpoint"]))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            folder = synth(seed, Path(tmp) / f"s{seed}", res=res, novel_views=novel_views, novel_poses=novel_poses,
                           appearance=appearance, wardrobe=wardrobe)  # fmt: skip
            for spec in methods:
                path = Path(tmp) / f"s{seed}_{len(rows)}.npz"
                seconds, peak = timed_lift(spec, folder, path)
                avatar = read_avatar(path)
                result = score_avatar(avatar, folder)
                config = {**spec.config, "res": res, "appearance": appearance, "wardrobe": wardrobe}
                if "checkpoint" in config:  # the weights by hash, not by local path; what they are
                    lift = avatar.extra.get("lift", {})
                    config.update(checkpoint=avatar.checkpoint[:16], preset=lift.get("preset"), variant=lift.get("variant"))
                for split in SPLITS:
                    rows.append(make_row(spec.name, config, split, seconds, peak, result[split], subject=seed))
                log(f"seed {seed} {spec.label}: lift {seconds:.1f} s, {peak:.0f} MB; " + "; ".join(
                    f"{s} {result[s]['psnr_masked']:.2f} dB masked, IoU {result[s]['iou']:.3f}" for s in SPLITS))
                os.unlink(path)
    return rows
