"""Export: the avatar's own Gaussians (what `dla render` splats) as splat files (docs/export.md).

Poses (`POSES`), all on the avatar's own body shape (phenotype):
- "rest": anny's zero pose, every rotation zero, pelvis at the origin, facing -Y (an A-pose;
  docs/body.md), the pose `--rig` binds to;
- "canonical": the input pose's joint rotations (body.json `pose`) with the root rotation and
  translation set to zero: the person as photographed, upright at the origin, facing -Y;
- "input": the whole body.json (joints, root rotation and translation), the pose of the views the
  avatar was lifted from: what `dla render` draws without `--motion`;
or a frame of a motion (`dla render --motion`'s pose of that frame).

Gaussians are sampled at the avatar's own count and seed (`avatar.posed.sample_settings`) and
placed with the posed body's tangent frames (avatar/posed.py). A pose-conditioned decoder
decodes F per pose; a view-conditioned one is evaluated from the front, as for USD (animate's
`usd_view_eye`), since a splat file has no camera.

Axes (`orient`): dla's world is +Z up, the body facing -Y. `up="z"` writes it as is. `up="y"`
writes what splat viewers assume: for .ply/.spz/.splat the 3DGS (COLMAP/OpenCV) convention, whose
viewers (PlayCanvas SuperSplat, splat-transform's `Transform.PLY`) show the data rotated 180
degrees about Z, i.e. file = R_3DGS world with R_3DGS: (x, y, z) -> (-x, -z, -y), +Z up becomes
-Y and the front (-Y) becomes +Z, so after the viewer's turn the body stands on +Y and faces the
default camera on +Z; for .glb, glTF's own axes (+Y up, front +Z): (x, y, z) -> (x, z, -y).
Positions, orientations and SH coefficients (degree > 0) are rotated alike.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.limits import SPLAT_SUFFIXES
from dlacli.types import Avatar, BodyParams, Gaussians, Motion

POSES = ("rest", "canonical", "input")
UPS = ("y", "z")
FORMATS = SPLAT_SUFFIXES

# rotation matrices, world -> file, as (x, y, z) -> row-vector images
R_3DGS = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])  # 180 deg about (0, 1, -1)/sqrt 2
R_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # -90 deg about +X
BATCH = 8  # motion frames posed at once


def pose_body(avatar: Avatar, pose: str) -> BodyParams:
    """The body parameters of a named pose (see the module docstring) on the avatar's shape."""
    body = avatar.body
    if pose == "input":
        return body
    if pose == "canonical":
        return replace(body, root_rotation=np.zeros(3), root_translation=np.zeros(3))
    if pose == "rest":
        return BodyParams(phenotype=dict(body.phenotype), model=body.model)
    raise DlaInputError("--pose", f"unknown pose {pose!r} (use one of {', '.join(POSES)})")


def file_rotation(suffix: str, up: str) -> np.ndarray:
    """[3, 3] world -> file rotation for an output suffix and `--up` (module docstring)."""
    if suffix == ".glb":
        return R_GLTF
    return R_3DGS if up == "y" else np.eye(3)


def rotate_sh(sh: torch.Tensor, rot: np.ndarray) -> torch.Tensor:
    """SH coefficients [N, K, 3] of Gaussians rotated by rot [3, 3]: the colour the new set shows
    towards R d is what the old one showed towards d. Per degree l the basis spans an invariant
    space, Y_l(R^T d) = D_l Y_l(d); D_l is solved by least squares on 64 directions (exact up to
    float64 rounding), then c' = D_l^T c."""
    if sh.shape[-2] == 1:
        return sh
    from dlacli.render.sh import sh_basis
    from dlacli.types import sh_degree_for_coeffs

    degree = sh_degree_for_coeffs(sh.shape[-2])
    i = np.arange(64) + 0.5  # Fibonacci sphere: well spread directions
    z = 1.0 - 2.0 * i / 64
    phi = np.pi * (1.0 + 5**0.5) * i
    dirs = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    rot = torch.as_tensor(rot, dtype=torch.float64)
    d = torch.as_tensor(dirs)
    a = sh_basis(degree, d)  # [M, K]
    b = sh_basis(degree, d @ rot)  # [M, K]: Y(R^T d), row vectors d R = (R^T d)^T
    out = sh.clone()
    for level in range(1, degree + 1):
        s = slice(level * level, (level + 1) * (level + 1))
        dt = torch.linalg.lstsq(a[:, s], b[:, s]).solution  # [2l+1, 2l+1] = D_l^T
        out[..., s, :] = torch.einsum("kj,njc->nkc", dt, sh[..., s, :].double()).to(sh.dtype)
    return out


