"""`dla train --method completion`: the completion prior (nn/completion.py) trained on synthetic
subjects, whose whole appearance is known (docs/train.md "The completion prior").

A sample per subject (`make_sample`, cached in dla's cache folder, `completion_samples/`): the
subject's input view that faces it most (within 45 degrees of its front: the dataset's start yaw
is random) is the photo; it goes through what `dla dream` does with a photo (MediaPipe detection
on the cut-out, the body fit, the framing, the displaced body) and is baked at the network's UV
resolution (stages/dream/completion.photo_evidence): the network's inputs. The target: the true subject
rendered from `TARGET_AZIMUTHS` around the fitted body (the dream's orbit, mapped into the
subject's world through the bodies, as `dla bench accuracy --input photo` maps cameras) and baked
onto the same displaced body, averaged with the bakes' weights. So the target is what the truth
looks like on the fitted body, fit errors and all; lit by the subject's lights fixed in its world
(`target_light` "world") or turned with each target camera as the photo's camera sees them
("photo": the subject as lit as in the photo from wherever it is seen).

One step: a batch of samples, each mirrored left-right with probability 1/2 (through the UV
map's mirror texels) and given a random colour gain and offset (the same for inputs and target:
the rule's fill is a convex mixture of the photo's colours, so it commutes with them); loss:
the target-weighted L1 of the corrected colour. Adam; the learning rate falls along a half
cosine; checkpoints, resume, train.json, loss.png and val/step_N.png as the other methods write.
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

from dlacli.errors import DlaInputError

SAMPLE_VERSION = "completion-sample/1"  # bump when the sample's recipe changes
TARGET_AZIMUTHS = tuple(float(a) for a in range(0, 360, 45))  # degrees, the dream's orbit
TARGET_SIZE = 256  # pixels of the target renders
PHOTO_RES = 512  # the framing of the photo (dla dream's default --res)
# how the target renders are lit (lit subjects): "world", the subject's lights fixed in its world
# (as its views are rendered); "photo", the lights turned with every target camera as the photo's
# camera sees them, so the target is the subject as lit as the photo from wherever it is seen
TARGET_LIGHTS = ("world", "photo")
FIELDS = ("colour", "weight", "completed", "target", "target_weight")


@dataclass
class CompletionTrainConfig:
    width: int = 32
    resolution: int = 128
    batch: int = 8
    steps: int = 3000
    lr: float = 1e-3
    lr_final: float = 0.05
    betas: tuple[float, float] = (0.9, 0.999)
    gain_jitter: float = 0.25  # colour gain in [1 - j, 1 + j] per channel
    offset_jitter: float = 0.08  # colour offset in [-j, j] per channel
    validation: int = 16
    eval_every: int = 250
    checkpoint_every: int = 250
    seed: int = 0
    target_light: str = "world"  # TARGET_LIGHTS

    @property
    def total_steps(self) -> int:
        return self.steps

    def lr_at(self, step: int) -> float:
        f = 0.5 * (1.0 + math.cos(math.pi * min(step / max(self.steps, 1), 1.0)))
        return self.lr * (self.lr_final + (1.0 - self.lr_final) * f)


def net_config(cfg: CompletionTrainConfig):
    from dlacli.nn.completion import CompletionConfig

    return CompletionConfig(width=cfg.width, resolution=cfg.resolution)


# ------------------------------------------------------------------------------ samples


def front_view(views) -> int:
    """The index of the view whose camera is nearest the body's front (anny faces -Y; the
    synthetic subjects' root is not turned)."""
    centres = views.cameras.c2w_opengl()[:, :3, 3]
    horizontal = np.linalg.norm(centres[:, :2], axis=1)
    return int(np.argmax(-centres[:, 1] / np.maximum(horizontal, 1e-9)))


def _scaled(cameras, size: int):
    from dlacli.types import Cameras

    ks = cameras.Ks.clone().double()
    ks[:, :2, :] *= size / cameras.width
    return Cameras(cameras.viewmats.clone(), ks.to(cameras.Ks.dtype), size, size)


