"""`dla bench accuracy --input photo`: the whole mission measured on synthetic subjects.

Per subject: its input view 0 (azimuth 0, RGBA, alpha = the person, as a cut-out photo) is the
photo; `dla dream` (person detection on, body fit, novel views at 90 / 180 / 270 by a dream
backend) makes a view folder; a lift method turns it into an avatar. The dream's world is not
the subject's: it is the fitted body's (pelvis at the origin, the photo camera at azimuth 0, the
fit's own scale). The two are aligned through the bodies (`align_bodies`): both are anny meshes
of one topology, so the similarity (scale, rotation, translation) that best carries the fitted
posed vertices onto the true posed ones, weighted by each vertex's share of the true body's
surface area, maps cameras between the worlds (`Alignment.to_true`, `Alignment.to_dream`).

Splits (`score_dream`):

    novel_views      the true novel cameras mapped into the dream's world render the avatar in
                     its own pose, against the true images
    novel_poses      the avatar posed with the true motion's bone rotations (its own fitted
    novel_view_pose  phenotype); each frame aligned on its own (fitted posed body -> true posed
                     body), the true cameras mapped through that frame's similarity; the front
                     camera / the other two, as for the 4-view input
    dreamed_views    the dream's views at 90 / 180 / 270 against the true subject rendered from
                     the dream's cameras mapped into the true world (dlacli.data.synth.render_subject)

The residual misalignment (weighted RMS distance of the aligned fitted body from the true one, mm)
goes in every row (`alignment_mm`; `pose_alignment_mm`: its mean over the motion frames), and the
masked PSNR per body region of the novel and dreamed views (`regions`, dlacli.bench.regions).

The error budget (`oracles=True`, config key `oracle`): the same subjects with part of the dream
replaced by the truth, so the gap to the four-view lift splits into its causes (`ORACLES`):

    true_body     the backend's views made on the true body and camera (no fit error): what is
                  left is the colour the backend invents and its silhouette beyond the body
    true_colours  the fitted body and the dream's cameras, but views 1-3 are the true subject
                  rendered from those cameras: what is left is the fit's error
    four_views    the subject's 4 true views and true body (`dla bench accuracy --input views`)
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dlacli.body.alignment import Alignment as Alignment
from dlacli.body.alignment import align_bodies, surface_weights
from dlacli.errors import DlaInputError
from dlacli.limits import FIT_STEPS
from dlacli.types import Cameras

INPUTS = ("views", "photo")  # what `dla bench accuracy --input` lifts: the 4 true views, or one photo
PHOTO_SPLITS = ("novel_views", "novel_poses", "novel_view_pose", "dreamed_views")
ORACLES = ("true_body", "true_colours", "four_views")  # the error budget's rows (module docstring)
DREAMED = (1, 2, 3)  # the dream's views scored against the truth (view 0 is the photo itself)


def _cat(cams: list[Cameras]) -> Cameras:
    import torch

    return Cameras(
        torch.cat([c.viewmats for c in cams]), torch.cat([c.Ks for c in cams]), cams[0].width, cams[0].height
    )


def _rendered(avatar, cameras: Cameras, times, motion=None) -> np.ndarray:
    from dlacli.stages.render import render_avatar

    shots = sorted(render_avatar(avatar, cameras, times, motion), key=lambda s: s.camera)
    return np.stack([s.rgba for s in shots])


def score_dream(
    dreamed, avatar, subject: Path, seed: int, appearance: str, wardrobe: str
) -> tuple[dict[str, dict[str, float]], dict]:
    """The avatar lifted from the dream's views (a ViewSet with the fitted body) scored against
    the synthetic subject `seed` (its folder `subject`, as `synth` wrote it with these appearance
    and wardrobe): ({split: metrics} for PHOTO_SPLITS, {alignment numbers, per-view dreamed
    metrics})."""
    import torch

    from dlacli.bench.accuracy import split_indices
    from dlacli.bench.score import scores
    from dlacli.body.model import get_body_model
    from dlacli.data.synth import render_subject
    from dlacli.io.motion import read_motion
    from dlacli.io.views import read_views
    from dlacli.stages.dream.orbit import AZIMUTHS

    model = get_body_model()
    faces = np.asarray(model.faces, np.int64)
    truth = read_views(subject)
    with torch.no_grad():
        true_v = model.forward_body(truth.body).vertices[0].double().numpy()
        fit_v = model.forward_body(avatar.body).vertices[0].double().numpy()
    weights = surface_weights(true_v, faces)
    align = align_bodies(fit_v, true_v, weights)
    out: dict[str, dict[str, float]] = {}

    nv = read_views(subject / "novel_views", require_body=False)
    pred_nv = _rendered(avatar, align.to_dream(nv.cameras), nv.times)
    out["novel_views"] = scores(pred_nv, _on_black(nv), nv.masks)

    npose = read_views(subject / "novel_poses", require_body=False)
    motion = read_motion(subject / "novel_poses" / "motion.npz")
    frames = np.array([int(t) for t in npose.times])
    used = np.unique(frames)
    fit_m = model.forward_motion(avatar.body.phenotype, motion, frames=used).vertices.double().numpy()
    true_m = model.forward_motion(truth.body.phenotype, motion, frames=used).vertices.double().numpy()
    per_frame = {
        int(f): align_bodies(fit_m[k], true_m[k], surface_weights(true_m[k], faces)) for k, f in enumerate(used)
    }
    cams = _cat([per_frame[int(f)].to_dream(npose.cameras.select(c)) for c, f in enumerate(frames)])
    pred = _rendered(avatar, cams, npose.times, motion)
    gt = _on_black(npose)
    for split, idx in split_indices(npose).items():
        out[split] = scores(pred[idx], gt[idx], npose.masks[idx])

    true_cams = align.to_true(dreamed.cameras.select(list(DREAMED)))
    true_rgba = render_subject(seed, true_cams, appearance=appearance, wardrobe=wardrobe)
    true_rgba = np.round(np.clip(true_rgba, 0.0, 1.0) * 255.0) / 255.0  # 8 bits, as synth's files hold its views
    sel = np.array(DREAMED)
    mine = np.concatenate([dreamed.images[sel] * dreamed.masks[sel][..., None], dreamed.masks[sel][..., None]], -1)
    true_rgb = true_rgba[..., :3] * true_rgba[..., 3:]
    out["dreamed_views"] = scores(mine, true_rgb, true_rgba[..., 3])
    regions = {
        "novel_views": _by_region(pred_nv, _on_black(nv), true_v, nv.cameras, nv.masks),
        "dreamed_views": _by_region(mine, true_rgb, true_v, true_cams, true_rgba[..., 3]),
    }
    info = {
        "alignment_mm": round(align.residual_mm, 2),
        "pose_alignment_mm": round(float(np.mean([a.residual_mm for a in per_frame.values()])), 2),
        "alignment_scale": round(align.scale, 4),
        "dreamed_per_view": {
            str(int(az)): scores(mine[k : k + 1], true_rgb[k : k + 1], true_rgba[k : k + 1, ..., 3])
            for k, az in enumerate(np.asarray(AZIMUTHS)[sel])
        },
        "regions": regions,
    }
    return out, info


def _by_region(pred: np.ndarray, gt: np.ndarray, vertices: np.ndarray, cameras: Cameras, masks: np.ndarray) -> dict:
    """Masked PSNR per body region (dlacli.bench.regions: the true body's parts, off body, the
    silhouette band) of pred [C, H, W, >=3] against gt [C, H, W, 3] inside the true masks [C, H, W]."""
    from dlacli.bench.regions import pixel_regions, region_psnr

    return region_psnr(pred[..., :3], gt, pixel_regions(vertices, cameras, masks))


def _on_black(views) -> np.ndarray:
    return views.images * views.masks[..., None]


def write_photo(subject: Path, path: Path) -> Path:
    """The subject's input view 0 (azimuth 0) as an RGBA PNG: the person cut out, alpha = mask."""
    from PIL import Image

    from dlacli.io.views import read_views

    views = read_views(subject)
    rgba = np.concatenate([views.images[0], views.masks[0][..., None]], axis=-1)
    Image.fromarray(np.round(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8), "RGBA").save(path)
    return path


