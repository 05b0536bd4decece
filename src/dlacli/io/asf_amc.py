"""Acclaim ASF (skeleton) + AMC (motion) files, read into a `SkeletonMotion` (dlacli.types).

Units: an ASF's `:units length L` says that one file unit is 1/L inch (CMU files have L = 0.45,
so one unit is 5.64 cm). Lengths are converted to metres here: the returned skeleton has
`metres_per_unit = 1`. Angles are degrees unless the ASF says `angle rad` or the AMC says
`:RADIANS`.

Bones become joints the way the CMU ASF-to-BVH converters do it: the joint named after bone b
sits at b's start (its parent bone's end, or the root) and its rotation turns bone b.
With C_b the bone's `axis` rotation and M_b the AMC rotation (both composed in the bone's axis
order: "XYZ" means R = Rz @ Ry @ Rx), bone b's world rotation is G_b = G_parent C_b M_b C_b^-1,
so the local rotation stored is C_b M_b C_b^-1 and the rest pose is the ASF's own (all
rotations identity). Translation and length dofs of non-root bones are read and ignored.

AMC files carry no frame rate: `fps` defaults to 120, the CMU capture rate.

An AMC needs its ASF: `find_asf` looks beside the AMC for `<stem>.asf`, then for the stem with
trailing `_<part>`s removed (cmu_01_01.amc -> cmu_01.asf), then for a lone .asf in the folder.
"""

from __future__ import annotations

import math
import os
import re
from array import array
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, excerpts
from dlacli.io.bvh import (
    MAX_DEPTH,
    MAX_JOINTS,
    check_angles,
    check_motion_size,
    check_skeleton_bounds,
    next_line,
    read_motion_text,
)
from dlacli.kinematics import euler_matrices, rest_height
from dlacli.types import SkeletonMotion

INCH = 0.0254
CMU_FPS = 120.0
MAX_ASF_BYTES = 16 * 2**20  # a skeleton; CMU's are 7 KB


@dataclass
class AsfBone:
    name: str
    direction: np.ndarray  # [3] unit vector, world axes at rest
    length: float  # file units
    axis: np.ndarray  # [3] degrees or radians as in the file
    axis_order: str  # e.g. "xyz"
    dofs: list[str]  # e.g. ["rx", "ry", "rz"]


@dataclass
class Asf:
    path: Path
    length_unit: float  # the `:units length` value: one file unit = 1 / length_unit inch
    angle_unit: str  # "deg" or "rad"
    root_order: list[str]  # e.g. ["tx", "ty", "tz", "rx", "ry", "rz"]
    root_axis_order: str  # e.g. "xyz"
    root_position: np.ndarray  # [3] file units
    root_orientation: np.ndarray  # [3] angle units
    bones: dict[str, AsfBone]
    children: dict[str, list[str]]  # parent name ("root" or a bone) -> child bone names

    @property
    def metres_per_unit(self) -> float:
        return INCH / self.length_unit


def _sections(text: str) -> dict[str, list[list[str]]]:
    out: dict[str, list[list[str]]] = {}
    current = None
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            head, _, rest = line.partition(" ")
            current = head[1:].lower()
            out.setdefault(current, [])
            if rest.strip():
                out[current].append(rest.split())
        elif current is not None:
            out[current].append(line.split())
    return out


def _floats(words: list[str], n: int, where: Path, what: str) -> np.ndarray:
    try:
        values = np.array([float(w) for w in words[:n]])
    except ValueError:
        raise DlaInputError(where, f"{what}: expected {n} numbers, got {excerpt(' '.join(words))}") from None
    if values.size != n or not np.all(np.isfinite(values)):
        raise DlaInputError(where, f"{what}: expected {n} finite numbers, got {excerpt(' '.join(words))}")
    return values


def _axis_order(word: str, where: Path, what: str) -> str:
    order = word.lower()
    if sorted(order) != ["x", "y", "z"]:
        raise DlaInputError(where, f"{what}: unsupported rotation order {excerpt(word)} (a permutation of XYZ needed)")
    return order


