"""Rig: an avatar's Gaussians bound to the body's skeleton by linear blend skinning (docs/rig.md).

dla itself places Gaussians with the posed body's tangent frames (x = T + R dx, R_g = R dR,
s = S ds; stages/animate.py). Tools that only know skeletons (Blender, game engines, a viewer
that poses with joint matrices) need the same Gaussians as a classic LBS rig instead:

- rest pose: the zero pose on the avatar's phenotype (what dla calls "rest": docs/body.md);
- per joint: its world transform in that rest pose (`bind_transforms`);
- per Gaussian: its rest-pose mean, orientation, scale, colour and opacity, and K joint
  weights: the barycentric blend of the skinning weights of its triangle's three corners
  (anny's own vertex weights), top K kept and renormalised;
- per frame: skinning matrices M_j = W_t,j W_rest,j^-1 (world from rest), and
  x_t = sum_j w_j M_j x_rest.

Orientation: each Gaussian turns with the rotation of its blended matrix A = sum_j w_j M_j[:3, :3]
made orthonormal by the polar decomposition A = U P (U the closest rotation to A in the
Frobenius norm; Newton's iteration, `polar_rotation`): q_t = quat(U) q_rest.
The polar factor is what LBS does to a small neighbourhood of the mean, minus its stretch and
shear; scales stay at their rest values (LBS has no per-Gaussian scale to give).

Only the canonical map is rigged: a pose- or view-conditioned decoder's F_delta depends on the
pose and cannot be baked into fixed Gaussians, so such avatars are rigged from F_c with a
one-line warning.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.types import Avatar, Motion

WEIGHT_CHUNK = 32_768  # Gaussians per chunk when blending corner weights (dense [chunk, J])


@dataclass
class Rig:
    """An avatar's Gaussians in the rest pose with LBS weights on anny's skeleton (numpy)."""

    joint_names: list[str]  # [J] anny bone labels
    parents: np.ndarray  # [J] int64, -1 for the root
    bind_transforms: np.ndarray  # [J, 4, 4] float64 world transform of each joint in the rest pose
    positions: np.ndarray  # [N, 3] float32 Gaussian means in the rest pose
    quats: np.ndarray  # [N, 4] float32 (w, x, y, z) rest-pose orientations
    scales: np.ndarray  # [N, 3] float32 standard deviations, metres
    opacities: np.ndarray  # [N] float32 in [0, 1]
    rgb: np.ndarray  # [N, 3] float32 in [0, 1]
    joint_indices: np.ndarray  # [N, K] int32 into joint_names (zero-weight slots allowed)
    joint_weights: np.ndarray  # [N, K] float32, rows sum to 1

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def __len__(self) -> int:
        return self.positions.shape[0]


def warn_conditioned(decoded, where: str) -> None:
    """One line on stderr when the avatar's decoder has a pose/view part the rig cannot carry."""
    if decoded.conditioned:
        print(
            f"warning: {where}: decoder {decoded.decoder.name!r} is pose/view-conditioned; the rig "
            "carries its canonical map F_c only (F_delta depends on the pose and cannot be baked in)",
            file=sys.stderr,
        )


def rig_decoded(avatar: Avatar, where: str = "avatar", checkpoint: str | None = None):
    """The avatar decoded for rigging (avatar/codec.Decoded; its F_c is what a rig carries), with
    `warn_conditioned`'s line when the decoder has a part the rig drops."""
    from dlacli.avatar.codec import Decoded

    decoded = Decoded(avatar, where, checkpoint)
    warn_conditioned(decoded, where)
    return decoded


