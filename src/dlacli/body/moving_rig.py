"""`MovingRig`: a `PointRig`'s points when only a few bones move, through a chain of those bones only.

A fit that rotates M of anny's 104 bones (the rest stay at their zero-pose rotation) does not
need the other bones' transforms one by one. With W_b the world pose of bone b, P_b its bind pose
and Q_pb the point's skinning term (`PointRig`), a point is sum_b W_b P_b^-1 Q_pb. For a bone b
that does not move, let a be its nearest moving ancestor (or itself when it moves): every bone
between them is at rest, so W_b = W_a G_b with the constant G_b = W0_a^-1 W0_b (W0: the zero-pose
world poses). Hence a point is sum_a W_a Q'_pa with Q'_pa = sum_{b: a(b) = a} G_b P_b^-1 Q_pb,
over the moving bones a only. The moving bones' own poses chain as W_c = W_a G_p K_c(D_c), p the
parent of c and a its nearest moving ancestor, where anny's "local-ref" step from p to c is
K_c(D) = [U_p^T D U_c | t_c] (U: the reference orientations, t_c constant) = [(U_p^T D U_p) R0_c | t_c]
with K0_c = [R0_c | t_c] = W0_p^-1 W0_c its zero-pose value (kinematics.forward_kinematic's
notation; the root's pose is [D_0 | d_0]). Exact for any pose of the moving bones; the constants
depend on the phenotype, which is linearised as `PointRig` does (`linearise`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from dlacli.body.keypoints import PointRig
from dlacli.body.model import axis_angle_to_pose_params
from dlacli.geometry import axis_angle_to_matrix


class MovingRig:
    """The points of `rig` (all of them, or the first `num_points`) as a function of the rotations
    of `bones` (labels; the root is always moving: root rotation and translation), all other bones
    at rest. Same phenotype handling as `PointRig` (`free_keys`, `linearise`). CPU float32."""

    def __init__(self, rig: PointRig, bones: Sequence[str], num_points: int | None = None) -> None:
        model = rig.model
        self.rig = rig
        self.bones = tuple(bones)
        ids = [model.bone_index(b, "bones") for b in self.bones]
        if 0 in ids or len(set(ids)) != len(ids):
            raise ValueError("bones must be distinct and exclude the root")
        self.num_points = rig.num_points if num_points is None else int(num_points)
        parents = model.bone_parents  # [J], root -1
        depth = [0] * len(parents)
        for j in range(1, len(parents)):
            depth[j] = depth[int(parents[j])] + 1  # anny's parents precede their children
        moving = [0, *sorted(ids, key=lambda j: depth[j])]  # root first, then by depth
        self._moving = torch.tensor(moving)
        self._param_of = torch.tensor([1 + ids.index(j) for j in moving[1:]])  # their slot in `rotations`
        slot = {j: k for k, j in enumerate(moving)}
        anchor = []  # each bone's nearest moving ancestor-or-self, as a slot in `moving`
        for j in range(len(parents)):
            a = j
            while a not in slot:
                a = int(parents[a])
            anchor.append(slot[a])
        self._anchor = torch.tensor(anchor)  # [J]
        self._parent = torch.tensor([int(parents[j]) for j in moving[1:]])  # [M-1] actual parents
        self._mparent = torch.tensor([anchor[int(parents[j])] for j in moving[1:]])  # [M-1] slots
        levels: dict[int, list[int]] = {}  # chain levels: a slot's moving ancestor lies in an earlier level
        lvl = [0] * len(moving)
        for k in range(1, len(moving)):
            lvl[k] = lvl[int(self._mparent[k - 1])] + 1
            levels.setdefault(lvl[k], []).append(k)
        self._levels = [torch.tensor(levels[d]) for d in sorted(levels)]
        ref = rig._anny.reference_bone_orientations  # noqa: SLF001 - [J, 3, 3]
        assert ref is not None, "anny without reference orientations: local-ref would differ"
        self._u_parent = ref[self._parent].float()  # [M-1, 3, 3]
        self.linearise(rig.phenotype0)

    def _constants(self, phenotype: dict[str, float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(Q' [P, M, 4], G_p [M-1, 4, 4], K0 [M-1, 4, 4]) for one phenotype (module doc)."""
        q, bind = self.rig._bind(phenotype)  # noqa: SLF001 - [P, J, 4], [J, 4, 4]
        q = q[: self.num_points]
        j = bind.shape[0]
        eye = torch.eye(4).expand(1, j, 4, 4)
        _, w0 = self.rig._anny.get_bone_transforms(eye, bind[None])  # noqa: SLF001 - zero pose, [1, J, 4, 4]
        w0 = w0[0]
        w0_anchor = w0[self._moving][self._anchor]  # [J, 4, 4]
        g = torch.linalg.solve(w0_anchor, w0)  # G_b = W0_a^-1 W0_b
        gp_inv = g @ torch.linalg.inv(bind)  # [J, 4, 4] G_b P_b^-1
        contrib = torch.einsum("bxy,pby->pbx", gp_inv, q)  # [P, J, 4]
        qm = torch.zeros(q.shape[0], len(self._moving), 4).index_add_(1, self._anchor, contrib)
        k0 = torch.linalg.solve(w0[self._parent], w0[self._moving[1:]])  # [M-1, 4, 4]
        return qm, g[self._parent], k0

    def linearise(self, phenotype: dict[str, float], step: float = 0.05) -> None:
        """Reference phenotype and forward-difference slopes of the constants (as `PointRig.linearise`)."""
        self.phenotype0 = {k: float(v) for k, v in phenotype.items()}
        base = self._constants(self.phenotype0)
        slopes = []
        for key in self.rig.free_keys:
            p = dict(self.phenotype0)
            v = p.get(key, 0.5)
            h = step if v + step <= 1.0 else -step
            p[key] = v + h
            slopes.append([(c1 - c0) / h for c0, c1 in zip(base, self._constants(p), strict=True)])
        self._base = base
        self._slopes = [torch.stack(s) if s else None for s in zip(*slopes, strict=True)] if slopes else None
        self._p0 = torch.tensor([self.phenotype0.get(k, 0.5) for k in self.rig.free_keys], dtype=torch.float32)

    def __call__(
        self,
        phenotype: torch.Tensor | None,  # [K] values of the rig's free keys (None: the reference)
        rotations: torch.Tensor,  # [S, len(bones), 3] axis-angle of `bones`, local-ref
        root_rotation: torch.Tensor,  # [S, 3]
        root_translation: torch.Tensor,  # [S, 3]
    ) -> torch.Tensor:
        """-> points [S, P, 3] in the world (equal to `PointRig` with the other bones at rest)."""
        qm, gp, k0 = self._base
        if phenotype is not None and self._slopes is not None:
            d = phenotype - self._p0  # [K]
            qm, gp, k0 = (c + torch.tensordot(d, s, dims=1) for c, s in zip(self._base, self._slopes, strict=True))
        s = rotations.shape[0]
        root = axis_angle_to_pose_params(
            torch.zeros(s, 1, 3, dtype=rotations.dtype), root_rotation.reshape(s, 3), root_translation.reshape(s, 3)
        )[:, 0]  # [S, 4, 4]
        dmat = axis_angle_to_matrix(rotations[:, self._param_of - 1])  # [S, M-1, 3, 3] in chain order
        rot = self._u_parent.transpose(-1, -2) @ dmat @ self._u_parent @ k0[:, :3, :3]  # (U^T D U) R0
        k = torch.cat([torch.cat([rot, k0[:, :3, 3:].expand(s, -1, -1, -1)], -1), k0[:, 3:].expand(s, -1, -1, -1)], -2)
        step = gp @ k  # [S, M-1, 4, 4]: W_c = W_a (G_p K_c)
        out = torch.empty(s, 1 + step.shape[1], 4, 4, dtype=root.dtype)
        out[:, 0] = root
        for level in self._levels:
            out[:, level] = out[:, self._mparent[level - 1]] @ step[:, level - 1]
        t34 = out[:, :, :3, :].transpose(2, 3).reshape(s, -1, 3)  # [S, M * 4, 3]
        return qm.reshape(qm.shape[0], -1) @ t34  # [S, P, 3]
