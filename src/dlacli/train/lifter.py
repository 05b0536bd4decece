"""Training the pose lifter (`dlacli.nn.lifter`; `dla train --method lifter`, docs/train.md).

Data, made here without rendering:
- poses: every frame (at 30 fps) of the given motion files, retargeted to anny as `dla animate`
  does, and half as many random flexions of the limbs, spine and clavicles (`random_poses`);
- bodies: `SHAPES` random adult phenotypes; each body takes `PER_SHAPE` random poses, and its 17
  COCO keypoints (anny's own regressor) are computed once (`keypoint_bank`);
- views, drawn afresh each step (`LifterViews`): the body turned to a random heading and mirrored
  left-right half of the time, at 1.2-7 m (log-uniform) before a level camera (pitch +-5 degrees,
  height 0.6-1.8 m) with a 40-60 degree vertical field of view, read with the fit's 50 degree
  guess; the keypoints jittered (per body a noise level up to 5 % of the torso's image length, one
  keypoint in 30 five times more) and a non-torso keypoint unseen with probability 0.05.
The loss is the mean squared error of the hip-centred points in torso lengths.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from dlacli.body.keypoints import COCO_MIRROR, HIPS, NUM_KEYPOINTS, SHOULDERS, TORSO, PointRig
from dlacli.body.model import get_body_model
from dlacli.nn.lifter import (
    LifterConfig,
    PoseLifter,
    lifter_inputs,
    lifter_targets,
    save_lifter,
)
from dlacli.stages.fit.photo import FOV_Y_DEG, LIMB_SEGMENTS

SHAPES = 40  # random bodies
PER_SHAPE = 8000  # poses each


def motion_poses(files: Sequence[str | Path], fps: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of the motion files at `fps`, retargeted: rotations [P, J, 3] (rig order) and
    root rotations [P, 3]."""
    from dlacli.stages.motion.source import load_motion

    model = get_body_model()
    rots, roots = [], []
    for f in files:
        m = load_motion(str(f), fps=fps)
        rots.append(model.motion_rotations(m))
        roots.append(np.asarray(m.root_rotation, np.float32))
    return np.concatenate(rots).astype(np.float32), np.concatenate(roots).astype(np.float32)


