"""Camera placement: look-at cameras and orbits around a subject (docs/conventions.md).

Azimuth 0 is on the -Y side (in front of a body at rest), 90 on +X; elevation is up from the
horizontal plane; all angles in degrees. Images are square unless width/height are given.
"""

from __future__ import annotations

import numpy as np

from dlacli.types import Cameras


def look_at_c2w(eyes: np.ndarray, targets: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [C, 4, 4] in OpenGL axes for eyes [C, 3] looking at targets [C, 3]."""
    eyes = np.atleast_2d(np.asarray(eyes, np.float64))
    targets = np.broadcast_to(np.asarray(targets, np.float64), eyes.shape)
    back = eyes - targets
    back /= np.linalg.norm(back, axis=1, keepdims=True)
    right = np.cross(np.asarray(up, np.float64), back)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    cam_up = np.cross(back, right)
    c2w = np.zeros((eyes.shape[0], 4, 4))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, cam_up, back, eyes
    c2w[:, 3, 3] = 1.0
    return c2w


def orbit_eyes(target, distance: float, azimuths, elevations) -> np.ndarray:
    """Eye positions [C, 3] at `distance` from target [3] (azimuths, elevations [C] in degrees)."""
    az = np.radians(np.atleast_1d(np.asarray(azimuths, np.float64)))
    el = np.radians(np.broadcast_to(np.asarray(elevations, np.float64), az.shape))
    offset = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    return np.asarray(target, np.float64) + distance * offset


def pinhole(c2w: np.ndarray, fov_deg: float, width: int, height: int | None = None) -> Cameras:
    """Cameras from camera-to-world [C, 4, 4] (OpenGL axes) with a vertical field of view."""
    height = width if height is None else height
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2.0)
    return Cameras.from_c2w_opengl(c2w, f, f, width / 2.0, height / 2.0, width, height)


def orbit_cameras(target, distance: float, azimuths, elevations, fov_deg: float, width: int,
                  height: int | None = None) -> Cameras:
    """Cameras on a sphere around target, looking at it."""
    eyes = orbit_eyes(target, distance, azimuths, elevations)
    return pinhole(look_at_c2w(eyes, np.asarray(target, np.float64)), fov_deg, width, height)


def framing_distance(extent: float, fov_deg: float, margin: float = 1.15) -> float:
    """Distance at which a subject `extent` metres tall fills the field of view (with a margin)."""
    return 0.5 * extent * margin / np.tan(np.radians(fov_deg) / 2.0)


def smooth_path(path: np.ndarray, fps: float, seconds: float = 0.5) -> np.ndarray:
    """Moving average of a path [T, D] over `seconds` (edges padded), for steady follow cameras."""
    window = max(1, int(round(seconds * fps)))
    kernel = np.ones(window) / window
    pad = ((window // 2, window - 1 - window // 2), (0, 0))
    padded = np.pad(np.asarray(path, np.float64), pad, mode="edge")
    return np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(padded.shape[1])], axis=1)
