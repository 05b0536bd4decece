"""A quick look at a motion: the default body mesh doing it, left side blue, right side red,
over a ground plane, from a camera that follows the hips (for checking retargets)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from dlacli.types import Motion

SKIN = (0.80, 0.68, 0.58)
LEFT = (0.45, 0.62, 0.90)  # bones *.L: the person's own left (+X at rest)
RIGHT = (0.90, 0.50, 0.45)
GROUND = (0.55, 0.57, 0.60)
BACKGROUND = (0.12, 0.12, 0.14)
FOV_DEG = 34.7  # focal length 1.6 x image size
CAMERA_OFFSET = (1.3, -3.6, 0.6)  # from the followed hip point: front-left, a little above
FOLLOW_SECONDS = 1.0


def motion_preview_frames(motion: Motion, res: int, batch: int = 16) -> Iterator[np.ndarray]:
    """Yield [res, res, 3] uint8 frames of the default body mesh doing `motion`."""
    from dlacli.body.model import get_body_model
    from dlacli.geometry import look_at_c2w, pinhole_cameras, smooth_path
    from dlacli.render.raster import render_mesh

    model = get_body_model()
    ground = float(model.zero_pose().vertices[0, :, 2].min())
    idx, wts = model.vertex_bone_weights
    dominant = [model.bone_labels[i] for i in idx[np.arange(idx.shape[0]), wts.argmax(axis=1)]]
    colors = np.array([LEFT if b.endswith(".L") else RIGHT if b.endswith(".R") else SKIN for b in dominant])

    path = np.asarray(motion.root_translation, dtype=np.float64)  # [T, 3]
    follow = smooth_path(path[:, :2], motion.fps, FOLLOW_SECONDS)
    lo, hi = path[:, :2].min(0) - 2.0, path[:, :2].max(0) + 2.0
    plane = np.array([[lo[0], lo[1], ground], [hi[0], lo[1], ground], [hi[0], hi[1], ground], [lo[0], hi[1], ground]])
    faces = np.concatenate([model.faces, np.array([[0, 1, 2], [0, 2, 3]]) + model.num_vertices])
    colors = np.concatenate([colors, np.tile(GROUND, (4, 1))]).astype(np.float32)

    for start in range(0, motion.num_frames, batch):
        sel = np.arange(start, min(start + batch, motion.num_frames))
        verts = model.forward_motion({}, motion, frames=sel).vertices.numpy()  # [B, V, 3]
        verts = np.concatenate([verts, np.broadcast_to(plane, (len(sel), 4, 3))], axis=1)
        targets = np.stack([follow[sel, 0], follow[sel, 1], np.full(len(sel), ground + 0.85)], axis=1)
        cams = pinhole_cameras(look_at_c2w(targets + np.asarray(CAMERA_OFFSET), targets), FOV_DEG, res)
        rgba = render_mesh(verts, faces, colors, cams, antialias=2, background=BACKGROUND, as_uint8=True)
        for frame in rgba:
            yield np.ascontiguousarray(frame[..., :3])
