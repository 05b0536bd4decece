"""The anny body model behind one small API (docs/body.md).

This module (with the rest of dlacli.body) is the only place that imports anny. anny is built
with rig "anny" (104 bones), topology "anny" (13,718 vertices, 27,420 triangles) and pose
parameterisation "local-ref", and is converted to float32. Skinning uses anny's dense torch LBS
("lbs"), which is differentiable, needs no Warp kernel compilation and is faster on CPU here.

Pose convention (see docs/body.md for the derivation):
- `rotations[:, c]` for c >= 1 is bone c's axis-angle in anny's "local-ref" sense: it turns bone
  c's subtree about the bone's head, expressed in the world-aligned axes of the zero pose.
- bone 0 ("root", at the pelvis) carries the root's world transform: its world pose is
  W_0 = [Rot(root_rotation) @ Rot(rotations[:, 0]) | root_translation]. The converters below
  always return `rotations[:, 0] = 0` and put the whole root rotation into `root_rotation`.
- all zeros is anny's zero pose: an A-pose, facing -Y, +Z up, pelvis at the origin.
"""

from __future__ import annotations

import copy
import functools
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from dlacli.paths import cache_dir
from dlacli.types import PHENOTYPE_KEYS, BodyParams, Motion

RIG = "anny"
TOPOLOGY = "anny"
POSE_PARAMETERIZATION = "local-ref"
NUM_BONES = 104


@dataclass
class BodyOutput:
    """A posed body for T frames (torch tensors, the input's dtype and device)."""

    vertices: torch.Tensor  # [T, V, 3] posed vertices, metres
    bone_transforms: torch.Tensor  # [T, J, 4, 4] world transforms applied to the bind mesh (LBS)
    bone_heads: torch.Tensor  # [T, J, 3] world positions of the bone heads (joints)
    bone_poses: torch.Tensor  # [T, J, 4, 4] world pose of each bone: orientation | head

    @property
    def num_frames(self) -> int:
        return self.vertices.shape[0]


# ---------------------------------------------------------------------------------------------
# pose parameter conversion (pure functions, no model needed)


def _as_torch(x) -> tuple[torch.Tensor, bool]:
    if isinstance(x, torch.Tensor):
        return x, False
    return torch.as_tensor(np.asarray(x, dtype=np.float32)), True


def axis_angle_to_pose_params(rotations, root_rotation, root_translation):
    """Axis-angles -> anny "local-ref" pose parameters.

    rotations [T, J, 3], root_rotation [T, 3], root_translation [T, 3] -> [T, J, 4, 4].
    Torch in, torch out (differentiable); numpy in, numpy float32 out.
    D_c = [Rot(rotations[:, c]) | 0] for c >= 1 and D_0 = [Rot(root_rotation) Rot(rotations[:, 0]) |
    root_translation], which is bone 0's world pose (anny's reference orientation of the root is I).
    """
    rot, was_np = _as_torch(rotations)
    rr, _ = _as_torch(root_rotation)
    rt, _ = _as_torch(root_translation)
    rr = rr.to(rot)
    rt = rt.to(rot)
    if rot.ndim != 3 or rot.shape[-1] != 3:
        raise ValueError(f"rotations must be [T, J, 3], got {tuple(rot.shape)}")
    t, j = rot.shape[:2]
    if rr.shape != (t, 3) or rt.shape != (t, 3):
        raise ValueError(
            f"root_rotation and root_translation must be [{t}, 3], got {tuple(rr.shape)} and {tuple(rt.shape)}"
        )
    mats = axis_angle_to_matrix(rot)  # [T, J, 3, 3]
    root = axis_angle_to_matrix(rr) @ mats[:, 0]  # [T, 3, 3]
    mats = torch.cat([root[:, None], mats[:, 1:]], dim=1)
    trans = torch.cat([rt[:, None], torch.zeros_like(rot[:, 1:])], dim=1)  # [T, J, 3]
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=rot.dtype, device=rot.device)
    params = torch.cat([torch.cat([mats, trans[..., None]], dim=-1), bottom.expand(t, j, 1, 4)], dim=-2)  # [T, J, 4, 4]
    return params.numpy() if was_np else params


