"""`dla train`: the learned method trained end to end through skinning and splatting.

One step, per item of the batch (docs/architecture.md "The method", Training):
  1. the U-Net G turns the 4 input views into pixel-aligned Gaussians; L_UG renders them at the
     input cameras and at the item's same-pose targets (L1 + mask);
  2. the encoder maps them into Z (posterior mean + noise, KL to N(0, I));
  3. the GPD decodes F = F_c + F_delta for each target's pose and camera; its Gaussians are skinned
     onto the target body and splatted at the target camera;
  4. losses against the target: L1, mask, perceptual (nn/losses.perceptual_loss), LSGAN with a
     PatchGAN discriminator, KL on Z, ||F_delta||^2.
Schedule: stage "low" (targets at low_size, L_UG + L1 only), then stage "full" (full_size, every
loss). Adam betas (0.5, 0.9); lr 1e-4 generator, 1e-6 discriminator (the paper's; presets for
CPU may raise them, and the run records what it used).

Data parallel: run under `torchrun --nproc_per_node K dla train ...` (gloo on CPU, nccl on CUDA).
Each step draws one global batch of batch x K items from (seed, step); rank r takes items
r*batch ... (r+1)*batch - 1 and its noise is seeded per global item, so K processes give the
same update as one process with the combined batch (DistributedDataParallel averages gradients;
every loss is a mean over items). Only rank 0 writes.

The run folder (formats/train-run.md):
  train.json          dla.train/1: settings, step, the loss history, validation scores, the latest checkpoint
  ckpt-<step>/generator/      dla.checkpoint/1 of LearnedAvatarNet (+ its Adam state)
  ckpt-<step>/discriminator/  dla.checkpoint/1 of PatchDiscriminator (+ its Adam state)
  loss.png            the loss curves
  val/step_<step>.png ground truth above prediction for validation subjects (novel view, novel pose)
`--resume` continues from train.json's checkpoint: same settings, same data order, same curve.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dlacli.errors import DlaInputError

FORMAT = "dla.train/1"
STAGES = ("low", "full")


@dataclass
class TrainConfig:
    preset: str = "tiny"
    variant: str = "full"
    batch: int = 2  # items per process per step
    targets: int = 2  # target images per item
    steps_low: int = 100  # stage "low": L_UG + L1 at low_size
    steps_full: int = 100  # stage "full": every loss at full_size
    low_size: int = 64
    full_size: int = 128
    lr_g: float = 1e-4
    lr_d: float = 1e-6
    betas: tuple[float, float] = (0.5, 0.9)
    w_l1: float = 1.0
    w_mask: float = 1.0
    w_perceptual: float = 0.2
    w_gan: float = 0.01
    w_kl: float = 1e-4
    w_delta: float = 0.01
    w_ug: float = 1.0
    validation: int = 2  # subjects held out of training (by seed order)
    eval_every: int = 50
    checkpoint_every: int = 50
    seed: int = 0
    alexnet: str = ""  # local AlexNet weights for the perceptual term ("" = the MS-SSIM substitute)
    gaussians: int = 0  # Gaussians sampled from F (0: the preset's)
    include_inputs: bool = False  # the input views may also be drawn as decoder targets

    @property
    def total_steps(self) -> int:
        return self.steps_low + self.steps_full

    def stage_at(self, step: int) -> str:
        return "low" if step < self.steps_low else "full"


# ------------------------------------------------------------------------------ distributed


@dataclass
class World:
    rank: int = 0
    size: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_world() -> World:
    """torchrun's environment -> the process group (gloo on CPU, nccl on CUDA); one process without."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    cuda = torch.cuda.is_available()
    local = int(os.environ.get("LOCAL_RANK", "0"))
    device = torch.device("cuda", local) if cuda else torch.device("cpu")
    if size > 1:
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group("nccl" if cuda else "gloo")
        if cuda:
            torch.cuda.set_device(device)
        return World(dist.get_rank(), dist.get_world_size(), device)
    return World(0, 1, device)


