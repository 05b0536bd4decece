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
goes in every row (`alignment_mm`; `pose_alignment_mm`: its mean over the motion frames).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.limits import FIT_STEPS
from dlacli.types import Cameras

INPUTS = ("views", "photo")  # what `dla bench accuracy --input` lifts: the 4 true views, or one photo
PHOTO_SPLITS = ("novel_views", "novel_poses", "novel_view_pose", "dreamed_views")
DREAMED = (1, 2, 3)  # the dream's views scored against the truth (view 0 is the photo itself)


@dataclass(frozen=True)
class Alignment:
    """x_true = scale * rotation @ x_dream + translation; residual_mm: the weighted RMS distance
    of the aligned fitted body from the true one."""

    scale: float
    rotation: np.ndarray  # [3, 3]
    translation: np.ndarray  # [3]
    residual_mm: float

    def points_to_true(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, np.float64) @ self.rotation.T + self.translation

    def to_true(self, cameras: Cameras) -> Cameras:
        """Cameras of the dream's world as the same cameras in the true world."""
        from dlacli.geometry import similarity_cameras

        return similarity_cameras(cameras, self.scale, self.rotation, self.translation)

    def to_dream(self, cameras: Cameras) -> Cameras:
        """Cameras of the true world as the same cameras in the dream's world."""
        from dlacli.geometry import similarity_cameras

        r = self.rotation.T
        return similarity_cameras(cameras, 1.0 / self.scale, r, -(r @ self.translation) / self.scale)


def surface_weights(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V] each vertex's share of the mesh's surface (a third of its triangles' areas): the
    alignment weighs the body's surface evenly, not anny's dense face and hands."""
    v = np.asarray(vertices, np.float64)
    tri = v[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    w = np.zeros(len(v))
    np.add.at(w, faces.reshape(-1), np.repeat(area / 3.0, 3))
    return w


def align_bodies(fitted: np.ndarray, true: np.ndarray, weights: np.ndarray) -> Alignment:
    """The similarity carrying the fitted posed body [V, 3] onto the true one [V, 3] (same
    topology), weighted per vertex (`surface_weights`)."""
    from dlacli.geometry import similarity_fit

    s, r, t = similarity_fit(fitted, true, weights)
    moved = s * np.asarray(fitted, np.float64) @ r.T + t
    err = np.sum((moved - np.asarray(true, np.float64)) ** 2, axis=1)
    residual = float(np.sqrt(np.sum(weights * err) / np.sum(weights))) * 1000.0
    return Alignment(s, r, t, residual)


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
    from dlacli.stages.dream import AZIMUTHS

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
    out["novel_views"] = scores(_rendered(avatar, align.to_dream(nv.cameras), nv.times), _on_black(nv), nv.masks)

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
    info = {
        "alignment_mm": round(align.residual_mm, 2),
        "pose_alignment_mm": round(float(np.mean([a.residual_mm for a in per_frame.values()])), 2),
        "alignment_scale": round(align.scale, 4),
        "dreamed_per_view": {
            str(int(az)): scores(mine[k : k + 1], true_rgb[k : k + 1], true_rgba[k : k + 1, ..., 3])
            for k, az in enumerate(np.asarray(AZIMUTHS)[sel])
        },
    }
    return out, info


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
    """Dream backends by name (dlacli.stages.dream.BACKENDS), in order, without repeats."""
    from dlacli.stages.dream import BACKENDS

    out = list(dict.fromkeys(n.strip() for n in names if n.strip()))
    if not out:
        raise DlaInputError("--backend", "name at least one dream backend")
    for n in out:
        if n not in BACKENDS:
            raise DlaInputError("--backend", f"unknown backend {n!r} (choose from {', '.join(BACKENDS)})")
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
) -> list[dict]:
    """dla.bench/1 rows, one per seed, backend, method and split (PHOTO_SPLITS), the subjects
    as `dla bench accuracy` makes them (bench/accuracy.run); a subject whose dream fails (e.g. no
    person detected) gives one row per split with status "error"."""
    from dlacli.bench.accuracy import subjects, timed_lift
    from dlacli.bench.rows import make_row
    from dlacli.io.avatar import read_avatar
    from dlacli.io.views import read_views
    from dlacli.stages.dream import dream

    backends = check_backends(backends)
    for spec in methods:
        spec.install()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed, subject in subjects(seeds, Path(tmp), res, novel_views, novel_poses, appearance, wardrobe, keep):
            photo = write_photo(subject, Path(tmp) / f"s{seed}_photo.png")
            for backend in backends:
                base = {
                    "res": res,
                    "appearance": appearance,
                    "wardrobe": wardrobe,
                    "input": "photo",
                    "backend": backend,
                }
                base["fit_steps"] = fit_steps
                folder = Path(tmp) / f"s{seed}_{backend}"
                t0 = time.perf_counter()
                try:
                    dream(photo, folder, backend=backend, res=res, fit_steps=fit_steps)
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
                dreamed = read_views(folder)
                for spec in methods:
                    path = Path(tmp) / f"s{seed}_{backend}_{len(rows)}.npz"
                    lift_s, peak = timed_lift(spec, folder, path)
                    avatar = read_avatar(path)
                    result, info = score_dream(dreamed, avatar, subject, seed, appearance, wardrobe)
                    fit = dreamed.extra.get("dream", {}).get("fit", {})
                    extra = {"stages": {"dream_s": round(dream_s, 3), "lift_s": round(lift_s, 3)}, **info, "fit": fit}
                    for split in PHOTO_SPLITS:
                        row = make_row(
                            spec.name, {**spec.options(), **base}, split, dream_s + lift_s, peak, result[split], seed
                        )
                        rows.append({**row, **extra})
                    log(
                        f"seed {seed} photo/{backend} {spec.label}: dream {dream_s:.1f} s, lift {lift_s:.1f} s, "
                        f"alignment {info['alignment_mm']:.1f} mm (poses {info['pose_alignment_mm']:.1f}); "
                        + "; ".join(
                            f"{s} {result[s]['psnr_masked']:.2f} dB masked, IoU {result[s]['iou']:.3f}"
                            for s in PHOTO_SPLITS
                        )
                    )
                    path.unlink()
    return rows
