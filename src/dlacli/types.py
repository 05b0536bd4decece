"""Plain data passed between layers (io, body, render, nn, stages).

Bottom layer: imports numpy only (torch is imported where a tensor is built, so that readers that
summarise files, e.g. `dla info`, never load it).

Conventions are written once in docs/conventions.md; in short:
- world frame: anny's (metres, +Z up, the body at rest faces -Y);
- quaternions are (w, x, y, z), unit length;
- Gaussians hold *activated* values: linear scales (metres), linear opacity in [0, 1];
  colour as real spherical-harmonic coefficients, rgb = 0.5 + SH_C0 * sh[:, 0];
- cameras are stored as world-to-camera matrices in OpenCV axes (+X right, +Y down, +Z forward),
  the convention the renderers use; view folders store camera-to-world in OpenGL axes and
  `Cameras.from_c2w_opengl` / `Cameras.c2w_opengl` convert.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from dlacli import limits

if TYPE_CHECKING:
    import torch

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))

# OpenGL camera axes (+Y up, looking down -Z) <-> OpenCV camera axes (+Y down, looking down +Z).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def sh_coeffs_for_degree(degree: int) -> int:
    """Number of SH coefficients per colour channel for a degree 0..3."""
    return (degree + 1) ** 2


def sh_degree_for_coeffs(k: int) -> int:
    """Inverse of `sh_coeffs_for_degree`; raises ValueError for counts that are not (d+1)^2."""
    for d in range(4):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for a degree 0..3")


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1 transfer function); dla's colours
    are sRGB-encoded, glTF's COLOR_0 and USD's displayColor are linear. Clipped to [0, 1] first."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """[..., 3] rgb in [0, 1] -> [..., 3] DC SH coefficient."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """[..., 3] DC SH coefficient -> [..., 3] rgb (not clamped)."""
    return sh0 * SH_C0 + 0.5


@dataclass
class Gaussians:
    """A set of N 3D Gaussians in activated parameters (see module docstring), optionally with
    leading batch dimensions B... (one set per avatar, pose or training item), as gsplat's
    `rasterization(means [..., N, 3], ...)`."""

    means: torch.Tensor  # [B..., N, 3] world position, metres
    quats: torch.Tensor  # [B..., N, 4] (w, x, y, z), unit
    scales: torch.Tensor  # [B..., N, 3] standard deviations along the local axes, metres
    opacities: torch.Tensor  # [B..., N] in [0, 1]
    sh: torch.Tensor  # [B..., N, K, 3] SH coefficients, K = (degree + 1)^2; sh[..., 0, :] is the DC term

    def __post_init__(self) -> None:
        lead, n = tuple(self.means.shape[:-2]), self.means.shape[-2]
        assert self.means.shape == (*lead, n, 3), self.means.shape
        assert self.quats.shape == (*lead, n, 4), (self.quats.shape, lead, n)
        assert self.scales.shape == (*lead, n, 3), (self.scales.shape, lead, n)
        assert self.opacities.shape == (*lead, n), (self.opacities.shape, lead, n)
        assert self.sh.shape[:-2] == (*lead, n) and self.sh.shape[-1] == 3, (self.sh.shape, lead, n)
        sh_degree_for_coeffs(self.sh.shape[-2])

    def __len__(self) -> int:
        return self.means.shape[-2]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """The leading batch dimensions (empty for one set)."""
        return tuple(self.means.shape[:-2])

    def item(self, index) -> Gaussians:
        """The set at `index` of the leading batch dimensions."""
        return Gaussians(*(t[index] for t in self._tensors()))

    @property
    def sh_degree(self) -> int:
        return sh_degree_for_coeffs(self.sh.shape[-2])

    @property
    def rgb(self) -> torch.Tensor:
        """[B..., N, 3] view-independent colour from the DC term, clamped to [0, 1]."""
        return sh0_to_rgb(self.sh[..., 0, :]).clamp(0.0, 1.0)

    @classmethod
    def from_rgb(cls, means, quats, scales, opacities, rgb) -> Gaussians:
        """Build degree-0 Gaussians from [B..., N, 3] rgb colours."""
        return cls(means, quats, scales, opacities, rgb_to_sh0(rgb)[..., None, :])

    def to(self, *args, **kwargs) -> Gaussians:
        return Gaussians(*(t.to(*args, **kwargs) for t in self._tensors()))

    def subset(self, index: torch.Tensor) -> Gaussians:
        """Gaussians selected by a boolean mask [N] or an index tensor [M] (one set, no batch)."""
        assert not self.batch_shape, f"subset of a batch {self.batch_shape}: take .item(i) first"
        return Gaussians(*(t[index] for t in self._tensors()))

    def _tensors(self) -> tuple[torch.Tensor, ...]:
        return (self.means, self.quats, self.scales, self.opacities, self.sh)


@dataclass
class Cameras:
    """C pinhole cameras sharing one image size (no distortion)."""

    viewmats: torch.Tensor  # [C, 4, 4] world-to-camera, OpenCV axes
    Ks: torch.Tensor  # [C, 3, 3] intrinsics: fx, fy, cx, cy in pixels
    width: int
    height: int

    def __post_init__(self) -> None:
        c = self.viewmats.shape[0]
        assert self.viewmats.shape == (c, 4, 4), self.viewmats.shape
        assert self.Ks.shape == (c, 3, 3), self.Ks.shape

    def __len__(self) -> int:
        return self.viewmats.shape[0]

    @classmethod
    def from_c2w_opengl(cls, c2w, fx, fy, cx, cy, width: int, height: int) -> Cameras:
        """From camera-to-world matrices in OpenGL axes [C, 4, 4] (the transforms.json convention).

        fx, fy, cx, cy are scalars or length-C sequences.
        """
        c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
        c = c2w.shape[0]
        w2c = np.linalg.inv(c2w @ _GL_TO_CV)
        ks = np.zeros((c, 3, 3))
        ks[:, 0, 0] = np.broadcast_to(np.asarray(fx, dtype=np.float64), (c,))
        ks[:, 1, 1] = np.broadcast_to(np.asarray(fy, dtype=np.float64), (c,))
        ks[:, 0, 2] = np.broadcast_to(np.asarray(cx, dtype=np.float64), (c,))
        ks[:, 1, 2] = np.broadcast_to(np.asarray(cy, dtype=np.float64), (c,))
        ks[:, 2, 2] = 1.0
        import torch

        return cls(torch.from_numpy(w2c).float(), torch.from_numpy(ks).float(), int(width), int(height))

    def c2w_opengl(self) -> np.ndarray:
        """[C, 4, 4] camera-to-world in OpenGL axes, float64."""
        w2c = self.viewmats.detach().cpu().double().numpy()
        return np.linalg.inv(w2c) @ _GL_TO_CV

    def to(self, *args, **kwargs) -> Cameras:
        return Cameras(self.viewmats.to(*args, **kwargs), self.Ks.to(*args, **kwargs), self.width, self.height)

    def select(self, index) -> Cameras:
        """The cameras at `index` (an int, a slice, a list or an index array), still batched [C']."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1)
        return Cameras(self.viewmats[index], self.Ks[index], self.width, self.height)

    def cropped(self, x0, y0, width: int, height: int) -> Cameras:
        """The same cameras seeing only the width x height window whose top-left pixel is (x0[c],
        y0[c]) in camera c's image (integers, per camera or one for all): the principal point moves
        by the offset, the focal lengths stay."""
        ks = self.Ks.clone()
        ks[:, 0, 2] -= ks.new_tensor(np.asarray(x0, dtype=np.float64))
        ks[:, 1, 2] -= ks.new_tensor(np.asarray(y0, dtype=np.float64))
        return Cameras(self.viewmats.clone(), ks, int(width), int(height))

    def resized(self, width: int, height: int, scale: float | None = None) -> Cameras:
        """The same cameras for images of width x height pixels: the intrinsics' first row (fx, cx)
        times width / self.width and the second (fy, cy) times height / self.height (the same field
        of view, pixel centres consistent), or both rows times `scale` where the new image is the
        scaled one cropped (e.g. blocks of 1 / scale pixels, the remainder dropped)."""
        sx, sy = (width / self.width, height / self.height) if scale is None else (scale, scale)
        ks = self.Ks.clone()
        ks[:, 0, :] *= sx
        ks[:, 1, :] *= sy
        return Cameras(self.viewmats.clone(), ks, int(width), int(height))


PHENOTYPE_KEYS = ("gender", "age", "muscle", "weight", "height", "proportions")


@dataclass
class BodyParams:
    """Body model parameters (the body.json contract, formats/body.md)."""

    phenotype: dict[str, float] = field(default_factory=lambda: {k: 0.5 for k in PHENOTYPE_KEYS})
    root_rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] axis-angle
    root_translation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] metres
    pose: dict[str, np.ndarray] = field(default_factory=dict)  # bone label -> [3] axis-angle
    model: str = "anny"