def check_backends(names: list[str]) -> list[str]:
    """Dream backends by name (dlacli.stages.dream.backends), in order, without repeats."""
    from dlacli.stages.dream.backends import BACKENDS

    out = list(dict.fromkeys(n.strip() for n in names if n.strip()))
    if not out:
        raise DlaInputError("--backend", "name at least one dream backend")
    for n in out:
        if n not in BACKENDS:
            raise DlaInputError("--backend", f"unknown backend {n!r} (choose from {', '.join(BACKENDS)})")
    return out


def truth_fit(subject: Path):
    """The subject's true body and input camera as a body fit (`dlacli.stages.fit.photo.FitResult`):
    what `dream` would use if the fit were perfect (oracle "true_body")."""
    import torch

    from dlacli.body.model import get_body_model
    from dlacli.io.views import read_views
    from dlacli.stages.dream.texture import mask_iou
    from dlacli.stages.fit.photo import FitResult

    truth = read_views(subject)
    with torch.no_grad():
        vertices = get_body_model().forward_body(truth.body).vertices[0].double().numpy()
    camera = truth.cameras.select(0)
    iou = mask_iou(truth.masks[0], camera, vertices)
    return FitResult(truth.body, camera, vertices, np.zeros((17, 3), np.float32), 0.0, iou)