def read_asf(path: str | os.PathLike) -> Asf:
    """Parse an ASF skeleton; bad content raises DlaInputError naming the file and the problem."""
    path = Path(path)
    sec = _sections(read_motion_text(path, MAX_ASF_BYTES))
    for need in ("root", "bonedata", "hierarchy"):
        if need not in sec:
            raise DlaInputError(path, f"not an ASF skeleton: no :{need} section (truncated file?)")

    units = {words[0].lower(): words[1] for words in sec.get("units", []) if len(words) >= 2}
    try:
        length_unit = float(units.get("length", "1"))
    except ValueError:
        raise DlaInputError(path, f":units length {excerpt(units['length'])} is not a number") from None
    if not np.isfinite(length_unit) or length_unit <= 0:
        raise DlaInputError(path, f":units length {length_unit} must be > 0")
    angle_unit = units.get("angle", "deg").lower()[:3]
    if angle_unit not in ("deg", "rad"):
        raise DlaInputError(path, f":units angle {excerpt(units['angle'])} (deg or rad expected)")

    root = {words[0].lower(): words[1:] for words in sec["root"] if words}
    root_order = [w.lower() for w in root.get("order", "TX TY TZ RX RY RZ".split())]
    if sorted(root_order) != sorted(["tx", "ty", "tz", "rx", "ry", "rz"]):
        raise DlaInputError(
            path, f":root order {excerpt(' '.join(root_order))} is not supported (TX TY TZ RX RY RZ in any order)"
        )
    root_axis = _axis_order(root.get("axis", ["XYZ"])[0], path, ":root axis")
    position = _floats(root.get("position", ["0", "0", "0"]), 3, path, ":root position")
    orientation = _floats(root.get("orientation", ["0", "0", "0"]), 3, path, ":root orientation")
    check_angles(orientation, path, ":root orientation", degrees=angle_unit == "deg")

    bones: dict[str, AsfBone] = {}
    block: dict[str, list[str]] | None = None
    for words in sec["bonedata"]:
        key = words[0].lower()
        if key == "begin":
            block = {}
        elif key == "end":
            if block is None:
                raise DlaInputError(path, ":bonedata has 'end' without 'begin'")
            bone = _make_bone(block, path)
            check_angles(bone.axis, path, f"bone {excerpt(bone.name)} axis", degrees=angle_unit == "deg")
            if bone.name in bones or bone.name == "root":
                raise DlaInputError(path, f"bone {excerpt(bone.name)} defined twice")
            if len(bones) >= MAX_JOINTS - 1:
                raise DlaInputError(path, f"more than {MAX_JOINTS - 1} bones in :bonedata")
            bones[bone.name] = bone
            block = None
        elif block is not None and not key.startswith("("):
            block.setdefault(key, words[1:])
    if block is not None:
        raise DlaInputError(path, ":bonedata ends inside a bone (truncated file?)")
    if not bones:
        raise DlaInputError(path, "no bones in :bonedata")

    # every bone has one parent and hangs below root: no cycles, no shared bones; depth capped
    children: dict[str, list[str]] = {}
    parent_of: dict[str, str] = {}
    for words in sec["hierarchy"]:
        if words[0].lower() in ("begin", "end"):
            continue
        parent, kids = words[0], words[1:]
        for name in [parent, *kids]:
            if name != "root" and name not in bones:
                raise DlaInputError(path, f":hierarchy names unknown bone {excerpt(name)}")
        for kid in kids:
            if kid == "root":
                raise DlaInputError(path, f":hierarchy makes root a child of {excerpt(parent)}")
            if kid in parent_of:
                raise DlaInputError(
                    path,
                    f":hierarchy gives bone {excerpt(kid)} two parents ({excerpt(parent_of[kid])} and "
                    f"{excerpt(parent)}): a cycle or a repeated line",
                )
            parent_of[kid] = parent
        children.setdefault(parent, []).extend(kids)
    reached = _order_bones(children)
    missing = sorted(set(bones) - set(reached))
    if missing:
        shown = excerpts(missing, 8)
        raise DlaInputError(path, f"bone(s) not reachable from root in :hierarchy (a cycle?): {shown}")
    depth = {"root": 0}
    for name in reached:  # parents come first
        depth[name] = depth[parent_of[name]] + 1
        if depth[name] > MAX_DEPTH:
            raise DlaInputError(path, f":hierarchy nests bones more than {MAX_DEPTH} deep (at {excerpt(name)})")
    return Asf(path, length_unit, angle_unit, root_order, root_axis, position, orientation, bones, children)


def _make_bone(block: dict[str, list[str]], path: Path) -> AsfBone:
    if "name" not in block or not block["name"]:
        raise DlaInputError(path, "a bone in :bonedata has no name")
    name = block["name"][0]
    for need in ("direction", "length", "axis"):
        if need not in block:
            raise DlaInputError(path, f"bone {excerpt(name)} has no {need}")
    direction = _floats(block["direction"], 3, path, f"bone {excerpt(name)} direction")
    norm = np.linalg.norm(direction)
    if norm < 1e-9:
        raise DlaInputError(path, f"bone {excerpt(name)} has a zero direction")
    length = float(_floats(block["length"], 1, path, f"bone {excerpt(name)} length")[0])
    axis = _floats(block["axis"], 3, path, f"bone {excerpt(name)} axis")
    order = _axis_order(block["axis"][3] if len(block["axis"]) > 3 else "XYZ", path, f"bone {excerpt(name)} axis")
    dofs = [d.lower() for d in block.get("dof", [])]
    for d in dofs:
        if d not in ("rx", "ry", "rz", "tx", "ty", "tz", "l"):
            raise DlaInputError(path, f"bone {excerpt(name)} has unsupported dof {excerpt(d)}")
    if len(set(dofs)) != len(dofs):
        raise DlaInputError(path, f"bone {excerpt(name)} repeats a dof: {' '.join(dofs)}")
    return AsfBone(name, direction / norm, length, axis, order, dofs)