@dataclass
class Motion:
    """A motion clip on the body model's rig (the motion.npz contract, formats/motion.md)."""

    bone_labels: list[str]  # [J]
    rotations: np.ndarray  # [T, J, 3] axis-angle, radians, local-ref
    root_rotation: np.ndarray  # [T, 3] axis-angle
    root_translation: np.ndarray  # [T, 3] metres
    fps: float
    model: str = "anny"

    def __post_init__(self) -> None:
        t, j = self.rotations.shape[:2]
        assert self.rotations.shape == (t, j, 3), self.rotations.shape
        assert len(self.bone_labels) == j, (len(self.bone_labels), j)
        assert self.root_rotation.shape == (t, 3), self.root_rotation.shape
        assert self.root_translation.shape == (t, 3), self.root_translation.shape

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]


# Limits every motion reader and resampler shares (docs/motion.md, "Limits").
MAX_FPS = limits.MAX_FPS  # frame rates above this are refused (by every motion reader, native ones too)
MIN_FPS = 0.01  # one frame per 100 s: slower "motions" are a broken frame time, not a clip
MAX_FRAMES = 200_000  # 27 minutes at 120 fps; longer motions are refused before they are built


@dataclass
class SkeletonMotion:
    """A third-party skeleton and its motion as read from a file (BVH, ASF/AMC, AMASS).

    The common in-memory form of every imported motion (`dlacli.io.bvh`, `dlacli.io.asf_amc`,
    `dlacli.io.amass` read it; `dlacli.body.retarget` turns it into a native `Motion` on anny's
    rig; `dlacli.kinematics` holds its forward kinematics). Convention (docs/motion.md):

    - joint j sits at its parent's position plus `offsets[j]` rotated by the parent's world rotation;
    - `rotations[t, j]` is joint j's *local* rotation matrix: its world rotation is
      G_j = G_parent @ rotations[t, j], and G_j rotates everything below j about j's position;
    - in the rest pose (all rotations identity) the skeleton stands as its offsets say, in the
      file's own world axes (`up` tells which world axis is up);
    - lengths are in the file's units; `metres_per_unit` converts them.
    """

    names: list[str]  # [J] joint names as in the file
    parents: np.ndarray  # [J] int64 parent index, -1 for the root (parents come before children)
    offsets: np.ndarray  # [J, 3] float64 rest offset from the parent joint, file units
    rotations: np.ndarray  # [T, J, 3, 3] float64 local rotation matrices
    root_positions: np.ndarray  # [T, 3] float64 world position of joint 0, file units
    fps: float
    up: str = "y"  # world up axis of the file: "y" (CMU BVH / ASF) or "z" (AMASS)
    metres_per_unit: float = 1.0
    units: str = "m"
    source: str = ""  # the file it came from (for messages)
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint -> [3] end offset
    dialect: str = ""  # naming convention hint, e.g. "smpl" for AMASS

    def __post_init__(self) -> None:
        j = len(self.names)
        t = self.rotations.shape[0]
        assert self.parents.shape == (j,), self.parents.shape
        assert self.offsets.shape == (j, 3), self.offsets.shape
        assert self.rotations.shape == (t, j, 3, 3), self.rotations.shape
        assert self.root_positions.shape == (t, 3), self.root_positions.shape
        assert all(self.parents[k] < k for k in range(j)), "parents must precede children"

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.names)


