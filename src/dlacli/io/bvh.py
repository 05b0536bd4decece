"""BVH motion files (Biovision hierarchy), read into a `dlacli.types.SkeletonMotion`.

`SkeletonMotion` (in `dlacli.types`) is the common in-memory form of every third-party motion this
toolkit imports (BVH here, ASF/AMC in `dlacli.io.asf_amc`, AMASS in `dlacli.io.amass`); its
convention is stated there, its kinematics are in `dlacli.kinematics`, and `dlacli.body.retarget`
turns it into a native Motion on anny's rig. This module only parses.

BVH specifics: a rotation channel list such as "Zrotation Yrotation Xrotation" means
R = Rz @ Ry @ Rx (the first listed rotation is the outermost); angles are degrees. Any order of
one to three distinct rotation axes is accepted. Position channels on the root give its path; on
another joint they give its offset from frame 0, except on the root's only child, whose path
then moves the root (exporters that put a fixed joint above the hips, such as the Bandai Namco
Research Motion dataset's `joint_Root`). BVH has no unit: `guess_bvh_units` infers it from the
skeleton's height.

Hostile files: the readers of this module, `asf_amc` and `amass` share the limits below
(`MAX_*` (MAX_FPS and MAX_FRAMES come from `dlacli.types`), `check_motion_size`, and
`check_skeleton_bounds`: motion.npz's bounds on distances and angles) and read text
through `read_motion_text` (regular files only, size capped); `Frames:` is checked against the data
present before anything is allocated for it, and hierarchies are parsed without recursion
(docs/motion.md, "Limits").
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, excerpts, one_line
from dlacli.io.validate import MAX_ANGLE, MAX_DISTANCE, check_magnitude
from dlacli.kinematics import euler_matrices, rest_height
from dlacli.types import MAX_FPS, MAX_FRAMES, MIN_FPS, SkeletonMotion

_ROT_CHANNELS = {"xrotation": "x", "yrotation": "y", "zrotation": "z"}
_POS_CHANNELS = {"xposition": 0, "yposition": 1, "zposition": 2}


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
# limits and safe reading (the same for BVH, ASF and AMC; docs/motion.md states them)

MAX_DEPTH = 256  # joints nested deeper than this are refused (real skeletons: < 30)
MAX_JOINTS = 1024
MAX_JOINT_FRAMES = 20_000_000  # frames x joints (the local rotations alone: 72 bytes each)


def read_motion_text(path: str | os.PathLike, max_bytes: int | None = None) -> str:
    """The text of a BVH, ASF or AMC file (UTF-8, bad bytes replaced) through the shared input
    checks (`dlacli.io.files`: regular files only, at most `max_bytes` (default MAX_TEXT_BYTES),
    never blocking on a FIFO); old Mac line ends ("\r") become "\n"."""
    from dlacli.io.files import MAX_TEXT_BYTES, read_text

    path = Path(path)
    try:
        text = read_text(path, MAX_TEXT_BYTES if max_bytes is None else max_bytes, errors="replace")
    except DlaInputError as err:
        if err.problem == "no such file":
            raise DlaInputError(path, "cannot read (no such file)") from None
        raise
    except OSError as err:
        raise DlaInputError(path, f"cannot read ({err.strerror or err})") from None
    if "\n" not in text and "\r" in text:
        text = text.replace("\r", "\n")
    return text


def check_motion_size(where: Any, frames: int, joints: int) -> None:
    """Refuse motions too large to hold (before anything of that size is allocated)."""
    if joints > MAX_JOINTS:
        raise DlaInputError(where, f"{joints} joints; at most {MAX_JOINTS} are supported")
    if frames > MAX_FRAMES:
        raise DlaInputError(where, f"{frames:,} frames; at most {MAX_FRAMES:,} are supported")
    if frames * joints > MAX_JOINT_FRAMES:
        raise DlaInputError(
            where, f"{frames:,} frames x {joints} joints is too large (at most {MAX_JOINT_FRAMES:,} joint-frames)"
        )


def check_angles(angles: np.ndarray, where: Any, name: str, degrees: bool) -> None:
    """Angles read from a motion file (radians, or degrees when `degrees`) within MAX_ANGLE
    radians, the bound of a motion.npz's rotations."""
    if degrees:
        check_magnitude(angles, math.degrees(MAX_ANGLE), where, name, "degrees")
    else:
        check_magnitude(angles, MAX_ANGLE, where, name, "rad")