def all_reduce_mean(values: dict[str, float], world: World) -> dict[str, float]:
    if world.size == 1:
        return values
    import torch.distributed as dist

    keys = sorted(values)
    t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=world.device)
    dist.all_reduce(t)
    return {k: float(v) / world.size for k, v in zip(keys, t.tolist())}


# ------------------------------------------------------------------------------ the step


class GeneratorLoss(nn.Module):
    """The generator's losses for a list of items (what DistributedDataParallel wraps)."""

    def __init__(self, net, cfg: TrainConfig, alexnet=None):
        super().__init__()
        self.net = net
        self.cfg = cfg
        self.alexnet = alexnet

    def forward(self, items, stage: str, size: int, noise_seeds: list[int], disc=None):
        from dlacli.avatar.codec import Decoded
        from dlacli.avatar.posed import PosedAvatar, render_set
        from dlacli.nn.encoder import kl_divergence
        from dlacli.nn.learned import subject_depth
        from dlacli.nn.losses import perceptual_loss

        net, cfg = self.net, self.cfg
        device = next(net.parameters()).device
        rgb = torch.stack([it.input_rgb for it in items]).to(device)
        cams = [it.input_cameras.to(device) for it in items]
        depth = torch.stack([subject_depth(c, it.input_vertices) for c, it in zip(cams, items)]).to(device)
        g, feats = net.reconstruct(rgb, cams, depth)
        mean, logvar = net.encode(
            g,
            feats,
            net.uv_positions(torch.stack([it.input_vertices for it in items]).to(device)),
            mask=torch.stack([it.input_mask for it in items]).to(device),
        )
        parts = {k: [] for k in ("l1", "mask", "ug", "perceptual", "gan", "kl", "delta")}
        fakes, reals = [], []
        for b, it in enumerate(items):
            gen = torch.Generator(device=device).manual_seed(int(noise_seeds[b]))
            eps = torch.randn(mean[b].shape, generator=gen, device=device, dtype=mean.dtype)
            z = mean[b] + torch.exp(0.5 * logvar[b]) * eps
            parts["kl"].append(kl_divergence(mean[b : b + 1], logvar[b : b + 1]))
            # L_UG: the U-Net's own Gaussians at the input views and the same-pose targets
            from dlacli.types import Gaussians

            pg = Gaussians.from_rgb(g.means[b], g.quats[b], g.scales[b], g.opacities[b], g.rgb[b])
            in_cams = it.input_cameras.resized(size, size).to(device)
            in_rgb = _resize(it.input_rgb, size).to(device)
            in_mask = _resize(it.input_mask, size).to(device)
            ug = render_set(pg, in_cams)
            ug_l = (ug.rgb - in_rgb.permute(0, 2, 3, 1)).abs().mean() + (ug.alpha - in_mask[:, 0]).abs().mean()
            t_rgb = _resize(it.target_rgb, size).to(device)  # [T, 3, H, H]
            t_mask = _resize(it.target_mask, size).to(device)
            t_cams = it.target_cameras.resized(size, size).to(device)
            same = [t for t, kind in enumerate(it.target_kind) if kind == "view"]
            if same:
                sel = torch.tensor(same)
                ug2 = render_set(pg, t_cams.select(sel))
                ug_l = (
                    ug_l
                    + (ug2.rgb - t_rgb[sel].permute(0, 2, 3, 1)).abs().mean()
                    + (ug2.alpha - t_mask[sel, 0]).abs().mean()
                )
            parts["ug"].append(ug_l)
            # the decoder's render of every target: F_c once, F_delta per target body and camera
            verts = it.target_vertices.to(device).float()  # [T, V, 3]
            one_each = [t_cams.select(t) for t in range(len(it.target_kind))]  # one camera per target body
            posed = PosedAvatar(Decoded.of(net, z, it.rest_vertices), net.samples, verts, one_each)
            preds, alphas, deltas = [], [], []
            for t in range(len(it.target_kind)):
                out = posed.render(t, deltas=deltas)
                preds.append(out.rgb[0])
                alphas.append(out.alpha[0])
            pred, alpha = torch.stack(preds), torch.stack(alphas)  # [T, H, W, 3], [T, H, W]
            delta = torch.cat(deltas) if net.conditioned else torch.zeros((), device=device)  # [T, 14, R, R]
            gt = t_rgb.permute(0, 2, 3, 1)
            gm_ = t_mask[:, 0]
            parts["l1"].append((pred - gt).abs().mean())
            parts["mask"].append((alpha - gm_).abs().mean())
            parts["delta"].append((delta**2).mean())
            if stage == "full":
                parts["perceptual"].append(perceptual_loss(pred, gt, gm_, self.alexnet))
                if disc is not None:
                    from dlacli.nn.discriminator import lsgan_generator_loss

                    parts["gan"].append(lsgan_generator_loss(disc(pred.permute(0, 3, 1, 2))))
            fakes.append(pred.detach())
            reals.append(gt)
        avg = {k: torch.stack(v).mean() for k, v in parts.items() if v}
        w = {"l1": cfg.w_l1, "ug": cfg.w_ug}
        if stage == "full":
            w.update(mask=cfg.w_mask, perceptual=cfg.w_perceptual, gan=cfg.w_gan, kl=cfg.w_kl, delta=cfg.w_delta)
        total = sum(w[k] * avg[k] for k in w if k in avg)
        return total, {k: float(v.detach()) for k, v in avg.items()}, torch.cat(fakes), torch.cat(reals)