def make_sample(folder: Path, resolution: int = 128, target_light: str = "world") -> dict[str, np.ndarray]:
    """One subject folder (`dla synth`) -> the network's evidence and its target (module doc):
    colour [N, 3], weight [N], completed [N, 3], target [N, 3], target_weight [N] over
    valid_texels(resolution), and photo [PHOTO_RES, PHOTO_RES, 4] uint8 (the framed photo).
    target_light: one of TARGET_LIGHTS."""
    from dlacli.body.alignment import align_bodies, surface_weights
    from dlacli.body.model import get_body_model
    from dlacli.data.dataset import synth_record
    from dlacli.data.synth import render_subject
    from dlacli.io.detect import detect_person
    from dlacli.io.views import read_views
    from dlacli.stages.dream.completion import photo_evidence
    from dlacli.stages.dream.orbit import body_pivot, orbit_cameras
    from dlacli.stages.dream.texture import bake, displaced_body
    from dlacli.stages.dream.views import frame_crop
    from dlacli.stages.fit.photo import fit_body

    rec = synth_record(folder)
    seed, appearance, wardrobe = int(rec["seed"]), rec.get("appearance", "albedo"), rec.get("wardrobe", "default")
    views = read_views(folder)
    k = front_view(views)
    image, mask = views.images[k], views.masks[k]
    det = detect_person(image, alpha=mask)
    fit = fit_body(image, mask, det.keypoints, landmarks_3d=det.world)
    rgb, alpha, cam = frame_crop(image, mask, fit.camera, PHOTO_RES)
    displaced, _ = displaced_body(alpha, cam, fit.vertices)
    colour, weight, completed = photo_evidence(rgb, alpha, cam, displaced, resolution)

    model = get_body_model()
    with torch.no_grad():
        true_v = model.forward_body(views.body).vertices[0].double().numpy()
    align = align_bodies(fit.vertices, true_v, surface_weights(true_v, np.asarray(model.faces, np.int64)))
    cams = _scaled(orbit_cameras(cam, body_pivot(fit.vertices), TARGET_AZIMUTHS), TARGET_SIZE)
    light_view = views.cameras.viewmats[k, :3, :3].double().numpy() if target_light == "photo" else None
    rgba = render_subject(seed, align.to_true(cams), appearance=appearance, wardrobe=wardrobe, light_view=light_view)
    rgba = np.clip(rgba, 0.0, 1.0)
    acc = np.zeros_like(completed, dtype=np.float64)
    wsum = np.zeros(completed.shape[0])
    for c in range(len(TARGET_AZIMUTHS)):
        col, w = bake(rgba[c, ..., :3], rgba[c, ..., 3], cams.select(c), displaced, resolution)
        acc += w[:, None] * col
        wsum += w
    target = acc / np.maximum(wsum, 1e-6)[:, None]
    photo = np.round(np.concatenate([rgb, alpha[..., None]], -1) * 255.0).astype(np.uint8)
    return {
        "colour": colour.astype(np.float32),
        "weight": weight.astype(np.float32),
        "completed": completed.astype(np.float32),
        "target": target.astype(np.float32),
        "target_weight": np.clip(wsum, 0.0, 1.0).astype(np.float32),
        "photo": photo,
    }


def sample_path(folder: Path, resolution: int, target_light: str = "world") -> Path:
    """The cache file of a subject's sample, keyed by the recipe, the folder and its files."""
    from dlacli.paths import cache_dir

    folder = Path(folder).resolve()
    stamps = [(f.name, f.stat().st_mtime_ns, f.stat().st_size) for f in sorted(folder.glob("*.json"))]
    recipe = (SAMPLE_VERSION, resolution, PHOTO_RES, str(folder), stamps)
    if target_light != "world":  # the world-lit samples keep the keys they were cached under
        recipe += (target_light,)
    key = hashlib.sha256(repr(recipe).encode()).hexdigest()[:20]
    return cache_dir("completion_samples") / f"{folder.name}-{key}.npz"


def cached_sample(folder: Path, resolution: int, target_light: str = "world") -> dict[str, np.ndarray] | None:
    """A subject's sample from the cache, or made (and cached) now; None when the detector finds
    no person in its photo (recorded in the cache too, as an empty file)."""
    from dlacli.io.atomic import atomic_path

    path = sample_path(folder, resolution, target_light)
    if path.is_file():
        try:
            with np.load(path) as z:
                return None if "none" in z.files else {k: z[k] for k in z.files}
        except (OSError, KeyError, ValueError):
            pass  # a damaged cache file is made again
    try:
        sample = make_sample(folder, resolution, target_light)
    except DlaInputError:
        sample = None
    with atomic_path(path, cache=True) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **(sample or {"none": np.zeros(0)}))
    return sample