def check_skeleton_bounds(skel: SkeletonMotion, where: Any) -> None:
    """Refuse a skeleton motion whose bones or root path reach beyond MAX_DISTANCE metres, the
    bound of a motion.npz's root_translation (io.validate): joint offsets, End Sites and root
    positions, in the file's units times `metres_per_unit`. Every motion reader calls it, so
    `dla animate` plays what `dla motion convert` converts, and nothing else."""
    ends = np.array(list(skel.end_sites.values())).reshape(-1, 3)
    with np.errstate(over="ignore"):  # a huge value times the unit is inf: refused below
        root = skel.root_positions
        lengths = (("a joint offset", skel.offsets), ("an End Site offset", ends), ("the root position", root))
        for name, arr in lengths:
            check_magnitude(np.abs(arr) * skel.metres_per_unit, MAX_DISTANCE, where, name, "m")


# ---------------------------------------------------------------------------------------------
# parsing

_TOKEN = re.compile(r"\S+")
_NON_SPACE = re.compile(r"\S")
_NON_SPACE_LINE = re.compile(r"^.*\S.*$", re.M)


class _Tokens:
    """Lazy whitespace tokens of the HIERARCHY; stops at a line that is only "MOTION"."""

    def __init__(self, text: str, where: Path):
        self.text = text
        self.where = where
        self._it = _TOKEN.finditer(text)
        self.end = 0  # offset just past the last token read
        self.motion_end: int | None = None  # offset just past the MOTION line, once seen

    def _is_motion_line(self, m: re.Match) -> bool:
        if m.group().upper() != "MOTION":
            return False
        start = self.text.rfind("\n", 0, m.start()) + 1
        stop = self.text.find("\n", m.end())
        return self.text[start : stop if stop >= 0 else len(self.text)].strip().upper() == "MOTION"

    def next_or_none(self) -> str | None:
        """The next token, or None at the end of the HIERARCHY (a MOTION line or the file end)."""
        if self.motion_end is not None:
            return None
        m = next(self._it, None)
        if m is None:
            return None
        if self._is_motion_line(m):
            stop = self.text.find("\n", m.end())
            self.motion_end = len(self.text) if stop < 0 else stop + 1
            return None
        self.end = m.end()
        return m.group()

    def next(self, what: str) -> str:
        tok = self.next_or_none()
        if tok is None:
            raise DlaInputError(self.where, f"unexpected end of HIERARCHY (expected {what})")
        return tok

    def line(self) -> int:
        return self.text.count("\n", 0, self.end) + 1

    def number(self, what: str) -> float:
        tok = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise DlaInputError(
                self.where, f"line {self.line()}: expected a number for {what}, got {excerpt(tok)}"
            ) from None
        if not np.isfinite(value):
            raise DlaInputError(self.where, f"line {self.line()}: {what} is {tok}")
        return value


