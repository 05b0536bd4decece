"""`dla train --method residual`: the residual lift's network (nn/residual.py) trained through
skinning and splatting on novel views and novel poses of synthetic subjects.

Per subject, what the network does not change is computed once and cached (`precomputed`): the
unprojected map F, its observation features and its view falloff (stages/lift/residual.residual_inputs on the
subject's input views). One step, per item of the batch: F' = F + corrections(F, features);
F' is placed on each target's posed body as the residual lift's avatar is (stages/lift/unproject.lifted_posed:
identity or view-cosine decoder) and splatted at the target camera; losses against the target:

    masked L1 (inside the target's mask)  + w_mask |alpha - mask|  + w_ssim (1 - SSIM)
    + w_delta mean(t^2) (t: the corrections before scaling, nn/residual.py)

Adam. Data parallel exactly as train/loop.py (its World, init_world and global_batch: K
processes give the update of one process with the combined batch); `--resume` continues bit for
bit; rank 0 writes train.json (dla.train/1), ckpt-<step>/generator (dla.checkpoint/1 of
ResidualNet + Adam state), loss.png and val/step_<step>.png (per validation target: truth,
unprojection, residual). Validation: masked PSNR and IoU of the residual and of unprojection
(the same F uncorrected) on validation subjects' novel views and novel poses.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dlacli.errors import DlaInputError
from dlacli.train.loop import (
    all_reduce_mean,
    draw_losses,
    global_batch,
    init_world,
    masked_psnr,
    new_record,
    resumed_record,
    save_png,
    start_run,
    write_record,
)

INPUTS_VERSION = "residual-inputs/1"  # bump when unprojection or the features change
WIDTHS = {"tiny": 8, "small": 32, "paper": 64}  # ResidualNet width per preset
VAL_TARGETS = {"view": 2, "pose": 2}  # validation targets per subject: the first novel views and poses


@dataclass
class ResidualTrainConfig:
    preset: str = "small"
    batch: int = 2  # items per process per step
    targets: int = 4  # target images per item
    steps: int = 2000
    size: int = 128  # target render size, pixels
    resolution: int = 128  # UV side of the unprojected map F
    gaussians: int = 32_768  # Gaussians sampled from F per render
    lr: float = 1e-3
    lr_final: float = 0.1  # the learning rate falls to lr * lr_final along a half cosine
    betas: tuple[float, float] = (0.9, 0.999)
    w_l1: float = 1.0
    w_mask: float = 1.0
    w_ssim: float = 0.2
    w_delta: float = 0.01
    validation: int = 8  # subjects held out (the lowest seeds, train/data.split_subjects)
    eval_every: int = 100
    checkpoint_every: int = 50
    seed: int = 0
    include_inputs: bool = False  # the input views may also be drawn as targets
    gain: bool = False  # train F_delta, the pose- and view-conditioned colour gain (nn/residual.py)
    init: str = ""  # start from this residual network's weights (folder, hash or "shipped"; "": from scratch)
    gain_only: bool = False  # train F_delta alone on the `init` network's frozen corrections
    # render targets this many times larger and box-filter them (1: at `size`). At 1 the network
    # learns corrections that only hold at the training render size: trained at 128 px it beat
    # unprojection by 2 dB at 128 px and lost 5-8 dB at 256-512 px (docs/train.md)
    supersample: int = 1

    @property
    def total_steps(self) -> int:
        return self.steps

    def lr_at(self, step: int) -> float:
        """The learning rate of step `step` (0-based): a half cosine from lr to lr * lr_final."""
        frac = step / max(self.steps - 1, 1)
        return self.lr * (self.lr_final + (1.0 - self.lr_final) * 0.5 * (1.0 + math.cos(math.pi * frac)))


def net_config(cfg: ResidualTrainConfig):
    from dlacli.nn.residual import ResidualNetConfig
    from dlacli.stages.lift.observations import feature_count

    if cfg.preset not in WIDTHS:
        raise DlaInputError("--preset", f"unknown preset {cfg.preset!r} (available: {', '.join(WIDTHS)})")
    return ResidualNetConfig(
        features=feature_count(),
        width=WIDTHS[cfg.preset],
        resolution=cfg.resolution,
        gaussians=cfg.gaussians,
        gain=cfg.gain,
    )


# ------------------------------------------------------------------------------ cached inputs


@dataclass
class Precomputed:
    fmap: torch.Tensor  # [14, R, R]
    features: torch.Tensor  # [features, R, R]
    falloff: float


def _lift_config(cfg: ResidualTrainConfig):
    from dlacli.stages.lift.methods.unproject import UnprojectConfig

    return UnprojectConfig(resolution=cfg.resolution, gaussians=cfg.gaussians, steps=0).resolved()


def precomputed(folder: Path, cfg: ResidualTrainConfig) -> Precomputed:
    """A subject's unprojection and features, from the cache or computed (and cached) now. The
    cache (dla's cache folder, `residual_inputs/`) is keyed by the subject folder (its path and
    its files' times and sizes), the code version and the lift settings, so runs share it."""
    from dlacli.io.atomic import atomic_path
    from dlacli.io.views import read_views
    from dlacli.paths import cache_dir
    from dlacli.stages.lift.residual import residual_inputs

    lcfg = _lift_config(cfg)
    folder = Path(folder).resolve()
    stamps = [(f.name, f.stat().st_mtime_ns, f.stat().st_size) for f in sorted(folder.glob("*.json"))]
    key = hashlib.sha256(repr((INPUTS_VERSION, asdict(lcfg), str(folder), stamps)).encode()).hexdigest()[:20]
    path = cache_dir("residual_inputs") / f"{folder.name}-{key}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                return Precomputed(torch.from_numpy(z["fmap"]), torch.from_numpy(z["features"]), float(z["falloff"]))
        except (OSError, KeyError, ValueError):
            pass  # a damaged cache file is recomputed
    inputs = residual_inputs(read_views(folder), lcfg)
    out = Precomputed(torch.from_numpy(inputs.base.fmap), torch.from_numpy(inputs.features), inputs.base.falloff)
    with atomic_path(path, cache=True) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, fmap=out.fmap.numpy(), features=out.features.numpy(), falloff=np.float64(out.falloff))
    return out


