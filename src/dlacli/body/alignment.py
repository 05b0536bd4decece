"""Two posed bodies of one topology aligned by a similarity (scale, rotation, translation): how
the single-photo benchmark and the completion prior's training map cameras between the dream's
world (the fitted body's) and a synthetic subject's (docs/dream.md "Measured end to end").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlacli.types import Cameras


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