def _order_bones(children: dict[str, list[str]]) -> list[str]:
    """Bones below root, depth first, parents before children (iterative: no recursion limit)."""
    out: list[str] = []
    seen: set[str] = set()
    stack = list(reversed(children.get("root", [])))
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        out.append(name)
        stack.extend(reversed(children.get(name, [])))
    return out


def _euler(angles: np.ndarray, order: str) -> np.ndarray:
    """angles [T, 3] radians about x, y, z; `order` "xyz" applies x first: R = Rz Ry Rx."""
    composed = order[::-1]  # outermost first
    return euler_matrices(angles[:, ["xyz".index(a) for a in composed]], composed)


def read_amc(amc_path: str | os.PathLike, asf: Asf | str | os.PathLike, fps: float = CMU_FPS) -> SkeletonMotion:
    """Parse an AMC motion against its ASF skeleton (an `Asf` or a path)."""
    amc_path = Path(amc_path)
    if not isinstance(asf, Asf):
        asf = read_asf(asf)
    text = read_motion_text(amc_path)

    names = _order_bones(asf.children)
    moving = ["root"] + [b for b in names if asf.bones[b].dofs]
    counts = {"root": 6, **{b: len(asf.bones[b].dofs) for b in names}}
    store = {b: array("d") for b in moving}  # values in reading order, 8 bytes each
    radians = asf.angle_unit == "rad"
    frames, seen = 0, set()
    pos = last = 0
    n = 1  # line number
    while (span := next_line(text, pos)) is not None:
        start, end, pos = span
        n += text.count("\n", last, start)
        last = start
        line = text[start:end].strip()
        if line.startswith("#"):
            continue
        if line.startswith(":"):
            radians = {"radians": True, "degrees": False}.get(line[1:].strip().lower(), radians)
            continue
        words = line.split()
        if len(words) == 1 and re.fullmatch(r"\d+", words[0]):
            if frames:
                _check_frame(amc_path, frames, moving, seen)
            frames += 1
            check_motion_size(amc_path, frames, len(names) + 1)
            seen = set()
            continue
        if not frames:
            raise DlaInputError(amc_path, f"line {n}: data before the first frame number")
        name = words[0]
        if name != "root" and name not in asf.bones:
            raise DlaInputError(amc_path, f"line {n}: bone {excerpt(name)} is not in the skeleton {asf.path.name}")
        if name in seen:
            raise DlaInputError(amc_path, f"line {n}: bone {excerpt(name)} appears twice in frame {frames}")
        seen.add(name)
        if name not in store:
            continue
        if len(words) - 1 != counts[name]:
            raise DlaInputError(
                amc_path, f"line {n}: bone {excerpt(name)} has {len(words) - 1} values, its dofs need {counts[name]}"
            )
        try:
            row = [float(w) for w in words[1:]]
        except ValueError:
            raise DlaInputError(amc_path, f"line {n}: non-numeric value for bone {excerpt(name)}") from None
        if not all(math.isfinite(v) for v in row):
            raise DlaInputError(amc_path, f"line {n}: non-finite value for bone {excerpt(name)} (frame {frames})")
        store[name].extend(row)
    if not frames:
        raise DlaInputError(amc_path, "no frames (an AMC motion needs at least one)")
    _check_frame(amc_path, frames, moving, seen)
    values = {b: np.frombuffer(store[b], dtype=np.float64).reshape(frames, counts[b]) for b in moving}
    for b in moving:  # the rotation dofs (the root's rx ry rz; a bone's r*): motion.npz's bound on angles
        dofs = asf.root_order if b == "root" else asf.bones[b].dofs
        rot = [i for i, d in enumerate(dofs) if d.startswith("r")]
        check_angles(values[b][:, rot], amc_path, f"rotation of bone {excerpt(b)}", degrees=not radians)

    to_rad = (lambda a: a) if radians else np.radians
    asf_rad = (lambda a: a) if asf.angle_unit == "rad" else np.radians
    scale = asf.metres_per_unit
    t = frames
    joint_names = ["root"] + names
    index = {n: i for i, n in enumerate(joint_names)}
    parents = np.full(len(joint_names), -1, dtype=np.int64)
    offsets = np.zeros((len(joint_names), 3))
    rotations = np.broadcast_to(np.eye(3), (t, len(joint_names), 3, 3)).copy()
    parent_of = {kid: p for p, kids in asf.children.items() for kid in kids}

    # root: position and rotation (in the :root axis order, about the :root orientation frame)
    rv = values["root"]
    pos = np.stack([rv[:, asf.root_order.index(k)] for k in ("tx", "ty", "tz")], axis=1)
    rot = np.stack([rv[:, asf.root_order.index(k)] for k in ("rx", "ry", "rz")], axis=1)
    c0 = _euler(asf_rad(asf.root_orientation)[None], asf.root_axis_order)[0]
    rotations[:, 0] = c0 @ _euler(to_rad(rot), asf.root_axis_order) @ c0.T
    offsets[0] = asf.root_position * scale

    end_sites: dict[int, np.ndarray] = {}
    for b in names:
        bone = asf.bones[b]
        k = index[b]
        parent = parent_of[b]
        parents[k] = index[parent]
        if parent != "root":
            pb = asf.bones[parent]
            offsets[k] = pb.direction * pb.length * scale
        if not asf.children.get(b):
            end_sites[k] = bone.direction * bone.length * scale
        if not bone.dofs:
            continue
        angles = np.zeros((t, 3))
        for i, d in enumerate(bone.dofs):
            if d[0] == "r":
                angles[:, "xyz".index(d[1])] = to_rad(values[b][:, i])
        c = _euler(asf_rad(bone.axis)[None], bone.axis_order)[0]
        rotations[:, k] = c @ _euler(angles, bone.axis_order) @ c.T

    skel = SkeletonMotion(
        names=joint_names,
        parents=parents,
        offsets=offsets,
        rotations=rotations,
        root_positions=pos * scale,
        fps=float(fps),
        up="y",
        metres_per_unit=1.0,
        units=f"m (from ASF length {asf.length_unit:g}: 1 unit = 1/{asf.length_unit:g} in)",
        source=str(amc_path),
        end_sites=end_sites,
    )
    check_skeleton_bounds(skel, amc_path)
    return skel


