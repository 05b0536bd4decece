"""The synth rig: where the cameras of a synthetic subject stand (docs/synth.md).

Cameras at DISTANCE from TARGET, looking at it, at azimuths / elevations in degrees
(docs/conventions.md): the 4 input views, the novel views and the novel-pose cameras.
"""

from __future__ import annotations

import numpy as np

from dlacli.types import Cameras

DISTANCE = 3.0  # metres from the target
TARGET = (0.0, 0.0, -0.1)  # look-at point: mid-body (pelvis at z = 0 in anny's zero pose)
FOV_DEG = 45.0  # vertical = horizontal field of view (square images)
INPUT_AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
INPUT_ELEVATION = 8.0  # degrees: the eye at ~0.32 m above the pelvis, chest height
NOVEL_ELEVATIONS = (0.0, 20.0, -5.0, 35.0)
POSE_AZIMUTHS = (0.0, 120.0, 240.0)  # cameras of the novel-pose folder
# dataset mode: random input yaw, slight elevation jitter (degrees)
ELEVATION_JITTER = 4.0


def synth_orbit_cameras(azimuths, elevations, res: int) -> Cameras:
    """The synth rig: cameras DISTANCE from TARGET at azimuths / elevations (degrees, [C] each),
    looking at it; res x res images with a FOV_DEG field of view (docs/conventions.md for the angles)."""
    from dlacli.geometry import look_at_orbit_cameras

    return look_at_orbit_cameras(TARGET, DISTANCE, azimuths, elevations, FOV_DEG, res)


def novel_view_angles(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n (azimuth, elevation) pairs in degrees spread around the subject, none on an input view."""
    az = (17.0 + 360.0 * np.arange(n) / max(n, 1)) % 360.0
    clash = np.min(np.abs(((az[:, None] - np.array(INPUT_AZIMUTHS)[None]) + 180.0) % 360.0 - 180.0), axis=1)
    az = np.where(clash < 5.0, az + 7.0, az)
    el = np.array([NOVEL_ELEVATIONS[i % len(NOVEL_ELEVATIONS)] for i in range(n)], np.float64)
    return az, el


def input_rig(seed: int, random_yaw: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(azimuths [4], elevations [4], start yaw) of the input cameras, degrees: the fixed rig
    (INPUT_AZIMUTHS at INPUT_ELEVATION), or with `random_yaw` (dataset mode) 4 cameras 90 degrees
    apart from a random start yaw, each raised by up to +-ELEVATION_JITTER (`default_rng([seed, 3])`)."""
    if not random_yaw:
        return np.array(INPUT_AZIMUTHS), np.full(4, INPUT_ELEVATION), 0.0
    rng = np.random.default_rng([int(seed), 3])
    yaw = float(rng.uniform(0.0, 360.0))
    return (yaw + np.array(INPUT_AZIMUTHS)) % 360.0, INPUT_ELEVATION + rng.uniform(-1, 1, 4) * ELEVATION_JITTER, yaw