def blend_corner_weights(
    face_id: np.ndarray,  # [N] int64 triangles of the body mesh
    bary: np.ndarray,  # [N, 3] barycentrics
    vertex_indices: np.ndarray,  # [V, Kv] bone indices per vertex
    vertex_weights: np.ndarray,  # [V, Kv] weights per vertex (rows sum to 1)
    faces: np.ndarray,  # [F, 3]
    num_joints: int,
    k: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-point weights sum_c b_c w(corner c), the k largest kept and renormalised:
    (indices [N, k] int32, weights [N, k] float32, rows sum to 1, non-negative)."""
    n = face_id.shape[0]
    out_i = np.zeros((n, k), np.int32)
    out_w = np.zeros((n, k), np.float32)
    corners = faces[face_id]  # [N, 3]
    for s in range(0, n, WEIGHT_CHUNK):
        c = corners[s : s + WEIGHT_CHUNK]  # [n_c, 3]
        b = np.clip(np.asarray(bary[s : s + WEIGHT_CHUNK], np.float64), 0.0, None)  # [n_c, 3]
        dense = np.zeros((c.shape[0], num_joints), np.float64)
        rows = np.repeat(np.arange(c.shape[0]), vertex_indices.shape[1])
        for corner in range(3):
            vals = b[:, corner, None] * vertex_weights[c[:, corner]]  # [n_c, Kv]
            np.add.at(dense, (rows, vertex_indices[c[:, corner]].reshape(-1)), vals.reshape(-1))
        top = np.argsort(-dense, axis=1, kind="stable")[:, :k]  # [n_c, k] largest first
        w = np.take_along_axis(dense, top, axis=1)
        total = w.sum(axis=1, keepdims=True)
        assert np.all(total > 0), "a point with no skinning weight"
        out_i[s : s + WEIGHT_CHUNK] = top
        out_w[s : s + WEIGHT_CHUNK] = w / total
    return out_i, out_w


@torch.no_grad()
def build_rig(
    avatar: Avatar,
    n_gaussians: int | None = None,
    seed: int | None = None,
    where: str = "avatar",
    checkpoint: str | None = None,
) -> Rig:
    """The avatar's Gaussians in the rest pose (zero pose, its own phenotype) with LBS weights.

    Count and seed of the sample points default to the avatar's own (avatar/posed.sample_settings).
    K = anny's weights per vertex (9)."""
    from dlacli.avatar.posed import PosedAvatar, avatar_samples
    from dlacli.body.model import get_body_model

    model = get_body_model()
    decoded = rig_decoded(avatar, where, checkpoint)
    samples = avatar_samples(avatar, n_gaussians, seed)
    rest = model.zero_pose(avatar.body.phenotype)
    placed = PosedAvatar(decoded, samples, rest.vertices, canonical_only=True).all()
    v_idx, v_w = model.vertex_bone_weights
    j_idx, j_w = blend_corner_weights(
        samples.face_id, samples.bary, v_idx, v_w, model.faces, model.num_bones, v_idx.shape[1]
    )
    return Rig(
        joint_names=list(model.bone_labels),
        parents=model.bone_parents.astype(np.int64).copy(),
        bind_transforms=rest.bone_poses[0].double().numpy(),
        positions=placed.means[0].numpy().astype(np.float32),
        quats=placed.quats[0].numpy().astype(np.float32),
        scales=placed.scales[0].numpy().astype(np.float32),
        opacities=placed.opacities.numpy().astype(np.float32),
        rgb=placed.rgb.numpy().astype(np.float32),
        joint_indices=j_idx,
        joint_weights=j_w,
    )


def skinning_matrices(avatar: Avatar, motion: Motion, where: str = "motion") -> np.ndarray:
    """[T, J, 4, 4] float32 M_t,j = W_t,j W_rest,j^-1 (world from rest) for every frame of `motion`
    on the avatar's phenotype, so that x_t = sum_j w_j M_t,j x_rest. Computed from anny's LBS
    transforms as M = T_t T_rest^-1 (the bind mesh cancels), in float64."""
    from dlacli.body.model import get_body_model

    if motion.model != "anny":
        raise DlaInputError(where, f"motion is for body model {motion.model!r}, not 'anny'")
    if motion.num_frames < 1:
        raise DlaInputError(where, "motion has no frames")
    model = get_body_model()
    rest = model.zero_pose(avatar.body.phenotype).bone_transforms[0].double().numpy()  # [J, 4, 4]
    posed = model.forward_motion(avatar.body.phenotype, motion).bone_transforms.double().numpy()
    return (posed @ np.linalg.inv(rest)[None]).astype(np.float32)


def polar_rotation(a: np.ndarray, iterations: int = 20, tol: float = 1e-12) -> np.ndarray:
    """[..., 3, 3] -> [..., 3, 3] float64 the rotation factor U of the polar decomposition a = U P
    (the closest rotation to a in the Frobenius norm; det U = +1).

    Newton's iteration X <- (X + X^-T) / 2 (Higham), with X^-T = cofactor(X) / det(X) in closed
    form: it converges quadratically to U for any non-singular a with det a > 0 (blended LBS
    rotations have singular values near 1: 2-3 steps). Matrices with det <= 0 (not reachable by
    blending rotations with non-negative weights in practice) take the SVD route."""
    x = np.array(a, dtype=np.float64)
    det0 = np.linalg.det(x)
    good = det0 > 1e-9
    for _ in range(iterations):
        r0, r1, r2 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
        cof = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-2)
        det = np.einsum("...i,...i->...", r0, cof[..., 0, :])
        det = np.where(good, det, 1.0)
        nxt = 0.5 * (x + cof / det[..., None, None])
        step = np.abs(nxt - x).max()
        x = nxt
        if step < tol:
            break
    if not np.all(good):
        w, _, vt = np.linalg.svd(np.asarray(a, np.float64)[~good])
        d = np.sign(np.linalg.det(w @ vt))
        w[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]
        x[~good] = w @ vt
    return x


