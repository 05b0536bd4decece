"""Retargeting: a third-party skeleton motion (`SkeletonMotion`) -> a native Motion on anny's rig.

Method (docs/motion.md has the derivation):
1. Joints are matched to anny bones by name (`DIALECTS`: CMU 3dsMax-style and MotionBuilder-style
   BVH names, CMU ASF bone names, Mixamo, Character Creator / iClone, the Bandai Namco Research
   Motion dataset, SMPL). Source joints without a counterpart (fingers, toes, twist, hip and
   collar helpers) are ignored; their rotations
   still reach the mapped joints below them, because the transfer works on world rotations.
   Every anny bone of the chosen table is needed (`NEEDED`): a file lacking one is refused
   unless missing joints are allowed, and then those bones stay at rest (relative to their
   parents).
2. Forward kinematics gives each source joint's world rotation G_s(t) (a delta from the source's
   rest pose). Axes change with A (Y-up, facing +Z -> anny's Z-up, facing -Y).
3. Rest-pose correction Q_b: a rotation taking the source's rest bone to anny's zero-pose bone:
   for limbs the shortest rotation between the two bone directions (this is what turns a T-pose
   source into anny's A-pose); for the torso (root, spine, neck, head) one rotation aligning the
   pelvis frames (up = pelvis->neck, left = right hip->left hip).
4. anny bone b's world delta is W_b = M_world G_s M_rest^-1 Q_b^-1, so that b points where the
   source bone points; unmapped bones follow their parent. anny's "local-ref" rotations compose
   root-first in world-aligned axes (W_c = W_parent L_c), so L_c = W_parent^-1 W_c; the root's W
   goes to `root_rotation`.
5. The hip centre's path (mean of the two hip joints, the root joint if the legs are unmapped)
   is scaled by anny leg length / source leg length (hip -> knee -> ankle) and anny's hip centre
   follows it: horizontally from the origin at frame 0; vertically a source hip centre at height h
   above the source ground (y = 0, or z = 0 for Z-up files: CMU and AMASS are ground-registered)
   goes to scale * h above anny's soles (the zero pose's lowest vertex), so feet stay on the ground.

The motion is made for one phenotype (the default unless given); it transfers to others as is.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.geometry import (
    axis_angle_to_quat,
    matrix_to_axis_angle,
    quat_normalize,
    quat_slerp,
    quat_to_axis_angle,
    rotation_between,
)
from dlacli.kinematics import forward_kinematics, rest_positions
from dlacli.types import MAX_FRAMES, Motion, SkeletonMotion

# Y-up, facing +Z (BVH, ASF, SMPL canonical) -> anny (Z-up, facing -Y): (x, y, z) -> (x, -z, y)
Y_UP_TO_ANNY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

TORSO = ("root", "spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03", "head")


def _sided(table: dict[str, str], left: str, right: str) -> dict[str, str]:
    """Expand '{S}'/'{s}' templates in a name table to both sides (names as written)."""
    out = {}
    for src, dst in table.items():
        if "{" in src:
            for side, s, lr in (("Left", "l", "L"), ("Right", "r", "R")):
                out[src.format(S=side, s=s)] = dst.format(side=lr)
        else:
            out[src] = dst
    return out


_LIMBS_MB = {
    "{S}Shoulder": "clavicle.{side}",
    "{S}Arm": "upperarm01.{side}",
    "{S}ForeArm": "lowerarm01.{side}",
    "{S}Hand": "wrist.{side}",
    "{S}UpLeg": "upperleg01.{side}",
    "{S}Leg": "lowerleg01.{side}",
    "{S}Foot": "foot.{side}",
}
_TABLES: dict[str, dict[str, str]] = {  # source joint name (as written) -> anny bone
    "cmu-3dsmax": _sided(
        {
            "Hips": "root",
            "lowerback": "spine05",
            "Chest": "spine03",
            "Chest2": "spine01",
            "lowerneck": "neck01",
            "Neck": "neck02",
            "Head": "head",
            "{S}Collar": "clavicle.{side}",
            "{S}Shoulder": "upperarm01.{side}",
            "{S}Elbow": "lowerarm01.{side}",
            "{S}Wrist": "wrist.{side}",
            "{S}Hip": "upperleg01.{side}",
            "{S}Knee": "lowerleg01.{side}",
            "{S}Ankle": "foot.{side}",
        },
        "L",
        "R",
    ),
    "cmu-motionbuilder": _sided(
        {
            "Hips": "root",
            "LowerBack": "spine05",
            "Spine": "spine03",
            "Spine1": "spine01",
            "Neck": "neck01",
            "Neck1": "neck02",
            "Head": "head",
            **_LIMBS_MB,
        },
        "L",
        "R",
    ),
    "cmu-asf": _sided(
        {
            "root": "root",
            "lowerback": "spine05",
            "upperback": "spine03",
            "thorax": "spine01",
            "lowerneck": "neck01",
            "upperneck": "neck02",
            "head": "head",
            "{s}clavicle": "clavicle.{side}",
            "{s}humerus": "upperarm01.{side}",
            "{s}radius": "lowerarm01.{side}",
            "{s}wrist": "wrist.{side}",
            "{s}femur": "upperleg01.{side}",
            "{s}tibia": "lowerleg01.{side}",
            "{s}foot": "foot.{side}",
        },
        "L",
        "R",
    ),
    "mixamo": _sided(
        {
            "Hips": "root",
            "Spine": "spine04",
            "Spine1": "spine02",
            "Spine2": "spine01",
            "Neck": "neck01",
            "Head": "head",
            **_LIMBS_MB,
        },
        "L",
        "R",
    ),
    "character-creator": _sided(  # Reallusion Character Creator / iClone ("CC_Base_" bones)
        {
            "CC_Base_Hip": "root",
            "CC_Base_Waist": "spine05",
            "CC_Base_Spine01": "spine03",
            "CC_Base_Spine02": "spine01",
            "CC_Base_NeckTwist01": "neck01",
            "CC_Base_NeckTwist02": "neck02",
            "CC_Base_Head": "head",
            "CC_Base_{s}_Clavicle": "clavicle.{side}",
            "CC_Base_{s}_Upperarm": "upperarm01.{side}",
            "CC_Base_{s}_Forearm": "lowerarm01.{side}",
            "CC_Base_{s}_Hand": "wrist.{side}",
            "CC_Base_{s}_Thigh": "upperleg01.{side}",
            "CC_Base_{s}_Calf": "lowerleg01.{side}",
            "CC_Base_{s}_Foot": "foot.{side}",
        },
        "L",
        "R",
    ),
    "bandai-namco": _sided(  # Bandai Namco Research Motion dataset (22 joints, "_L"/"_R" suffixes)
        {
            "Hips": "root",
            "Spine": "spine04",
            "Chest": "spine01",
            "Neck": "neck01",
            "Head": "head",
            "Shoulder_{s}": "clavicle.{side}",
            "UpperArm_{s}": "upperarm01.{side}",
            "LowerArm_{s}": "lowerarm01.{side}",
            "Hand_{s}": "wrist.{side}",
            "UpperLeg_{s}": "upperleg01.{side}",
            "LowerLeg_{s}": "lowerleg01.{side}",
            "Foot_{s}": "foot.{side}",
        },
        "L",
        "R",
    ),
    "smpl": {
        "pelvis": "root",
        "spine1": "spine04",
        "spine2": "spine02",
        "spine3": "spine01",
        "neck": "neck01",
        "head": "head",
        **{
            f"{side}_{src}": f"{dst}.{lr}"
            for side, lr in (("left", "L"), ("right", "R"))
            for src, dst in (
                ("collar", "clavicle"),
                ("shoulder", "upperarm01"),
                ("elbow", "lowerarm01"),
                ("wrist", "wrist"),
                ("hip", "upperleg01"),
                ("knee", "lowerleg01"),
                ("ankle", "foot"),
            )
        },
    },
}

# the name tables, keyed by lower-case name (matching is case-insensitive)
DIALECTS: dict[str, dict[str, str]] = {d: {k.lower(): v for k, v in t.items()} for d, t in _TABLES.items()}
# Every anny bone a table maps is *needed* from a file of that family: they are the limbs, spine,
# neck and head that every such skeleton has (fingers, toes and face are in no table). A file
# lacking one is refused unless the caller allows missing joints (those bones then stay at rest).
NEEDED: dict[str, dict[str, list[str]]] = {
    d: {bone: [k for k, v in t.items() if v == bone] for bone in dict.fromkeys(t.values())} for d, t in _TABLES.items()
}

# joints known to have no anny counterpart (no warning when ignored)
_KNOWN_EXTRA = (
    "hipjoint",
    "toe",
    "finger",
    "thumb",
    "hand",
    "end",
    "site",
    "clavicle",
    "collar",
    "foot",
    "eye",
    "jaw",
    "neck",
    "spine",
    "index",
    "middle",
    "ring",
    "pinky",
    "chest",
)


@dataclass
class AnnyRig:
    """The constants of anny's rig that retargeting needs (for one phenotype)."""

    bone_labels: list[str]  # [J]
    bone_parents: np.ndarray  # [J] int, -1 for the root
    rest_heads: np.ndarray  # [J, 3] zero-pose bone heads, metres
    ground_z: float  # height of the soles in the zero pose (lowest vertex z), metres

    def index(self, label: str) -> int:
        return self.bone_labels.index(label)


