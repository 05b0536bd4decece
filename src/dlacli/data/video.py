"""A synthetic video of a person doing a known motion (the ground truth of `dla motion
from-video`'s tests and speed benchmark): the seeded synthetic subject (default wardrobe, albedo
appearance) posed by the motion, seen by a level, static camera with the photo fit's 50 degree
field of view, over a flat grey background."""

from __future__ import annotations

import os

import numpy as np
import torch

from dlacli.types import Motion

BACKGROUND = 0.45
FOV_DEG = 50.0  # = stages.fit.photo.FOV_Y_DEG: the focal length the from-video fit guesses
DISTANCE = 3.6  # metres from the camera to the motion's mean root position (the camera on its -Y side)


def render_motion_video(
    motion: Motion, path: str | os.PathLike, *, res: int = 320, seed: int = 0, blank: tuple[int, int] | None = None
) -> int:
    """Write `motion` (at its own fps) as an mp4 of res x res frames; frames blank[0]..blank[1]
    (inclusive) show the background only. Returns the number of frames."""
    from dlacli.body.model import get_body_model
    from dlacli.data.garments import DressedBody
    from dlacli.data.images import render
    from dlacli.data.subject import sample_subject
    from dlacli.geometry import look_at_c2w, pinhole_cameras
    from dlacli.io.video import write_video

    model = get_body_model()
    body = DressedBody(sample_subject(seed, "default"))
    rot = model.motion_rotations(motion)
    centre = np.asarray(motion.root_translation, np.float64).mean(0)
    cams = pinhole_cameras(look_at_c2w((centre + [0.0, -DISTANCE, 0.0])[None], centre[None]), FOV_DEG, res)
    rr = torch.from_numpy(np.asarray(motion.root_rotation, np.float32))
    rt = torch.from_numpy(np.asarray(motion.root_translation, np.float32))

    def frames():
        for s in range(0, motion.num_frames, 8):
            verts = body.vertices(rot[s : s + 8], rr[s : s + 8], rt[s : s + 8])
            for k, v in enumerate(verts, start=s):
                if blank is not None and blank[0] <= k <= blank[1]:
                    yield np.full((res, res, 3), BACKGROUND, np.float32)
                    continue
                rgba = render(body, v, cams, seed)[0]
                yield rgba[..., :3] * rgba[..., 3:] + BACKGROUND * (1.0 - rgba[..., 3:])

    return write_video(frames(), path, motion.fps)
