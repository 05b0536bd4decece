"""Render an avatar from given cameras, in its own pose or at frames of a motion.

Frame entries of a transforms.json that carry `time` are rendered at that motion frame; others at
motion frame 0, or in the avatar's own pose (the pose it was lifted in) when no motion is given.
Outputs are RGBA images named f{frame:04d}_c{camera:03d}.png (frame = motion frame, camera = the
entry's index in the frames list).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.types import Avatar, Cameras, Motion

TURNTABLE_ELEVATION = 5.0
TURNTABLE_FOV = 40.0
TURNTABLE_EXTENT = 2.2


@dataclass
class Shot:
    frame: int  # motion frame (0 without a motion)
    camera: int  # index of the camera
    rgba: np.ndarray  # [H, W, 4] float32

    @property
    def name(self) -> str:
        return f"f{self.frame:04d}_c{self.camera:03d}.png"


def _pose_vertices(avatar: Avatar, motion: Motion | None, frames: np.ndarray) -> torch.Tensor:
    """Posed body vertices [len(frames), V, 3] for motion frames (or the avatar's own pose)."""
    from dlacli.body.model import get_body_model

    model = get_body_model()
    if motion is None:
        return model.forward_body(avatar.body).vertices.expand(len(frames), -1, -1)
    if frames.size and frames.max() >= motion.num_frames:
        raise DlaInputError(
            "--cameras", f"a frame's time {int(frames.max())} is past the motion's last frame ({motion.num_frames - 1})"
        )
    return model.forward_motion(avatar.body.phenotype, motion, frames=frames).vertices


@torch.no_grad()
def render_avatar(
    avatar: Avatar,
    cameras: Cameras,
    times: list[int | None],
    motion: Motion | None = None,
    n_gaussians: int | None = None,
    seed: int | None = None,
    where: str = "avatar",
    progress: Callable[[int, int], None] | None = None,
    checkpoint: str | None = None,
) -> Iterator[Shot]:
    """Shots for each camera (times [C]: motion frame per camera, None = frame 0 / own pose).

    The frames' bodies and the cameras go through avatar/posed.py (`PosedAvatar`): F_c once, F
    per motion frame when the decoder is pose-conditioned and per camera when it is
    view-conditioned. Gaussian count and seed default to the ones the avatar records
    (`sample_settings`)."""
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar, avatar_samples

    decoded = Decoded(avatar, where, checkpoint)
    samples = avatar_samples(avatar, n_gaussians, seed)
    frame_of = np.array([0 if t is None else int(t) for t in times], dtype=np.int64)
    done = 0
    for frame in np.unique(frame_of):
        cams = np.nonzero(frame_of == frame)[0]
        sub = cameras.select(cams)
        verts = _pose_vertices(avatar, motion, np.array([frame]))  # [1, V, 3]
        posed = PosedAvatar(decoded, samples, verts, sub)
        for group, out in posed.renders():
            for k, c in enumerate(cams[group]):
                rgba = out.rgba(k)
                yield Shot(int(frame), int(c), rgba)
                done += 1
                if progress is not None:
                    progress(done, len(times))


def turntable_cameras(avatar: Avatar, n: int, size: int) -> Cameras:
    """n cameras evenly around the avatar's own body, azimuth 0 in front."""
    from dlacli.body.model import get_body_model
    from dlacli.geometry import framing_distance, look_at_orbit_cameras

    if n < 1:
        raise DlaInputError("--turntable", f"needs at least 1 camera, got {n}")
    verts = get_body_model().forward_body(avatar.body).vertices[0].numpy()
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    target = 0.5 * (lo + hi)
    dist = framing_distance(max(TURNTABLE_EXTENT, float(hi[2] - lo[2]) + 0.2), TURNTABLE_FOV, margin=1.0)
    azimuths = 360.0 * np.arange(n) / n
    return look_at_orbit_cameras(target, dist, azimuths, TURNTABLE_ELEVATION, TURNTABLE_FOV, size)