def _sample_worker(task: tuple[str, int, str]) -> tuple[str, bool]:
    from dlacli.data.dataset import single_threaded

    single_threaded()
    folder, resolution, target_light = task
    return folder, cached_sample(Path(folder), resolution, target_light) is not None


def prepare_samples(
    folders: list[Path], resolution: int, jobs: int = 1, log=None, target_light: str = "world"
) -> list[Path]:
    """Make (or find) every subject's sample, `jobs` processes in parallel; -> the folders that
    have one (a subject whose photo shows no detectable person is left out)."""
    say = log or (lambda line: None)
    todo = [f for f in folders if not sample_path(f, resolution, target_light).is_file()]
    if todo:
        say(f"making {len(todo)} completion samples ({len(folders) - len(todo)} cached), {jobs} jobs")
    t0 = time.perf_counter()
    tasks = [(str(f), resolution, target_light) for f in todo]
    if jobs > 1 and len(tasks) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as pool:
            for n, _ in enumerate(pool.map(_sample_worker, tasks), 1):
                if n % 10 == 0 or n == len(tasks):
                    say(f"  {n}/{len(tasks)} samples, {time.perf_counter() - t0:.0f} s")
    else:
        for n, task in enumerate(tasks, 1):
            _sample_worker(task) if jobs > 1 else cached_sample(Path(task[0]), resolution, target_light)
            if n % 10 == 0 or n == len(tasks):
                say(f"  {n}/{len(tasks)} samples, {time.perf_counter() - t0:.0f} s")
    return [f for f in folders if cached_sample(f, resolution, target_light) is not None]


# ------------------------------------------------------------------------------ batches


class Samples:
    """The samples of a list of subjects as flat texel arrays, and batches of network inputs."""

    def __init__(self, samples: list[dict[str, np.ndarray]], resolution: int):
        from dlacli.stages.dream.texture import mirror_texels

        self.samples, self.resolution = samples, resolution
        self.mirror = mirror_texels(resolution)

    def __len__(self) -> int:
        return len(self.samples)

    def item(self, i: int, rng: np.random.Generator | None, cfg: CompletionTrainConfig):
        """(inputs [22, r, r], completed [3, r, r], unseen [1, r, r] = 1 - a, target [3, r, r],
        target weight [1, r, r]) of sample i, augmented when rng is given (module doc)."""
        from dlacli.stages.dream.completion import confidence, grid, prior_inputs

        s = {k: self.samples[i][k] for k in FIELDS}
        if rng is not None:
            if rng.random() < 0.5:
                s = {k: v[self.mirror] for k, v in s.items()}
            gain = rng.uniform(1.0 - cfg.gain_jitter, 1.0 + cfg.gain_jitter, 3).astype(np.float32)
            offset = rng.uniform(-cfg.offset_jitter, cfg.offset_jitter, 3).astype(np.float32)
            for k in ("colour", "completed", "target"):
                s[k] = np.clip(s[k] * gain + offset, 0.0, 1.0)
        r = self.resolution
        inputs = prior_inputs(s["colour"], s["weight"], s["completed"], r)
        unseen = 1.0 - confidence(s["weight"])[:, None]
        maps = [grid(s["completed"], r), grid(unseen, r), grid(s["target"], r), grid(s["target_weight"][:, None], r)]
        return (inputs, *(torch.from_numpy(m) for m in maps))

    def batch(self, picks, rng_of, cfg):
        items = [self.item(i, rng_of(i), cfg) for i in picks]
        return [torch.stack(parts) for parts in zip(*items)]


def corrected_maps(net, inputs, completed, unseen):
    """The network's colours [B, 3, r, r] at its own resolution (stages/dream/completion.correct's rule)."""
    from dlacli.nn.completion import corrected_colour

    return corrected_colour(completed, net(inputs) * unseen)


def weighted_l1(pred, target, weight) -> torch.Tensor:
    return ((pred - target).abs().mean(1, keepdim=True) * weight).sum() / weight.sum().clamp_min(1e-6)