def _resize(x: torch.Tensor, size: int) -> torch.Tensor:
    """[N, C, h, w] -> [N, C, size, size] (area when shrinking)."""
    import torch.nn.functional as nnf

    if x.shape[-1] == size:
        return x
    return nnf.interpolate(x, size=(size, size), mode="area" if x.shape[-1] > size else "bilinear")


class DiscriminatorLoss(nn.Module):
    def __init__(self, disc):
        super().__init__()
        self.disc = disc

    def forward(self, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
        from dlacli.nn.discriminator import lsgan_discriminator_loss

        return lsgan_discriminator_loss(self.disc(real.permute(0, 3, 1, 2)), self.disc(fake.permute(0, 3, 1, 2)))


# ------------------------------------------------------------------------------ the run


def _settings(cfg: TrainConfig, data: str) -> dict:
    d = asdict(cfg)
    d["betas"] = list(cfg.betas)
    d["data"] = data
    return d


def global_batch(cfg: TrainConfig, step: int, n_train: int, world: World) -> tuple[list[int], list[int]]:
    """(subject indices, noise seeds) of this rank's share of step `step`'s global batch."""
    rng = np.random.default_rng([cfg.seed, step])
    total = cfg.batch * world.size
    picks = rng.integers(0, n_train, size=total)
    lo = world.rank * cfg.batch
    mine = list(range(lo, lo + cfg.batch))
    return [int(picks[j]) for j in mine], mine


def train(
    data: str | os.PathLike,
    out: str | os.PathLike,
    cfg: TrainConfig,
    *,
    resume: bool = False,
    until: int | None = None,
    log=None,
) -> dict:
    """Train (or resume) a run; returns train.json's content. `until`: stop (with a checkpoint)
    after that many steps in all, to be resumed later."""
    from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
    from dlacli.nn.discriminator import PatchDiscriminator
    from dlacli.nn.discriminator import preset as disc_preset
    from dlacli.nn.learned import LearnedAvatarNet, learned_config
    from dlacli.nn.losses import load_alexnet
    from dlacli.train.data import TrainingData, split_subjects

    world = init_world()
    say = (log or (lambda line: print(line, file=sys.stderr, flush=True))) if world.main else (lambda line: None)
    out = Path(out)
    record_path = out / "train.json"
    train_ids, val_ids = split_subjects(data, cfg.validation)
    if not train_ids:
        raise DlaInputError(data, f"has no training subjects after holding out {cfg.validation} for validation")
    lcfg = learned_config(cfg.preset, cfg.variant)
    if cfg.gaussians:
        from dataclasses import replace

        lcfg = replace(lcfg, gaussians=int(cfg.gaussians))
    torch.manual_seed(cfg.seed)
    net = LearnedAvatarNet(lcfg).to(world.device)
    disc = PatchDiscriminator(disc_preset(cfg.preset)).to(world.device)
    opt_g = torch.optim.Adam(net.parameters(), lr=cfg.lr_g, betas=tuple(cfg.betas))
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr_d, betas=tuple(cfg.betas))
    settings = _settings(cfg, str(data))
    if not resume:
        start_run(out)
    record = resumed_record(record_path, settings) if resume else new_record(settings, world, train_ids, val_ids)
    if record["checkpoint"]:
        ck = out / record["checkpoint"]
        lg, ld = (
            load_checkpoint(ck / "generator", map_location=world.device),
            load_checkpoint(ck / "discriminator", map_location=world.device),
        )
        net.load_state_dict(lg.module.state_dict())
        disc.load_state_dict(ld.module.state_dict())
        opt_g.load_state_dict(lg.optimizer_state)
        opt_d.load_state_dict(ld.optimizer_state)
    alexnet = load_alexnet(cfg.alexnet).to(world.device) if cfg.alexnet else None
    g_loss, d_loss = GeneratorLoss(net, cfg, alexnet), DiscriminatorLoss(disc)
    if world.size > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        g_run, d_run = DDP(g_loss, find_unused_parameters=True), DDP(d_loss, find_unused_parameters=True)
    else:
        g_run, d_run = g_loss, d_loss
    full = TrainingData(
        data, lcfg.unet.image_size, cfg.full_size, cfg.targets, subjects=train_ids, include_inputs=cfg.include_inputs
    )
    val = (
        TrainingData(data, lcfg.unet.image_size, cfg.full_size, cfg.targets, subjects=val_ids, include_inputs=False)
        if val_ids
        else None
    )
    full.item(0, np.random.default_rng(0))  # bad data fails here, before anything is written
    if val is not None:
        val.item(0, np.random.default_rng(0))
    if world.main:
        out.mkdir(parents=True, exist_ok=True)
    start = int(record["step"])
    t_start = time.perf_counter() - float(record["seconds"])
    net.train()
    disc.train()
    stop = cfg.total_steps if until is None else min(int(until), cfg.total_steps)
    for step in range(start, stop):
        stage = cfg.stage_at(step)
        size = cfg.low_size if stage == "low" else cfg.full_size
        picks, slots = global_batch(cfg, step, len(full), world)
        items = [full.item(i, np.random.default_rng([cfg.seed, step, s, 1])) for i, s in zip(picks, slots)]
        noise = [int(np.random.default_rng([cfg.seed, step, s, 2]).integers(2**62)) for s in slots]
        use_d = stage == "full" and cfg.w_gan > 0
        disc.requires_grad_(False)
        opt_g.zero_grad(set_to_none=True)
        total, parts, fake, real = g_run(items, stage, size, noise, disc if use_d else None)
        total.backward()
        opt_g.step()
        if use_d:
            disc.requires_grad_(True)
            opt_d.zero_grad(set_to_none=True)
            ld = d_run(real, fake)
            ld.backward()
            opt_d.step()
            parts["disc"] = float(ld.detach())
        parts["total"] = float(total.detach())
        parts = all_reduce_mean(parts, world)
        entry = {"step": step + 1, "stage": stage, **{k: round(v, 6) for k, v in sorted(parts.items())}}
        record["history"].append(entry)
        record["step"] = step + 1
        record["seconds"] = time.perf_counter() - t_start
        if world.main and ((step + 1) % 10 == 0 or step + 1 == cfg.total_steps or step == start):
            say(
                f"step {step + 1}/{cfg.total_steps} [{stage}] loss {parts['total']:.4f} (l1 {parts['l1']:.4f}, "
                f"ug {parts['ug']:.4f}) {record['seconds']:.0f} s"
            )
        last = step + 1 == cfg.total_steps
        if val is not None and ((step + 1) % cfg.eval_every == 0 or last):
            scores, picture = validate(net, val, size=cfg.full_size, seed=cfg.seed)
            if world.main:
                record["validation"].append({"step": step + 1, **scores})
                save_png(out / "val" / f"step_{step + 1:06d}.png", picture)
                say(
                    f"validation at step {step + 1}: masked PSNR {scores['psnr_masked']:.2f} dB, "
                    f"whole {scores['psnr']:.2f} dB, IoU {scores['iou']:.3f}"
                )
            net.train()
        if world.main and ((step + 1) % cfg.checkpoint_every == 0 or last or step + 1 == stop):
            name = f"ckpt-{step + 1:06d}"
            extra = {"train": {"step": step + 1, "preset": cfg.preset, "variant": cfg.variant, "data": str(data)}}
            tmp = out / (name + ".partial")
            shutil.rmtree(tmp, ignore_errors=True)
            save_checkpoint(tmp / "generator", net, lcfg, step=step + 1, optimizer=opt_g, extra=extra)
            save_checkpoint(tmp / "discriminator", disc, disc.config, step=step + 1, optimizer=opt_d, extra=extra)
            shutil.rmtree(out / name, ignore_errors=True)
            tmp.rename(out / name)
            old = record["checkpoint"]
            record["checkpoint"] = name
            write_record(record_path, record)
            if old and old != name:
                shutil.rmtree(out / old, ignore_errors=True)
            draw_losses(record, out / "loss.png")
    if world.size > 1:
        import torch.distributed as dist

        dist.barrier()
    return record


