"""COCO-17 keypoints of the anny body, and a fast differentiable posed-point model for fitting.

- `coco_keypoints(vertices [T, V, 3]) -> [T, 17, 3]`: anny's own COCO keypoint regressor
  (anny/data/keypoints/coco.pth: per keypoint, weights over the 19,158 hm08 base-mesh vertices
  that sum to 1), mapped to our "anny" topology through the model's `base_mesh_vertex_indices`
  (as anny's `KeypointsRegressor` does), restricted to the 17 COCO keypoints in COCO order.
  Left/right are the person's own (anny's +X is the person's left; docs/conventions.md).
- `PointRig`: world positions of a fixed set of "points" (keypoints and surface samples, each a
  fixed linear combination of mesh vertices) for a pose, differentiable in the pose *and* in the
  phenotype, at a cost of a few milliseconds. Because linear blend skinning is linear in the bind
  vertices, a point p = sum_v a_pv sum_b w_vb T_b x_v equals sum_b T_b Q_pb with
  Q_pb = sum_v a_pv w_vb [x_v; 1], so only the bone transforms T_b have to be computed per step.
  The phenotype enters through the bind state (bind vertices and bind bone poses), which is
  linearised around a reference phenotype by finite differences (`PointRig.linearise`); the
  exact body is always recomputed with `BodyModel.forward` at the end of a fit.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch

from dlacli.body.model import BodyModel, anny_data_dir, axis_angle_to_pose_params, get_body_model
from dlacli.types import PHENOTYPE_KEYS

COCO_NAMES = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)
NUM_KEYPOINTS = len(COCO_NAMES)
# a keypoint detected below this confidence counts as unseen (the photo fit, the video fit, the lifter)
MIN_CONF = 0.3
SHOULDERS = (5, 6)  # COCO left, right shoulder
HIPS = (11, 12)  # COCO left, right hip
TORSO = (*SHOULDERS, *HIPS)
# left <-> right: the keypoint each one becomes in a mirror image of the person
COCO_MIRROR = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)
# Pairs drawn as a skeleton (COCO's own skeleton, 0-based).
COCO_SKELETON = (
    (15, 13),
    (13, 11),
    (16, 14),
    (14, 12),
    (11, 12),
    (5, 11),
    (6, 12),
    (5, 6),
    (5, 7),
    (6, 8),
    (7, 9),
    (8, 10),
    (1, 2),
    (0, 1),
    (0, 2),
    (1, 3),
    (2, 4),
    (3, 5),
    (4, 6),
)


@functools.lru_cache(maxsize=1)
def coco_regressor() -> np.ndarray:
    """[17, V] float32 regression weights over the "anny" topology's vertices (rows sum to 1)."""
    model = get_body_model()
    a = model._anny  # noqa: SLF001 - body/ is the only package that touches anny
    data = torch.load(anny_data_dir() / "keypoints" / "coco.pth", weights_only=True, map_location="cpu")
    idx = a.base_mesh_vertex_indices.detach().cpu().numpy().astype(np.int64)  # [V] hm08 ids
    out = np.stack([data[name].numpy()[idx] for name in COCO_NAMES]).astype(np.float64)
    sums = out.sum(axis=1)
    assert np.all(np.abs(sums - 1.0) < 1e-3), sums  # the mapped weights still sum to 1
    return (out / sums[:, None]).astype(np.float32)


def coco_keypoints(vertices):
    """Posed vertices [T, V, 3] (or [V, 3]) -> COCO-17 world keypoints [T, 17, 3] (or [17, 3]).

    Torch in, torch out (differentiable, the input's dtype and device); numpy in, numpy out.
    """
    reg = coco_regressor()
    if vertices.shape[-2:] != (reg.shape[1], 3):
        raise ValueError(f"vertices must be [..., {reg.shape[1]}, 3], got {tuple(vertices.shape)}")
    if isinstance(vertices, torch.Tensor):
        r = torch.from_numpy(reg).to(device=vertices.device, dtype=vertices.dtype)
        return torch.einsum("kv,...vd->...kd", r, vertices)
    v = np.asarray(vertices)
    return np.einsum("kv,...vd->...kd", reg.astype(v.dtype if v.dtype.kind == "f" else np.float32), v)