def blended_matrices(rig: Rig, mats: np.ndarray) -> np.ndarray:
    """[N, 3, 4] float64 sum_k w_k M[j_k][:3, :4] per Gaussian, for mats [J, 4, 4]."""
    mats = np.asarray(mats, np.float64)[:, :3, :]  # [J, 3, 4]
    out = np.zeros((len(rig), 3, 4), np.float64)
    for k in range(rig.joint_indices.shape[1]):
        out += rig.joint_weights[:, k, None, None].astype(np.float64) * mats[rig.joint_indices[:, k]]
    return out


def skin(rig: Rig, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LBS of the rig's Gaussians by joint matrices mats [J, 4, 4] (world from rest, e.g. one frame
    of `skinning_matrices`) -> positions [N, 3] float32, quats [N, 4] float32 (w, x, y, z, unit):
    means by the blended matrix, orientations by its polar rotation (module docstring)."""
    from dlacli.geometry import matrix_to_quat, quat_multiply, quat_normalize

    mats = np.asarray(mats)
    if mats.shape != (rig.num_joints, 4, 4):
        raise DlaInputError("mats", f"expected shape [{rig.num_joints}, 4, 4], got {list(mats.shape)}")
    if not np.all(np.isfinite(mats)):
        raise DlaInputError("mats", "contains NaN or Inf")
    a = blended_matrices(rig, mats)  # [N, 3, 4]
    pos = np.einsum("nij,nj->ni", a[:, :, :3], rig.positions.astype(np.float64)) + a[:, :, 3]
    rot_q = matrix_to_quat(polar_rotation(a[:, :, :3]))  # [N, 4]
    quats = quat_normalize(quat_multiply(rot_q, rig.quats.astype(np.float64)))
    return pos.astype(np.float32), quats.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# the rigged mesh for DCC tools (io/usd_rig.py, formats/usd-rig.md)

TEXTURE_DILATION = 8  # texels the colours are grown into the empty UV space (bilinear filtering
# and mip-maps at chart borders then read the chart's own colours, not black)


def dilate_texture(rgb: np.ndarray, mask: np.ndarray, steps: int = TEXTURE_DILATION) -> np.ndarray:
    """rgb [R, R, 3] valid where mask [R, R]: each step fills the empty texels next to filled ones
    (4-neighbours) with their mean; what is still empty after `steps` gets the mean colour."""
    out = np.where(mask[..., None], rgb, 0.0).astype(np.float64)
    filled = mask.copy()
    for _ in range(steps):
        acc = np.zeros_like(out)
        cnt = np.zeros(mask.shape, np.float64)
        for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
            acc += np.roll(np.where(filled[..., None], out, 0.0), shift, axis)
            cnt += np.roll(filled, shift, axis)
        grow = (~filled) & (cnt > 0)
        out[grow] = acc[grow] / cnt[grow, None]
        filled = filled | grow
    if filled.any():
        out[~filled] = out[filled].mean(axis=0)
    return out


@torch.no_grad()
def body_mesh(fmap: torch.Tensor, phenotype: dict[str, float]) -> dict[str, np.ndarray]:
    """The anny body in the rest pose with the avatar's map applied at each vertex -> points
    [V, 3], normals [V, 3], rgb [V, 3] (sRGB in [0, 1]), opacity [V].

    Each vertex moves along its normal n by h = max(0, n . mean_c(R_c dxyz_c)): the map's offset
    at the vertex's UV corners c (more than one at seams), world = R dxyz in each corner's tangent
    frame, averaged. Only the outward part is kept: one mesh layer stands for the outermost layer
    of Gaussians, which is what a splat render shows (inner Gaussians are covered); the tangential
    part (median ~1 cm on lifted avatars) only slides the surface under its own texture and made
    the mesh crumple. Normals are the bare body's smooth ones, so the noise of the offsets does
    not show as shading noise. Measured on the demo avatar (docs/rig.md): this gave the best
    silhouette agreement with the splats of the variants tried (full offsets, normal offsets,
    smoothed, none)."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.body.model import get_body_model
    from dlacli.body.uv import tangent_frames, vertex_normals

    model = get_body_model()
    rest = model.zero_pose(phenotype).vertices[0]  # [V, 3]
    faces, uv, face_uv = model.faces, model.uv, model.face_uv
    f_ids = np.repeat(np.arange(faces.shape[0]), 3)  # [3F] one entry per face corner
    bary = np.tile(np.eye(3, dtype=np.float32), (faces.shape[0], 1))  # [3F, 3]
    params = gm.lookup(fmap.float(), uv[face_uv.reshape(-1)])  # [3F, 14]
    _, frames_r, _ = tangent_frames(rest, f_ids, bary)  # [3F, 3, 3]
    offsets = (frames_r @ params[:, gm.OFFSET, None])[..., 0].double().numpy()  # [3F, 3]
    corner_v = faces.reshape(-1)
    count = np.bincount(corner_v, minlength=rest.shape[0]).astype(np.float64)[:, None]
    assert np.all(count > 0), "a vertex in no face"

    def mean(values: np.ndarray) -> np.ndarray:
        acc = np.zeros((rest.shape[0], values.shape[1]), np.float64)
        np.add.at(acc, corner_v, values)
        return acc / count

    bare = rest.double().numpy()
    normals = vertex_normals(rest.double()[None])[0].numpy()  # [V, 3] unit
    height = np.maximum((mean(offsets) * normals).sum(axis=1), 0.0)  # [V] outward only
    points = bare + height[:, None] * normals
    rgb = mean(params[:, gm.RGB].double().clamp(0, 1).numpy())
    opacity = mean(torch.sigmoid(params[:, gm.OPACITY].double()).numpy())[:, 0]
    return {
        "points": points.astype(np.float32),
        "normals": normals.astype(np.float32),
        "rgb": rgb.astype(np.float32),
        "opacity": opacity.astype(np.float32),
    }