def prior_label(spec: str | None, net) -> str:
    """A body backend's completion prior in rows: "none", "shipped" or the checkpoint's short hash."""
    from dlacli.avatar.checkpoint import short_id

    if net is None:
        return "none"
    return "shipped" if spec == "shipped" else short_id(net.checkpoint_hash)


def oracle_folder(
    oracle: str,
    subject: Path,
    seed: int,
    dreamed: Path,
    out: Path,
    backend: str,
    res: int,
    appearance,
    wardrobe,
    prior=None,
) -> Path:
    """The view folder of an error-budget oracle (`ORACLES`) at `out`: "true_body": the backend's
    views on the true body; "true_colours": the dream's folder `dreamed` with views 1-3 replaced by
    the true subject rendered from its cameras (mapped into the true world through the bodies);
    "four_views": the subject folder itself (returned as is). `prior`: the body backend's
    completion network for "true_body" (or None)."""
    import torch

    from dlacli.body.model import get_body_model
    from dlacli.data.synth import render_subject
    from dlacli.io.views import read_views, write_views
    from dlacli.stages.dream.views import build_views, write_dream_folder

    if oracle == "four_views":
        return subject
    truth = read_views(subject)
    if oracle == "true_body":
        fit = truth_fit(subject)
        views = build_views(truth.images[0], truth.masks[0], fit, backend=backend, res=res, prior=prior)
        views.extra["dream"]["oracle"] = oracle
        overlay = np.round(truth.images[0] * truth.masks[0][..., None] * 255.0)
        return write_dream_folder(views, overlay, out)
    if oracle != "true_colours":
        raise ValueError(f"unknown oracle {oracle!r}")
    views = read_views(dreamed)
    model = get_body_model()
    with torch.no_grad():
        true_v = model.forward_body(truth.body).vertices[0].double().numpy()
        fit_v = model.forward_body(views.body).vertices[0].double().numpy()
    align = align_bodies(fit_v, true_v, surface_weights(true_v, np.asarray(model.faces, np.int64)))
    sel = list(DREAMED)
    rgba = render_subject(seed, align.to_true(views.cameras.select(sel)), appearance=appearance, wardrobe=wardrobe)
    rgba = np.clip(rgba, 0.0, 1.0)
    images, masks = views.images.copy(), views.masks.copy()
    images[sel], masks[sel] = rgba[..., :3], rgba[..., 3]
    views.extra.setdefault("dream", {})["oracle"] = oracle
    write_views(type(views)(images, masks, views.cameras, views.body, views.file_paths, views.times, views.extra), out)
    return out


