"""`dla bench accuracy`: every method on held-out synthetic subjects, the paper's protocol.

Each seed becomes a `dla synth` subject (by default lit, in the held-out wardrobe: garments no
training subject wore) at 512² on black. Every method lifts its 4 input views in a fresh process
(wall time of the lift alone, and the child's peak resident memory), then its avatar is scored on
the paper's three splits:

    novel_views      the input pose from 12 other cameras
    novel_poses      8 other poses seen from the front input camera (azimuth 0)
    novel_view_pose  the same 8 poses from azimuths 120 and 240 (no input camera there)

With `--input photo` (bench/single_photo.run_photo) the subject's view 0 alone goes through
`dla dream` (one or more backends) before the lift, and the splits are scored in the dream's world
aligned to the subject's through the bodies, plus the dreamed views themselves.

Metrics: PSNR over the whole image, PSNR inside the person's mask, SSIM, alpha IoU
(bench/score.py). LPIPS needs AlexNet weights the toolkit does not ship: it is absent, and the
report says so. Methods (`--methods`) are specs of dlacli.stages.lift.methods, e.g.

    unproject                              mesh unprojection (ablation A.i)
    unproject:steps=50,render_size=256     + 50 refinement steps rendering at 256 px
    learned:checkpoint=CKPT,steps=20       the learned encoder + GPD from a checkpoint, + 20 steps of Z

(and the older spellings refine:STEPS[@SIZE], learned:CKPT[:STEPS]).
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.stages.lift.methods import MethodSpec

SPLITS = ("novel_views", "novel_poses", "novel_view_pose")
FRONT_AZIMUTH = 0.0  # the novel-pose camera that coincides with an input camera's direction


def _child(spec: MethodSpec, folder: str, out: str, threads: int) -> tuple[float, float]:
    import torch

    from dlacli.io.avatar import write_avatar
    from dlacli.io.views import read_views

    torch.set_num_threads(threads)
    views = read_views(folder)
    t0 = time.perf_counter()
    avatar = spec.lift(views).avatar
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


def score_avatar(avatar, folder: Path) -> dict[str, dict[str, float]]:
    """The avatar's metrics on the subject's three splits."""
    from dlacli.bench.score import render_split, scores
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


def subjects(
    seeds,
    folder: Path,
    res: int,
    novel_views: int,
    novel_poses: int,
    appearance: str,
    wardrobe: str,
    keep: Path | None = None,
):
    """(seed, subject folder) per seed: each synthetic subject written under `folder` as the
    accuracy benchmarks score it (its views, novel views and novel poses). With `keep`, subjects
    live in keep/<settings>/s<seed> instead, and one already complete there is reused (synth is
    deterministic: the same seed and settings give the same files)."""
    from dlacli.data.synth import synth

    if keep is not None:
        folder = Path(keep) / f"{appearance}-{wardrobe}-{res}px-{novel_views}v-{novel_poses}p"
        folder.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        out = folder / f"s{seed}"
        if keep is None or not _complete(out, seed):
            synth(
                seed,
                out,
                res=res,
                novel_views=novel_views,
                novel_poses=novel_poses,
                appearance=appearance,
                wardrobe=wardrobe,
            )
        yield seed, out


def _complete(folder: Path, seed: int) -> bool:
    """Whether `folder` holds the synthetic subject `seed` (synth writes its folder atomically, so
    one that exists is whole)."""
    import json

    try:
        record = json.loads((folder / "transforms.json").read_text())["dla"]["synth"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return record.get("seed") == seed


def run(
    seeds: list[int],
    methods: list[MethodSpec],
    res: int = 512,
    appearance: str = "lit",
    wardrobe: str = "heldout",
    novel_views: int = 12,
    novel_poses: int = 8,
    log: Callable[[str], None] = print,
    keep: Path | None = None,
) -> list[dict]:
    """dla.bench/1 rows: one per seed, method and split (the 4 true views as the input; one photo
    through `dla dream`: bench/single_photo.run_photo). `keep`: a folder the subjects are kept in
    and reused from (`subjects`)."""
    from dlacli.bench.rows import make_row
    from dlacli.io.avatar import read_avatar

    for spec in methods:  # the renders find a learned avatar's decoder by its hash, as after `dla lift`
        spec.install()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed, folder in subjects(seeds, Path(tmp), res, novel_views, novel_poses, appearance, wardrobe, keep):
            for spec in methods:
                path = Path(tmp) / f"s{seed}_{len(rows)}.npz"
                seconds, peak = timed_lift(spec, folder, path)
                avatar = read_avatar(path)
                result = score_avatar(avatar, folder)
                config = {**spec.options(), "res": res, "appearance": appearance, "wardrobe": wardrobe}
                # the weights by hash, not by local path (shipped ones too: rows of two networks
                # must not pool); what they are
                lift = avatar.extra.get("lift", {})
                digest = avatar.checkpoint or avatar.extra.get("residual", {}).get("checkpoint", "")
                named = {"checkpoint": digest[:16], "preset": lift.get("preset"), "variant": lift.get("variant")}
                config.update({k: v for k, v in named.items() if v})
                for split in SPLITS:
                    rows.append(make_row(spec.name, config, split, seconds, peak, result[split], subject=seed))
                log(
                    f"seed {seed} {spec.label}: lift {seconds:.1f} s, {peak:.0f} MB; "
                    + "; ".join(
                        f"{s} {result[s]['psnr_masked']:.2f} dB masked, IoU {result[s]['iou']:.3f}" for s in SPLITS
                    )
                )
                os.unlink(path)
    return rows