# ------------------------------------------------------------------------------ evaluation


@torch.no_grad()
def validate(net, data, size: int, seed: int = 0, subjects: int = 2):
    """Masked and whole-image PSNR and alpha IoU of the decoder's renders on validation items (the
    posterior mean, no noise), and a picture: ground truth above prediction per target."""
    from dlacli.nn.learned import subject_depth
    from dlacli.stages.lift.learned import render_targets

    net.eval()
    psnr, psnr_m, iou, tiles_gt, tiles_pred = [], [], [], [], []
    for i in range(min(subjects, len(data))):
        it = data.item(i, np.random.default_rng([seed, 7, i]))
        cams = it.input_cameras
        g, feats = net.reconstruct(it.input_rgb[None], [cams], subject_depth(cams, it.input_vertices)[None])
        mean, _ = net.encode(g, feats, net.uv_positions(it.input_vertices[None]), mask=it.input_mask[None])
        t_cams = it.target_cameras.resized(size, size)
        for t in range(len(it.target_kind)):
            pred, alpha = render_targets(net, mean[0], it.target_vertices[t], it.rest_vertices, t_cams.select(t))
            gt = _resize(it.target_rgb[t : t + 1], size)[0].permute(1, 2, 0)
            m = _resize(it.target_mask[t : t + 1], size)[0, 0]
            psnr.append(masked_psnr(pred[0], gt, None))
            psnr_m.append(masked_psnr(pred[0], gt, m))
            inter = torch.minimum(alpha[0], m).sum()
            union = torch.maximum(alpha[0], m).sum().clamp_min(1e-9)
            iou.append(float(inter / union))
            tiles_gt.append(gt.numpy())
            tiles_pred.append(pred[0].clamp(0, 1).numpy())
    picture = np.concatenate([np.concatenate(tiles_gt, axis=1), np.concatenate(tiles_pred, axis=1)], axis=0)
    return {"psnr": float(np.mean(psnr)), "psnr_masked": float(np.mean(psnr_m)), "iou": float(np.mean(iou))}, picture


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> float:
    err = (pred.clamp(0, 1) - gt) ** 2
    if mask is not None:
        w = (mask > 0.5).float()[..., None].expand_as(err)
        mse = float((err * w).sum() / w.sum().clamp_min(1.0))
    else:
        mse = float(err.mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


# ------------------------------------------------------------------------------ files


def _read_record(path: Path) -> dict:
    """train.json of the run to resume, through the guarded JSON reader (io.validate.load_json),
    with the shape this loop relies on checked before use; the checkpoint it names must be a
    folder name train writes (ckpt-NNNNNN), never a path that leads elsewhere."""
    from dlacli.errors import excerpt
    from dlacli.io.validate import as_float, load_json

    rec = load_json(path)
    if not isinstance(rec, dict) or rec.get("format") != FORMAT:
        raise DlaInputError(path, f"not a {FORMAT} run record")
    if not isinstance(rec.get("settings"), dict):
        raise DlaInputError(path, "'settings' must be an object")
    step = rec.get("step")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise DlaInputError(path, f"'step' must be a whole number >= 0, found {excerpt(step)}")
    if as_float(rec.get("seconds"), path, "seconds") < 0:
        raise DlaInputError(path, "'seconds' must be >= 0")
    name = rec.get("checkpoint")
    if name is not None and not (isinstance(name, str) and re.fullmatch(r"ckpt-\d{6,9}", name)):
        problem = f"'checkpoint' must be null or a checkpoint folder name (ckpt-NNNNNN), found {excerpt(name)}"
        raise DlaInputError(path, problem)
    for key in ("history", "validation"):
        entries = rec.get(key)
        ok = isinstance(entries, list) and all(
            isinstance(e, dict)
            and _is_number(e.get("step"))
            and all(isinstance(v, str) or _is_number(v) for v in e.values())
            for e in entries
        )
        if not ok:
            raise DlaInputError(path, f"'{key}' must be a list of objects holding a 'step' and numbers")
    return rec


def new_record(settings: dict, world: World, train_ids: list, val_ids: list) -> dict:
    """train.json's content before the first step (formats/train-run.md)."""
    return {
        "format": FORMAT,
        "settings": settings,
        "step": 0,
        "history": [],
        "validation": [],
        "checkpoint": None,
        "seconds": 0.0,
        "world_size": world.size,
        "train_subjects": train_ids,
        "validation_subjects": val_ids,
    }


def start_run(out: Path) -> None:
    """A new run needs a new or empty folder (one-line error otherwise)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DlaInputError(out, "exists and is not an empty folder (use --resume to continue a run, or a new folder)")


def resumed_record(record_path: Path, settings: dict) -> dict:
    """train.json of a run to resume, refused (one line) when it was trained with other settings."""
    record = _read_record(record_path)
    if record["settings"] != settings:
        diff = sorted(k for k in settings if record["settings"].get(k) != settings[k])
        raise DlaInputError(
            record_path, f"was trained with other settings ({', '.join(diff)}); resume with the same ones"
        )
    return record


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def write_record(path: Path, record: dict) -> None:
    from dlacli.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")


def save_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    from dlacli.io.atomic import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp, format="PNG")


def draw_losses(record: dict, path: Path) -> None:
    """The loss curves (log y) and validation masked PSNR of a run record, as a PNG."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return  # the curves are also in train.json; the PNG needs the `train` extra
    from dlacli.io.atomic import atomic_path

    hist = record["history"]
    steps = [h["step"] for h in hist]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    for key in ("total", "l1", "ug", "mask", "ssim", "perceptual", "gan", "kl", "delta", "disc"):
        pts = [(h["step"], h[key]) for h in hist if key in h and h[key] > 0]
        if pts:
            ax.plot(*zip(*pts), label=key, lw=1)
    low = record["settings"].get("steps_low", 0)
    if 0 < low < (steps[-1] if steps else 0):
        ax.axvline(low, color="grey", ls=":", lw=1)
        ax.text(low, ax.get_ylim()[1] if ax.has_data() else 1, " full", va="top", fontsize=8, color="grey")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title("training losses")
    ax.legend(fontsize=7, ncol=2)
    val = record.get("validation", [])
    if val:
        bx.plot([v["step"] for v in val], [v["psnr_masked"] for v in val], "o-", label="masked PSNR")
        bx.plot([v["step"] for v in val], [v["psnr"] for v in val], "s-", label="whole-image PSNR")
        bx.legend(fontsize=8)
    bx.set_xlabel("step")
    bx.set_ylabel("dB")
    bx.set_title("validation (held-out subjects)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