def _psnr(pred, target, weight) -> float:
    mse = float((((pred - target) ** 2).mean(1, keepdim=True) * weight).sum() / weight.sum().clamp_min(1e-6))
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def validate(net, val: Samples, cfg: CompletionTrainConfig, pictures: int = 3) -> tuple[dict, np.ndarray]:
    """Scores on the validation samples (target-weighted, on every texel and on those the photo
    does not see, a < 1/2), for the network and the rule; a picture per sample of the first
    `pictures`: the rule | the network | the target (UV maps, black where the target is unknown)."""
    inputs, completed, unseen, target, tw = val.batch(range(len(val)), lambda i: None, cfg)
    with torch.no_grad():
        pred = corrected_maps(net, inputs, completed, unseen)
    hidden = tw * (unseen > 0.5)
    scores = {
        "psnr": _psnr(pred, target, tw),
        "psnr_masked": _psnr(pred, target, hidden),
        "base_psnr": _psnr(completed, target, tw),
        "base_psnr_masked": _psnr(completed, target, hidden),
        "l1_hidden": float(weighted_l1(pred, target, hidden)),
        "base_l1_hidden": float(weighted_l1(completed, target, hidden)),
    }
    rows = []
    for k in range(min(pictures, len(val))):
        rows.append(np.concatenate([m[k].permute(1, 2, 0).numpy() for m in (completed, pred, target * tw)], axis=1))
    return scores, np.concatenate(rows, axis=0) if rows else np.zeros((1, 1, 3))


# ------------------------------------------------------------------------------ the run


def _settings(cfg: CompletionTrainConfig, data: str) -> dict:
    return {"method": "completion", **asdict(cfg), "betas": list(cfg.betas), "data": data, "sample": SAMPLE_VERSION}


def load_samples(data, cfg: CompletionTrainConfig, jobs: int = 1, log=None):
    """(train ids, validation ids, train Samples, validation Samples or None); a subject whose
    photo shows no detectable person is left out (and said so)."""
    from dlacli.train.data import discover, split_subjects

    say = log or (lambda line: None)
    train_ids, val_ids = split_subjects(data, cfg.validation)
    folders = {name: folder for _, name, folder in discover(Path(data))}
    prepare_samples([folders[n] for n in val_ids + train_ids], cfg.resolution, jobs, say, cfg.target_light)
    out = []
    for ids in (train_ids, val_ids):
        kept = [(n, cached_sample(folders[n], cfg.resolution, cfg.target_light)) for n in ids]
        if len(kept) > sum(s is not None for _, s in kept):
            say(f"left out (no person detected): {', '.join(n for n, s in kept if s is None)}")
        out.append([(n, s) for n, s in kept if s is not None])
    (train, val) = out
    if not train:
        raise DlaInputError(data, f"has no training subjects with a sample after holding out {cfg.validation}")
    val_set = Samples([s for _, s in val], cfg.resolution) if val else None
    return [n for n, _ in train], [n for n, _ in val], Samples([s for _, s in train], cfg.resolution), val_set


