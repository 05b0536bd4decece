"""BVH motion files (Biovision hierarchy), read into a `SkeletonMotion`.

`SkeletonMotion` is the common in-memory form of every third-party motion this toolkit imports
(BVH here, ASF/AMC in `dlacli.io.asf_amc`, AMASS in `dlacli.io.amass`); `dlacli.body.retarget`
turns it into a native Motion on anny's rig. Its convention (docs/motion.md):

- joint j sits at its parent's position plus `offsets[j]` rotated by the parent's world rotation;
- `rotations[t, j]` is joint j's *local* rotation matrix: its world rotation is
  G_j = G_parent @ rotations[t, j], and G_j rotates everything below j about j's position;
- in the rest pose (all rotations identity) the skeleton stands as its offsets say, in the
  file's own world axes (`up` tells which world axis is up);
- lengths are in the file's units; `metres_per_unit` converts them.

BVH specifics: a rotation channel list such as "Zrotation Yrotation Xrotation" means
R = Rz @ Ry @ Rx (the first listed rotation is the outermost); angles are degrees. Any order of
one to three distinct rotation axes is accepted. Position channels on a joint replace its offset
for that frame. BVH has no unit: `guess_bvh_units` infers it from the skeleton's height.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError

_ROT_CHANNELS = {"xrotation": "x", "yrotation": "y", "zrotation": "z"}
_POS_CHANNELS = {"xposition": 0, "yposition": 1, "zposition": 2}


@dataclass
class SkeletonMotion:
    """A skeleton and its motion as read from a third-party file (see the module docstring)."""

    names: list[str]  # [J] joint names as in the file
    parents: np.ndarray  # [J] int64 parent index, -1 for the root (parents come before children)
    offsets: np.ndarray  # [J, 3] float64 rest offset from the parent joint, file units
    rotations: np.ndarray  # [T, J, 3, 3] float64 local rotation matrices
    root_positions: np.ndarray  # [T, 3] float64 world position of joint 0, file units
    fps: float
    up: str = "y"  # world up axis of the file: "y" (CMU BVH / ASF) or "z" (AMASS)
    metres_per_unit: float = 1.0
    units: str = "m"
    source: str = ""  # the file it came from (for messages)
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> [3] end offset
    dialect: str = ""  # naming convention hint, e.g. "smpl" for AMASS

    def __post_init__(self) -> None:
        j = len(self.names)
        t = self.rotations.shape[0]
        assert self.parents.shape == (j,), self.parents.shape
        assert self.offsets.shape == (j, 3), self.offsets.shape
        assert self.rotations.shape == (t, j, 3, 3), self.rotations.shape
        assert self.root_positions.shape == (t, 3), self.root_positions.shape
        assert all(self.parents[k] < k for k in range(j)), "parents must precede children"

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.names)


def euler_matrices(angles: np.ndarray, axes: str) -> np.ndarray:
    """Rotation matrices R = R_axes[0] @ R_axes[1] @ ... (first listed is outermost).

    angles [T, K] radians, axes a string of K letters from "xyz" -> [T, 3, 3] float64.
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), (angles.shape[0], 3, 3)).copy()
    for k, axis in enumerate(axes):
        out = out @ axis_rotation(axis, angles[:, k])
    return out


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """Right-handed rotations about a coordinate axis: angle [T] radians -> [T, 3, 3]."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(angle.shape + (3, 3))
    i = "xyz".index(axis)
    j, k = (i + 1) % 3, (i + 2) % 3
    m[..., i, i] = 1.0
    m[..., j, j] = c
    m[..., k, k] = c
    m[..., j, k] = -s
    m[..., k, j] = s
    return m


def forward_kinematics(skel: SkeletonMotion, frames: np.ndarray | None = None):
    """World rotations [T, J, 3, 3] and positions [T, J, 3] (file units) of every joint.

    A plain loop over joints; `frames` [T'] selects frames (all by default).
    """
    idx = np.arange(skel.num_frames) if frames is None else np.asarray(frames)
    local = skel.rotations[idx]  # [T, J, 3, 3]
    t, j = local.shape[:2]
    glob = np.empty_like(local)
    pos = np.empty((t, j, 3))
    for k in range(j):
        p = skel.parents[k]
        if p < 0:
            glob[:, k] = local[:, k]
            pos[:, k] = skel.root_positions[idx]
        else:
            glob[:, k] = glob[:, p] @ local[:, k]
            pos[:, k] = pos[:, p] + glob[:, p] @ skel.offsets[k]
    return glob, pos


def rest_positions(skel: SkeletonMotion) -> np.ndarray:
    """[J, 3] joint positions in the rest pose with the root at the origin (file units)."""
    pos = np.zeros((skel.num_joints, 3))
    for k in range(skel.num_joints):
        p = skel.parents[k]
        if p >= 0:
            pos[k] = pos[p] + skel.offsets[k]
    return pos


def rest_height(skel: SkeletonMotion) -> float:
    """Extent of the rest skeleton (joints and End Sites) along its up axis, file units."""
    rest = rest_positions(skel)
    ends = [rest[k] + e for k, e in skel.end_sites.items()]
    return float(np.ptp(np.vstack([rest, *ends])[:, "xyz".index(skel.up)]))


def clean_fps(fps: float) -> float:
    """Snap a frame rate read as 1 / frame time (e.g. 1 / .0083333) to the integer it rounds."""
    return float(round(fps)) if abs(fps - round(fps)) < 1e-3 * fps else float(fps)


def guess_bvh_units(height: float) -> tuple[str, float]:
    """(unit name, metres per unit) for a rest skeleton `height` (top joint minus lowest joint).

    up to 3 -> metres; 3..10 -> decimetres; 10..60 -> CMU units (1/0.45 inch, what the CMU
    ASF-to-BVH converters write); 60..120 -> inches; 120..300 -> centimetres; else millimetres.
    """
    if height <= 3.0:
        return "m", 1.0
    if height <= 10.0:
        return "dm", 0.1
    if height <= 60.0:
        return "cmu (1/0.45 in)", 0.0254 / 0.45
    if height <= 120.0:
        return "in", 0.0254
    if height <= 300.0:
        return "cm", 0.01
    return "mm", 0.001


# ---------------------------------------------------------------------------------------------
# parsing


class _Tokens:
    def __init__(self, text: str, where: Path):
        self.where = where
        self.lines = text.splitlines()
        self.items: list[tuple[str, int]] = []
        self.pos = 0
        self.motion_line = None
        for n, line in enumerate(self.lines):
            if line.strip().upper() == "MOTION":
                self.motion_line = n
                break
            self.items.extend((tok, n + 1) for tok in line.split())

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise DlaInputError(self.where, f"unexpected end of HIERARCHY (expected {what})")
        tok = self.items[self.pos][0]
        self.pos += 1
        return tok

    def line(self) -> int:
        return self.items[min(self.pos, len(self.items)) - 1][1] if self.items else 0

    def number(self, what: str) -> float:
        tok = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise DlaInputError(self.where, f"line {self.line()}: expected a number for {what}, got {tok!r}") from None
        if not np.isfinite(value):
            raise DlaInputError(self.where, f"line {self.line()}: {what} is {tok}")
        return value


def _parse_joint(tok: _Tokens, name: str, parent: int, joints: list[dict], end_sites: dict) -> None:
    index = len(joints)
    joint = {"name": name, "parent": parent, "offset": None, "channels": []}
    joints.append(joint)
    if tok.next("'{'") != "{":
        raise DlaInputError(tok.where, f"line {tok.line()}: expected '{{' after joint {name!r}")
    while True:
        word = tok.next("'}'")
        key = word.upper()
        if key == "OFFSET":
            joint["offset"] = [tok.number(f"OFFSET of {name!r}") for _ in range(3)]
        elif key == "CHANNELS":
            count = tok.number(f"CHANNELS count of {name!r}")
            if count != int(count) or not 0 <= count <= 6:
                raise DlaInputError(tok.where, f"line {tok.line()}: joint {name!r} has {count} channels (0..6 allowed)")
            joint["channels"] = [tok.next(f"channel of {name!r}") for _ in range(int(count))]
            _check_channels(joint["channels"], name, tok)
        elif key == "JOINT":
            _parse_joint(tok, tok.next("joint name"), index, joints, end_sites)
        elif key == "END":
            tok.next("'Site'")
            if tok.next("'{'") != "{" or tok.next("OFFSET").upper() != "OFFSET":
                raise DlaInputError(tok.where, f"line {tok.line()}: malformed End Site under {name!r}")
            end_sites[index] = np.array([tok.number("End Site OFFSET") for _ in range(3)])
            if tok.next("'}'") != "}":
                raise DlaInputError(tok.where, f"line {tok.line()}: expected '}}' closing an End Site")
        elif key == "}":
            break
        else:
            raise DlaInputError(tok.where, f"line {tok.line()}: unexpected {word!r} in joint {name!r}")
    if joint["offset"] is None:
        raise DlaInputError(tok.where, f"joint {name!r} has no OFFSET")


def _check_channels(channels: list[str], name: str, tok: _Tokens) -> None:
    rot_axes = []
    for ch in channels:
        low = ch.lower()
        if low in _ROT_CHANNELS:
            rot_axes.append(_ROT_CHANNELS[low])
        elif low not in _POS_CHANNELS:
            raise DlaInputError(tok.where, f"line {tok.line()}: joint {name!r} has unsupported channel {ch!r}")
    if len(set(rot_axes)) != len(rot_axes):
        raise DlaInputError(
            tok.where,
            f"line {tok.line()}: joint {name!r} has unsupported rotation order "
            f"{' '.join(c for c in channels if c.lower() in _ROT_CHANNELS)} (an axis repeats)",
        )
    pos = [c.lower() for c in channels if c.lower() in _POS_CHANNELS]
    if len(set(pos)) != len(pos):
        raise DlaInputError(tok.where, f"line {tok.line()}: joint {name!r} repeats a position channel")


def read_bvh(path: str | os.PathLike, metres_per_unit: float | None = None) -> SkeletonMotion:
    """Parse a BVH file. Bad content raises DlaInputError naming the file and the problem.

    `metres_per_unit` overrides the unit guess (`guess_bvh_units`).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise DlaInputError(path, f"cannot read ({err.strerror or err})") from None
    tok = _Tokens(text, path)
    if not tok.items or tok.items[0][0].upper() != "HIERARCHY":
        raise DlaInputError(path, "not a BVH file (it does not start with HIERARCHY)")
    tok.pos = 1
    if tok.next("ROOT").upper() != "ROOT":
        raise DlaInputError(path, f"line {tok.line()}: expected ROOT")
    joints: list[dict] = []
    end_sites: dict[int, np.ndarray] = {}
    _parse_joint(tok, tok.next("root name"), -1, joints, end_sites)
    if tok.pos != len(tok.items):
        raise DlaInputError(path, f"line {tok.line()}: unexpected {tok.items[tok.pos][0]!r} after the hierarchy (one ROOT supported)")
    if tok.motion_line is None:
        raise DlaInputError(path, "no MOTION section (truncated file?)")
    names = [j["name"] for j in joints]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DlaInputError(path, f"joint name(s) repeated: {', '.join(dup)}")

    frames, frame_time, values = _parse_motion(tok.lines, tok.motion_line, path)
    num_channels = sum(len(j["channels"]) for j in joints)
    need = frames * num_channels
    if values.size < need:
        raise DlaInputError(
            path, f"truncated: Frames: {frames} x {num_channels} channels needs {need} values, found {values.size}"
        )
    if values.size > need:
        raise DlaInputError(path, f"{values.size - need} values more than Frames: {frames} x {num_channels} channels")
    data = values.reshape(frames, num_channels)
    bad = ~np.isfinite(data)
    if bad.any():
        f, c = np.argwhere(bad)[0]
        raise DlaInputError(path, f"non-finite value ({data[f, c]}) at frame {f}, channel {c}")

    offsets = np.array([j["offset"] for j in joints], dtype=np.float64)
    rotations = np.broadcast_to(np.eye(3), (frames, len(joints), 3, 3)).copy()
    root_positions = np.broadcast_to(offsets[0], (frames, 3)).copy()
    col = 0
    for k, joint in enumerate(joints):
        chans = [c.lower() for c in joint["channels"]]
        block = data[:, col : col + len(chans)]
        col += len(chans)
        rot_cols = [i for i, c in enumerate(chans) if c in _ROT_CHANNELS]
        if rot_cols:
            axes = "".join(_ROT_CHANNELS[chans[i]] for i in rot_cols)
            rotations[:, k] = euler_matrices(np.radians(block[:, rot_cols]), axes)
        pos_cols = {_POS_CHANNELS[c]: i for i, c in enumerate(chans) if c in _POS_CHANNELS}
        for axis, i in pos_cols.items():
            if k == 0:
                root_positions[:, axis] = block[:, i]
            else:  # a non-root joint's translation: bones keep their length, take frame 0's
                offsets[k, axis] = block[0, i]

    skel = SkeletonMotion(
        names=names,
        parents=np.array([j["parent"] for j in joints], dtype=np.int64),
        offsets=offsets,
        rotations=rotations,
        root_positions=root_positions,
        fps=clean_fps(1.0 / frame_time),
        up="y",
        source=str(path),
        end_sites=end_sites,
    )
    height = rest_height(skel)
    if metres_per_unit is None:
        skel.units, skel.metres_per_unit = guess_bvh_units(height)
    else:
        skel.units, skel.metres_per_unit = "given", float(metres_per_unit)
    return skel


def _parse_motion(lines: list[str], start: int, path: Path) -> tuple[int, float, np.ndarray]:
    header: dict[str, str] = {}
    n = start + 1
    while n < len(lines) and len(header) < 2:
        line = lines[n].strip()
        n += 1
        if not line:
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise DlaInputError(path, f"line {n}: expected 'Frames:' and 'Frame Time:', got {line[:40]!r}")
        header[key.strip().lower()] = value.strip()
    try:
        frames = int(header["frames"])
        frame_time = float(header["frame time"])
    except KeyError as err:
        raise DlaInputError(path, f"MOTION section lacks {err.args[0].title()!r} (truncated file?)") from None
    except ValueError:
        raise DlaInputError(path, f"bad MOTION header: {header}") from None
    if frames <= 0:
        raise DlaInputError(path, f"motion has {frames} frames (at least one needed)")
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise DlaInputError(path, f"Frame Time {frame_time} must be > 0")
    body = " ".join(lines[n:])
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError:
        bad = next(t for t in body.split() if not _is_float(t))
        raise DlaInputError(path, f"non-numeric value {bad[:20]!r} in the MOTION data") from None
    return frames, frame_time, values


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def summarize_bvh(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of a BVH file (for `dla info`)."""
    skel = read_bvh(path)
    return {
        "kind": "bvh",
        "format": "bvh",
        "frames": skel.num_frames,
        "fps": skel.fps,
        "duration_s": (skel.num_frames - 1) / skel.fps,
        "joints": skel.num_joints,
        "joint_names": skel.names,
        "units": skel.units,
        "height_m": rest_height(skel) * skel.metres_per_unit,
        "root_travel_m": float(
            np.linalg.norm(skel.root_positions[-1] - skel.root_positions[0]) * skel.metres_per_unit
        ),
    }