@dataclass
class ViewSet:
    """A view folder in memory (formats/views.md)."""

    images: np.ndarray  # [V, H, W, 3] float32 rgb in [0, 1]
    masks: np.ndarray  # [V, H, W] float32 person alpha in [0, 1]
    cameras: Cameras
    body: BodyParams | None  # None when read without body.json (require_body=False)
    file_paths: list[str]  # [V] image paths relative to the folder
    times: list[int | None]  # [V] motion frame index per view, or None
    extra: dict[str, Any] = field(default_factory=dict)  # the top-level "dla" object
    # [V, H, W] float32 in [0, 1]: how far each pixel's colour shows the surface the body puts
    # there (0: a limb in front that the fit placed elsewhere); None: every pixel, as a mask
    # allows. Only the lift's colour bake reads it (formats/views.md, "Colour trust")
    trust: np.ndarray | None = None

    def __len__(self) -> int:
        return self.images.shape[0]

    def targets(self, max_size: int) -> tuple[torch.Tensor, torch.Tensor, Cameras]:
        """The views as render targets at most max_size pixels on the long side: (rgb [V, h, w, 3]
        premultiplied on black, mask [V, h, w], the cameras resized to match), float32 tensors,
        downsampled with an antialiased bilinear filter."""
        import torch
        import torch.nn.functional as nnf

        h, w = self.masks.shape[1:]
        f = min(1.0, max_size / max(h, w))
        rh, rw = max(1, round(h * f)), max(1, round(w * f))
        rgba = np.concatenate([self.images * self.masks[..., None], self.masks[..., None]], -1)
        x = torch.from_numpy(rgba).float().permute(0, 3, 1, 2)
        if (rh, rw) != (h, w):
            x = nnf.interpolate(x, size=(rh, rw), mode="bilinear", antialias=True, align_corners=False)
        x = x.permute(0, 2, 3, 1).clamp(0.0, 1.0)
        return x[..., :3].contiguous(), x[..., 3].contiguous(), self.cameras.resized(rw, rh)