def anny_rig(phenotype: dict[str, float] | None = None) -> AnnyRig:
    """AnnyRig of the body model (default phenotype unless given)."""
    from dlacli.body.model import get_body_model

    model = get_body_model()
    zero = model.zero_pose(phenotype)
    return AnnyRig(
        bone_labels=list(model.bone_labels),
        bone_parents=np.asarray(model.bone_parents),
        rest_heads=zero.bone_heads[0].double().numpy(),
        ground_z=float(zero.vertices[0, :, 2].min()),
    )


def match_joints(names: list[str], dialect: str = "") -> tuple[str, dict[int, str]]:
    """(dialect, {source joint index: anny bone label}) for the best-matching name table.

    Names are compared case-insensitively after dropping a "prefix:" (e.g. "mixamorig:").
    """
    keys = [n.rsplit(":", 1)[-1].lower() for n in names]
    tables = {dialect: DIALECTS[dialect]} if dialect in DIALECTS else DIALECTS
    best, best_map, best_score = "", {}, (0, 0)
    for name, table in tables.items():
        found = {i: table[k] for i, k in enumerate(keys) if k in table}
        bones = set(found.values())
        score = (len(bones), -len(NEEDED[name].keys() - bones))  # most matches, then fewest gaps
        if bones and score > best_score:
            best, best_map, best_score = name, found, score
    # one source joint per anny bone: keep the first (closest to the root)
    seen: set[str] = set()
    unique = {}
    for i, label in sorted(best_map.items()):
        if label not in seen:
            unique[i] = label
            seen.add(label)
    return best, unique


