"""The dream backend "diffusion": the paper's pose-controlled video diffusion (dlacli.nn.video_diffusion;
extra "diffusion" and local weights). The fitted body's COCO skeleton is drawn along a 360-degree
orbit of `frames` frames; the pipeline animates the framed photo along it, and the frames at
azimuths 90, 180 and 270 are the novel views, keyed off their white background inside the shell
backend's silhouettes."""

from __future__ import annotations

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.stages.dream.backends import Backend, register
from dlacli.types import Cameras


def orbit_frame_azimuths(frames: int) -> np.ndarray:
    """[frames + 1] azimuths (degrees) of the orbit video: frame k at 360 k / frames, so frame 0
    is the input view and frame `frames` closes the circle (360 = 0). With the paper's 80 frames,
    its 1-based frames 20 / 40 / 60 / 80 are our frames 20 / 40 / 60 / 80 at 90 / 180 / 270 / 360;
    the leading frame 0 makes the video 81 frames long, which Wan needs (4 k + 1)."""
    return 360.0 * np.arange(frames + 1) / frames


def view_frames(frames: int) -> tuple[int, int, int]:
    """Video frame indices of the novel views at azimuths 90, 180, 270."""
    return frames // 4, frames // 2, 3 * frames // 4


def key_masks(frames: np.ndarray, prior: np.ndarray, threshold: float = 0.1) -> np.ndarray:
    """Person masks [N, H, W] of generated frames [N, H, W, 3] on a white background.

    A pixel is the person where it differs from white by more than `threshold` (max over channels)
    and lies within the dilated prior silhouette [N, H, W] (the template shell seen from the same
    camera), which removes stray marks elsewhere; where keying finds less than 30 % of the
    prior's area (a failed generation) the prior itself is used."""
    from scipy import ndimage

    out = np.empty(prior.shape, np.float32)
    for i in range(frames.shape[0]):
        p = prior[i] > 0.5
        near = ndimage.binary_dilation(p, iterations=max(1, prior.shape[1] // 32))
        keyed = (np.abs(1.0 - frames[i]).max(axis=-1) > threshold) & near
        keyed = ndimage.binary_fill_holes(ndimage.binary_opening(keyed))
        out[i] = keyed if keyed.sum() >= 0.3 * p.sum() else prior[i]
    return out


def diffusion_views(
    rgb,
    alpha,
    camera: Cameras,
    vertices: np.ndarray,
    pipe,
    *,
    frames: int = 80,
    steps: int = 50,
    seed: int = 0,
    progress=None,
):
    """The paper's procedure on a framed photo (see dlacli.nn.video_diffusion).

    rgb [R, R, 3], alpha [R, R], camera (the crop's), vertices [V, 3] fitted body ->
    (images [4, R, R, 3], masks [4, R, R], cameras, skeleton video [frames + 1, R, R, 3] uint8).
    """
    from dlacli.body.keypoints import COCO_SKELETON, coco_keypoints
    from dlacli.nn.video_diffusion import draw_skeletons, generate_orbit, project_points
    from dlacli.stages.dream.orbit import body_pivot, orbit_cameras
    from dlacli.stages.dream.shell import template_views

    if frames < 4 or frames % 4:
        raise DlaInputError("--frames", f"must be a positive multiple of 4, got {frames}")
    orbit = orbit_cameras(camera, body_pivot(vertices), orbit_frame_azimuths(frames))
    pts, front = project_points(coco_keypoints(np.asarray(vertices, np.float64)), orbit)
    skeletons = draw_skeletons(pts, front, COCO_SKELETON, camera.width)
    reference = rgb * alpha[..., None] + (1.0 - alpha[..., None])  # on white
    if progress:
        progress(f"diffusion: {frames + 1} frames, {steps} steps")
    video = generate_orbit(pipe, reference, skeletons, steps=steps, seed=seed)
    pick = list(view_frames(frames))
    _, prior, cams = template_views(rgb, alpha, camera, vertices)
    masks = key_masks(video[pick], prior[1:])
    novel = np.where(masks[..., None] > 0, video[pick], 0.0)
    images = np.concatenate([rgb[None], novel]).astype(np.float32)
    return images, np.concatenate([alpha[None], masks]).astype(np.float32), cams, skeletons


def load_diffusion(model, device, res, frames, say):
    from dlacli.nn.video_diffusion import DEFAULT_MODEL, load_pipeline

    if res % 16:
        raise DlaInputError("--res", f"the diffusion backend needs a multiple of 16, got {res}")
    if frames < 4 or frames % 4:
        raise DlaInputError("--frames", f"must be a positive multiple of 4, got {frames}")
    say("loading the diffusion pipeline")
    model = model or DEFAULT_MODEL
    return load_pipeline(model, device=device), model


def diffusion_backend_views(rgb, alpha, cam, vertices, pipe, *, frames, steps, seed, say, prior=None):
    if pipe is None:
        raise DlaInputError("--backend diffusion", "no pipeline loaded")
    images, masks, cams, _ = diffusion_views(
        rgb, alpha, cam, vertices, pipe, frames=frames, steps=steps, seed=seed, progress=say
    )
    settings = {"steps": steps, "frames": frames, "seed": seed, "video_frames": [0, *view_frames(frames)]}
    return images, masks, cams, settings


register(
    Backend(
        "diffusion",
        "pose-controlled video diffusion (extra 'diffusion' and local weights)",
        diffusion_backend_views,
        load_diffusion,
    )
)
