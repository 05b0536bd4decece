"""The target poses of a synthetic subject: seeded pose kinds and frames of motion clips.

`novel_motion` draws poses on top of the subject's input pose from `default_rng([seed, 1])`;
`target_motion` mixes them with random frames of motion clips (`default_rng([seed, 5])`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from dlacli.data.subject import BonePose, SubjectSpec, radians_between
from dlacli.types import Motion

POSE_KINDS = ("arms_raised", "step", "turn", "reach")

# the heights (m) between which a clip frame's body is kept (the synth rig's cameras see ~+-1.24 m
# about its target at its distance)
FRAME_Z = (-1.2, 0.98)


def novel_motion(seed: int, spec: SubjectSpec, n: int) -> Motion:
    """n seeded poses on anny's rig, cycling through POSE_KINDS on top of the input pose."""
    from dlacli.body.model import get_body_model

    labels = get_body_model().bone_labels
    rng = np.random.default_rng([int(seed), 1])
    rots = np.zeros((n, len(labels), 3), np.float32)
    root = np.zeros((n, 3), np.float32)
    for t in range(n):
        kind = POSE_KINDS[t % len(POSE_KINDS)]
        p = BonePose(labels, spec.rotations)
        side, s = (("L", 1.0), ("R", -1.0))[int(rng.integers(2))]
        if kind == "arms_raised":
            for sd, sg in (("L", 1.0), ("R", -1.0)):
                p.rotate(f"upperarm01.{sd}", y=-sg * radians_between(rng, 45, 85))
        elif kind == "step":
            p.rotate(f"upperleg01.{side}", x=-radians_between(rng, 15, 30))
            p.rotate(f"lowerleg01.{side}", x=radians_between(rng, 10, 35))
            other = "R" if side == "L" else "L"
            p.rotate(f"upperleg01.{other}", x=radians_between(rng, 5, 15))
        elif kind == "turn":
            root[t] = [0.0, 0.0, s * radians_between(rng, 30, 75)]
            p.rotate("spine03", z=s * radians_between(rng, 5, 15))
            p.rotate("neck01", z=s * radians_between(rng, 5, 20))
        else:  # reach: one arm forward
            p.rotate(f"upperarm01.{side}", x=-radians_between(rng, 40, 80), y=-s * radians_between(rng, 10, 25))
            p.rotate(f"lowerarm01.{side}", x=-radians_between(rng, 0, 20))
        rots[t] = p.rot
    return Motion(list(labels), rots, root, np.zeros((n, 3), np.float32), 30.0)


def target_motion(seed: int, spec: SubjectSpec, n: int, clips: Sequence[str] = ()) -> tuple[Motion, list[str]]:
    """n target poses and their kinds: `novel_motion`'s; with `clips` (built-in motion names or
    motion files, loaded and retargeted for the subject's phenotype as `dla animate` does), poses
    0, 2, 4, ... are random frames of random clips (`default_rng([seed, 5])`) and poses 1, 3, ...
    `novel_motion`'s kinds in their cycle. A clip frame keeps its root rotation and height, but
    the root is put above the origin and moved down or up as far as needed to keep the (naked)
    body between FRAME_Z[0] and FRAME_Z[1] metres, so the cameras see all of it."""
    from dlacli.body.model import get_body_model
    from dlacli.stages.motion.source import load_motion

    if not clips or n == 0:
        return novel_motion(seed, spec, n), [POSE_KINDS[t % len(POSE_KINDS)] for t in range(n)]
    model = get_body_model()
    labels = list(model.bone_labels)
    rots = np.zeros((n, len(labels), 3), np.float32)
    root_rot, root_pos = np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32)
    kinds = [""] * n
    novel = novel_motion(seed, spec, n // 2)
    for j, t in enumerate(range(1, n, 2)):
        rots[t], root_rot[t], root_pos[t] = novel.rotations[j], novel.root_rotation[j], novel.root_translation[j]
        kinds[t] = POSE_KINDS[j % len(POSE_KINDS)]
    rng = np.random.default_rng([int(seed), 5])
    loaded: dict[int, tuple[Motion, np.ndarray]] = {}
    for t in range(0, n, 2):
        c = int(rng.integers(len(clips)))
        if c not in loaded:
            clip = load_motion(clips[c], phenotype=spec.phenotype)
            loaded[c] = (clip, model.motion_rotations(clip))
        clip, clip_rots = loaded[c]
        i = int(rng.integers(clip.num_frames))
        rots[t], root_rot[t] = clip_rots[i], clip.root_rotation[i]
        root_pos[t] = [0.0, 0.0, float(clip.root_translation[i, 2])]
        kinds[t] = f"{Path(clips[c]).name}@{i}"
    # keep every clip frame's body between the FRAME_Z heights (a raised hand, a crouch)
    sel = np.arange(0, n, 2)
    z = (
        model.forward(
            spec.phenotype,
            torch.from_numpy(rots[sel]),
            torch.from_numpy(root_rot[sel]),
            torch.from_numpy(root_pos[sel]),
        )
        .vertices[..., 2]
        .numpy()
    )
    low, high = z.min(axis=1), z.max(axis=1)
    shift = np.minimum(FRAME_Z[1] - high, 0.0)
    shift = np.where(low + shift < FRAME_Z[0], np.minimum(FRAME_Z[0] - low, FRAME_Z[1] - high), shift)
    root_pos[sel, 2] += shift.astype(np.float32)
    return Motion(labels, rots, root_rot, root_pos, novel.fps), kinds