def orient(g: Gaussians, rot: np.ndarray) -> Gaussians:
    """Gaussians [N] rotated by rot [3, 3] (positions, orientations, SH); scales, opacities and
    colours seen along rotated directions unchanged. Positions are exact for the signed
    permutations R_3DGS / R_GLTF (products with +-1 and 0 round nothing)."""
    from dlacli.geometry import matrix_to_quat, quat_multiply

    if np.array_equal(rot, np.eye(3)):
        return g
    r = torch.as_tensor(rot, dtype=g.means.dtype)
    q = torch.as_tensor(matrix_to_quat(np.asarray(rot, dtype=np.float64)), dtype=torch.float64)
    quats = quat_multiply(q.expand(g.quats.shape), g.quats.double())
    quats = quats / quats.norm(dim=-1, keepdim=True)
    return Gaussians(g.means @ r.T, quats.to(g.quats.dtype), g.scales, g.opacities, rotate_sh(g.sh, rot))


def export_frames(
    avatar: Avatar,
    pose: str = "input",
    motion: Motion | None = None,
    frames: list[int] | None = None,
    n_gaussians: int | None = None,
    seed: int | None = None,
    where: str = "avatar",
    checkpoint: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[tuple[int | None, Gaussians]]:
    """(motion frame or None, world Gaussians [N]) for a named pose, or for `frames` of `motion`
    (all of them when None), in dla's world axes; `orient` them for a file."""
    from dlacli.avatar.codec import Decoded
    from dlacli.avatar.posed import PosedAvatar, avatar_samples
    from dlacli.body.model import get_body_model
    from dlacli.stages.animate import usd_view_eyes

    model = get_body_model()
    decoded = Decoded(avatar, where, checkpoint)
    samples = avatar_samples(avatar, n_gaussians, seed)

    def placed(body):  # the Gaussians on P posed bodies (a BodyOutput) -> avatar.posed.Placed [P]
        return PosedAvatar(decoded, samples, body.vertices, eyes=usd_view_eyes(body.bone_heads[:, 0])).all()

    with torch.no_grad():
        if motion is None:
            yield None, placed(model.forward_body(pose_body(avatar, pose))).item(0)
            if progress is not None:
                progress(1, 1)
            return
        sel = np.arange(motion.num_frames) if frames is None else np.asarray(frames, dtype=np.int64)
        if sel.size and (sel.min() < 0 or sel.max() >= motion.num_frames):
            bad = int(sel.max() if sel.max() >= motion.num_frames else sel.min())
            raise DlaInputError("--frame", f"frame {bad} is outside the motion's frames 0..{motion.num_frames - 1}")
        for start in range(0, sel.size, BATCH):
            part = sel[start : start + BATCH]
            batch = placed(model.forward_motion(avatar.body.phenotype, motion, frames=part))
            for k, t in enumerate(part):
                yield int(t), batch.item(k)
                if progress is not None:
                    progress(start + k + 1, sel.size)


def write_gaussians(g: Gaussians, path: str | os.PathLike, up: str = "y") -> None:
    """Write world Gaussians to path (format by suffix, FORMATS), oriented for `up`."""
    from pathlib import Path

    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise DlaInputError(path, f"unknown splat format {suffix or '(no suffix)'!r} (use {', '.join(FORMATS)})")
    if up not in UPS:
        raise DlaInputError("--up", f"unknown up axis {up!r} (use y or z)")
    g = orient(g, file_rotation(suffix, up))
    if suffix == ".ply":
        from dlacli.io.ply import write_ply

        write_ply(g, path)
    elif suffix == ".splat":
        from dlacli.io.splat import write_splat

        write_splat(g, path)
    elif suffix == ".spz":
        from dlacli.io.spz import write_spz

        write_spz(g, path)
    else:
        from dlacli.io.gltf_splat import write_glb

        write_glb(g, path)