def albedo_texture(fmap: torch.Tensor) -> np.ndarray:
    """The map's colour channels as an 8-bit sRGB image [R, R, 3] (row 0 = v near 1, the UV
    image convention), dilated into the empty texels."""
    from dlacli.avatar import gaussian_map as gm
    from dlacli.body.uv import uv_raster

    r = int(fmap.shape[-1])
    rgb = fmap[gm.RGB].permute(1, 2, 0).double().clamp(0, 1).numpy()  # [R, R, 3]
    out = dilate_texture(rgb, uv_raster(r).mask)
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def rig_asset(
    avatar: Avatar,
    motion: Motion | None = None,
    where: str = "avatar",
    checkpoint: str | None = None,
):
    """The UsdSkel asset of an avatar (io.usd_rig.RigAsset): anny's skeleton bound in the rest
    pose, the body mesh with the avatar's offsets and colours, anny's own vertex weights, the
    colour texture, and (with a motion) each joint's world transform per frame."""
    from dlacli.body.model import get_body_model
    from dlacli.io.usd_rig import RigAsset

    model = get_body_model()
    decoded = rig_decoded(avatar, where, checkpoint)
    mesh = body_mesh(decoded.f_c, avatar.body.phenotype)
    v_idx, v_w = model.vertex_bone_weights
    poses = fps = None
    if motion is not None:
        if motion.model != "anny":
            raise DlaInputError("motion", f"motion is for body model {motion.model!r}, not 'anny'")
        poses = model.forward_motion(avatar.body.phenotype, motion).bone_poses.double().numpy()
        fps = float(motion.fps)
    return RigAsset(
        joint_names=list(model.bone_labels),
        parents=model.bone_parents.astype(np.int64).copy(),
        bind_transforms=model.zero_pose(avatar.body.phenotype).bone_poses[0].double().numpy(),
        points=mesh["points"],
        normals=mesh["normals"],
        faces=model.faces,
        uv=model.uv,
        face_uv=model.face_uv,
        vertex_rgb=mesh["rgb"],
        joint_indices=v_idx.astype(np.int32),
        joint_weights=(v_w / v_w.sum(axis=1, keepdims=True)).astype(np.float32),
        texture=albedo_texture(decoded.f_c),
        fps=fps,
        joint_poses=poses,
    )


def write_rigged_usd(
    avatar: Avatar,
    path,
    motion: Motion | None = None,
    n_gaussians: int | None = None,
    seed: int | None = None,
    where: str = "avatar",
    checkpoint: str | None = None,
):
    """Write the avatar as a rigged UsdSkel asset (formats/usd-rig.md) at `path` (.usdc, .usda or
    .usd) and its colour texture beside it (`<stem>.albedo.png`); with `motion`, the joint
    animation too. Returns the texture's path.

    The mesh is the body surface the avatar's map describes, not its Gaussians, so `n_gaussians`
    and `seed` (the Gaussian sample settings of `dla export`) do not change the file; they are
    checked like everywhere else (avatar/posed.sample_settings)."""
    from pathlib import Path

    from dlacli.avatar.posed import sample_settings
    from dlacli.io.atomic import check_outputs
    from dlacli.io.usd_rig import SUFFIXES, texture_path, write_rig_usd

    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"a rigged avatar is a .usdc, .usda or .usd file, not {path.suffix!r}")
    check_outputs(files=[path, texture_path(path)])
    sample_settings(avatar, n_gaussians, seed)
    return write_rig_usd(path, rig_asset(avatar, motion, where, checkpoint))