def _check_frame(where: Path, frame: int, moving: list[str], seen: set[str]) -> None:
    missing = next((b for b in moving if b not in seen), None)
    if missing is not None:
        raise DlaInputError(where, f"frame {frame} lacks bone {excerpt(missing)} (truncated file?)")


def find_asf(amc_path: str | os.PathLike) -> Path:
    """The ASF skeleton beside an AMC (see the module docstring) or DlaInputError."""
    amc_path = Path(amc_path)
    folder = amc_path.parent
    stem = amc_path.stem
    while True:
        for suffix in (".asf", ".ASF"):
            cand = folder / (stem + suffix)
            if cand.is_file():
                return cand
        if "_" not in stem:
            break
        stem = stem.rsplit("_", 1)[0]
    lone = sorted(p for p in folder.glob("*") if p.suffix.lower() == ".asf") if folder.is_dir() else []
    if len(lone) == 1:
        return lone[0]
    raise DlaInputError(
        amc_path,
        "no ASF skeleton found beside this AMC "
        f"({'several .asf files' if lone else 'no .asf file'} in {folder}); name it as CLIP.amc:SUBJECT.asf",
    )


def summarize_asf(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of an ASF skeleton (for `dla info`)."""
    asf = read_asf(path)
    names = _order_bones(asf.children)
    return {
        "kind": "asf",
        "format": "asf",
        "bones": len(names),
        "bone_names": names,
        "moving_bones": sum(1 for b in names if asf.bones[b].dofs),
        "length_unit": asf.length_unit,
        "metres_per_unit": asf.metres_per_unit,
        "angle_unit": asf.angle_unit,
    }


def summarize_amc(path: str | os.PathLike, asf: str | os.PathLike | None = None) -> dict[str, Any]:
    """JSON-able summary of an AMC motion; its ASF is found with `find_asf` unless given."""
    asf_path = Path(asf) if asf is not None else find_asf(path)
    skel = read_amc(path, asf_path)
    return {
        "kind": "amc",
        "format": "amc",
        "asf": str(asf_path),
        "frames": skel.num_frames,
        "fps": skel.fps,
        "duration_s": (skel.num_frames - 1) / skel.fps,
        "joints": skel.num_joints,
        "height_m": rest_height(skel),
        "root_travel_m": float(np.linalg.norm(skel.root_positions[-1] - skel.root_positions[0])),
    }