def pose_params_to_axis_angle(params):
    """anny "local-ref" pose parameters [T, J, 4, 4] -> (rotations [T, J, 3], root_rotation [T, 3],
    root_translation [T, 3]); rotations[:, 0] is always zero. The translations of bones c >= 1
    (zero in every pose this toolkit makes) are ignored. Torch in, torch out; numpy in, numpy out."""
    p, was_np = _as_torch(params)
    if p.ndim != 4 or p.shape[-2:] != (4, 4):
        raise ValueError(f"pose parameters must be [T, J, 4, 4], got {tuple(p.shape)}")
    aa = matrix_to_axis_angle(p[..., :3, :3])  # [T, J, 3]
    root_rotation = aa[:, 0]
    rotations = torch.cat([torch.zeros_like(aa[:, :1]), aa[:, 1:]], dim=1)
    root_translation = p[:, 0, :3, 3]
    out = (rotations, root_rotation, root_translation)
    return tuple(o.numpy() for o in out) if was_np else out


# ---------------------------------------------------------------------------------------------
# loading anny


def _anny_cache_is_cold() -> bool:
    root = os.environ.get("ANNY_CACHE_DIR")
    if not root:
        return True
    return not any(Path(root).glob("v*/build_compact_model_data_*.safetensors"))


def _quiet_warp() -> None:
    """anny's cold build may initialise NVIDIA Warp, which prints banners on stdout: silence them."""
    try:
        import warp
    except ImportError:  # pragma: no cover - warp is optional for anny
        return
    if hasattr(warp.config, "quiet"):
        warp.config.quiet = True
    if hasattr(warp.config, "log_level") and hasattr(warp, "LOG_WARNING"):
        warp.config.log_level = warp.LOG_WARNING


def build_anny(topology: str = TOPOLOGY, label: str = "building the anny body model (first run, ~1 min)"):
    """anny with our rig and pose parameterisation and the given topology ("anny", or "anny-full"
    for the garments), float32, cached in cache_dir("anny"); a spinner shows while a cold build runs.
    This is the only place that imports anny's model (`anny_data_dir` the only other use)."""
    os.environ.setdefault("ANNY_CACHE_DIR", str(cache_dir("anny")))
    cold = _anny_cache_is_cold()
    if cold or "warp" in sys.modules:
        _quiet_warp()
    import anny

    def build():
        return anny.Anny(
            rig=RIG,
            topology=topology,
            pose_parameterization=POSE_PARAMETERIZATION,
            skinning_method="lbs",
        )

    model = build_with_status(build, label, cold)
    return model.to(dtype=torch.float32).eval()


def anny_data_dir() -> Path:
    """anny's shipped data folder (segmentation, keypoint regressors, ...)."""
    from anny.paths import get_anny_root_dir

    return Path(get_anny_root_dir()) / "data"


def build_with_status(build, label: str, show: bool = True):
    """Run `build()` under a spinner on stderr (when it is a terminal and `show`)."""
    if not (show and sys.stderr.isatty()):
        return build()
    from rich.console import Console

    with Console(stderr=True).status(label):
        return build()


# ---------------------------------------------------------------------------------------------
# the model