def _frame(up: np.ndarray, left: np.ndarray) -> np.ndarray:
    """[3, 3] orthonormal frame with columns (left, forward, up) from rough up and left vectors."""
    z = up / np.linalg.norm(up)
    x = left - np.dot(left, z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _segment_end(skel: SkeletonMotion, rest: np.ndarray, s: int, mapped: dict[int, str], children) -> int | None:
    """The source joint that ends joint s's segment: its first mapped descendant, else the first
    descendant (or End Site, returned as -1 - s) at a non-zero distance."""
    stack = list(children[s])
    first_far = None
    while stack:
        c = stack.pop(0)
        if c in mapped:
            return c
        if first_far is None and np.linalg.norm(rest[c] - rest[s]) > 1e-6:
            first_far = c
        stack.extend(children[c])
    if first_far is None and s in skel.end_sites and np.linalg.norm(skel.end_sites[s]) > 1e-6:
        return -1 - s
    return first_far


# A standing rest pose has its shoulders parallel to its hips; a source whose rest shoulders are
# turned further than this from its hips (about its spine) has orientations baked into its trunk's
# rotation channels (the Bandai Namco files: a 90 degree twist in "Spine").
TRUNK_TWIST_DEG = 20.0


def _upper_torso(skel: SkeletonMotion, mapped: dict[int, str], by_label: dict[str, int]) -> set[int]:
    """The torso source joints that carry the shoulders: the trunk joints above the root that are
    ancestors of an upper arm, and the neck and head above them."""
    root = by_label.get("root", 0)
    moved = set()
    for side in "LR":
        p = int(skel.parents[by_label[f"upperarm01.{side}"]])
        while p >= 0 and p != root:
            if mapped.get(p) in TORSO:
                moved.add(p)
            p = int(skel.parents[p])
    for s, label in mapped.items():  # the neck and head: torso joints below the upper trunk
        p = int(skel.parents[s])
        while label in TORSO and p >= 0 and s not in moved:
            if p in moved:
                moved.add(s)
            p = int(skel.parents[p])
    return moved


def rest_corrections(skel: SkeletonMotion, rig: AnnyRig, mapped: dict[int, str]) -> dict[int, np.ndarray]:
    """{source joint: Q [3, 3]} taking the source rest bone (in anny axes) onto anny's zero pose."""
    rest = rest_positions(skel) @ Y_UP_TO_ANNY.T  # [J, 3] rest skeleton in anny axes
    children: dict[int, list[int]] = {k: [] for k in range(skel.num_joints)}
    for k in range(1, skel.num_joints):
        children[int(skel.parents[k])].append(k)
    heads = rig.rest_heads
    by_label = {label: s for s, label in mapped.items()}

    def anny_head(label: str) -> np.ndarray:
        return heads[rig.index(label)]

    # torso: align pelvis frames (up = root -> top, left = right -> left hip)
    src_top = next((by_label[b] for b in ("head", "neck02", "neck01", "spine01") if b in by_label), None)
    q_torso, q_chest, upper = np.eye(3), None, set()
    if src_top is not None and "upperleg01.L" in by_label and "upperleg01.R" in by_label:
        dst_top = next(b for b in ("head", "neck02", "neck01", "spine01") if b in by_label)
        src_up, dst_up = rest[src_top] - rest[by_label.get("root", 0)], anny_head(dst_top) - anny_head("root")

        def align(left: str, right: str) -> np.ndarray:  # the frame with this pair's left
            src = _frame(src_up, rest[by_label[left]] - rest[by_label[right]])
            return _frame(dst_up, anny_head(left) - anny_head(right)) @ src.T

        q_torso = align("upperleg01.L", "upperleg01.R")
        if "upperarm01.L" in by_label and "upperarm01.R" in by_label:
            # the chest frame (left = the upper arms) where the rest trunk is twisted (TRUNK_TWIST_DEG)
            q_chest = align("upperarm01.L", "upperarm01.R")
            twist = np.degrees(np.arccos(np.clip((np.trace(q_chest.T @ q_torso) - 1.0) / 2.0, -1.0, 1.0)))
            upper = _upper_torso(skel, mapped, by_label) if twist > TRUNK_TWIST_DEG else set()

    q: dict[int, np.ndarray] = {}
    for s in sorted(mapped):
        label = mapped[s]
        if label in TORSO:
            q[s] = q_chest if s in upper else q_torso
            continue
        end = _segment_end(skel, rest, s, mapped, children)
        b = rig.index(label)
        if end is None:
            d_src = None
        elif end < 0:
            d_src = Y_UP_TO_ANNY @ skel.end_sites[-1 - end]
        else:
            d_src = rest[end] - rest[s]
        if end is not None and end >= 0 and end in mapped:
            d_dst = anny_head(mapped[end]) - heads[b]
        else:  # an end joint: towards the mean of anny's child heads (fingers, toes)
            kids = np.flatnonzero(rig.bone_parents == b)
            d_dst = heads[kids].mean(axis=0) - heads[b] if kids.size else None
        if d_src is None or d_dst is None or np.linalg.norm(d_src) < 1e-9 or np.linalg.norm(d_dst) < 1e-9:
            p = int(skel.parents[s])
            while p >= 0 and p not in q:
                p = int(skel.parents[p])
            q[s] = q[p] if p >= 0 else q_torso
        else:
            q[s] = rotation_between(d_src, d_dst)
    return q


def _leg_length(points: np.ndarray, chain: list[int]) -> float:
    return float(sum(np.linalg.norm(points[b] - points[a]) for a, b in zip(chain, chain[1:])))


def _names(names: list[str], most: int = 8) -> str:
    return ", ".join(n[:40] for n in names[:most]) + (" ..." if len(names) > most else "")


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def missing_bones(dialect: str, mapped: dict[int, str]) -> dict[str, list[str]]:
    """{anny bone: source names tried} for the bones `dialect` needs that no joint maps to."""
    have = set(mapped.values())
    return {bone: names for bone, names in NEEDED.get(dialect, {}).items() if bone not in have}


def retarget(skel: SkeletonMotion, rig: AnnyRig, allow_missing: bool = False) -> Motion:
    """Turn a source skeleton motion into a native Motion on anny's rig (see module docstring).

    Raises DlaInputError when no joint (or not the root) matches anny's rig, and when a bone that
    the file's naming family always has (`NEEDED`: limbs, spine, neck, head) has no source joint,
    unless `allow_missing` (then those bones stay at rest, and a note on stderr names them).
    Warns on stderr about unknown joints that are ignored.
    """
    dialect, mapped = match_joints(skel.names, skel.dialect)
    if not mapped:
        raise DlaInputError(
            skel.source,
            f"none of its {skel.num_joints} joints match anny's rig (known naming: "
            f"{', '.join(DIALECTS)}; e.g. Hips, LeftUpLeg, LeftArm)",
        )
    if "root" not in mapped.values() or len(mapped) < 2:
        raise DlaInputError(
            skel.source,
            f"too few joints match anny's rig ({', '.join(skel.names[i] for i in mapped)}); a root "
            "(Hips/root/pelvis) and limbs are needed",
        )
    unknown = [n for i, n in enumerate(skel.names) if i not in mapped and not any(k in n.lower() for k in _KNOWN_EXTRA)]
    missing = missing_bones(dialect, mapped)
    if missing:
        tried = ", ".join(n for names in missing.values() for n in names)
        problem = f"no source joint for anny bone(s) {', '.join(missing)} (tried {tried}: {dialect} names)"
        if not allow_missing:
            unmatched = unknown + [n for i, n in enumerate(skel.names) if i not in mapped and n not in unknown]
            hint = f"; unmatched joints in the file: {_names(unmatched, 4)}" if unmatched else ""
            raise DlaInputError(skel.source, f"{problem}{hint}; --allow-missing-joints leaves those bones at rest")
        print(f"note: {skel.source}: {problem}; they stay at rest (--allow-missing-joints)", file=sys.stderr)
    if unknown:
        _warn(f"{skel.source}: ignoring {len(unknown)} joint(s) with no anny counterpart: {_names(unknown)}")

    q = rest_corrections(skel, rig, mapped)
    glob, pos = forward_kinematics(skel)  # [T, J, 3, 3], [T, J, 3]
    if not (np.isfinite(glob).all() and np.isfinite(pos).all()):
        raise DlaInputError(skel.source, "its joint positions overflow (values too large to be a motion)")
    m_rest = Y_UP_TO_ANNY
    m_world = Y_UP_TO_ANNY if skel.up == "y" else np.eye(3)
    t = skel.num_frames
    nb = len(rig.bone_labels)

    world = np.empty((t, nb, 3, 3))  # W_b: world rotation deltas of anny's bones
    src_of = {rig.index(label): s for s, label in mapped.items()}
    for b in range(nb):  # parents precede children in anny's rig
        if b in src_of:
            s = src_of[b]
            world[:, b] = m_world @ glob[:, s] @ m_rest.T @ q[s].T
        elif rig.bone_parents[b] >= 0:
            world[:, b] = world[:, rig.bone_parents[b]]
        else:
            world[:, b] = np.eye(3)
    local = np.empty_like(world)
    local[:, 0] = np.eye(3)
    par = rig.bone_parents[1:]
    local[:, 1:] = np.swapaxes(world[:, par], -1, -2) @ world[:, 1:]

    # pelvis path: anny's hip centre goes where the scaled source hip centre is (metres, Z up),
    # heights measured from each one's ground; horizontally the path starts at the origin
    by_label = {label: s for s, label in mapped.items()}
    hips = [by_label[b] for b in ("upperleg01.L", "upperleg01.R") if b in by_label]
    anchor = hips if len(hips) == 2 else [by_label["root"]]
    src_centre = pos[:, anchor].mean(axis=1) * skel.metres_per_unit @ m_world.T  # [T, 3]
    labels = ("upperleg01.L", "upperleg01.R") if len(hips) == 2 else ("root",)
    offset = rig.rest_heads[[rig.index(b) for b in labels]].mean(axis=0) - rig.rest_heads[0]  # [3]
    trans = _scale(skel, rig, mapped) * src_centre - world[:, 0] @ offset  # [T, 3]
    trans[:, :2] -= trans[0, :2]
    trans[:, 2] += rig.ground_z

    if not np.isfinite(trans.astype(np.float32)).all():
        raise DlaInputError(skel.source, "its root path overflows (positions too large to be a motion)")
    return Motion(
        bone_labels=list(rig.bone_labels),
        rotations=matrix_to_axis_angle(local).astype(np.float32),
        root_rotation=matrix_to_axis_angle(world[:, 0]).astype(np.float32),
        root_translation=trans.astype(np.float32),
        fps=float(skel.fps),
    )


def _scale(skel: SkeletonMotion, rig: AnnyRig, mapped: dict[int, str]) -> float:
    """anny leg length / source leg length (hip -> knee -> ankle, mean of both sides); 1 if unknown."""
    by_label = {label: s for s, label in mapped.items()}
    rest = rest_positions(skel) * skel.metres_per_unit
    ratios = []
    for side in "LR":
        chain = [f"upperleg01.{side}", f"lowerleg01.{side}", f"foot.{side}"]
        if all(c in by_label for c in chain):
            src = _leg_length(rest, [by_label[c] for c in chain])
            dst = _leg_length(rig.rest_heads, [rig.index(c) for c in chain])
            if src > 1e-6:
                ratios.append(dst / src)
    return float(np.mean(ratios)) if ratios else 1.0


# ---------------------------------------------------------------------------------------------
# frame-rate resampling


def resample_motion(motion: Motion, fps: float) -> Motion:
    """The motion at another frame rate over the same duration: frame n is at time n / fps;
    rotations are slerped, translations linearly interpolated. Exact source frames come back
    unchanged when fps divides the source rate (120 -> 30 keeps every 4th frame)."""
    if not np.isfinite(fps) or fps <= 0:
        raise DlaInputError("--fps", f"{fps} must be > 0")
    src_t = motion.num_frames
    if abs(fps - motion.fps) < 1e-9 or src_t == 1:
        return Motion(
            list(motion.bone_labels),
            motion.rotations,
            motion.root_rotation,
            motion.root_translation,
            float(fps),
            motion.model,
        )
    duration = (src_t - 1) / motion.fps
    frames = np.floor(duration * fps + 1e-6) + 1
    if not frames <= MAX_FRAMES:  # also NaN / inf
        raise DlaInputError(
            "--fps", f"{fps:g} fps over {duration:g} s would be {frames:g} frames (at most {MAX_FRAMES:,})"
        )
    count = int(frames)
    pos = np.arange(count) * (motion.fps / fps)  # fractional source frame of each new frame
    i0 = np.clip(np.floor(pos + 1e-9).astype(np.int64), 0, src_t - 1)
    i1 = np.minimum(i0 + 1, src_t - 1)
    w = np.clip(pos - i0, 0.0, 1.0)
    w = np.where(w < 1e-9, 0.0, w)

    def rot(aa: np.ndarray) -> np.ndarray:  # [T, ..., 3]
        q = axis_angle_to_quat(np.asarray(aa, dtype=np.float64))
        extra = (1,) * (q.ndim - 2)
        out = quat_normalize(quat_slerp(q[i0], q[i1], w.reshape((-1,) + extra + (1,)), shortest=True))
        exact = (w == 0).reshape((-1,) + extra + (1,))
        return np.where(exact[..., :1], np.asarray(aa, dtype=np.float64)[i0], quat_to_axis_angle(out))

    trans = np.asarray(motion.root_translation, dtype=np.float64)
    trans = (1.0 - w)[:, None] * trans[i0] + w[:, None] * trans[i1]
    return Motion(
        list(motion.bone_labels),
        rot(motion.rotations).astype(np.float32),
        rot(motion.root_rotation).astype(np.float32),
        trans.astype(np.float32),
        float(fps),
        motion.model,
    )
