"""Animate: an avatar and a motion -> world Gaussians per frame -> USD and a preview video.

The Gaussian map F is decoded once (identity decoder: F = Z, so the canonical part is F itself),
Gaussians are drawn at fixed surface samples (avatar/gaussian_map.py), and each frame only
recomputes the posed body's tangent frames and the skinning x = T + R dx, R_g = R dR, s = S ds
(avatar/posed.py: a conditioned decoder's F is decoded per frame there).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from dlacli.avatar import gaussian_map as gm
from dlacli.errors import DlaInputError
from dlacli.limits import MAX_GAUSSIAN_FRAMES
from dlacli.types import Avatar, Cameras, Gaussians, Motion, rgb_to_sh0

PREVIEW_AZIMUTH = 25.0  # degrees: a three-quarter front view
PREVIEW_ELEVATION = 8.0
PREVIEW_FOV = 40.0
PREVIEW_EXTENT = 2.3  # metres of the scene the preview frames vertically
FOLLOW_SECONDS = 0.5  # the preview camera follows the pelvis smoothed over this window
USD_VIEW_AZIMUTH = 0.0  # degrees: view-conditioned decoders are evaluated from the front for USD
USD_VIEW_DISTANCE = 3.0  # metres


@dataclass
class Animation:
    """Gaussians over T frames (numpy float32), the animate stage's output before writing."""

    positions: np.ndarray  # [T, N, 3]
    quats: np.ndarray  # [T, N, 4] (w, x, y, z)
    scales: np.ndarray  # [T, N, 3]
    opacities: np.ndarray  # [N], or [T, N] from a conditioned decoder
    rgb: np.ndarray  # [N, 3], or [T, N, 3] from a conditioned decoder
    pelvis: np.ndarray  # [T, 3] root bone head per frame
    fps: float

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]

    def frame(self, t: int) -> Gaussians:
        opacities = self.opacities[t] if self.opacities.ndim == 2 else self.opacities
        rgb = self.rgb[t] if self.rgb.ndim == 3 else self.rgb
        return Gaussians.from_rgb(
            torch.from_numpy(self.positions[t]),
            torch.from_numpy(self.quats[t]),
            torch.from_numpy(self.scales[t]),
            torch.from_numpy(opacities),
            torch.from_numpy(rgb),
        )


@torch.no_grad()
def pose_avatar(
    avatar: Avatar,
    motion: Motion,
    n_gaussians: int | None = None,
    seed: int | None = None,
    batch: int = 8,
    where: str = "avatar",
    progress: Callable[[int, int], None] | None = None,
    checkpoint: str | None = None,
) -> Animation:
    """Skin the avatar's Gaussians for every frame of `motion` (on the avatar's own body shape).

    The canonical map is decoded once; a conditioned decoder adds F_delta per frame, seen from
    USD_VIEW_AZIMUTH when it is view-conditioned (formats/usd.md: a USD file has no camera), and
    then colours and opacities are per frame too. Count and seed default to the avatar's own;
    frames x count is at most limits.MAX_GAUSSIAN_FRAMES (the arrays of every frame are held)."""
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar, sample_settings
    from dlacli.body.model import get_body_model

    count, seed = sample_settings(avatar, n_gaussians, seed)
    if motion.num_frames * count > MAX_GAUSSIAN_FRAMES:
        too_many = f"{motion.num_frames} frames x {count} Gaussians is more than dla animates at once"
        raise DlaInputError(
            "--gaussians",
            f"{too_many} ({MAX_GAUSSIAN_FRAMES:.3g} Gaussian-frames): lower --fps or --gaussians, or cut the motion",
        )
    model = get_body_model()
    decoded = Decoded(avatar, where, checkpoint)
    samples = gm.make_samples(count, seed)
    t_total, n = motion.num_frames, len(samples)
    out = {k: np.empty((t_total, n, d), np.float32) for k, d in (("pos", 3), ("quat", 4), ("scale", 3))}
    if decoded.conditioned:
        out.update(rgb=np.empty((t_total, n, 3), np.float32), alpha=np.empty((t_total, n), np.float32))
    pelvis = np.empty((t_total, 3), np.float32)
    placed = None
    for start in range(0, t_total, batch):
        sel = np.arange(start, min(start + batch, t_total))
        body = model.forward_motion(avatar.body.phenotype, motion, frames=sel)
        posed = PosedAvatar(decoded, samples, body.vertices, eyes=usd_view_eyes(body.bone_heads[:, 0]))
        # frame by frame into the arrays when each frame has its own map (no stacked copy)
        sets = (posed.placed(p) for p in range(len(sel))) if decoded.conditioned else [posed.all()]
        for k, placed in enumerate(sets):
            parts = {"pos": placed.means, "quat": placed.quats, "scale": placed.scales}
            if decoded.conditioned:  # colours and opacities per frame too
                parts.update(rgb=placed.rgb, alpha=placed.opacities)
            rows = sel[k : k + 1] if decoded.conditioned else sel
            for key, x in parts.items():
                out[key][rows] = x.numpy()
        pelvis[sel] = body.bone_heads[:, 0].numpy()
        if progress is not None:
            progress(int(sel[-1]) + 1, t_total)
    if not decoded.conditioned:  # one F for every frame
        out.update(alpha=placed.opacities.numpy(), rgb=placed.rgb.numpy())
    return Animation(out["pos"], out["quat"], out["scale"], out["alpha"], out["rgb"], pelvis, motion.fps)