class BodyModel:
    """anny with rig "anny", topology "anny", "local-ref" poses; see the module docstring."""

    def __init__(self) -> None:
        self._anny = build_anny()
        self._copies: dict[tuple[torch.device, torch.dtype], object] = {}
        self._bind_cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        a = self._anny
        self.bone_labels: list[str] = list(a.bone_labels)  # [J]
        self.bone_parents = np.asarray(a.bone_parents, dtype=np.int64).copy()  # [J]
        self.bone_parents[0] = -1
        self.faces = a.faces.detach().cpu().numpy().astype(np.int64)  # [F, 3]
        assert self.faces.ndim == 2 and self.faces.shape[1] == 3, self.faces.shape
        self.uv = a.texture_coordinates.detach().cpu().numpy().astype(np.float32)  # [Vt, 2]
        self.face_uv = a.face_texture_coordinate_indices.detach().cpu().numpy().astype(np.int64)
        self.num_vertices = int(a.template_vertices.shape[0])
        self._bone_index = {name: i for i, name in enumerate(self.bone_labels)}
        assert len(self.bone_labels) == NUM_BONES, len(self.bone_labels)
        assert self.bone_labels[0] == "root"
        ref = a.reference_bone_orientations
        assert ref is None or torch.allclose(ref[0], torch.eye(3, dtype=ref.dtype)), (
            "anny's root reference orientation is not I: the root convention would change"
        )

    @property
    def num_bones(self) -> int:
        return len(self.bone_labels)

    @property
    def vertex_bone_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Sparse skinning weights: (indices [V, K] int64, weights [V, K] float32)."""
        a = self._anny
        return (
            a.vertex_bone_indices.detach().cpu().numpy().astype(np.int64),
            a.vertex_bone_weights.detach().cpu().numpy().astype(np.float32),
        )

    def bone_index(self, label: str, where: str = "bone") -> int:
        if label not in self._bone_index:
            raise DlaInputError(where, _unknown_bone_problem(label, self.bone_labels))
        return self._bone_index[label]

    def _model_for(self, like: torch.Tensor):
        key = (like.device, like.dtype)
        if key == (torch.device("cpu"), torch.float32):
            return self._anny
        if key not in self._copies:
            self._copies[key] = copy.deepcopy(self._anny).to(device=like.device, dtype=like.dtype)
        return self._copies[key]

    def _phenotype_kwargs(self, phenotype: dict[str, float] | None, like: torch.Tensor) -> dict:
        phenotype = dict(phenotype or {})
        unknown = sorted(set(phenotype) - set(PHENOTYPE_KEYS))
        if unknown:
            raise DlaInputError("phenotype", f"unknown key(s) {unknown}; valid keys: {', '.join(PHENOTYPE_KEYS)}")
        out = {}
        for key in PHENOTYPE_KEYS:
            value = float(phenotype.get(key, 0.5))
            if not (0.0 <= value <= 1.0):
                raise DlaInputError("phenotype", f"{key} = {value} is outside [0, 1]")
            out[key] = torch.tensor([value], dtype=like.dtype, device=like.device)
        return out

    def forward(
        self,
        phenotype: dict[str, float],
        rotations: torch.Tensor,  # [T, J, 3] axis-angle, local-ref
        root_rotation: torch.Tensor,  # [T, 3] axis-angle
        root_translation: torch.Tensor,  # [T, 3] metres
    ) -> BodyOutput:
        """Pose the body for T frames (differentiable in the pose tensors)."""
        if not isinstance(rotations, torch.Tensor):
            rotations = torch.as_tensor(np.asarray(rotations, dtype=np.float32))
        if not rotations.is_floating_point():
            rotations = rotations.float()
        if rotations.ndim != 3 or rotations.shape[1:] != (self.num_bones, 3):
            raise ValueError(f"rotations must be [T, {self.num_bones}, 3], got {tuple(rotations.shape)}")
        t = rotations.shape[0]
        root_rotation = torch.as_tensor(root_rotation).to(rotations).reshape(-1, 3)
        root_translation = torch.as_tensor(root_translation).to(rotations).reshape(-1, 3)
        if root_rotation.shape[0] != t or root_translation.shape[0] != t:
            raise ValueError(
                f"root_rotation/root_translation must be [{t}, 3], got "
                f"{tuple(root_rotation.shape)} and {tuple(root_translation.shape)}"
            )
        model = self._model_for(rotations)
        bind_vertices, bind_poses = self._bind(model, phenotype, rotations)  # [1, V, 3], [1, J, 4, 4]
        params = axis_angle_to_pose_params(rotations, root_rotation, root_translation)
        # anny's own kinematics and skinning (as in Anny.forward), on the cached bind state
        transforms, poses = model.get_bone_transforms(params, bind_poses)  # T_c, W_c [T, J, 4, 4]
        vertices = model.get_skinned_vertices(bind_vertices.expand(t, -1, -1), transforms)
        return BodyOutput(
            vertices=vertices,
            bone_transforms=transforms,
            bone_heads=poses[..., :3, 3],
            bone_poses=poses,
        )

    def _bind(self, model, phenotype: dict[str, float] | None, like: torch.Tensor):
        """anny's bind state (phenotype-shaped template vertices [1, V, 3] and bone poses
        [1, J, 4, 4]) for a phenotype, cached: it depends on the phenotype only, and computing it
        (blend shapes + a Procrustes fit per bone) costs more than posing."""
        kwargs = self._phenotype_kwargs(phenotype, like)
        key = (like.device, like.dtype, tuple(float(v) for v in kwargs.values()))
        if key not in self._bind_cache:
            with torch.no_grad():
                out = model(None, kwargs)
            if len(self._bind_cache) >= 16:
                self._bind_cache.pop(next(iter(self._bind_cache)))
            self._bind_cache[key] = (out["rest_vertices"], out["rest_bone_poses"])
        return self._bind_cache[key]

    __call__ = forward

    def forward_body(self, body: BodyParams) -> BodyOutput:
        """One frame from body.json content (T = 1)."""
        rot = torch.from_numpy(pose_to_rotations(body.pose, "pose", self)[None])
        rr = torch.as_tensor(np.asarray(body.root_rotation, dtype=np.float32).reshape(1, 3))
        rt = torch.as_tensor(np.asarray(body.root_translation, dtype=np.float32).reshape(1, 3))
        return self.forward(body.phenotype, rot, rr, rt)

    def motion_rotations(self, motion: Motion, where: str = "motion") -> np.ndarray:
        """The motion's rotations [T, J, 3] reordered to this rig's bones (missing bones at rest)."""
        if list(motion.bone_labels) == self.bone_labels:
            return np.asarray(motion.rotations, dtype=np.float32)
        out = np.zeros((motion.num_frames, self.num_bones, 3), dtype=np.float32)
        for k, label in enumerate(motion.bone_labels):
            out[:, self.bone_index(str(label), where)] = motion.rotations[:, k]
        return out

    @torch.no_grad()
    def forward_motion(
        self,
        body_phenotype: dict[str, float],
        motion: Motion,
        frames: Sequence[int] | np.ndarray | slice | None = None,
        batch: int = 64,
    ) -> BodyOutput:
        """Pose the body for (a selection of) a motion's frames, `batch` frames at a time."""
        rotations = self.motion_rotations(motion)  # [T, J, 3]
        idx = np.arange(motion.num_frames)
        if frames is not None:
            idx = idx[frames] if isinstance(frames, slice) else np.asarray(frames, dtype=np.int64)
            if idx.size and (idx.min() < -motion.num_frames or idx.max() >= motion.num_frames):
                raise DlaInputError("frames", f"index out of range for {motion.num_frames} frames")
        if idx.size == 0:
            raise DlaInputError("frames", "no frames selected")
        parts = []
        for start in range(0, idx.size, max(1, int(batch))):
            sel = idx[start : start + max(1, int(batch))]
            parts.append(
                self.forward(
                    body_phenotype,
                    torch.from_numpy(rotations[sel]),
                    torch.from_numpy(np.asarray(motion.root_rotation[sel], dtype=np.float32)),
                    torch.from_numpy(np.asarray(motion.root_translation[sel], dtype=np.float32)),
                )
            )
        return BodyOutput(*(torch.cat([getattr(p, f) for p in parts]) for f in BodyOutput.__dataclass_fields__))

    @torch.no_grad()
    def zero_pose(self, phenotype: dict[str, float] | None = None) -> BodyOutput:
        """The zero pose (all rotations zero, root at the origin) of a phenotype, T = 1."""
        z = torch.zeros(1, self.num_bones, 3)
        return self.forward(phenotype or {}, z, torch.zeros(1, 3), torch.zeros(1, 3))

    def rest_vertices(self, phenotype: dict[str, float] | None = None) -> np.ndarray:
        """[V, 3] vertices in the zero pose (the "rest" of the UV relative-position maps)."""
        return self.zero_pose(phenotype).vertices[0].numpy()

    def rest_bone_heads(self, phenotype: dict[str, float] | None = None) -> np.ndarray:
        """[J, 3] joint (bone head) positions in the zero pose."""
        return self.zero_pose(phenotype).bone_heads[0].numpy()