def _parse_hierarchy(tok: _Tokens, root: str) -> tuple[list[dict], dict[int, np.ndarray]]:
    """Joints (parents first) and End Sites, read iteratively: nesting depth is capped, never
    a RecursionError."""
    joints: list[dict] = []
    end_sites: dict[int, np.ndarray] = {}
    open_joints: list[int] = []

    def begin(name: str, parent: int) -> None:
        if len(name) > 200:
            raise DlaInputError(tok.where, f"line {tok.line()}: a joint name of {len(name)} characters (at most 200)")
        if len(open_joints) >= MAX_DEPTH:
            raise DlaInputError(tok.where, f"line {tok.line()}: joints nested more than {MAX_DEPTH} deep")
        if len(joints) >= MAX_JOINTS:
            raise DlaInputError(tok.where, f"line {tok.line()}: more than {MAX_JOINTS} joints")
        joints.append({"name": name, "parent": parent, "offset": None, "channels": []})
        if tok.next("'{'") != "{":
            raise DlaInputError(tok.where, f"line {tok.line()}: expected '{{' after joint {excerpt(name)}")
        open_joints.append(len(joints) - 1)

    begin(root, -1)
    while open_joints:
        index = open_joints[-1]
        joint = joints[index]
        name = joint["name"]
        word = tok.next("'}'")
        key = word.upper()
        if key == "OFFSET":
            joint["offset"] = [tok.number(f"OFFSET of {excerpt(name)}") for _ in range(3)]
        elif key == "CHANNELS":
            count = tok.number(f"CHANNELS count of {excerpt(name)}")
            if count != int(count) or not 0 <= count <= 6:
                problem = f"joint {excerpt(name)} has {count} channels (0..6 allowed)"
                raise DlaInputError(tok.where, f"line {tok.line()}: {problem}")
            joint["channels"] = [tok.next(f"channel of {excerpt(name)}") for _ in range(int(count))]
            _check_channels(joint["channels"], name, tok)
        elif key == "JOINT":
            begin(tok.next("joint name"), index)
        elif key == "END":
            tok.next("'Site'")
            if tok.next("'{'") != "{" or tok.next("OFFSET").upper() != "OFFSET":
                raise DlaInputError(tok.where, f"line {tok.line()}: malformed End Site under {excerpt(name)}")
            end_sites[index] = np.array([tok.number("End Site OFFSET") for _ in range(3)])
            if tok.next("'}'") != "}":
                raise DlaInputError(tok.where, f"line {tok.line()}: expected '}}' closing an End Site")
        elif key == "}":
            if joint["offset"] is None:
                raise DlaInputError(tok.where, f"joint {excerpt(name)} has no OFFSET")
            open_joints.pop()
        else:
            raise DlaInputError(tok.where, f"line {tok.line()}: unexpected {excerpt(word)} in joint {excerpt(name)}")
    return joints, end_sites


def _check_channels(channels: list[str], name: str, tok: _Tokens) -> None:
    rot_axes = []
    for ch in channels:
        low = ch.lower()
        if low in _ROT_CHANNELS:
            rot_axes.append(_ROT_CHANNELS[low])
        elif low not in _POS_CHANNELS:
            problem = f"joint {excerpt(name)} has unsupported channel {excerpt(ch)}"
            raise DlaInputError(tok.where, f"line {tok.line()}: {problem}")
    if len(set(rot_axes)) != len(rot_axes):
        raise DlaInputError(
            tok.where,
            f"line {tok.line()}: joint {excerpt(name)} has unsupported rotation order "
            f"{' '.join(c for c in channels if c.lower() in _ROT_CHANNELS)} (an axis repeats)",
        )
    pos = [c.lower() for c in channels if c.lower() in _POS_CHANNELS]
    if len(set(pos)) != len(pos):
        raise DlaInputError(tok.where, f"line {tok.line()}: joint {excerpt(name)} repeats a position channel")


