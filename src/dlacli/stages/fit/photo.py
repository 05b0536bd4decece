"""Fit the anny body to one photo: 2D keypoints + person mask -> body parameters and camera.

Method (docs/fit.md):
- camera: a pinhole with a fixed 50 degree vertical field of view (fy = fx = 0.5 H / tan 25deg),
  principal point at the image centre; it looks along world +Y with +Z up ("azimuth 0", on the
  person's front side, docs/conventions.md). The fit itself runs with the camera at the world
  origin; at the end the world is shifted so that the pelvis (the root) is at the origin and the
  camera sits at -t (root_translation is 0 in the result).
- unknowns: root translation and rotation, the rotations of the major joints (`FIT_BONES`) and the
  phenotype keys `FREE_PHENOTYPE` (in [0, 1] through a sigmoid).
- losses: Geman-McClure robust keypoint reprojection (residuals in units of the person's height
  in pixels, weighted by confidence), a silhouette loss (projected surface samples vs the mask:
  distance transform outside the mask + distance from mask pixels to the nearest sample; see
  `fit_silhouette.SilhouetteTargets` and docs/fit.md for why not the splatter), pose priors (rotations near the
  zero pose; generous joint limits for spine, neck, hips and knees), phenotype prior to 0.5.
- coarse to fine (Adam): A) root only, torso keypoints (20 % of the steps); B) + joint rotations,
  all keypoints, the thighs started flexed when foreshortened (`_init_thighs`), the silhouette
  from half-way (40 %); C) + phenotype, narrower robust kernel (40 %).
- with 3D landmarks (MediaPipe's world-landmark frame): a robust limb-direction prior
  (`limb_loss`) and three starts optimised together (default; inverse kinematics from the
  landmarks; the most ambiguous limb's depth flipped), the best by the stage-B loss at the
  silhouette switch continuing alone.
- per-joint report: `FitResult.joint_error` / `worst_joint`; `fit_report.fit_info`, `fit_warning`, `overlay_png`.
The posed points come from `dlacli.body.keypoints.PointRig` (a few ms a step); the result is
recomputed exactly with the body model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from dlacli.body.keypoints import COCO_NAMES, MIN_CONF, NUM_KEYPOINTS, TORSO, PointRig, coco_keypoints
from dlacli.body.model import get_body_model, rotations_to_pose
from dlacli.body.uv import sample_surface
from dlacli.errors import DlaInputError
from dlacli.geometry import project_points, project_to_cameras
from dlacli.limits import FIT_STEPS
from dlacli.stages.fit.silhouette import SilhouetteTargets, silhouette_iou
from dlacli.types import BodyParams, Cameras

FOV_Y_DEG = 50.0
FIT_BONES = (
    "spine03",
    "spine01",
    "neck01",
    "head",
    "upperarm01.L",
    "upperarm01.R",
    "lowerarm01.L",
    "lowerarm01.R",
    "upperleg01.L",
    "upperleg01.R",
    "lowerleg01.L",
    "lowerleg01.R",
)
FREE_PHENOTYPE = ("height", "weight", "gender", "age")
# per-bone weight of the "stay near the zero pose" prior (spine, neck and head are stiffer)
BONE_PRIOR = (4.0, 4.0, 2.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3, 0.2, 0.2)
# Joint limits, radians, per world-aligned axis (x, y, z) of the local-ref rotation (the body
# faces -Y): spine/neck/head +x bends forward; hip -x lifts the leg forward, z twists it; knee +x
# flexes. Shoulders and elbows are limited only by the prior above. Generous on purpose.
NO_LIMIT = 10.0
JOINT_LIMITS = {
    "spine03": ((-0.5, 0.8), (-0.5, 0.5), (-0.6, 0.6)),
    "spine01": ((-0.5, 0.8), (-0.5, 0.5), (-0.6, 0.6)),
    "neck01": ((-0.6, 0.8), (-0.6, 0.6), (-0.8, 0.8)),
    "head": ((-0.6, 0.8), (-0.6, 0.6), (-0.8, 0.8)),
    "upperleg01.L": ((-2.4, 0.6), (-1.0, 1.0), (-0.7, 0.7)),
    "upperleg01.R": ((-2.4, 0.6), (-1.0, 1.0), (-0.7, 0.7)),
    "lowerleg01.L": ((0.0, 2.6), (-0.2, 0.2), (-0.3, 0.3)),
    "lowerleg01.R": ((0.0, 2.6), (-0.2, 0.2), (-0.3, 0.3)),
}
# Geman-McClure scales (fractions of the person's height in pixels): stage B starts wide and
# narrows; stage C, with the silhouette on, is narrow so that a wrong keypoint loses to the mask.
SIGMA_B = (0.3, 0.05)
SIGMA_C = 0.03
SIL_FROM_B = 0.5  # the silhouette term starts this fraction of the way into stage B
# world -> camera rotation of the photo camera (OpenCV axes): x_cam = X, y_cam = -Z, z_cam = Y
_R_W2C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# [4, 4] world-to-camera of the fitting world (camera at the origin); its entries are 0 and +-1,
# so projecting through it is exact (the same numbers as reading x, -z, y off the points)
_FIT_VIEWMAT = torch.eye(4)
_FIT_VIEWMAT[:3, :3] = torch.from_numpy(_R_W2C).float()
_FIT_NEAR = 1e-3  # metres: depth guard of the fitting projection (points closer are clamped to it)
# Limb-direction (depth) prior from 3D landmarks: COCO segments (from, to): upper and lower arms,
# thighs and shins of both sides, then the shoulder line and the hip line (the torso's facing).
LIMB_SEGMENTS = ((5, 7), (7, 9), (6, 8), (8, 10), (11, 13), (13, 15), (12, 14), (14, 16), (6, 5), (12, 11))
LIMB_WEIGHT = 0.05  # weight of the limb-direction prior next to the keypoint loss (a mean of rho <= 1)
LIMB_SIGMA = 0.5  # Geman-McClure scale on the squared chord |u - v|^2 of the unit directions (~41 deg)
# the limbs (root, middle, end) whose depth a flipped start may reverse: arms, legs
_LIMB_CHAINS = ((5, 7, 9), (6, 8, 10), (11, 13, 15), (12, 14, 16))


@dataclass
class FitResult:
    body: BodyParams  # phenotype + pose (anny local-ref) + root rotation/translation, world frame
    camera: Cameras  # 1 camera: the photo's pinhole camera in the world frame (width/height = photo)
    vertices: np.ndarray  # [V, 3] fitted posed body (anny topology), world frame
    keypoints_2d: np.ndarray  # [17, 3] the keypoints used (x, y, conf)
    reprojection_px: float  # median reprojection error of confident keypoints, pixels
    mask_iou: float  # IoU of the fitted body's silhouette vs the person mask
    # [17] 2D distance from each confident keypoint to its fitted one, as a fraction of the
    # person's height in pixels (the mask's vertical extent); NaN where confidence < 0.3
    joint_error: np.ndarray | None = None
    start: str = "default"  # the start that won (`fit_body`): "default", "landmarks" or "flip:<limb>"
    start_scores: dict[str, float] = field(default_factory=dict)  # each start's objective (with 3D landmarks)

    @property
    def worst_joint(self) -> tuple[str, float]:
        """(COCO name, error as a fraction of the person's height) of the worst confident keypoint."""
        if self.joint_error is None or not np.isfinite(self.joint_error).any():
            return "", 0.0
        k = int(np.nanargmax(self.joint_error))
        return COCO_NAMES[k], float(self.joint_error[k])


def photo_intrinsics(width: int, height: int) -> np.ndarray:
    """[3, 3] pinhole intrinsics: 50 degree vertical field of view, centred principal point."""
    f = 0.5 * height / math.tan(math.radians(FOV_Y_DEG) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def photo_camera(width: int, height: int, center=(0.0, 0.0, 0.0)) -> Cameras:
    """The photo camera at world position `center` [3], looking along +Y, +Z up."""
    w2c = np.eye(4)
    w2c[:3, :3] = _R_W2C
    w2c[:3, 3] = -_R_W2C @ np.asarray(center, dtype=np.float64)
    k = photo_intrinsics(width, height)
    return Cameras(torch.from_numpy(w2c[None]).float(), torch.from_numpy(k[None]).float(), int(width), int(height))


def project_fit(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """points [..., N, 3] in the fitting world (camera at the origin), K [3, 3] -> pixels [..., N, 2]."""
    return project_points(points, _FIT_VIEWMAT.to(points), K, _FIT_NEAR)[0]


def geman_mcclure(r2: torch.Tensor, sigma: float) -> torch.Tensor:
    """rho(r) = r^2 / (r^2 + sigma^2) from the squared residual r2 (any shape)."""
    return r2 / (r2 + sigma * sigma)


# ---------------------------------------------------------------------------------------------
# validation


def _check_inputs(image, mask, keypoints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise DlaInputError("image", f"expected [H, W, 3], got {list(img.shape)}")
    h, w = img.shape[:2]
    m = np.asarray(mask, dtype=np.float32)
    if m.shape != (h, w):
        raise DlaInputError("mask", f"expected [{h}, {w}] (the image size), got {list(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise DlaInputError("mask", "contains NaN or infinite values")
    if (m > 0.5).sum() < 16:
        raise DlaInputError("mask", "empty mask: no person pixels (alpha > 0.5)")
    kp = np.asarray(keypoints, dtype=np.float32)
    if kp.shape != (NUM_KEYPOINTS, 3):
        raise DlaInputError("keypoints", f"expected [17, 3] (x, y, conf), got {list(kp.shape)}")
    if not np.all(np.isfinite(kp)):
        raise DlaInputError("keypoints", "contains NaN or infinite values")
    kp = kp.copy()
    kp[:, 2] = np.clip(kp[:, 2], 0.0, 1.0)
    conf = kp[:, 2] >= MIN_CONF
    if conf.sum() < 4 or not (conf[[5, 6]].any() and conf[[11, 12]].any()):
        raise DlaInputError(
            "keypoints",
            f"too few confident keypoints ({int(conf.sum())}): need >= 4, with a shoulder and a hip",
        )
    return img, m, kp


# ---------------------------------------------------------------------------------------------
# initialisation


def _initial_root(kp: np.ndarray, K: np.ndarray, rest_kp: np.ndarray, mask: np.ndarray):
    """Root translation [3] and rotation [3] from the torso keypoints (camera at the origin)."""
    conf = kp[:, 2] >= MIN_CONF

    def mid(a, b, pts):  # the mean of the confident ones of two keypoints
        sel = [i for i in (a, b) if conf[i]]
        return pts[sel].mean(0)

    sh2, hip2 = mid(5, 6, kp[:, :2]), mid(11, 12, kp[:, :2])
    sh3, hip3 = mid(5, 6, rest_kp), mid(11, 12, rest_kp)
    torso_px = float(np.linalg.norm(sh2 - hip2))
    torso_m = float(np.linalg.norm(sh3 - hip3))
    f = float(K[1, 1])
    ys = np.nonzero(mask > 0.5)[0]
    height_px = float(ys.max() - ys.min() + 1)
    # depth from the torso length, bounded by what the mask's height allows (a bent torso is short)
    depth_torso = f * torso_m / max(torso_px, 1.0)
    depth_mask = f * 1.7 / height_px  # a ~1.7 m person standing upright
    depth = depth_torso if 0.5 * depth_mask < depth_torso < 1.5 * depth_mask else depth_mask
    ray = np.array([(hip2[0] - K[0, 2]) / f, 1.0, -(hip2[1] - K[1, 2]) / f])
    t = ray * depth - hip3
    facing_camera = True
    if conf[5] and conf[6]:
        facing_camera = kp[5, 0] >= kp[6, 0]  # the person's left shoulder on the image right
    rr = np.zeros(3) if facing_camera else np.array([0.0, 0.0, math.pi])
    return t, rr, depth


# ---------------------------------------------------------------------------------------------
# the fit


def fit_body(
    image: np.ndarray,  # [H, W, 3] float rgb (only its size is used)
    mask: np.ndarray,  # [H, W] float person mask in [0, 1]
    keypoints: np.ndarray,  # [17, 3] (x, y, confidence), COCO order, pixels
    *,
    steps: int = FIT_STEPS,
    progress: Callable[[int, int], None] | None = None,
    surface_samples: int = 2000,
    silhouette_samples: int = 2000,
    sil_weight: float = 10.0,
    landmarks_3d: np.ndarray | None = None,  # [17, 4] (x, y, z metres, confidence), MediaPipe's frame
) -> FitResult:
    """Fit the body to a photo (module docstring); `progress(done, total)` after every step.

    `landmarks_3d`: 3D COCO keypoints in MediaPipe's world-landmark frame (x right, y down, z away
    from the camera, metres; any origin): adds the limb-direction prior and the extra starts
    (docs/fit.md). None: the 2D fit alone, one start.

    Runs torch single-threaded (restored afterwards): every tensor here is small, and on 2 cores
    a 2-thread [17, 416] @ [416, 3] product took 5 ms against 13 us on one thread (measured).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit(
            image, mask, keypoints, landmarks_3d, steps, progress, surface_samples, silhouette_samples, sil_weight
        )
    finally:
        torch.set_num_threads(threads)


def check_landmarks_3d(landmarks_3d) -> np.ndarray:
    """[17, 4] (x, y, z, confidence) -> float32 copy with confidence clipped to [0, 1]; DlaInputError
    when the shape is wrong, a value is NaN/inf or a coordinate is beyond +-10 m."""
    lm = np.asarray(landmarks_3d, dtype=np.float64)
    if lm.shape != (NUM_KEYPOINTS, 4):
        raise DlaInputError("landmarks_3d", f"expected [17, 4] (x, y, z, conf), got {list(lm.shape)}")
    if not np.all(np.isfinite(lm)):
        raise DlaInputError("landmarks_3d", "contains NaN or infinite values")
    if np.abs(lm[:, :3]).max() > 10.0:
        raise DlaInputError("landmarks_3d", "holds a coordinate beyond +-10 m (expected metres around the hips)")
    lm = lm.astype(np.float32)
    lm[:, 3] = np.clip(lm[:, 3], 0.0, 1.0)
    return lm


def _limb_targets(lm: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions [S, 3] (camera axes) of `LIMB_SEGMENTS` in the landmarks and their
    confidences [S] (the smaller of the two ends; 0 for a segment shorter than 1 mm)."""
    a = np.array([s[0] for s in LIMB_SEGMENTS])
    b = np.array([s[1] for s in LIMB_SEGMENTS])
    d = lm[b, :3].astype(np.float64) - lm[a, :3]
    n = np.linalg.norm(d, axis=1)
    conf = np.minimum(lm[a, 3], lm[b, 3]) * (n > 1e-3)
    u = d / np.maximum(n, 1e-9)[:, None]
    return torch.from_numpy(u).float(), torch.from_numpy(conf).float()


_SEG_A = [s[0] for s in LIMB_SEGMENTS]
_SEG_B = [s[1] for s in LIMB_SEGMENTS]


def _limb_directions(pts17: torch.Tensor) -> torch.Tensor:
    """[..., 17, 3] keypoints in the fitting world -> [..., S, 3] unit segment directions in
    camera axes (x right, y down, z along the view: x_cam = X, y_cam = -Z, z_cam = Y)."""
    d = pts17[..., _SEG_B, :] - pts17[..., _SEG_A, :]
    d = torch.stack([d[..., 0], -d[..., 2], d[..., 1]], dim=-1)
    return d / d.norm(dim=-1, keepdim=True).clamp(min=1e-9)


def limb_loss(pts17: torch.Tensor, dirs: torch.Tensor, wts: torch.Tensor, sigma: float | None = LIMB_SIGMA):
    """Confidence-weighted mean over the segments of rho(|u - v|^2) (rho = Geman-McClure with
    scale `sigma`, or the plain squared chord when sigma is None); pts17 [..., 17, 3], dirs
    [..., S, 3], wts [S] -> [...]."""
    r2 = ((_limb_directions(pts17) - dirs) ** 2).sum(-1)
    rho = r2 if sigma is None else geman_mcclure(r2, sigma)
    return (wts * rho).sum(-1) / wts.sum().clamp(min=1e-6)


def facing_from_landmarks(lm: np.ndarray) -> np.ndarray | None:
    """Root rotation [3] (a turn about +Z) that points the body's left (+X at rest) along the
    landmarks' right->left shoulder and hip lines, or None when they are not confident."""
    v = np.zeros(3)
    for left, right in ((5, 6), (11, 12)):
        c = min(lm[left, 3], lm[right, 3])
        v += c * (lm[left, :3] - lm[right, :3])
    world = np.array([v[0], v[2], -v[1]])  # camera axes -> fitting world
    if np.hypot(world[0], world[1]) < 1e-3:
        return None
    return np.array([0.0, 0.0, math.atan2(world[1], world[0])])


def _most_ambiguous_limb(lm: np.ndarray) -> int:
    """Index into `_LIMB_CHAINS` of the limb whose depth is least certain: low landmark confidence
    and a short image-plane length relative to its 3D length (pointing at or away from the camera)."""
    scores = []
    for r, m, e in _LIMB_CHAINS:
        conf = float(min(lm[r, 3], lm[m, 3], lm[e, 3]))
        full = np.linalg.norm(lm[m, :3] - lm[r, :3]) + np.linalg.norm(lm[e, :3] - lm[m, :3])
        flat = np.linalg.norm(lm[m, :2] - lm[r, :2]) + np.linalg.norm(lm[e, :2] - lm[m, :2])
        scores.append((1.0 - conf) + (1.0 - flat / max(full, 1e-6)))
    return int(np.argmax(scores))


_LIMB_NAMES = ("left_arm", "right_arm", "left_leg", "right_leg")


class _Starts:
    """S starts of the fit, optimised together (one batched rig call per step): their unknowns
    (leading dimension S) and one Adam over them (Adam is per element, so this equals S
    separate runs)."""

    LR = (0.02, 0.03, 0.03, 0.05)  # root translation (x depth / 3 m), root rotation, pose, phenotype

    def __init__(self, names, root_t, root_r, pose, phen_logit, depth0, init_thighs):
        self.names = list(names)
        self.init_thighs = list(init_thighs)
        self.depth0 = depth0
        self.root_t = torch.as_tensor(root_t, dtype=torch.float32).clone().requires_grad_(True)  # [S, 3]
        self.root_r = torch.as_tensor(root_r, dtype=torch.float32).clone().requires_grad_(True)  # [S, 3]
        self.pose = pose.clone().requires_grad_(True)  # [S, B, 3]
        self.phen_logit = phen_logit.clone().requires_grad_(True)  # [S, K]; sigmoid(0) = 0.5
        self.params = (self.root_t, self.root_r, self.pose, self.phen_logit)
        self.opt = torch.optim.Adam(
            [
                {"params": [self.root_t], "lr": self.LR[0] * max(1.0, depth0 / 3.0)},
                {"params": [self.root_r], "lr": self.LR[1]},
                {"params": [self.pose], "lr": 0.0},
                {"params": [self.phen_logit], "lr": 0.0},
            ]
        )

    def select(self, i: int) -> _Starts:
        """Start i alone, with its Adam state and learning rates."""
        one = _Starts(
            [self.names[i]],
            self.root_t.detach()[i : i + 1],
            self.root_r.detach()[i : i + 1],
            self.pose.detach()[i : i + 1],
            self.phen_logit.detach()[i : i + 1],
            self.depth0,
            [self.init_thighs[i]],
        )
        for g_old, g_new in zip(self.opt.param_groups, one.opt.param_groups, strict=True):
            g_new["lr"] = g_old["lr"]
        for old, new in zip(self.params, one.params, strict=True):
            state = self.opt.state.get(old)
            if state:
                one.opt.state[new] = {k: (v.clone() if k == "step" else v[i : i + 1].clone()) for k, v in state.items()}
        return one


def _fit(image, mask, keypoints, landmarks_3d, steps, progress, surface_samples, silhouette_samples, sil_weight):
    img, msk, kp = _check_inputs(image, mask, keypoints)
    lm = None if landmarks_3d is None else check_landmarks_3d(landmarks_3d)
    if steps < 3:
        raise DlaInputError("steps", f"must be >= 3, got {steps}")
    h, w = img.shape[:2]
    model = get_body_model()
    K = photo_intrinsics(w, h)
    Kt = torch.from_numpy(K).float()

    face_id, bary = sample_surface(surface_samples, seed=0)
    rig = PointRig((model.faces[face_id], bary), free_keys=FREE_PHENOTYPE, model=model)
    bone_ids = torch.tensor([model.bone_index(b) for b in FIT_BONES])
    prior_w = torch.tensor(BONE_PRIOR)[:, None]  # [B, 1]
    lim = torch.tensor([JOINT_LIMITS.get(b, ((-NO_LIMIT, NO_LIMIT),) * 3) for b in FIT_BONES])  # [B, 3, 2]

    with torch.no_grad():
        rest_pts, _ = rig(None, torch.zeros(model.num_bones, 3), torch.zeros(3), torch.zeros(3))
    rest_kp = rest_pts[:NUM_KEYPOINTS].numpy()
    t0, rr0, depth0 = _initial_root(kp, K, rest_kp, msk)

    target = torch.from_numpy(kp[:, :2])  # [17, 2]
    conf = torch.from_numpy(kp[:, 2])  # [17]
    ys = np.nonzero(msk > 0.5)[0]
    scale_px = float(max(ys.max() - ys.min() + 1, 16))  # person height in pixels
    torso_w = torch.zeros(NUM_KEYPOINTS)
    torso_w[list(TORSO)] = 1.0
    sil = SilhouetteTargets(msk, scale_px, samples=silhouette_samples)
    dirs, dir_w = (None, None) if lm is None else _limb_targets(lm)

    n_a = max(1, int(0.2 * steps))
    n_b = max(1, int(0.4 * steps))
    n_c = steps - n_a - n_b
    n_sil = n_a + int(SIL_FROM_B * n_b)  # first step with the silhouette term

    def pose_priors(pose):  # [..., B, 3] -> [...]
        over = torch.relu(lim[..., 0] - pose) + torch.relu(pose - lim[..., 1])  # [..., B, 3]
        return 2e-3 * (prior_w * pose**2).sum((-2, -1)) + (over**2).sum((-2, -1))

    def posed(pose, root_r, root_t, phen=None, keypoints_only=True):  # [S, B, 3] ... -> [S, P, 3]
        rot = torch.zeros(pose.shape[0], model.num_bones, 3).index_copy(1, bone_ids, pose)
        return rig(phen, rot, root_r, root_t, keypoints_only=keypoints_only)[0]

    def losses(st: _Starts, step: int, silhouette: bool | None = None) -> torch.Tensor:
        """[S] the loss of each start at `step` of the schedule (`silhouette` overrides its switch)."""
        stage = "A" if step < n_a else ("B" if step < n_a + n_b else "C")
        use_sil = (step >= n_sil) if silhouette is None else silhouette
        phen = torch.sigmoid(st.phen_logit[0]) if stage == "C" else None  # one start by stage C
        pts = posed(st.pose, st.root_r, st.root_t, phen, keypoints_only=not use_sil)  # [S, P, 3]
        uv = project_fit(pts[:, :NUM_KEYPOINTS], Kt)  # [S, 17, 2]
        r2 = ((uv - target) ** 2).sum(-1) / scale_px**2  # [S, 17]
        if stage == "A":
            wk = conf * (torso_w + 0.1)
            return (wk * geman_mcclure(r2, 0.5)).sum(-1) / wk.sum().clamp(min=1e-6)
        sigma = SIGMA_C if stage == "C" else SIGMA_B[0 if step < n_a + n_b // 2 else 1]
        loss = (conf * geman_mcclure(r2, sigma)).sum(-1) / conf.sum().clamp(min=1e-6)
        loss = loss + pose_priors(st.pose)
        if dirs is not None:
            loss = loss + LIMB_WEIGHT * limb_loss(pts[:, :NUM_KEYPOINTS], dirs, dir_w)
        if use_sil:
            loss = loss + sil_weight * torch.stack([sil(project_fit(p[NUM_KEYPOINTS:], Kt)) for p in pts])
        if stage == "C":
            loss = loss + 0.01 * ((phen - 0.5) ** 2).sum()
        return loss

    def run(st: _Starts, lo: int, hi: int) -> None:
        for step in range(lo, hi):
            if step == n_a:
                st.opt.param_groups[2]["lr"] = _Starts.LR[2]
                with torch.no_grad():
                    for i, flag in enumerate(st.init_thighs):
                        if flag:
                            _init_thighs(rig, kp, K, st.pose[i], st.root_r[i], st.root_t[i], bone_ids)
            if step == n_a + n_b:
                st.opt.param_groups[3]["lr"] = _Starts.LR[3]
            if step == n_a + n_b + n_c // 2:
                with torch.no_grad():  # re-linearise the phenotype around the current estimate
                    rig.linearise(_phenotype_values(rig, st.phen_logit[0]))
            st.opt.zero_grad()
            losses(st, step).sum().backward()
            st.opt.step()
            if progress is not None:
                progress(step + 1, steps)

    names, rrs, poses, thighs = ["default"], [rr0], [torch.zeros(len(FIT_BONES), 3)], [True]
    if lm is not None:
        facing = facing_from_landmarks(lm)
        rr_lm = rr0 if facing is None else facing
        limb = _most_ambiguous_limb(lm)
        flipped = dirs.clone()
        r, m, e = _LIMB_CHAINS[limb]
        for s, seg in enumerate(LIMB_SEGMENTS):
            if seg in ((r, m), (m, e)):
                flipped[s, 2] = -flipped[s, 2]  # toward <-> away from the camera
        limb_only = dir_w.clone()
        limb_only[8:] = 0.0  # the IK poses the limbs; the root's facing comes from the torso lines
        ik = _ik_pose(
            posed, pose_priors, np.stack([rr_lm, rr_lm]), np.stack([t0, t0]), torch.stack([dirs, flipped]), limb_only
        )
        names += ["landmarks", f"flip:{_LIMB_NAMES[limb]}"]
        rrs += [rr_lm, rr_lm]
        poses += [ik[0], ik[1]]
        thighs += [False, False]
    n = len(names)
    st = _Starts(
        names,
        np.stack([t0] * n),
        np.stack(rrs),
        torch.stack(poses),
        torch.zeros(n, len(FREE_PHENOTYPE)),
        depth0,
        thighs,
    )
    # every start runs the keypoint-only part of the schedule (A and B up to the silhouette);
    # the best by the same objective for all (the loss of the step where the silhouette starts,
    # silhouette included: keypoints at GM scale SIGMA_B[1], pose priors, limb prior, silhouette)
    # continues alone
    scores: dict[str, float] = {}
    if n > 1:
        run(st, 0, n_sil)
        with torch.no_grad():
            score = losses(st, n_sil, silhouette=True)
        scores = {name: float(v) for name, v in zip(names, score, strict=True)}
        st = st.select(int(torch.argmin(score)))
        run(st, n_sil, steps)
    else:
        run(st, 0, steps)

    with torch.no_grad():
        phenotype = _phenotype_values(rig, st.phen_logit[0])
        rot = torch.zeros(model.num_bones, 3).index_put((bone_ids,), st.pose[0].detach())
        res = _finish(img, msk, kp, phenotype, rot, st.root_r[0].detach(), st.root_t[0].detach())
    res.start = st.names[0]
    res.start_scores = scores
    return res


def _ik_pose(posed, pose_priors, root_r, root_t, dirs, wts, iters: int = 40) -> torch.Tensor:
    """Bone rotations [S, B, 3] that point each limb along its landmark direction: inverse
    kinematics by Adam on the squared chord between the fitted and the landmark unit directions
    (dirs [S, segments, 3]; root rotation/translation [S, 3] fixed), all S at once."""
    rr = torch.as_tensor(root_r, dtype=torch.float32)
    rt = torch.as_tensor(root_t, dtype=torch.float32)
    pose = torch.zeros(dirs.shape[0], len(FIT_BONES), 3, requires_grad=True)
    opt = torch.optim.Adam([pose], lr=0.1)
    for _ in range(iters):
        opt.zero_grad()
        pts = posed(pose, rr, rt)  # [S, 17, 3]
        (limb_loss(pts, dirs, wts, sigma=None) + pose_priors(pose)).sum().backward()
        opt.step()
    return pose.detach()


def _init_thighs(rig, kp, K, pose, root_r, root_t, bone_ids) -> None:
    """Start each thigh flexed toward the camera when its image is foreshortened.

    From the rest pose the projected knee height does not change to first order when the thigh
    swings toward the camera (cos at 0), so a seated person's knees are out of reach of the
    gradient. When the 2D hip->knee length is below 85 % of the rest thigh's projected length,
    the hip is flexed by acos(ratio) (forward, the likely direction) and the knee by the same
    angle, so that the shin keeps its rest direction.
    """
    model = rig.model
    rot = torch.zeros(model.num_bones, 3).index_put((bone_ids,), pose)
    pts, _ = rig(None, rot, root_r, root_t, keypoints_only=True)
    kp3 = pts.numpy()  # [17, 3], camera at the origin looking along +Y
    for side, hip, knee in (("L", 11, 13), ("R", 12, 14)):
        if kp[hip, 2] < MIN_CONF or kp[knee, 2] < MIN_CONF:
            continue
        depth = max(float(kp3[hip, 1]), 1e-3)
        rest_px = float(K[1, 1]) * float(np.linalg.norm(kp3[knee] - kp3[hip])) / depth
        ratio = float(np.linalg.norm(kp[knee, :2] - kp[hip, :2])) / max(rest_px, 1e-6)
        if ratio < 0.85:
            angle = math.acos(max(0.0, ratio))
            pose[FIT_BONES.index(f"upperleg01.{side}"), 0] = -angle
            pose[FIT_BONES.index(f"lowerleg01.{side}"), 0] = angle


def _phenotype_values(rig: PointRig, phen_logit: torch.Tensor) -> dict[str, float]:
    return rig.phenotype_dict(torch.sigmoid(phen_logit.detach()))


def _finish(img, msk, kp, phenotype, rot, root_r, root_t) -> FitResult:
    """Exact body, shift the world so that the pelvis is at the origin, measure the fit."""
    model = get_body_model()
    h, w = img.shape[:2]
    zero = torch.zeros(1, 3)
    out = model.forward(phenotype, rot[None], root_r[None], zero)  # pelvis at the origin
    verts = out.vertices[0].numpy().astype(np.float32)  # [V, 3]
    t = root_t.numpy().astype(np.float64)
    camera = photo_camera(w, h, center=-t)
    kp3 = coco_keypoints(verts)  # [17, 3]
    uv = _project_world(kp3, camera)
    conf = kp[:, 2] >= MIN_CONF
    err = np.linalg.norm(uv - kp[:, :2], axis=1)
    body = BodyParams(
        phenotype={k: float(v) for k, v in phenotype.items()},
        root_rotation=root_r.numpy().astype(np.float64),
        root_translation=np.zeros(3),
        pose={k: v.astype(np.float64) for k, v in rotations_to_pose(rot.numpy(), model).items()},
    )
    iou = silhouette_iou(verts, camera, msk)
    ys = np.nonzero(msk > 0.5)[0]
    height_px = float(ys.max() - ys.min() + 1)
    joint_error = np.where(conf, err / height_px, np.nan)
    return FitResult(body, camera, verts, kp, float(np.median(err[conf])), iou, joint_error)


def _project_world(points: np.ndarray, camera: Cameras) -> np.ndarray:
    """World points [N, 3] -> pixels [N, 2] with camera 0 (float64)."""
    return project_to_cameras(points, camera)[0][0]
