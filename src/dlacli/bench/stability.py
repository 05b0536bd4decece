"""How lift degrades when its inputs are wrong: degradation curves per method (`dla bench stability`).

A method (a spec of dlacli.stages.lift.methods: "unproject", "unproject:steps=50", ...) turns a
ViewSet into an Avatar. A perturbation
(`PERTURBATIONS`) has levels, the first its clean baseline, and changes either the input views
handed to the method (body parameters, images, cameras, which views) or the synthetic subject
itself (its pose, its distance from the cameras). Every run is scored, as `dla bench pipeline`
does, on the subject's held-out novel views (same pose as the inputs) and novel poses (the
unperturbed subject's motion, fixed cameras at the standard distance), so a level changes only
what the method was given. Each run records its status: "ok", "nan" (the avatar or its renders
hold NaN or inf), "empty" (no Gaussian with opacity > EMPTY_OPACITY) or "error" (an exception,
caught and recorded).

Perturbations of the views leave view 0 alone (the photo; the others stand in for the
diffusion-made views, whose failure modes they imitate) except pose and shape noise, which
perturb the one body.json every view shares.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from dlacli.stages.lift.methods import MethodSpec
from dlacli.types import Avatar, Cameras, Motion, ViewSet

EMPTY_OPACITY = 0.01
DROP_DB = 2.0  # the report states the first level at which masked PSNR has dropped this much


# --------------------------------------------------------------------------------- subjects


@dataclass
class Subject:
    """A synthetic subject in memory (what `dla synth` writes), for one perturbation level."""

    seed: int
    views: ViewSet  # the 4 input views with the true body
    novel_views: ViewSet
    novel_poses: ViewSet
    motion: Motion  # what novel_poses' times index
    info: dict  # measured facts about the subject (hand clearance, fill of the frame)


def make_subject(
    seed: int,
    res: int,
    novel_views: int = 4,
    novel_poses: int = 2,
    pose: Callable | None = None,
    distance: float | None = None,
) -> Subject:
    """The synth subject `seed` at res px (as dlacli.data.synth.synth, in memory): `pose(spec)`
    returns the input pose [J, 3] in place of the relaxed one; `distance` (metres) moves the
    input cameras (novel views and poses keep the standard rig)."""
    import torch

    from dlacli.data.cameras import (
        DISTANCE,
        FOV_DEG,
        INPUT_AZIMUTHS,
        INPUT_ELEVATION,
        POSE_AZIMUTHS,
        TARGET,
        novel_view_angles,
        synth_orbit_cameras,
    )
    from dlacli.data.garments import DressedBody
    from dlacli.data.images import render
    from dlacli.data.poses import novel_motion
    from dlacli.data.subject import hand_clearance, sample_subject
    from dlacli.data.synth import body_params, view_set

    base = sample_subject(seed)
    spec = replace(base, rotations=np.asarray(pose(base), np.float32)) if pose is not None else base
    body = DressedBody(spec)
    zero = torch.zeros(1, 3)
    verts = body.vertices(spec.rotations[None], zero, zero)[0]
    truth = body_params(spec, spec.rotations)
    from dlacli.geometry import look_at_orbit_cameras

    dist = DISTANCE if distance is None else float(distance)
    cams = look_at_orbit_cameras(TARGET, dist, INPUT_AZIMUTHS, INPUT_ELEVATION, FOV_DEG, res)
    rgba = render(body, verts, cams, seed)
    views = view_set(rgba, cams, truth, [None] * 4, {})
    az, el = novel_view_angles(novel_views)
    ncams = synth_orbit_cameras(az, el, res)
    nv = view_set(render(body, verts, ncams, seed), ncams, truth, [None] * novel_views, {})
    motion = novel_motion(seed, base, novel_poses)
    posed_body = DressedBody(base) if pose is not None else body
    posed = posed_body.vertices(
        motion.rotations, torch.from_numpy(motion.root_rotation), torch.from_numpy(motion.root_translation)
    )
    k = len(POSE_AZIMUTHS)
    cams1 = synth_orbit_cameras(POSE_AZIMUTHS, INPUT_ELEVATION, res)
    pcams = Cameras(cams1.viewmats.repeat(novel_poses, 1, 1), cams1.Ks.repeat(novel_poses, 1, 1), res, res)
    prgba = render(posed_body, np.repeat(posed, k, axis=0), pcams, seed)
    npose = view_set(prgba, pcams, body_params(base, None), [t for t in range(novel_poses) for _ in range(k)], {})
    rows = np.nonzero(views.masks.max(axis=(0, 2)) > 0.5)[0]
    info = {
        "fill": float((rows.max() - rows.min() + 1) / res) if rows.size else 0.0,
        "hand_clearance_m": hand_clearance(spec),
    }
    return Subject(int(seed), views, nv, npose, motion, info)


# --------------------------------------------------------------------------------- perturbations


def _rotation_noise(rot: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """Each axis-angle [J, 3] turned by `degrees` about its own random axis (world frame of the bone)."""
    from scipy.spatial.transform import Rotation

    axes = rng.normal(size=rot.shape)
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    noise = Rotation.from_rotvec(axes * math.radians(degrees))
    return (noise * Rotation.from_rotvec(rot)).as_rotvec().astype(np.float32)


def pose_noise(views: ViewSet, degrees: float, rng: np.random.Generator) -> ViewSet:
    """Every bone of the rig (bone 0, the root, included) off by `degrees` about a random axis."""
    from dlacli.body.model import get_body_model, pose_to_rotations, rotations_to_pose

    model = get_body_model()
    rot = _rotation_noise(pose_to_rotations(views.body.pose, "pose", model), degrees, rng)
    body = replace(views.body, pose=rotations_to_pose(rot, model))
    return replace(views, body=body)


def shape_noise(views: ViewSet, sigma: float, rng: np.random.Generator) -> ViewSet:
    """Every phenotype value plus N(0, sigma^2), clipped to [0, 1]."""
    pheno = {k: float(np.clip(v + rng.normal(0.0, sigma), 0.0, 1.0)) for k, v in views.body.phenotype.items()}
    return replace(views, body=replace(views.body, phenotype=pheno))


def colour_shift(views: ViewSet, sigma: float, rng: np.random.Generator) -> ViewSet:
    """Views 1.. get per-channel gains exp(N(0, sigma^2)) (a white-balance / exposure shift)."""
    images = views.images.copy()
    for v in range(1, len(views)):
        images[v] = np.clip(images[v] * np.exp(rng.normal(0.0, sigma, 3)), 0.0, 1.0)
    return replace(views, images=images.astype(np.float32))


def misregister_px(views: ViewSet, pixels: float, rng: np.random.Generator) -> ViewSet:
    """Views 1..: image and mask shifted `pixels` in a random direction (the cameras stay)."""
    from scipy import ndimage

    images, masks = views.images.copy(), views.masks.copy()
    for v in range(1, len(views)):
        a = rng.uniform(0.0, 2.0 * math.pi)
        dy, dx = pixels * math.sin(a), pixels * math.cos(a)
        images[v] = ndimage.shift(views.images[v], (dy, dx, 0), order=1, mode="constant", cval=0.0)
        masks[v] = ndimage.shift(views.masks[v], (dy, dx), order=1, mode="constant", cval=0.0)
    return replace(
        views, images=np.clip(images, 0, 1).astype(np.float32), masks=np.clip(masks, 0, 1).astype(np.float32)
    )


def misregister_deg(views: ViewSet, degrees: float, rng: np.random.Generator) -> ViewSet:
    """Views 1..: the camera the view claims is `degrees` of azimuth (+-, random) away from the one
    that saw the image (an orbit about the vertical axis through the synth rig's target)."""
    import torch

    from dlacli.data.cameras import TARGET

    w2c = views.cameras.viewmats.double().numpy().copy()
    t = np.asarray(TARGET, np.float64)
    for v in range(1, len(views)):
        a = math.radians(degrees) * (1.0 if rng.uniform() < 0.5 else -1.0)
        m = np.eye(4)
        m[:3, :3] = [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
        m[:3, 3] = t - m[:3, :3] @ t  # rotate about the vertical line through the target
        w2c[v] = w2c[v] @ np.linalg.inv(m)  # the claimed camera is the true one moved by m
    cams = Cameras(torch.from_numpy(w2c).float(), views.cameras.Ks.clone(), views.cameras.width, views.cameras.height)
    return replace(views, cameras=cams)


VIEW_SUBSETS = {4: (0, 1, 2, 3), 3: (0, 1, 3), 2: (0, 2), 1: (0,)}  # front, sides, back by count


def fewer_views(views: ViewSet, count: float, rng: np.random.Generator) -> ViewSet:
    """Only `count` of the 4 views: 3 = front and both sides, 2 = front and back, 1 = the front."""
    import torch

    keep = list(VIEW_SUBSETS[int(count)])
    idx = torch.tensor(keep)
    cams = Cameras(views.cameras.viewmats[idx], views.cameras.Ks[idx], views.cameras.width, views.cameras.height)
    return replace(
        views,
        images=views.images[keep],
        masks=views.masks[keep],
        cameras=cams,
        file_paths=[views.file_paths[k] for k in keep] if views.file_paths else [],
        times=[views.times[k] for k in keep],
    )


def extreme_pose(spec, degrees: float) -> np.ndarray:
    """The relaxed pose plus both arms raised, one leg stepping and the spine bent, `degrees` each
    (legs 0.6x, knee 0.8x, spine 0.25x)."""
    from dlacli.body.model import get_body_model
    from dlacli.data.subject import BonePose

    p = BonePose(get_body_model().bone_labels, spec.rotations)
    a = math.radians(degrees)
    for side, s in (("L", 1.0), ("R", -1.0)):
        p.rotate(f"upperarm01.{side}", y=-s * a)
    p.rotate("upperleg01.L", x=-0.6 * a)
    p.rotate("lowerleg01.L", x=0.8 * a)
    p.rotate("spine03", x=0.25 * a)
    return p.rot


def self_contact(spec, degrees: float) -> np.ndarray:
    """The relaxed pose with both upper arms brought `degrees` further down against the torso."""
    from dlacli.body.model import get_body_model
    from dlacli.data.subject import BonePose

    p = BonePose(get_body_model().bone_labels, spec.rotations)
    for side, s in (("L", 1.0), ("R", -1.0)):
        p.rotate(f"upperarm01.{side}", y=s * math.radians(degrees))
    return p.rot


@dataclass(frozen=True)
class Perturbation:
    name: str
    unit: str
    levels: tuple[float, ...]  # the first is the clean baseline
    views: Callable[[ViewSet, float, np.random.Generator], ViewSet] | None = None  # on the inputs
    pose: Callable | None = None  # (spec, level) -> input pose [J, 3]
    distance: bool = False  # level x the synth rig's distance for the input cameras

    def subject_level(self) -> bool:
        return self.views is None


PERTURBATIONS = {
    p.name: p
    for p in (
        Perturbation("pose_noise", "degrees per bone", (0.0, 1.0, 2.0, 5.0, 10.0), views=pose_noise),
        Perturbation("shape_noise", "phenotype s.d.", (0.0, 0.02, 0.05, 0.1, 0.2), views=shape_noise),
        Perturbation("colour_shift", "log-gain s.d.", (0.0, 0.05, 0.1, 0.2, 0.4), views=colour_shift),
        Perturbation("misregister_px", "pixels", (0.0, 1.0, 2.0, 4.0, 8.0), views=misregister_px),
        Perturbation("misregister_deg", "degrees of azimuth", (0.0, 1.0, 2.0, 5.0, 10.0), views=misregister_deg),
        Perturbation("fewer_views", "views", (4.0, 3.0, 2.0, 1.0), views=fewer_views),
        Perturbation("extreme_pose", "degrees", (0.0, 40.0, 80.0, 120.0), pose=extreme_pose),
        Perturbation("self_contact", "degrees of arm adduction", (0.0, 8.0, 16.0, 24.0), pose=self_contact),
        Perturbation("small_in_frame", "x camera distance", (1.0, 1.5, 2.0, 3.0, 4.0), distance=True),
        Perturbation("large_in_frame", "x camera distance", (1.0, 0.9, 0.8, 0.75), distance=True),
    )
}


def quick_levels(p: Perturbation, k: int) -> tuple[float, ...]:
    """The baseline and at most k - 1 of the levels, spread out to include the worst."""
    if k >= len(p.levels):
        return p.levels
    idx = np.unique(np.linspace(0, len(p.levels) - 1, max(k, 2)).round().astype(int))
    return tuple(p.levels[i] for i in idx)


# --------------------------------------------------------------------------------- running


def visible_gaussians(avatar: Avatar) -> int:
    """Gaussians of the avatar's canonical map, at its own samples, with opacity > EMPTY_OPACITY."""
    import torch

    from dlacli.avatar import gaussian_map as gm
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import sample_settings

    samples = gm.make_samples(*sample_settings(avatar))
    logits = gm.lookup(Decoded(avatar).f_c[gm.OPACITY], samples.uv)[:, 0]
    return int((torch.sigmoid(logits) > EMPTY_OPACITY).sum())


def score(avatar: Avatar, subject: Subject) -> tuple[str, dict[str, dict[str, float]]]:
    """(status, {split: metrics}) of an avatar on the subject's novel views and poses."""
    from dlacli.bench.score import render_split, scores

    if not np.isfinite(avatar.z).all():
        return "nan", {}
    if visible_gaussians(avatar) == 0:
        return "empty", {}
    out = {}
    for split, views, motion in (
        ("novel_views", subject.novel_views, None),
        ("novel_poses", subject.novel_poses, subject.motion),
    ):
        pred, gt = render_split(avatar, views, motion)
        if not np.isfinite(pred).all():
            return "nan", {}
        out[split] = scores(pred, gt, views.masks)
    if any(not math.isfinite(v) for m in out.values() for v in m.values()):
        return "nan", {}
    return "ok", out


def run_one(spec: MethodSpec, views: ViewSet, subject: Subject) -> dict:
    """One method on one (perturbed) input: {status, error, seconds, metrics per split}."""
    t0 = time.perf_counter()
    try:
        avatar = spec.lift(views).avatar
        seconds = time.perf_counter() - t0
        status, metrics = score(avatar, subject)
        error = None
    except Exception as err:  # noqa: BLE001 - every failure is a result here, recorded in the row
        seconds, status, metrics = time.perf_counter() - t0, "error", {}
        error = f"{type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return {"status": status, "error": error, "seconds": seconds, "metrics": metrics}


def _rows(spec: MethodSpec, res, subject, pert: Perturbation, level, result, device) -> list[dict]:
    from dlacli.bench.rows import stability_row

    cfg = {**spec.options(), "res": res, **{f"subject_{k}": round(v, 4) for k, v in subject.info.items()}}
    return [
        stability_row(
            spec.name,
            cfg,
            split,
            result["seconds"],
            None,
            result["metrics"].get(split, {}),
            pert.name,
            level,
            result["status"],
            result["error"],
            subject=subject.seed,
            device=device,
        )
        for split in ("novel_views", "novel_poses")
    ]


def run(
    seeds: list[int],
    methods: list[MethodSpec],
    perturbations: list[str] | None = None,
    res: int = 256,
    levels: int | None = None,
    novel_views: int = 4,
    novel_poses: int = 2,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Every method (stages.methods specs) on every level of every perturbation, per seed ->
    stability rows. `levels`: at most this many levels per perturbation (`quick_levels`). The
    clean run is made once per method and seed and reported as each perturbation's baseline."""
    from dlacli.bench.rows import default_device

    names = list(PERTURBATIONS) if perturbations is None else perturbations
    device = default_device()
    rows: list[dict] = []
    for seed in seeds:
        clean = make_subject(seed, res, novel_views, novel_poses)
        baseline = [run_one(spec, clean.views, clean) for spec in methods]
        for name in names:
            pert = PERTURBATIONS[name]
            lv = pert.levels if levels is None else quick_levels(pert, levels)
            for i, level in enumerate(lv):
                if level == pert.levels[0]:
                    subject, results = clean, baseline
                else:
                    rng = np.random.default_rng([seed, list(PERTURBATIONS).index(name), i])
                    if pert.subject_level():
                        subject = make_subject(
                            seed,
                            res,
                            novel_views,
                            novel_poses,
                            pose=(lambda spec, lv_=level, p_=pert: p_.pose(spec, lv_)) if pert.pose else None,
                            distance=level * _rig_distance() if pert.distance else None,
                        )
                        inputs = subject.views
                    else:
                        subject, inputs = clean, pert.views(clean.views, level, rng)
                    results = [run_one(spec, inputs, subject) for spec in methods]
                for spec, result in zip(methods, results):
                    rows += _rows(spec, res, subject, pert, level, result, device)
                    nv = result["metrics"].get("novel_views", {}).get("psnr_masked")
                    log(
                        f"seed {seed} {name} {level:g}: {spec.label} {result['status']}"
                        + (
                            f", novel views masked PSNR {nv:.2f}"
                            if nv is not None
                            else f" ({result['error']})"
                            if result["error"]
                            else ""
                        )
                    )
    return rows


def _rig_distance() -> float:
    from dlacli.data.cameras import DISTANCE

    return DISTANCE


# --------------------------------------------------------------------------------- summary


def curves(rows: list[dict], split: str = "novel_views", metric: str = "psnr_masked") -> dict:
    """{perturbation: {method and setting (rows.label): [(level, mean metric over subjects with
    status ok, runs, failures)]}}, perturbations in PERTURBATIONS' order, levels in the order the
    rows first give them."""
    from dlacli.bench.rows import label

    out: dict[str, dict[str, dict[float, list]]] = {}
    for r in rows:
        if r.get("kind") != "stability" or r["split"] != split:
            continue
        cell = out.setdefault(r["perturbation"], {}).setdefault(label(r), {}).setdefault(r["level"], [[], 0, 0])
        cell[1] += 1
        if r["status"] == "ok":
            cell[0].append(r["metrics"][metric])
        else:
            cell[2] += 1
    order = sorted(out, key=lambda p: (list(PERTURBATIONS).index(p) if p in PERTURBATIONS else len(PERTURBATIONS), p))
    return {
        p: {
            m: [(lv, float(np.mean(v)) if v else float("nan"), n, f) for lv, (v, n, f) in out[p][m].items()]
            for m in sorted(out[p])
        }
        for p in order
    }


def drop_level(curve: list[tuple], drop_db: float = DROP_DB) -> float | None:
    """The first level (after the baseline, the first entry) whose mean has fallen `drop_db` or
    more below the baseline's, or that failed on every subject; None when none has."""
    if not curve or not math.isfinite(curve[0][1]):
        return curve[0][0] if curve else None
    base = curve[0][1]
    for level, value, _runs, fails in curve[1:]:
        if (not math.isfinite(value) and fails) or value <= base - drop_db:
            return level
    return None