def random_poses(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n random flexions (independent per pose) of hips, knees, shoulders, elbows, clavicles, spine
    and neck from anny's zero pose, in broad anatomical ranges (radians, anny's local-ref axes)."""
    from scipy.spatial.transform import Rotation

    labels = list(get_body_model().bone_labels)
    rot = np.zeros((n, len(labels), 3), np.float32)

    def put(bone: str, x, y, z) -> None:
        e = np.stack([np.broadcast_to(np.asarray(a, np.float64), (n,)) for a in (x, y, z)], 1)
        rot[:, labels.index(bone)] = Rotation.from_euler("ZYX", e[:, ::-1]).as_rotvec()

    u = lambda lo, hi: rng.uniform(lo, hi, n)  # noqa: E731
    for side, sg in (("L", 1.0), ("R", -1.0)):
        put(f"upperleg01.{side}", u(-1.8, 0.5), sg * u(-0.2, 0.7), u(-0.5, 0.5))
        put(f"lowerleg01.{side}", u(0.0, 2.2), 0.0, 0.0)
        put(f"upperarm01.{side}", u(-1.6, 1.0), sg * u(-1.2, 1.0), u(-0.8, 0.8))
        put(f"lowerarm01.{side}", u(-0.3, 0.3), sg * u(-2.2, 0.0), 0.0)
        put(f"clavicle.{side}", 0.0, -sg * u(-0.1, 0.6), u(-0.2, 0.2))
    put("spine01", u(-0.3, 0.6), u(-0.3, 0.3), u(-0.4, 0.4))
    put("spine05", u(-0.2, 0.5), u(-0.2, 0.2), u(-0.3, 0.3))
    put("neck01", u(-0.4, 0.5), u(-0.3, 0.3), u(-0.6, 0.6))
    root = np.zeros((n, 3), np.float32)
    root[:, 0] = rng.uniform(-0.5, 0.3, n)  # leaning forward or back
    return rot, root


def random_phenotype(rng: np.random.Generator) -> dict[str, float]:
    """An adult's phenotype, broader than the synthetic subjects' (`data.subject.sample_subject`)."""
    return {
        "gender": float(rng.uniform(0.0, 1.0)),
        "age": float(rng.uniform(0.55, 1.0)),
        "muscle": float(rng.uniform(0.1, 0.9)),
        "weight": float(rng.uniform(0.1, 0.9)),
        "height": float(rng.uniform(0.1, 0.8)),
        "proportions": float(rng.uniform(0.2, 0.8)),
    }


@torch.no_grad()
def keypoint_bank(
    rotations: np.ndarray, roots: np.ndarray, shapes: int, per_shape: int, rng: np.random.Generator, chunk: int = 2048
) -> np.ndarray:
    """[shapes * per_shape, 17, 3] world keypoints (anny's axes, root at the origin) of random poses
    of the pool (rotations [P, J, 3], roots [P, 3]) on `shapes` random bodies."""
    rig = PointRig(model=get_body_model())
    out = []
    for _ in range(shapes):
        rig.linearise(random_phenotype(rng))
        pick = rng.integers(len(rotations), size=per_shape)
        for lo in range(0, per_shape, chunk):
            sel = pick[lo : lo + chunk]
            r = torch.from_numpy(rotations[sel])
            pts, _ = rig(None, r, torch.from_numpy(roots[sel]), torch.zeros(len(sel), 3), keypoints_only=True)
            out.append(pts.numpy())
    return np.concatenate(out).astype(np.float32)


class LifterViews:
    """Random views of a keypoint bank [M, 17, 3] (module doc): `sample(batch)` -> (inputs, targets)."""

    def __init__(self, bank: np.ndarray, seed: int) -> None:
        self.bank = torch.from_numpy(bank)
        self.gen = torch.Generator().manual_seed(int(seed))
        self.tan_guess = math.tan(math.radians(FOV_Y_DEG) / 2)

    def _u(self, n: int, lo: float, hi: float) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=self.gen)

    def sample(self, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.gen
        p = self.bank[torch.randint(len(self.bank), (batch,), generator=g)].clone()  # [B, 17, 3]
        flip = torch.rand(batch, generator=g) < 0.5
        p[flip] = p[flip][:, list(COCO_MIRROR)] * torch.tensor([-1.0, 1.0, 1.0])
        hip = p[:, list(HIPS)].mean(1, keepdim=True)
        yaw = self._u(batch, 0.0, 2 * math.pi)
        c, s = torch.cos(yaw), torch.sin(yaw)
        x = p[..., 0] - hip[..., 0]
        y = p[..., 1] - hip[..., 1]
        z = p[..., 2] - p[..., 2].amin(1, keepdim=True)  # feet (lowest keypoint) on the ground
        xr = c[:, None] * x - s[:, None] * y
        yr = s[:, None] * x + c[:, None] * y
        depth = torch.exp(self._u(batch, math.log(1.2), math.log(7.0)))
        tan_half = torch.tan(torch.deg2rad(self._u(batch, 40.0, 60.0)) / 2)
        lateral = self._u(batch, -0.6, 0.6) * depth * tan_half
        cam_h = self._u(batch, 0.6, 1.8)
        cam = torch.stack([xr + lateral[:, None], -(z - cam_h[:, None]), yr + depth[:, None]], -1)  # x, y down, z
        pitch = torch.deg2rad(self._u(batch, -5.0, 5.0))
        cp, sp = torch.cos(pitch)[:, None], torch.sin(pitch)[:, None]
        cam = torch.stack([cam[..., 0], cp * cam[..., 1] - sp * cam[..., 2], sp * cam[..., 1] + cp * cam[..., 2]], -1)
        rays = cam[..., :2] / cam[..., 2:3].clamp(min=0.1) * (self.tan_guess / tan_half)[:, None, None]
        torso_img = (rays[:, list(SHOULDERS)].mean(1) - rays[:, list(HIPS)].mean(1)).norm(dim=-1)  # [B]
        sigma = self._u(batch, 0.0, 0.05) * torso_img
        noise = torch.randn(batch, NUM_KEYPOINTS, 2, generator=g) * sigma[:, None, None]
        noise = noise * torch.where(torch.rand(batch, NUM_KEYPOINTS, 1, generator=g) < 1 / 30, 5.0, 1.0)
        seen = torch.rand(batch, NUM_KEYPOINTS, generator=g) >= 0.05
        seen[:, list(TORSO)] = True
        return lifter_inputs(rays + noise, seen), lifter_targets(cam)


def train_lifter(
    bank: np.ndarray,
    out: Path,
    *,
    steps: int,
    batch: int = 512,
    lr: float = 1e-3,
    seed: int = 0,
    log_every: int = 500,
    val_bank: np.ndarray | None = None,
    width: int = 512,
) -> list[dict]:
    """Adam with a cosine decay; writes `out` (float16 safetensors, `save_lifter`). Every
    `log_every` steps (and at the end) prints and records the mean training loss since the last
    record and the mean limb-angle error on `val_bank` views (degrees); returns the records."""
    torch.manual_seed(seed)
    model = PoseLifter(LifterConfig(width=width))
    views = LifterViews(bank, seed)
    val = LifterViews(val_bank, seed + 1).sample(4096) if val_bank is not None else None
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1), eta_min=lr * 0.02)
    t0, run, history = time.time(), 0.0, []
    for step in range(1, steps + 1):
        x, y = views.sample(batch)
        loss = ((model(x) - y) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        run += loss.item()
        if step % log_every == 0 or step == steps:
            done = step - (history[-1]["step"] if history else 0)
            record = {"step": step, "loss": run / done, "seconds": round(time.time() - t0, 1)}
            msg = f"step {step}/{steps} loss {record['loss']:.4f} {record['seconds']:.0f}s"
            if val is not None:
                record["val_limb_angle_deg"] = limb_angle_error(model, *val)
                msg += f" val limb angle {record['val_limb_angle_deg']:.2f} deg"
            print(msg, file=sys.stderr, flush=True)
            history.append(record)
            run = 0.0
    save_lifter(model, out, {"steps": steps, "batch": batch, "lr": lr, "seed": seed, "poses": int(len(bank))})
    return history


LIMBS = LIMB_SEGMENTS[:8]  # upper and lower arms and legs


@torch.no_grad()
def limb_angle_error(model: PoseLifter, x: torch.Tensor, y: torch.Tensor) -> float:
    """Mean angle (degrees) between predicted and true upper/lower arm and leg directions."""
    was = model.training
    model.eval()
    p = model(x)
    model.train(was)
    a, b = [s[0] for s in LIMBS], [s[1] for s in LIMBS]
    dp = torch.nn.functional.normalize(p[:, b] - p[:, a], dim=-1)
    dy = torch.nn.functional.normalize(y[:, b] - y[:, a], dim=-1)
    return float(torch.rad2deg(torch.acos((dp * dy).sum(-1).clamp(-1, 1))).mean())


def motion_files(folder: Path) -> list[Path]:
    """The motion files of a folder (not its subfolders), sorted by name."""
    from dlacli.stages.motion.source import SUFFIXES

    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES)


def run_lifter_training(
    data: Path, output: Path, *, steps: int, batch: int, lr: float, seed: int, validation: int
) -> Path:
    """`dla train --method lifter`: the motion files of `data` (the first `validation` by name held
    out: their views give the validation limb angle), 40 bodies x 8,000 poses, `steps` of Adam;
    writes OUTPUT/lifter.safetensors and OUTPUT/train.json. Returns the weights' path."""
    import json

    from dlacli.errors import DlaInputError

    if not data.is_dir():
        raise DlaInputError(data, "expected a folder of motion files (.bvh, .amc, .npz)")
    files = motion_files(data)
    if len(files) <= validation:
        raise DlaInputError(data, f"holds {len(files)} motion file(s); more than --validation {validation} are needed")
    if steps < 1:
        raise DlaInputError("--steps-full", "no steps to train")
    held, used = files[:validation], files[validation:]
    rng = np.random.default_rng(seed)
    rot, root = motion_poses(used)
    extra = random_poses(max(len(rot) // 2, 1), rng)
    bank = keypoint_bank(np.concatenate([rot, extra[0]]), np.concatenate([root, extra[1]]), SHAPES, PER_SHAPE, rng)
    val_bank = keypoint_bank(*motion_poses(held), 8, 1000, rng) if held else None
    output.mkdir(parents=True, exist_ok=True)
    path = output / "lifter.safetensors"
    history = train_lifter(bank, path, steps=steps, batch=batch, lr=lr, seed=seed, val_bank=val_bank)
    record = {
        "format": "dla.lifter-run/1",
        "steps": steps,
        "batch": batch,
        "lr": lr,
        "seed": seed,
        "motion_frames": int(len(rot)),
        "random_poses": int(len(extra[0])),
        "train_files": [p.name for p in used],
        "validation_files": [p.name for p in held],
        "history": history,
    }
    (output / "train.json").write_text(json.dumps(record, indent=1))
    return path


def train_from_options(data: Path, output: Path, o) -> Path:
    """`dla train --method lifter` (train/methods.py): 20,000 steps, batch 512, lr 1e-3 unless given."""
    steps, batch, lr = o.get("steps_full"), o.get("batch"), o.get("lr_g")
    return run_lifter_training(
        data, output, steps=20_000 if steps is None else steps, batch=batch or 512, lr=lr or 1e-3, seed=o["seed"],
        validation=o["validation"],
    )  # fmt: skip