class PointRig:
    """Differentiable world positions of fixed vertex combinations for one pose (see module doc).

    Points: the 17 COCO keypoints first, then the optional `surface` samples (vertex ids [P, 3],
    barycentric weights [P, 3]: each is sum_k bary[p, k] * vertex[ids[p, k]]). `free_keys` are
    the phenotype keys the points are differentiable in (linearised, `linearise`). CPU float32.
    """

    def __init__(
        self,
        surface: tuple[np.ndarray, np.ndarray] | None = None,  # ([P, 3] vertex ids, [P, 3] bary)
        free_keys: Sequence[str] = (),
        model: BodyModel | None = None,
    ) -> None:
        self.model = model or get_body_model()
        self._anny = self.model._anny  # noqa: SLF001
        self.free_keys = tuple(free_keys)
        reg = coco_regressor()  # [17, V]
        kv = [np.nonzero(r)[0] for r in reg]
        m = max(len(k) for k in kv)
        ids = np.zeros((NUM_KEYPOINTS, m), np.int64)
        wts = np.zeros((NUM_KEYPOINTS, m), np.float32)
        for k, sel in enumerate(kv):
            ids[k, : len(sel)] = sel
            wts[k, : len(sel)] = reg[k, sel]
        self._blocks = [(ids, wts)]
        if surface is not None:
            sid, sw = surface
            self._blocks.append((np.asarray(sid, np.int64), np.asarray(sw, np.float32)))
        self.num_points = sum(b[0].shape[0] for b in self._blocks)
        bidx, bw = self.model.vertex_bone_weights  # [V, K] each
        self._bone_idx = torch.from_numpy(bidx)
        self._bone_w = torch.from_numpy(bw)
        self.linearise({})

    def _bind(self, phenotype: dict[str, float]) -> tuple[torch.Tensor, torch.Tensor]:
        like = torch.zeros(1)
        verts, poses = self.model._bind(self._anny, phenotype, like)  # noqa: SLF001
        return self._q_of(verts[0]), poses[0]  # Q [P, J, 4], bind poses [J, 4, 4]

    def _q_of(self, bind_vertices: torch.Tensor) -> torch.Tensor:
        """Bind vertices [V, 3] -> Q [P, J, 4] (skinning weight x homogeneous bind position)."""
        j = self.model.num_bones
        xh = torch.cat([bind_vertices, torch.ones_like(bind_vertices[:, :1])], dim=1)  # [V, 4]
        out = []
        for ids, wts in self._blocks:
            ids_t = torch.from_numpy(ids)  # [P, M]
            w_t = torch.from_numpy(wts)  # [P, M]
            p = ids.shape[0]
            bones = self._bone_idx[ids_t]  # [P, M, K]
            bw = self._bone_w[ids_t] * w_t[..., None]  # [P, M, K]
            contrib = bw[..., None] * xh[ids_t][:, :, None, :]  # [P, M, K, 4]
            q = torch.zeros(p, j, 4)
            flat = (torch.arange(p)[:, None, None] * j + bones).reshape(-1)  # [P*M*K]
            q.view(p * j, 4).index_add_(0, flat, contrib.reshape(-1, 4))
            out.append(q)
        return torch.cat(out, dim=0)

    def linearise(self, phenotype: dict[str, float], step: float = 0.05) -> None:
        """Set the reference phenotype p0 and the finite-difference slopes of the bind state with
        respect to each free phenotype key (forward difference, backward near 1)."""
        self.phenotype0 = {k: float(v) for k, v in phenotype.items()}
        q0, b0 = self._bind(self.phenotype0)
        self._q0, self._b0 = q0, b0
        dq, db = [], []
        for key in self.free_keys:
            p = dict(self.phenotype0)
            v = p.get(key, 0.5)
            h = step if v + step <= 1.0 else -step
            p[key] = v + h
            q1, b1 = self._bind(p)
            dq.append((q1 - q0) / h)
            db.append((b1 - b0) / h)
        self._dq = torch.stack(dq) if dq else torch.zeros((0,) + q0.shape)  # [K, P, J, 4]
        self._db = torch.stack(db) if db else torch.zeros((0,) + b0.shape)  # [K, J, 4, 4]
        self._p0 = torch.tensor([self.phenotype0.get(k, 0.5) for k in self.free_keys], dtype=torch.float32)  # [K]

    def __call__(
        self,
        phenotype: torch.Tensor | None,  # [K] values of `free_keys` (None = the reference)
        rotations: torch.Tensor,  # [J, 3] axis-angle, local-ref, or [S, J, 3] for S poses at once
        root_rotation: torch.Tensor,  # [3] (or [S, 3])
        root_translation: torch.Tensor,  # [3] (or [S, 3])
        keypoints_only: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (points [P, 3] world, the first 17 being the COCO keypoints (only those with
        `keypoints_only`); joints [J, 3]); with [S, J, 3] rotations [S, P, 3] and [S, J, 3]
        (one call for S poses costs about as much as one: the bone chain dominates)."""
        n = NUM_KEYPOINTS if keypoints_only else self.num_points
        q, b = self._q0[:n], self._b0
        if phenotype is not None and len(self.free_keys):
            d = phenotype - self._p0  # [K]
            q = q + (d @ self._dq[:, :n].reshape(d.shape[0], -1)).reshape(q.shape)
            b = b + (d @ self._db.reshape(d.shape[0], -1)).reshape(b.shape)
        batched = rotations.dim() == 3
        rot = rotations if batched else rotations[None]
        s = rot.shape[0]
        params = axis_angle_to_pose_params(rot, root_rotation.reshape(s, 3), root_translation.reshape(s, 3))
        transforms, poses = self._anny.get_bone_transforms(params, b[None].expand(s, *b.shape))  # [S, J, 4, 4]
        t34 = transforms[:, :, :3, :].transpose(2, 3).reshape(s, -1, 3)  # [S, J * 4, 3]
        pts = q.reshape(q.shape[0], -1) @ t34  # [S, P, 3] = sum_j T_j[:3] q_pj
        if not batched:
            return pts[0], poses[0, :, :3, 3]
        return pts, poses[:, :, :3, 3]

    def phenotype_dict(self, phenotype: torch.Tensor | None) -> dict[str, float]:
        """The full phenotype for `phenotype` [K] (other keys from the reference)."""
        out = {k: 0.5 for k in PHENOTYPE_KEYS}
        out.update(self.phenotype0)
        if phenotype is not None:
            for k, v in zip(self.free_keys, phenotype.detach().cpu().tolist()):
                out[k] = float(min(1.0, max(0.0, v)))
        return out
