"""The dream's cameras: the photo's camera turned about the vertical axis through the fitted
body (docs/dream.md step 3), shared by dream, its backends (stages/dream/texture.py, stages/dream/shell.py)
and the completion prior's training targets."""

from __future__ import annotations

import math

import numpy as np

from dlacli.types import Cameras

AZIMUTHS = (0.0, 90.0, 180.0, 270.0)  # degrees, view order in the folder


def body_pivot(vertices: np.ndarray) -> np.ndarray:
    """[V, 3] -> [3] the centre of the body's bounding box: the orbit's vertical axis passes here."""
    v = np.asarray(vertices, np.float64)
    return (v.min(axis=0) + v.max(axis=0)) / 2.0


def orbit_cameras(camera: Cameras, pivot: np.ndarray, azimuths_deg) -> Cameras:
    """The first camera turned about the vertical (+Z) line through pivot [3] by each azimuth
    (degrees, counter-clockwise seen from above) -> len(azimuths) cameras, same intrinsics."""
    c2w = camera.c2w_opengl()[0]  # [4, 4]
    p = np.asarray(pivot, np.float64)
    mats = []
    for a in azimuths_deg:
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        rot = np.eye(4)
        rot[:2, :2] = [[c, -s], [s, c]]
        move = np.eye(4)
        move[:3, 3] = p
        back = np.eye(4)
        back[:3, 3] = -p
        mats.append(move @ rot @ back @ c2w)
    k = camera.Ks[0].double().numpy()
    return Cameras.from_c2w_opengl(np.stack(mats), k[0, 0], k[1, 1], k[0, 2], k[1, 2], camera.width, camera.height)