def read_bvh(path: str | os.PathLike, metres_per_unit: float | None = None) -> SkeletonMotion:
    """Parse a BVH file. Bad content raises DlaInputError naming the file and the problem.

    `metres_per_unit` overrides the unit guess (`guess_bvh_units`). Limits: `MAX_TEXT_BYTES`,
    `MAX_DEPTH`, `MAX_JOINTS`, `check_motion_size`; the frame count is checked against the data
    present before anything is allocated for it.
    """
    path = Path(path)
    text = read_motion_text(path)
    tok = _Tokens(text, path)
    first = tok.next_or_none()
    if first is None or first.upper() != "HIERARCHY":
        raise DlaInputError(path, "not a BVH file (it does not start with HIERARCHY)")
    if tok.next("ROOT").upper() != "ROOT":
        raise DlaInputError(path, f"line {tok.line()}: expected ROOT")
    joints, end_sites = _parse_hierarchy(tok, tok.next("root name"))
    extra = tok.next_or_none()
    if extra is not None:
        raise DlaInputError(
            path, f"line {tok.line()}: unexpected {excerpt(extra)} after the hierarchy (one ROOT supported)"
        )
    if tok.motion_end is None:
        raise DlaInputError(path, "no MOTION section (truncated file?)")
    names = [j["name"] for j in joints]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DlaInputError(path, f"joint name(s) repeated: {excerpts(dup)}")

    num_channels = sum(len(j["channels"]) for j in joints)
    frames, frame_time, data = _parse_motion(text, tok.motion_end, path, num_channels, len(joints))

    offsets = np.array([j["offset"] for j in joints], dtype=np.float64)
    rotations = np.broadcast_to(np.eye(3), (frames, len(joints), 3, 3)).copy()
    root_positions = np.broadcast_to(offsets[0], (frames, 3)).copy()
    # A root with one child that carries the translation (joint_Root -> Hips, as some exporters
    # write): that child's per-frame positions become the root's path (`carried`)
    children = [k for k, j in enumerate(joints) if j["parent"] == 0]
    carrier = children[0] if len(children) == 1 else None
    carried = None if carrier is None else np.broadcast_to(offsets[carrier], (frames, 3)).copy()
    col = 0
    for k, joint in enumerate(joints):
        chans = [c.lower() for c in joint["channels"]]
        block = data[:, col : col + len(chans)]
        col += len(chans)
        rot_cols = [i for i, c in enumerate(chans) if c in _ROT_CHANNELS]
        if rot_cols:
            check_angles(block[:, rot_cols], path, f"rotation of joint {excerpt(joint['name'])}", degrees=True)
            axes = "".join(_ROT_CHANNELS[chans[i]] for i in rot_cols)
            rotations[:, k] = euler_matrices(np.radians(block[:, rot_cols]), axes)
        pos_cols = {_POS_CHANNELS[c]: i for i, c in enumerate(chans) if c in _POS_CHANNELS}
        for axis, i in pos_cols.items():
            if k == 0:
                root_positions[:, axis] = block[:, i]
            elif k == carrier:  # the root's only child moves the body: its path is the root's
                carried[:, axis] = block[:, i]
            else:  # a non-root joint's translation: bones keep their length, take frame 0's
                offsets[k, axis] = block[0, i]
    if carrier is not None and np.ptp(carried, axis=0).max() > 0:
        # Exact: the root's own position moves to its child's, everything below is where it was.
        root_positions += np.einsum("tij,tj->ti", rotations[:, 0], carried)
        offsets[carrier] = 0.0
    elif carrier is not None:
        offsets[carrier] = carried[0]

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
    with np.errstate(over="ignore", invalid="ignore"):  # huge offsets: inf, then refused below
        height = rest_height(skel)
    if metres_per_unit is None:
        skel.units, skel.metres_per_unit = guess_bvh_units(height)
    else:
        skel.units, skel.metres_per_unit = "given", float(metres_per_unit)
    check_skeleton_bounds(skel, path)
    return skel


def next_line(text: str, pos: int) -> tuple[int, int, int] | None:
    """(start, end, next pos) of the next non-blank line at or after `pos`, or None."""
    m = _NON_SPACE.search(text, pos)
    if m is None:
        return None
    start = text.rfind("\n", 0, m.start()) + 1
    end = text.find("\n", m.start())
    end = len(text) if end < 0 else end
    return start, end, end + 1