def usd_view_eye(pelvis: torch.Tensor) -> torch.Tensor:
    """The camera centre [3] a view-conditioned decoder is evaluated from for USD (formats/usd.md):
    in front of the body (azimuth 0, the input photo's side), at pelvis height, 3 m away, moving
    with the pelvis so the view of the body does not change as it walks."""
    from dlacli.geometry import orbit_eyes

    eye = orbit_eyes(pelvis.double().numpy(), USD_VIEW_DISTANCE, USD_VIEW_AZIMUTH, 0.0)
    return torch.as_tensor(np.asarray(eye, dtype=np.float32).reshape(3))


def usd_view_eyes(pelvis: torch.Tensor) -> torch.Tensor:
    """`usd_view_eye` of P bodies: pelvis [P, 3] -> eyes [P, 1, 3], one camera per body
    (avatar/posed.PosedAvatar's eyes)."""
    return torch.stack([usd_view_eye(p) for p in pelvis])[:, None]


def follow_cameras(pelvis: np.ndarray, fps: float, size: int) -> Cameras:
    """One camera per frame ([T] cameras) at a fixed three-quarter angle, following the pelvis
    [T, 3] smoothed over FOLLOW_SECONDS, so turning and walking read clearly."""
    from dlacli.geometry import framing_distance, look_at_c2w, orbit_eyes, pinhole_cameras, smooth_path

    target = smooth_path(pelvis, fps, FOLLOW_SECONDS)
    target[:, 2] = pelvis[:, 2].mean() - 0.05  # steady height: the body may crouch or jump in frame
    dist = framing_distance(PREVIEW_EXTENT, PREVIEW_FOV, margin=1.0)
    eyes = np.concatenate([orbit_eyes(t, dist, PREVIEW_AZIMUTH, PREVIEW_ELEVATION) for t in target])
    return pinhole_cameras(look_at_c2w(eyes, target), PREVIEW_FOV, size)


def animation_preview_frames(anim: Animation, size: int = 512) -> Iterator[np.ndarray]:
    """RGBA float frames [H, W, 4] of the animation's Gaussians splatted from `follow_cameras`,
    composited by the fast kernel (playback: `exact=False`)."""
    from dlacli.avatar.posed import render_set

    cams = follow_cameras(anim.pelvis, anim.fps, size)
    for t in range(anim.num_frames):
        with torch.no_grad():
            out = render_set(anim.frame(t), cams.select(t), exact=False)
        yield out.rgba(0)


def write_animation(
    anim: Animation, path: str | os.PathLike, schema: str = "instancer", tolerance: float = 0.0
) -> None:
    """The USD contract (formats/usd.md). `tolerance` (metres) > 0 compacts the time samples:
    rigid parts, and samples USD's interpolation reproduces within it left out; 0 writes every
    frame exactly (scales only where they change)."""
    from dlacli.io.usd import write_usd

    sh = rgb_to_sh0(torch.from_numpy(anim.rgb)).numpy()[:, None, :] if anim.rgb.ndim == 2 else None
    write_usd(
        path,
        anim.positions,
        anim.quats,
        anim.scales,
        anim.rgb,
        anim.opacities,
        anim.fps,
        sh=sh,
        schema=schema,
        tolerance=tolerance,
    )