def _unknown_bone_problem(label: str, labels: list[str]) -> str:
    examples = ", ".join(labels[i] for i in (0, 41, 52, 101))  # root, spine05, wrist.L, head
    return f"unknown bone '{label}' (anny rig has {len(labels)} bones, e.g. {examples})"


@functools.lru_cache(maxsize=1)
def get_body_model() -> BodyModel:
    """The process-wide body model (built once, then cached)."""
    return BodyModel()


# ---------------------------------------------------------------------------------------------
# body.json pose dictionaries


def pose_to_rotations(pose: dict[str, np.ndarray], where: str, model: BodyModel | None = None) -> np.ndarray:
    """{bone label: axis-angle (3)} -> [J, 3] float32 (omitted bones at rest).

    Raises DlaInputError(where, ...) for an unknown bone label or a value that is not 3 finite
    numbers. A "root" entry is allowed: it is composed under root_rotation (see module docstring).
    """
    model = model or get_body_model()
    out = np.zeros((model.num_bones, 3), dtype=np.float32)
    for label, value in pose.items():
        j = model.bone_index(str(label), where)
        try:
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DlaInputError(where, f"bone '{label}': expected 3 numbers, got {value!r}") from None
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise DlaInputError(where, f"bone '{label}': expected 3 finite numbers, got {value!r}")
        out[j] = arr
    return out


def rotations_to_pose(rotations: np.ndarray, model: BodyModel | None = None) -> dict[str, np.ndarray]:
    """[J, 3] axis-angles -> {bone label: [3] float32}, omitting bones at rest (zero rotation)."""
    model = model or get_body_model()
    rot = np.asarray(
        rotations.detach().cpu().numpy() if isinstance(rotations, torch.Tensor) else rotations,
        dtype=np.float32,
    )
    if rot.shape != (model.num_bones, 3):
        raise ValueError(f"rotations must be [{model.num_bones}, 3], got {rot.shape}")
    return {model.bone_labels[j]: rot[j].copy() for j in range(model.num_bones) if np.any(rot[j] != 0.0)}