def train_completion(
    data: str | os.PathLike,
    out: str | os.PathLike,
    cfg: CompletionTrainConfig,
    *,
    resume: bool = False,
    jobs: int = 1,
    until: int | None = None,
    log=None,
) -> dict:
    """Train (or resume) a completion run; returns train.json's content. `until`: stop (with a
    checkpoint) after that many steps in all, to be resumed later."""
    from dlacli.avatar.checkpoint import load_checkpoint
    from dlacli.nn.completion import CompletionNet
    from dlacli.train.loop import init_world, new_record, resumed_record, save_png, start_run

    world = init_world()
    if world.size > 1:
        raise DlaInputError("--method completion", "trains in one process (it is small); run it without torchrun")
    say = log or (lambda line: print(line, file=sys.stderr, flush=True))
    out = Path(out)
    record_path = out / "train.json"
    ncfg = net_config(cfg)
    settings = _settings(cfg, str(data))
    record = resumed_record(record_path, settings) if resume else None
    if not resume:
        start_run(out)
    train_ids, val_ids, train, val = load_samples(data, cfg, jobs, say)
    torch.manual_seed(cfg.seed)
    net = CompletionNet(ncfg)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
    if record is None:
        record = new_record(settings, world, train_ids, val_ids)
    if record["checkpoint"]:
        loaded = load_checkpoint(out / record["checkpoint"] / "prior")
        net.load_state_dict(loaded.module.state_dict())
        opt.load_state_dict(loaded.optimizer_state)
    out.mkdir(parents=True, exist_ok=True)
    start = int(record["step"])
    t_start = time.perf_counter() - float(record["seconds"])
    stop = cfg.total_steps if until is None else min(int(until), cfg.total_steps)
    net.train()
    for step in range(start, stop):
        rng = np.random.default_rng([cfg.seed, step])
        picks = rng.choice(len(train), size=min(cfg.batch, len(train)), replace=False)
        batch = train.batch(picks, lambda i, s=step: np.random.default_rng([cfg.seed, s, int(i), 1]), cfg)
        inputs, completed, unseen, target, tw = batch
        for group in opt.param_groups:
            group["lr"] = cfg.lr_at(step)
        opt.zero_grad(set_to_none=True)
        loss = weighted_l1(corrected_maps(net, inputs, completed, unseen), target, tw)
        loss.backward()
        opt.step()
        with torch.no_grad():
            base = float(weighted_l1(completed, target, tw))
        l1 = float(loss.detach())
        record["history"].append({"step": step + 1, "stage": "full", "l1": round(l1, 6), "rule_l1": round(base, 6)})
        record["step"] = step + 1
        record["seconds"] = time.perf_counter() - t_start
        last = step + 1 == cfg.total_steps
        if (step + 1) % 25 == 0 or last or step == start:
            say(f"step {step + 1}/{cfg.total_steps} l1 {l1:.4f} (rule {base:.4f}) {record['seconds']:.0f} s")
        if val is not None and ((step + 1) % cfg.eval_every == 0 or last):
            net.eval()
            scores, picture = validate(net, val, cfg)
            net.train()
            record["validation"].append({"step": step + 1, **{k: round(v, 4) for k, v in scores.items()}})
            save_png(out / "val" / f"step_{step + 1:06d}.png", picture)
            say(
                f"validation at step {step + 1}: unseen texels {scores['psnr_masked']:.2f} dB "
                f"(rule {scores['base_psnr_masked']:.2f}), all {scores['psnr']:.2f} dB (rule {scores['base_psnr']:.2f})"
            )
        if (step + 1) % cfg.checkpoint_every == 0 or last or step + 1 == stop:
            _checkpoint(out, record, net, ncfg, opt, step + 1, str(data))
    return record


def _checkpoint(out: Path, record: dict, net, ncfg, opt, step: int, data: str) -> None:
    from dlacli.avatar.checkpoint import save_checkpoint
    from dlacli.train.loop import draw_losses, write_record

    name = f"ckpt-{step:06d}"
    extra = {"train": {"step": step, "method": "completion", "data": data}}
    tmp = out / (name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    save_checkpoint(tmp / "prior", net, ncfg, step=step, optimizer=opt, extra=extra)
    shutil.rmtree(out / name, ignore_errors=True)
    tmp.rename(out / name)
    old = record["checkpoint"]
    record["checkpoint"] = name
    write_record(out / "train.json", record)
    if old and old != name:
        shutil.rmtree(out / old, ignore_errors=True)
    draw_losses(record, out / "loss.png")


def train_from_options(data: Path, output: Path, o) -> Path:
    """`dla train --method completion` (train/methods.py): -> the last checkpoint's prior folder.
    Options not given take CompletionTrainConfig's defaults."""
    target_light = o.get("target_light") or "world"
    if target_light not in TARGET_LIGHTS:
        raise DlaInputError("--target-light", f"must be {' or '.join(TARGET_LIGHTS)}, got {target_light!r}")
    given = dict(steps=o.get("steps_full"), batch=o.get("batch"), lr=o.get("lr_g"))
    cfg = CompletionTrainConfig(
        validation=o["validation"],
        eval_every=o["eval_every"],
        checkpoint_every=o["checkpoint_every"],
        seed=o["seed"],
        target_light=target_light,
        **{k: v for k, v in given.items() if v is not None},
    )
    if cfg.total_steps == 0:
        raise DlaInputError("--steps-full", "no steps to train")
    record = train_completion(data, output, cfg, resume=bool(o.get("resume")), jobs=o.get("jobs") or 1)
    return output / record["checkpoint"] / "prior"