# The channels of F, the [14, R, R] UV Gaussian map an avatar decodes to (formats/avatar.md, "The
# Gaussian map F"), written once: dlacli.avatar.gaussian_map samples and places F with them, and
# dlacli.io.avatar checks an avatar file's z and canonical maps with them.
F_CHANNELS = 14
F_OPACITY = slice(0, 1)  # opacity, as a logit
F_RGB = slice(1, 4)  # colour, rgb
F_OFFSET = slice(4, 7)  # position offset dxyz in the texel's tangent frame, metres
F_ROTATION = slice(7, 11)  # rotation dR in the tangent frame, quaternion (w, x, y, z)
F_LOG_SCALE = slice(11, 14)  # log of the scale multiplier ds


@dataclass
class Avatar:
    """An avatar code Z aligned with the body's UV space (formats/avatar.md)."""

    z: np.ndarray  # [C, H, W] float32
    encoder: str  # e.g. "unproject" or "learned"
    decoder: str  # e.g. "identity" or "gpd"
    body: BodyParams
    uv_layout: str  # e.g. "anny"
    checkpoint: str = ""  # sha256 of the learned weights, "" for non-learned paths
    canonical: np.ndarray | None = None  # [14, H, W] cached canonical Gaussian map, optional
    extra: dict[str, Any] = field(default_factory=dict)