# ------------------------------------------------------------------------------ the step


def _supersampled(render, cameras, factor: int):
    """render(cameras) -> (rgb [C, H, W, 3], alpha [C, H, W]) at `factor` times the cameras' size,
    box-filtered back to it: the splatter's low-resolution footprint (its 0.3 px dilation) then
    does not reward corrections that only hold at one render size."""
    if factor <= 1:
        return render(cameras)
    import torch.nn.functional as nnf

    rgb, alpha = render(cameras.resized(cameras.width * factor, cameras.height * factor))
    rgb = nnf.avg_pool2d(rgb.permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1)
    return rgb, nnf.avg_pool2d(alpha[:, None], factor)[:, 0]


def render_map(z: torch.Tensor, falloff: float, vertices: torch.Tensor, cameras, samples, supersample: int = 1):
    """F z [14, R, R] (differentiable) on one posed body (vertices [V, 3]) seen from each of
    `cameras`, as the residual lift's avatar renders -> (rgb [C, H, W, 3], alpha [C, H, W]);
    `supersample`: rendered that many times larger and box-filtered (`_supersampled`)."""
    from dlacli.stages.lift.unproject import lifted_posed

    def render(cams):
        out = lifted_posed(z, falloff, vertices, cams, samples).render()
        return out.rgb, out.alpha

    return _supersampled(render, cameras, supersample)


def code_of(net, p: Precomputed) -> tuple[torch.Tensor, torch.Tensor]:
    """The avatar code of one subject's inputs (F', or with the gain the residual-gain code) and
    the corrections t, on the network's device."""
    device = next(net.parameters()).device
    fmap, feats = p.fmap[None].to(device), p.features[None].to(device)
    z, t = net.encode(fmap, feats, p.falloff) if net.config.gain else net(fmap, feats)
    return z[0], t