def run_photo(
    seeds: list[int],
    methods,
    backends: list[str],
    res: int = 512,
    appearance: str = "lit",
    wardrobe: str = "heldout",
    novel_views: int = 12,
    novel_poses: int = 8,
    fit_steps: int = FIT_STEPS,
    log: Callable[[str], None] = print,
    keep: Path | None = None,
    oracles: bool = False,
    priors: list[str] | None = None,
) -> list[dict]:
    """dla.bench/1 rows, one per seed, backend, method and split (PHOTO_SPLITS), the subjects
    as `dla bench accuracy` makes them (bench/accuracy.run); a subject whose dream fails (e.g. no
    person detected) gives one row per split with status "error". `oracles`: also the error
    budget's rows (`ORACLES`, config `oracle`; "four_views" once per subject, backend "truth").
    `priors`: the body backend's completion priors to compare (`dla dream --prior`; default:
    "none"), each its own rows (config `prior`: "none", "shipped" or the checkpoint's short hash)."""
    from dlacli.bench.accuracy import subjects, timed_lift
    from dlacli.bench.rows import make_row
    from dlacli.io.avatar import read_avatar
    from dlacli.io.views import read_views
    from dlacli.stages.dream.completion import load_prior
    from dlacli.stages.dream.views import dream

    backends = check_backends(backends)
    priors = list(dict.fromkeys(priors or ["none"]))
    nets = {p: load_prior(p) for p in priors}  # a bad checkpoint fails before any subject is made
    variants_of = {b: priors if b == "body" else [None] for b in backends}
    variants = [(b, p) for b in backends for p in variants_of[b]]
    for spec in methods:
        spec.install()
    rows: list[dict] = []
    work = Path(tempfile.mkdtemp(prefix="dla-photo-bench-"))

    def lift_and_score(folder: Path, base: dict, seed: int, subject: Path, dream_s: float, tag: str) -> None:
        dreamed = read_views(folder)
        # views 1-3 of these oracles are the truth itself: their dreamed split would be exact
        splits = PHOTO_SPLITS[:3] if base.get("oracle") in ("true_colours", "four_views") else PHOTO_SPLITS
        for spec in methods:
            path = work / f"{folder.name}_{len(rows)}.npz"
            lift_s, peak = timed_lift(spec, folder, path)
            avatar = read_avatar(path)
            result, info = score_dream(dreamed, avatar, subject, seed, appearance, wardrobe)
            fit = dreamed.extra.get("dream", {}).get("fit", {})
            extra = {"stages": {"dream_s": round(dream_s, 3), "lift_s": round(lift_s, 3)}, **info, "fit": fit}
            for split in splits:
                row = make_row(
                    spec.name, {**spec.options(), **base}, split, dream_s + lift_s, peak, result[split], seed
                )
                rows.append({**row, **extra})
            log(
                f"seed {seed} {tag} {spec.label}: dream {dream_s:.1f} s, lift {lift_s:.1f} s, "
                f"alignment {info['alignment_mm']:.1f} mm (poses {info['pose_alignment_mm']:.1f}); "
                + "; ".join(f"{s} {result[s]['psnr_masked']:.2f} dB masked, IoU {result[s]['iou']:.3f}" for s in splits)
            )
            path.unlink()

    with tempfile.TemporaryDirectory(dir=work) as tmp:
        for seed, subject in subjects(seeds, Path(tmp), res, novel_views, novel_poses, appearance, wardrobe, keep):
            photo = write_photo(subject, Path(tmp) / f"s{seed}_photo.png")
            common = {"res": res, "appearance": appearance, "wardrobe": wardrobe, "input": "photo"}
            for backend, prior in variants:
                base = {**common, "backend": backend, "fit_steps": fit_steps}
                name = f"{backend}"
                if backend == "body":
                    base["prior"] = prior_label(prior, nets[prior])
                    name += f"_{base['prior']}"
                folder = Path(tmp) / f"s{seed}_{name}"
                t0 = time.perf_counter()
                try:
                    dream(photo, folder, backend=backend, res=res, fit_steps=fit_steps, prior=prior or "none")
                except DlaInputError as err:
                    for spec in methods:
                        for split in PHOTO_SPLITS:
                            config = {**spec.options(), **base}
                            rows.append(
                                make_row(spec.name, config, split, 0.0, None, {}, seed, status="error", error=str(err))
                            )
                    log(f"seed {seed} photo/{backend}: dream failed: {err}")
                    continue
                dream_s = time.perf_counter() - t0
                lift_and_score(folder, base, seed, subject, dream_s, f"photo/{name}")
                first = prior == variants_of[backend][0]
                for oracle in [o for o in ORACLES[:2] if oracles and (first or o == "true_body")]:
                    out = Path(tmp) / f"s{seed}_{name}_{oracle}"
                    t0 = time.perf_counter()
                    oracle_folder(
                        oracle, subject, seed, folder, out, backend, res, appearance, wardrobe, prior=nets.get(prior)
                    )
                    tag = f"photo/{name} oracle={oracle}"
                    lift_and_score(out, {**base, "oracle": oracle}, seed, subject, time.perf_counter() - t0, tag)
            if oracles:
                base = {**common, "backend": "truth", "oracle": "four_views"}
                lift_and_score(subject, base, seed, subject, 0.0, "oracle=four_views")
    work.rmdir()
    return rows
