"""One synthetic subject with ground truth as a view folder: `dla synth` (docs/synth.md).

`synth(seed, out)` writes a view folder of a seeded subject (4 input views), its true body.json,
and optionally ground-truth novel views and novel poses. Everything random comes from
`numpy.random.default_rng` generators seeded by `seed`, so a seed gives the same bytes on every run.
Dataset mode (many subjects, a manifest, parallel and resumable) is dlacli.data.dataset.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from dlacli.data.appearance import APPEARANCES, ambient_occlusion, sample_lighting
from dlacli.data.cameras import (
    INPUT_AZIMUTHS,
    INPUT_ELEVATION,
    POSE_AZIMUTHS,
    input_rig,
    novel_view_angles,
    synth_orbit_cameras,
)
from dlacli.data.garments import DressedBody
from dlacli.data.images import render
from dlacli.data.poses import target_motion
from dlacli.data.subject import WARDROBES, SubjectSpec, sample_subject
from dlacli.errors import DlaInputError
from dlacli.types import BodyParams, Cameras, ViewSet

Progress = Callable[[str], None]


def body_params(spec: SubjectSpec, rotations: np.ndarray | None) -> BodyParams:
    from dlacli.body.model import rotations_to_pose

    pose = {} if rotations is None else rotations_to_pose(rotations)
    pose = {k: np.asarray(v, np.float64) for k, v in pose.items()}
    return BodyParams(phenotype=dict(spec.phenotype), pose=pose)


def view_set(rgba: np.ndarray, cams: Cameras, body: BodyParams, times, extra: dict) -> ViewSet:
    return ViewSet(
        images=rgba[..., :3], masks=rgba[..., 3], cameras=cams, body=body, file_paths=[], times=list(times), extra=extra
    )


# what synth writes (paths relative to the subject folder; dla.io.atomic.check_outputs)
SUBJECT_LAYOUT = (
    "transforms.json",
    "body.json",
    "images",
    "images/view_*.png",
    *(
        f"{sub}{rest}"
        for sub in ("novel_views", "novel_poses")
        for rest in ("", "/transforms.json", "/body.json", "/images", "/images/view_*.png")
    ),
    "novel_poses/motion.npz",
)


def check_options(res, novel_views, novel_poses, appearance: str, wardrobe: str) -> None:
    checks = (("--res", res, 16), ("--novel-views", novel_views, 0), ("--novel-poses", novel_poses, 0))
    for name, value, lo in checks:
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lo:
            raise DlaInputError(name, f"must be an integer >= {lo}, got {value!r}")
    if res > 4096:
        raise DlaInputError("--res", f"must be <= 4096, got {res}")
    if appearance not in APPEARANCES:
        raise DlaInputError("--appearance", f"must be one of {', '.join(APPEARANCES)}, got {appearance!r}")
    if wardrobe not in WARDROBES:
        raise DlaInputError("--wardrobe", f"must be one of {', '.join(WARDROBES)}, got {wardrobe!r}")


def _dressed_subject(seed: int, appearance: str, wardrobe: str):
    """(spec, dressed body, lighting or None, vertices [V, 3] in the input pose, ao [V] or None)."""
    spec = sample_subject(seed, wardrobe)
    body = DressedBody(spec)
    lighting = sample_lighting(seed) if appearance == "lit" else None
    zero = torch.zeros(1, 3)
    verts = body.vertices(spec.rotations[None], zero, zero)[0]  # [V, 3] the input pose
    ao = None if lighting is None else ambient_occlusion(verts, body.faces)
    return spec, body, lighting, verts, ao


def render_subject(
    seed: int, cameras: Cameras, *, appearance: str = "albedo", wardrobe: str = "default", light_view=None
) -> np.ndarray:
    """The subject `seed` in its input pose (that of its input and novel views, in its world:
    body.json's pose, root at the origin) from any cameras -> RGBA [C, H, W, 4] float32 (straight
    alpha), rendered exactly as `synth` renders its views (the benchmarks' ground truth for
    cameras the subject folder does not hold). `light_view`: see `dlacli.data.images.render`."""
    check_options(16, 0, 0, appearance, wardrobe)
    _, body, lighting, verts, ao = _dressed_subject(seed, appearance, wardrobe)
    return render(body, verts, cameras, seed, lighting=lighting, ao=ao, light_view=light_view)


def synth(
    seed: int,
    out: str | os.PathLike,
    *,
    res: int = 512,
    novel_views: int = 12,
    novel_poses: int = 8,
    appearance: str = "albedo",
    wardrobe: str = "default",
    random_yaw: bool = False,
    motions: Sequence[str] = (),
    progress: Progress | None = None,
) -> Path:
    """Write the synthetic subject `seed` as the view folder `out` (atomic as a whole):
    4 input views + body.json, novel_views/ (n ground-truth views of the same pose) and
    novel_poses/ (frames with `time` into novel_poses/motion.npz) when n > 0.
    appearance "albedo" | "lit", wardrobe "default" | "full" (module doc, `sample_subject`);
    random_yaw: the dataset's input rig (`input_rig`); motions: clips for the target poses
    (`target_motion`). The defaults write today's subject, byte for byte."""
    from dlacli.io.atomic import atomic_dir
    from dlacli.io.motion import write_motion
    from dlacli.io.views import write_views

    check_options(res, novel_views, novel_poses, appearance, wardrobe)
    say = progress or (lambda msg: None)
    out = Path(out)
    say("sampling and dressing the subject")
    spec, body, lighting, verts, ao = _dressed_subject(seed, appearance, wardrobe)
    info = {
        "seed": int(seed),
        "outfit": list(spec.outfit),
        "suit_pattern": spec.palette["suit"]["pattern"],
        "generator": "dla synth",
    }
    if wardrobe != "default":
        info["wardrobe"] = wardrobe
    if lighting is not None:
        info.update(appearance=appearance, lighting=lighting.as_dict())
    truth = body_params(spec, spec.rotations)
    az0, el0, yaw = input_rig(seed, random_yaw)
    with atomic_dir(out) as tmp:
        say("rendering the 4 input views")
        cams = synth_orbit_cameras(az0, el0, res)
        rgba = render(body, verts, cams, seed, lighting=lighting, ao=ao)
        rig = {"azimuths": list(INPUT_AZIMUTHS), "elevation": INPUT_ELEVATION}
        if random_yaw:
            rig = {"azimuths": az0.tolist(), "elevations": el0.tolist(), "start_yaw": yaw}
        write_views(view_set(rgba, cams, truth, [None] * 4, {"synth": {**info, **rig}}), tmp)
        if novel_views:
            say(f"rendering {novel_views} novel views")
            az, el = novel_view_angles(novel_views)
            az = (az + yaw) % 360.0 if random_yaw else az
            cams = synth_orbit_cameras(az, el, res)
            rgba = render(body, verts, cams, seed, lighting=lighting, ao=ao)
            extra = {"synth": {**info, "azimuths": az.tolist(), "elevations": el.tolist()}}
            write_views(view_set(rgba, cams, truth, [None] * novel_views, extra), tmp / "novel_views")
        if novel_poses:
            motion, kinds = target_motion(seed, spec, novel_poses, motions)
            say(f"rendering {novel_poses} novel poses x {len(POSE_AZIMUTHS)} cameras")
            posed = body.vertices(
                motion.rotations, torch.from_numpy(motion.root_rotation), torch.from_numpy(motion.root_translation)
            )  # [T, V, 3]
            pose_az = (np.array(POSE_AZIMUTHS) + yaw) % 360.0 if random_yaw else list(POSE_AZIMUTHS)
            cams1 = synth_orbit_cameras(pose_az, INPUT_ELEVATION, res)
            k = len(POSE_AZIMUTHS)
            cams = Cameras(cams1.viewmats.repeat(novel_poses, 1, 1), cams1.Ks.repeat(novel_poses, 1, 1), res, res)
            pose_ao = None if lighting is None else np.repeat(ambient_occlusion(posed, body.faces), k, axis=0)
            rgba = render(body, np.repeat(posed, k, axis=0), cams, seed, lighting=lighting, ao=pose_ao)
            times = [t for t in range(novel_poses) for _ in range(k)]
            extra = {
                "synth": {**info, "azimuths": np.asarray(pose_az).tolist(), "elevation": INPUT_ELEVATION},
                "motion": "motion.npz",
                "pose_kinds": kinds,
            }
            write_views(view_set(rgba, cams, body_params(spec, None), times, extra), tmp / "novel_poses")
            write_motion(motion, tmp / "novel_poses" / "motion.npz")
    return out