def _parse_motion(text: str, pos: int, path: Path, num_channels: int, num_joints: int) -> tuple[int, float, np.ndarray]:
    """Frames, frame time and the [frames, channels] values of the MOTION section at `pos`."""

    def line_no(offset: int) -> int:
        return text.count("\n", 0, offset) + 1

    header: dict[str, str] = {}
    while len(header) < 2:
        span = next_line(text, pos)
        if span is None:
            break
        start, end, pos = span
        line = text[start:end].strip()
        key, sep, value = line.partition(":")
        if not sep:
            problem = f"expected 'Frames:' and 'Frame Time:', got {excerpt(line)}"
            raise DlaInputError(path, f"line {line_no(start)}: {problem}")
        header[key.strip().lower()] = value.strip()
    try:
        frames = int(header["frames"])
        frame_time = float(header["frame time"])
    except KeyError as err:
        raise DlaInputError(path, f"MOTION section lacks {err.args[0].title()!r} (truncated file?)") from None
    except ValueError:
        shown = one_line("; ".join(f"{k[:20]}: {v[:20]}" for k, v in header.items()))
        raise DlaInputError(
            path, f"bad MOTION header ({shown}): Frames must be an integer, Frame Time a number"
        ) from None
    if frames <= 0:
        raise DlaInputError(path, f"motion has {frames} frames (at least one needed)")
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise DlaInputError(path, f"Frame Time {frame_time} must be > 0")
    if 1.0 / frame_time < MIN_FPS:
        raise DlaInputError(
            path, f"Frame Time {frame_time:g} s is {1.0 / frame_time:g} fps; at least {MIN_FPS:g} fps is supported"
        )
    if 1.0 / frame_time > MAX_FPS:
        raise DlaInputError(
            path, f"Frame Time {frame_time:g} s is {1.0 / frame_time:g} fps; at most {MAX_FPS:g} fps is supported"
        )
    if num_channels == 0:
        raise DlaInputError(path, "the hierarchy has no CHANNELS: there is no motion to read")
    # the frame count against what the rest of the file can hold, before allocating for it:
    # one line per frame, each of `num_channels` values (at least 2 characters each)
    remaining = len(text) - pos
    lines_left = text.count("\n", pos) + 1
    if frames > lines_left or frames * (2 * num_channels - 1) > remaining:
        found = _count_lines(text, pos)
        have = f"{found} frame lines follow" if found is not None else f"the {remaining:,} bytes left cannot hold them"
        raise DlaInputError(path, f"truncated: Frames: {frames} x {num_channels} channels, but {have}")
    check_motion_size(path, frames, num_joints)

    data = np.empty((frames, num_channels))
    for f in range(frames):
        span = next_line(text, pos)
        if span is None:
            raise DlaInputError(path, f"truncated: Frames: {frames}, but only {f} frame lines follow")
        start, end, pos = span
        words = text[start:end].split()
        if len(words) != num_channels:
            last = f == frames - 1 and next_line(text, pos) is None
            if last and len(words) < num_channels:
                raise DlaInputError(
                    path, f"truncated: the last frame (line {line_no(start)}) has {len(words)} of {num_channels} values"
                )
            raise DlaInputError(
                path, f"line {line_no(start)}: {len(words)} values, expected {num_channels} (one per channel)"
            )
        try:
            data[f] = np.array(words, dtype=np.float64)
        except ValueError:
            bad = next(t for t in words if not _is_float(t))
            raise DlaInputError(
                path, f"line {line_no(start)}: non-numeric value {excerpt(bad)} in the MOTION data"
            ) from None
    span = next_line(text, pos)
    if span is not None:
        more = _count_lines(text, span[0])
        raise DlaInputError(
            path, f"{more or 'more'} frame line(s) more than Frames: {frames} (from line {line_no(span[0])})"
        )
    bad = ~np.isfinite(data)
    if bad.any():
        f, c = np.argwhere(bad)[0]
        raise DlaInputError(path, f"non-finite value ({data[f, c]}) at frame {f}, channel {c}")
    return frames, frame_time, data


def _count_lines(text: str, pos: int) -> int | None:
    """Non-blank lines from `pos` on (None when over 1 MiB are left: only for messages)."""
    return len(_NON_SPACE_LINE.findall(text, pos)) if len(text) - pos < 2**20 else None


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
        "root_travel_m": float(np.linalg.norm(skel.root_positions[-1] - skel.root_positions[0]) * skel.metres_per_unit),
    }
