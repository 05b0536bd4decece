"""Dream: one photo of a person -> a view folder (input view + novel views) and the fitted body.

Steps (docs/dream.md):
1. person mask (--mask, else the photo's alpha channel, else mediapipe) and COCO-17 keypoints
   (--keypoints, else mediapipe); the body fit (stages/fit/photo.py `fit_body`) gives the body and
   the photo's camera;
2. framing: a square crop of the photo around the person, resampled to res x res; the crop's
   camera is the input camera with adjusted intrinsics (`frame_crop`);
3. novel views at azimuths 90 / 180 / 270 degrees: the input camera turned about the vertical
   (+Z) axis through the body's centre, counter-clockwise seen from above (stages/dream/orbit.py), so
   azimuth 90 puts the camera on the +X side when the input camera is at azimuth 0 (-Y side);
4. the novel views, from the backend `--backend` names (stages/dream/backends/: body, the default,
   shell and diffusion; each module says what it does).
View 0 is always the cropped photo itself, so the input view is exact.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.limits import DEFAULT_LANDMARKS, FIT_STEPS
from dlacli.stages.dream.backends import BACKENDS, DEFAULT, get
from dlacli.stages.dream.orbit import AZIMUTHS
from dlacli.stages.dream.plausibility import plausibility
from dlacli.types import Cameras, ViewSet

MARGIN = 0.08  # crop margin around the person's bounding box, fraction of its longer side
MIN_PERSON_PX = 32  # the person must be at least this many pixels tall in the photo


Progress = Callable[[str], None]


def crop_box(mask: np.ndarray, margin: float = MARGIN) -> tuple[int, int, int]:
    """[H, W] person mask -> (x0, y0, side): an integer square around the person (may extend
    past the image; the outside is transparent)."""
    ys, xs = np.nonzero(mask > 0.5)
    if ys.size == 0:
        raise DlaInputError("mask", "the person mask is empty (no pixel above 0.5)")
    h = ys.max() + 1 - ys.min()
    if h < MIN_PERSON_PX:
        raise DlaInputError("photo", f"the person is only {h} px tall; need at least {MIN_PERSON_PX} px")
    side = int(math.ceil(max(h, xs.max() + 1 - xs.min()) * (1.0 + 2.0 * margin)))
    cx, cy = (xs.min() + xs.max() + 1) / 2.0, (ys.min() + ys.max() + 1) / 2.0
    return int(round(cx - side / 2.0)), int(round(cy - side / 2.0)), side


def _window(arr: np.ndarray, x0: int, y0: int, side: int) -> np.ndarray:
    """arr [H, W, C] -> [side, side, C] window starting at (x0, y0), zero outside the image."""
    h, w = arr.shape[:2]
    out = np.zeros((side, side, arr.shape[2]), np.float32)
    ax0, ay0, ax1, ay1 = max(x0, 0), max(y0, 0), min(x0 + side, w), min(y0 + side, h)
    if ax1 > ax0 and ay1 > ay0:
        out[ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0] = arr[ay0:ay1, ax0:ax1]
    return out


def resample(arr: np.ndarray, res: int) -> np.ndarray:
    """[S, S, C] -> [res, res, C] area-correct resampling (antialiased bilinear, edges to edges)."""
    if arr.shape[0] == res:
        return arr.astype(np.float32)
    t = torch.from_numpy(np.ascontiguousarray(arr, np.float32)).permute(2, 0, 1)[None]
    out = torch.nn.functional.interpolate(t, size=(res, res), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def frame_crop(
    image: np.ndarray, mask: np.ndarray, camera: Cameras, res: int
) -> tuple[np.ndarray, np.ndarray, Cameras]:
    """Square crop around the person resampled to res x res.

    image [H, W, 3], mask [H, W] in [0, 1], camera: 1 camera of the photo ->
    (rgb [res, res, 3] straight colour, alpha [res, res], the crop's camera). Pixel coordinates
    map as u' = (u - x0) * s with s = res / side, so K' = diag(s, s, 1) [fx, 0, cx - x0; ...].
    """
    x0, y0, side = crop_box(mask)
    rgba = np.concatenate([image * mask[..., None], mask[..., None]], axis=-1)  # premultiplied
    out = np.clip(resample(_window(rgba.astype(np.float32), x0, y0, side), res), 0.0, 1.0)
    alpha = out[..., 3]
    rgb = np.where(alpha[..., None] > 1e-6, out[..., :3] / np.maximum(alpha[..., None], 1e-6), 0.0)
    s = res / side
    ks = camera.Ks[:1].clone().double()
    ks[0, 0, 2] -= x0
    ks[0, 1, 2] -= y0
    ks[0, :2, :] *= s
    cam = Cameras(camera.viewmats[:1].clone(), ks.to(camera.Ks.dtype), res, res)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), alpha.astype(np.float32), cam


# ------------------------------------------------------------------------------- orchestration


def _read_inputs(photo, mask_path, keypoints_path, notes: list[str], detection=None, landmarks=DEFAULT_LANDMARKS):
    """-> image [H, W, 3], mask [H, W], keypoints [17, 3], 3D landmarks [17, 4] or None, whether
    the detector ran. Mask:
    --mask, else the photo's alpha channel (dlacli.io.photo's rule), else mediapipe; keypoints:
    --keypoints (with its optional "keypoints_3d"), else mediapipe (its world landmarks). When the
    mask is known, the detector sees the photo composited over grey (`detect_person`'s alpha), as
    the stored test keypoints were made. `detection`: a started `dlacli.io.detect.BackgroundDetection`
    of the same photo and mask (the CLI starts one before importing torch), used instead;
    `landmarks`: MediaPipe's landmark model (io.detect.landmark_model)."""
    from dlacli.io.photo import read_coco_keypoints_3d, read_photo

    image, mask, keypoints = read_photo(photo, mask_path=mask_path, keypoints_path=keypoints_path, notes=notes)
    world = None if keypoints_path is None else read_coco_keypoints_3d(keypoints_path)
    detected = mask is None or keypoints is None
    if detected:
        try:
            if detection is not None:
                det = detection.result()
            else:
                from dlacli.io.detect import detect_person

                det = detect_person(image, alpha=mask, landmarks=landmarks)
        except DlaInputError as err:
            missing = " and ".join(n for n, v in (("--mask", mask), ("--keypoints", keypoints)) if v is None)
            why = " (the photo has no alpha channel)" if mask is None else ""
            raise DlaInputError(photo, f"{err.problem}: pass {missing}{why}") from None
        mask = det.mask if mask is None else mask
        if keypoints is None:
            keypoints, world = det.keypoints, det.world
    return image, np.asarray(mask, np.float32), np.asarray(keypoints, np.float32), world, detected


def build_views(
    image: np.ndarray,
    mask: np.ndarray,
    fit,
    *,
    backend: str = DEFAULT,
    res: int = 512,
    pipe=None,
    frames: int = 80,
    steps: int = 50,
    seed: int = 0,
    progress: Progress | None = None,
    prior=None,
) -> ViewSet:
    """Photo [H, W, 3] + person mask [H, W] + body fit (`dlacli.stages.fit.photo.FitResult`) -> the
    4 views (azimuths 0, 90, 180, 270) as a ViewSet with the fitted body. `prior`: see stages/dream/backends/."""
    from dlacli.stages.dream.texture import photo_trust
    from dlacli.stages.fit.report import fit_info

    say = progress or (lambda msg: None)
    rgb, alpha, cam = frame_crop(image, mask, fit.camera, res)
    info = {
        "backend": backend,
        "azimuths": list(AZIMUTHS),
        "fit_overlay": "fit_overlay.png",
        "fit": fit_info(fit),
    }
    images, masks, cams, settings = get(backend).views(
        rgb, alpha, cam, fit.vertices, pipe, frames=frames, steps=steps, seed=seed, say=say, prior=prior
    )
    info.update(settings)
    info["plausibility"] = plausibility(images, masks, cams, fit.vertices)
    info["silhouette_excess"] = info["plausibility"]["excess"]
    names = [f"images/view_{i:03d}.png" for i in range(len(images))]
    trust = np.ones(masks.shape, np.float32)  # views 1-3 show the backend's own surface
    trust[0] = photo_trust(rgb, alpha, cam, fit.vertices)
    return ViewSet(images, masks, cams, fit.body, names, [None] * len(images), {"dream": info}, trust)


def write_dream_folder(views: ViewSet, overlay: np.ndarray, output: str | os.PathLike) -> Path:
    """Write the view folder plus fit_overlay.png [H, W, 3] uint8, atomically as a whole."""
    from PIL import Image

    from dlacli.io.atomic import atomic_dir
    from dlacli.io.views import write_views

    with atomic_dir(output) as tmp:
        write_views(views, tmp)
        Image.fromarray(np.asarray(overlay, np.uint8)).save(tmp / "fit_overlay.png")
    return Path(output)


def dream(
    photo: str | os.PathLike,
    output: str | os.PathLike,
    *,
    backend: str = DEFAULT,
    keypoints: str | os.PathLike | None = None,
    mask: str | os.PathLike | None = None,
    res: int = 512,
    model: str | None = None,
    steps: int = 50,
    frames: int = 80,
    seed: int = 0,
    fit_steps: int = FIT_STEPS,
    device: str | None = None,
    progress: Progress | None = None,
    detection=None,
    prior: str | None = None,
    landmarks: str = DEFAULT_LANDMARKS,
) -> Path:
    """One photo -> a view folder at `output` (written atomically; see the module docstring).
    `detection`, `landmarks`: see `_read_inputs`. `prior`: the body backend's completion prior, "none",
    "shipped" or a checkpoint (dlacli.stages.dream.completion.load_prior); None: its default."""
    from dlacli.stages.fit.photo import fit_body
    from dlacli.stages.fit.report import fit_warning, overlay_png

    say = progress or (lambda msg: None)
    chosen = get(backend)
    if not 64 <= res <= 4096:
        raise DlaInputError("--res", f"must be in [64, 4096], got {res}")
    if steps < 1:
        raise DlaInputError("--steps", f"must be >= 1, got {steps}")
    from dlacli.stages.dream.completion import DEFAULT_PRIOR, load_prior

    if not chosen.takes_prior and prior not in (None, "none"):
        takers = [b.name for b in BACKENDS.values() if b.takes_prior]
        raise DlaInputError("--prior", f"applies to --backend {' or '.join(takers)} only")
    completion_prior = load_prior(DEFAULT_PRIOR if prior is None else prior) if chosen.takes_prior else None
    pipe = None
    if chosen.load is not None:
        pipe, model = chosen.load(model, device, res, frames, say)
    notes: list[str] = []
    image, person, kps, world, detected = _read_inputs(photo, mask, keypoints, notes, detection, landmarks)
    for note in notes:
        say(note)
    crop_box(person)  # fail early on an empty mask or a tiny person
    say("fitting the body")
    fit = fit_body(
        image,
        person,
        kps,
        steps=fit_steps,
        landmarks_3d=world,
        progress=lambda done, total: say(f"fitting the body {done}/{total}"),
    )
    warning = fit_warning(fit)
    if warning:
        notes.append(warning)
        say(warning)
    views = build_views(
        image,
        person,
        fit,
        backend=backend,
        res=res,
        pipe=pipe,
        frames=frames,
        steps=steps,
        seed=seed,
        progress=say,
        prior=completion_prior,
    )
    views.extra["dream"]["photo"] = Path(photo).name
    if notes:
        views.extra["dream"]["notes"] = notes
    if model is not None:
        views.extra["dream"]["model"] = str(model)
    if detected:
        views.extra["dream"]["landmarks"] = landmarks
    say("writing the view folder")
    return write_dream_folder(views, overlay_png(image * person[..., None], fit), output)