def render_target(net, code: torch.Tensor, p: Precomputed, vertices, rest, cameras, samples, supersample: int = 1):
    """`render_map` of a code from `code_of`; with the gain through the residual-gain decoder
    (rest [V, 3]: the body's zero pose, for the pose conditioning)."""
    vertices = vertices.to(code.device)
    if not net.config.gain:
        return render_map(code, p.falloff, vertices, cameras, samples, supersample)
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar

    decoded = Decoded.of(net, code, np.asarray(rest.cpu()))

    def render(cams):
        out = PosedAvatar(decoded, samples, vertices[None].float(), cams).render()
        return out.rgb, out.alpha

    return _supersampled(render, cameras, supersample)


def image_losses(pred: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> dict:
    """pred, gt [T, H, W, 3]; alpha, mask [T, H, W] -> {"l1" (inside the mask), "mask", "ssim"}."""
    from dlacli.nn.losses import ssim_map
    from dlacli.stages.lift.unproject import fixed_order_mean

    m = mask[..., None]
    l1 = fixed_order_mean((pred - gt).abs() * m) / fixed_order_mean(m.expand_as(pred)).clamp_min(1e-6)
    return {
        "l1": l1,
        "mask": fixed_order_mean((alpha - mask).abs()),
        "ssim": 1.0 - fixed_order_mean(ssim_map(pred, gt)),
    }


class ResidualLoss(nn.Module):
    """The losses of a list of (item, Precomputed) pairs (what DistributedDataParallel wraps)."""

    def __init__(self, net, cfg: ResidualTrainConfig, samples):
        super().__init__()
        self.net, self.cfg, self.samples = net, cfg, samples

    def forward(self, items, pre):
        cfg = self.cfg
        parts = {k: [] for k in ("l1", "mask", "ssim", "delta")}
        for it, p in zip(items, pre):
            code, t = code_of(self.net, p)
            preds, alphas = [], []
            for k in range(len(it.target_kind)):
                cam = it.target_cameras.select(k)
                rgb, a = render_target(
                    self.net, code, p, it.target_vertices[k], it.rest_vertices, cam, self.samples, cfg.supersample
                )
                preds.append(rgb[0])
                alphas.append(a[0])
            gt, mask = it.target_rgb.permute(0, 2, 3, 1).to(code.device), it.target_mask[:, 0].to(code.device)
            losses = image_losses(torch.stack(preds), torch.stack(alphas), gt, mask)
            for k, v in losses.items():
                parts[k].append(v)
            parts["delta"].append((t**2).mean())
        avg = {k: torch.stack(v).mean() for k, v in parts.items()}
        total = cfg.w_l1 * avg["l1"] + cfg.w_mask * avg["mask"] + cfg.w_ssim * avg["ssim"] + cfg.w_delta * avg["delta"]
        return total, {k: float(v.detach()) for k, v in avg.items()}


# ------------------------------------------------------------------------------ validation


class Validator:
    """Masked PSNR and IoU of the residual and of unprojection (the uncorrected F) on the first
    novel views and novel poses (VAL_TARGETS) of validation subjects; unprojection's renders are
    made once."""

    def __init__(self, data, folders: list[Path], cfg: ResidualTrainConfig, samples):
        self.data, self.folders, self.cfg, self.samples = data, folders, cfg, samples
        self._base: dict[int, tuple] = {}

    def _item(self, i: int):
        kinds = self.data.kinds(i)
        pick = [j for kind, n in VAL_TARGETS.items() for j in [j for j, k in enumerate(kinds) if k == kind][:n]]
        return self.data.item_at(i, pick)

    @torch.no_grad()
    def __call__(self, net, pictures: int = 2) -> tuple[dict, np.ndarray]:
        scores: dict[str, list[float]] = {}
        rows = []
        for i in range(len(self.data)):
            it = self._item(i)
            p = precomputed(self.folders[i], self.cfg)
            code, _ = code_of(net, p)
            gt, mask = it.target_rgb.permute(0, 2, 3, 1), it.target_mask[:, 0]
            renders = {}
            for name in ("base", "residual"):
                if name == "base" and i in self._base:
                    renders[name] = self._base[i]
                    continue
                made = [
                    render_map(
                        p.fmap.to(code.device),
                        p.falloff,
                        it.target_vertices[k].to(code.device),
                        it.target_cameras.select(k),
                        self.samples,
                        self.cfg.supersample,
                    )
                    if name == "base"
                    else render_target(
                        net,
                        code,
                        p,
                        it.target_vertices[k],
                        it.rest_vertices,
                        it.target_cameras.select(k),
                        self.samples,
                        self.cfg.supersample,
                    )
                    for k in range(len(it.target_kind))
                ]
                renders[name] = (torch.cat([m[0] for m in made]).cpu(), torch.cat([m[1] for m in made]).cpu())
            self._base[i] = renders["base"]
            for name, (rgb, alpha) in renders.items():
                prefix = "" if name == "residual" else "base_"
                for k, kind in enumerate(it.target_kind):
                    psnr_m = masked_psnr(rgb[k], gt[k], mask[k])
                    inter = torch.minimum(alpha[k], mask[k]).sum()
                    iou = float(inter / torch.maximum(alpha[k], mask[k]).sum().clamp_min(1e-9))
                    for key, v in (
                        ("psnr_masked", psnr_m),
                        (f"psnr_masked_{kind}", psnr_m),
                        ("psnr", masked_psnr(rgb[k], gt[k], None)),
                        ("iou", iou),
                    ):
                        scores.setdefault(prefix + key, []).append(v)
            if i < pictures:
                rows.append(
                    np.concatenate(
                        [
                            np.concatenate(list(gt.numpy()), axis=1),
                            np.concatenate(list(renders["base"][0].clamp(0, 1).numpy()), axis=1),
                            np.concatenate(list(renders["residual"][0].clamp(0, 1).numpy()), axis=1),
                        ]
                    )
                )
        out = {k: float(np.mean(v)) for k, v in sorted(scores.items())}
        out["gain_db"] = out["psnr_masked"] - out["base_psnr_masked"]
        width = max(r.shape[1] for r in rows)
        rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
        return out, np.concatenate(rows)


# ------------------------------------------------------------------------------ the run


def _settings(cfg: ResidualTrainConfig, data: str) -> dict:
    d = asdict(cfg)
    d["betas"] = list(cfg.betas)
    d["data"] = data
    d["method"] = "residual"
    return d


# what a run's network and its --init network must share
_SAME = ("features", "width", "internal", "groups", "max_opacity", "max_offset", "max_log_scale")
_SAME += ("resolution", "gaussians")


def check_init(cfg: ResidualTrainConfig):
    """The `init` network and its hash (None without one); one-line errors for `init` /
    `gain_only` that cannot work, before any work is done."""
    if cfg.gain_only and not (cfg.gain and cfg.init):
        raise DlaInputError("--gain-only", "needs --gain and --init (F_delta on a trained network's corrections)")
    return _init_network(cfg.init, net_config(cfg)) if cfg.init else None


def _init_network(init: str, ncfg):
    """(ResidualNet, hash) of checkpoint `init` (folder, hash, or "shipped": the weights in the
    package), checked to fit a run of config ncfg."""
    from dlacli.avatar.checkpoint import load_checkpoint, resolve_checkpoint
    from dlacli.nn.residual import ResidualNet
    from dlacli.stages.lift.residual import SHIPPED

    loaded = load_checkpoint(SHIPPED if init == "shipped" else resolve_checkpoint(init))
    theirs = loaded.module
    if not isinstance(theirs, ResidualNet):
        raise DlaInputError("--init", f"{init} holds a {type(theirs).__name__}, not a residual lift network")
    for key in _SAME:
        if getattr(theirs.config, key) != getattr(ncfg, key):
            raise DlaInputError(
                "--init", f"{init} has {key} {getattr(theirs.config, key)}, this run {getattr(ncfg, key)}"
            )
    if theirs.config.gain and not ncfg.gain:
        raise DlaInputError("--init", f"{init} has a gain branch (F_delta): train it with --gain")
    return theirs, loaded.hash


def _setup(data, cfg: ResidualTrainConfig):
    from dlacli.train.data import TrainingData, discover, split_subjects

    train_ids, val_ids = split_subjects(data, cfg.validation)
    if not train_ids:
        raise DlaInputError(data, f"has no training subjects after holding out {cfg.validation} for validation")
    folders = {name: folder for _, name, folder in discover(Path(data))}
    full = TrainingData(data, cfg.size, cfg.size, cfg.targets, subjects=train_ids, include_inputs=cfg.include_inputs)
    val = TrainingData(data, cfg.size, cfg.size, 1, subjects=val_ids, include_inputs=False) if val_ids else None
    full.item(0, np.random.default_rng(0))  # bad data fails here, before anything is written
    return train_ids, val_ids, folders, full, val


def train_residual(
    data: str | os.PathLike,
    out: str | os.PathLike,
    cfg: ResidualTrainConfig,
    *,
    resume: bool = False,
    until: int | None = None,
    log=None,
) -> dict:
    """Train (or resume) a residual run; returns train.json's content. `until`: stop (with a
    checkpoint) after that many steps in all, to be resumed later."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.avatar.checkpoint import load_checkpoint
    from dlacli.nn.residual import GAIN_MODULES, ResidualNet

    world = init_world()
    say = (log or (lambda line: print(line, file=sys.stderr, flush=True))) if world.main else (lambda line: None)
    out = Path(out)
    record_path = out / "train.json"
    ncfg = net_config(cfg)
    init = check_init(cfg)
    settings = _settings(cfg, str(data))
    if init is not None:
        settings["init_hash"] = init[1]  # the weights it started from, wherever they lie
    record = resumed_record(record_path, settings) if resume else None
    if not resume:
        start_run(out)
    train_ids, val_ids, folders, full, val = _setup(data, cfg)
    torch.manual_seed(cfg.seed)
    net = ResidualNet(ncfg).to(world.device)
    if init is not None:  # a gain branch init lacks keeps its initialisation (zero head: gain 1)
        missing, unexpected = net.load_state_dict(init[0].state_dict(), strict=False)
        assert not unexpected and all(k.split(".")[0] in GAIN_MODULES for k in missing), (missing, unexpected)
    if cfg.gain_only:  # F_c stays the init network's: only the gain branch learns
        for name, p in net.named_parameters():
            p.requires_grad_(name.split(".")[0] in GAIN_MODULES)
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=cfg.lr, betas=tuple(cfg.betas))
    if record is None:
        record = new_record(settings, world, train_ids, val_ids)
    if record["checkpoint"]:
        loaded = load_checkpoint(out / record["checkpoint"] / "generator", map_location=world.device)
        net.load_state_dict(loaded.module.state_dict())
        opt.load_state_dict(loaded.optimizer_state)
    samples = gm.make_samples(cfg.gaussians, 0)
    loss = ResidualLoss(net, cfg, samples)
    if world.size > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        run = DDP(loss)
    else:
        run = loss
    validator = Validator(val, [folders[s] for s in val_ids], cfg, samples) if val is not None else None
    if world.main:
        out.mkdir(parents=True, exist_ok=True)
    start = int(record["step"])
    t_start = time.perf_counter() - float(record["seconds"])
    net.train()
    stop = cfg.total_steps if until is None else min(int(until), cfg.total_steps)
    for step in range(start, stop):
        picks, slots = global_batch(cfg, step, len(full), world)
        items = [full.item(i, np.random.default_rng([cfg.seed, step, s, 1])) for i, s in zip(picks, slots)]
        pre = [precomputed(folders[full.subjects[i]], cfg) for i in picks]
        for group in opt.param_groups:
            group["lr"] = cfg.lr_at(step)
        opt.zero_grad(set_to_none=True)
        total, parts = run(items, pre)
        total.backward()
        opt.step()
        parts["total"] = float(total.detach())
        parts = all_reduce_mean(parts, world)
        record["history"].append(
            {"step": step + 1, "stage": "full", **{k: round(v, 6) for k, v in sorted(parts.items())}}
        )
        record["step"] = step + 1
        record["seconds"] = time.perf_counter() - t_start
        if world.main and ((step + 1) % 10 == 0 or step + 1 == cfg.total_steps or step == start):
            say(
                f"step {step + 1}/{cfg.total_steps} loss {parts['total']:.4f} (l1 {parts['l1']:.4f}, "
                f"mask {parts['mask']:.4f}, ssim {parts['ssim']:.4f}) {record['seconds']:.0f} s"
            )
        last = step + 1 == cfg.total_steps
        if validator is not None and world.main and ((step + 1) % cfg.eval_every == 0 or last):
            net.eval()
            scores, picture = validator(net)
            net.train()
            record["validation"].append({"step": step + 1, **{k: round(v, 4) for k, v in scores.items()}})
            save_png(out / "val" / f"step_{step + 1:06d}.png", picture)
            say(
                f"validation at step {step + 1}: masked PSNR {scores['psnr_masked']:.2f} dB "
                f"(unprojection {scores['base_psnr_masked']:.2f}), IoU {scores['iou']:.3f} "
                f"(unprojection {scores['base_iou']:.3f})"
            )
        if world.main and ((step + 1) % cfg.checkpoint_every == 0 or last or step + 1 == stop):
            _checkpoint(out, record, net, ncfg, opt, step + 1, cfg, str(data))
    if world.size > 1:
        import torch.distributed as dist

        dist.barrier()
    return record


def _checkpoint(out: Path, record: dict, net, ncfg, opt, step: int, cfg: ResidualTrainConfig, data: str) -> None:
    from dlacli.avatar.checkpoint import save_checkpoint

    name = f"ckpt-{step:06d}"
    extra = {"train": {"step": step, "method": "residual", "preset": cfg.preset, "data": data}}
    tmp = out / (name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    save_checkpoint(tmp / "generator", net, ncfg, step=step, optimizer=opt, extra=extra)
    shutil.rmtree(out / name, ignore_errors=True)
    tmp.rename(out / name)
    old = record["checkpoint"]
    record["checkpoint"] = name
    write_record(out / "train.json", record)
    if old and old != name:
        shutil.rmtree(out / old, ignore_errors=True)
    draw_losses(record, out / "loss.png")


def train_from_options(data: Path, output: Path, o) -> Path:
    """`dla train --method residual` (train/methods.py): -> the last generator checkpoint's folder.
    Options not given take ResidualTrainConfig's defaults; the render size, the data's image size
    (the scale the loss sees is the scale whose corrections hold)."""
    from dlacli.train.data import image_size

    size = image_size(data) if o.get("full_size") is None else o["full_size"]
    given = dict(steps=o.get("steps_full"), size=size, batch=o.get("batch"), targets=o.get("targets"), lr=o.get("lr_g"))
    cfg = ResidualTrainConfig(
        preset=o.get("preset") or "small",
        validation=o["validation"],
        eval_every=o["eval_every"],
        checkpoint_every=o["checkpoint_every"],
        seed=o["seed"],
        gain=bool(o.get("gain")),
        supersample=o.get("supersample") or 1,
        init=o.get("init") or "",
        gain_only=bool(o.get("gain_only")),
        **{k: v for k, v in given.items() if v is not None},
    )
    net_config(cfg)  # an unknown preset is refused before any work
    if cfg.total_steps == 0:
        raise DlaInputError("--steps-full", "no steps to train")
    record = train_residual(data, output, cfg, resume=bool(o.get("resume")))
    # under torchrun, ranks other than 0 write nothing and their record names no checkpoint
    return output / record["checkpoint"] / "generator" if record.get("checkpoint") else output
