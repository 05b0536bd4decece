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
  `_SilhouetteTargets` and docs/fit.md for why not the splatter), pose priors (rotations near the
  zero pose; generous joint limits for spine, neck, hips and knees), phenotype prior to 0.5.
- coarse to fine (Adam): A) root only, torso keypoints (20 % of the steps); B) + joint rotations,
  all keypoints, the thighs started flexed when foreshortened (`_init_thighs`), the silhouette
  from half-way (40 %); C) + phenotype, narrower robust kernel (40 %).
The posed points come from `dlacli.body.keypoints.PointRig` (a few ms a step); the result is
recomputed exactly with the body model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from dlacli.body.keypoints import COCO_SKELETON, NUM_KEYPOINTS, PointRig, coco_keypoints
from dlacli.body.model import get_body_model, rotations_to_pose
from dlacli.body.uv import sample_surface
from dlacli.errors import DlaInputError
from dlacli.geometry import project_points, project_to_cameras
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
_BONE_PRIOR = (4.0, 4.0, 2.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3, 0.2, 0.2)
# Joint limits, radians, per world-aligned axis (x, y, z) of the local-ref rotation (the body
# faces -Y): spine/neck/head +x bends forward; hip -x lifts the leg forward, z twists it; knee +x
# flexes. Shoulders and elbows are limited only by the prior above. Generous on purpose.
_INF = 10.0
_LIMITS = {
    "spine03": ((-0.5, 0.8), (-0.5, 0.5), (-0.6, 0.6)),
    "spine01": ((-0.5, 0.8), (-0.5, 0.5), (-0.6, 0.6)),
    "neck01": ((-0.6, 0.8), (-0.6, 0.6), (-0.8, 0.8)),
    "head": ((-0.6, 0.8), (-0.6, 0.6), (-0.8, 0.8)),
    "upperleg01.L": ((-2.4, 0.6), (-1.0, 1.0), (-0.7, 0.7)),
    "upperleg01.R": ((-2.4, 0.6), (-1.0, 1.0), (-0.7, 0.7)),
    "lowerleg01.L": ((0.0, 2.6), (-0.2, 0.2), (-0.3, 0.3)),
    "lowerleg01.R": ((0.0, 2.6), (-0.2, 0.2), (-0.3, 0.3)),
}
_TORSO = (5, 6, 11, 12)  # COCO shoulders and hips
# Geman-McClure scales (fractions of the person's height in pixels): stage B starts wide and
# narrows; stage C, with the silhouette on, is narrow so that a wrong keypoint loses to the mask.
SIGMA_B = (0.3, 0.05)
SIGMA_C = 0.03
COVER_WEIGHT = 1.0  # weight of "every mask pixel is covered" relative to "no body outside the mask"
SIL_FROM_B = 0.5  # the silhouette term starts this fraction of the way into stage B
_MIN_CONF = 0.3  # keypoints with confidence >= this count as "confident"
# world -> camera rotation of the photo camera (OpenCV axes): x_cam = X, y_cam = -Z, z_cam = Y
_R_W2C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# [4, 4] world-to-camera of the fitting world (camera at the origin); its entries are 0 and +-1,
# so projecting through it is exact (the same numbers as reading x, -z, y off the points)
_FIT_VIEWMAT = torch.eye(4)
_FIT_VIEWMAT[:3, :3] = torch.from_numpy(_R_W2C).float()
_FIT_NEAR = 1e-3  # metres: depth guard of the fitting projection (points closer are clamped to it)


@dataclass
class FitResult:
    body: BodyParams  # phenotype + pose (anny local-ref) + root rotation/translation, world frame
    camera: Cameras  # 1 camera: the photo's pinhole camera in the world frame (width/height = photo)
    vertices: np.ndarray  # [V, 3] fitted posed body (anny topology), world frame
    keypoints_2d: np.ndarray  # [17, 3] the keypoints used (x, y, conf)
    reprojection_px: float  # median reprojection error of confident keypoints, pixels
    mask_iou: float  # IoU of the fitted body's silhouette vs the person mask


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


def _project_fit(points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
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
    conf = kp[:, 2] >= _MIN_CONF
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
    conf = kp[:, 2] >= _MIN_CONF

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


class _SilhouetteTargets:
    """A differentiable silhouette loss between projected surface samples and the mask.

    Two one-sided distances, in units of the person's height in pixels: (1) every projected body
    sample should lie in the mask: its distance to the nearest mask pixel (a distance transform,
    read bilinearly); (2) every mask pixel should be covered: the distance from each of a fixed
    random set of mask pixels to the nearest projected sample. Both are means of sqrt(d^2 + e^2)
    (robust to clothing and hair the body cannot cover).
    """

    def __init__(self, mask: np.ndarray, scale_px: float, samples: int, seed: int = 0) -> None:
        from scipy.ndimage import distance_transform_edt

        inside = mask > 0.5
        h, w = mask.shape
        self.scale = float(scale_px)
        dt = distance_transform_edt(~inside).astype(np.float32)  # [H, W] px to the mask, 0 inside
        self.dt = torch.from_numpy(dt)[None, None]  # [1, 1, H, W]
        self.size = (w, h)
        ys, xs = np.nonzero(inside)
        rng = np.random.default_rng(seed)
        pick = rng.choice(ys.size, size=min(samples, ys.size), replace=False)
        self.pix = torch.from_numpy(
            np.stack([xs[pick] + 0.5, ys[pick] + 0.5], axis=1).astype(np.float32)
        )  # [M, 2] pixel centres

    def __call__(self, uv: torch.Tensor) -> torch.Tensor:  # uv [P, 2] projected samples, pixels
        w, h = self.size
        grid = torch.stack([uv[:, 0] / w * 2 - 1, uv[:, 1] / h * 2 - 1], dim=-1)[None, None]
        d_out = torch.nn.functional.grid_sample(
            self.dt, grid, mode="bilinear", padding_mode="border", align_corners=False
        )[0, 0, 0]  # [P]
        # outside the image the border value underestimates: add the distance to the image
        d_out = d_out + (
            torch.relu(-uv[:, 0]) + torch.relu(uv[:, 0] - w) + torch.relu(-uv[:, 1]) + torch.relu(uv[:, 1] - h)
        )
        d_cov = torch.cdist(self.pix, uv).min(dim=1).values  # [M]
        e = 0.5
        out = torch.sqrt(d_out**2 + e * e).mean() + COVER_WEIGHT * torch.sqrt(d_cov**2 + e * e).mean()
        return out / self.scale


def fit_body(
    image: np.ndarray,  # [H, W, 3] float rgb (only its size is used)
    mask: np.ndarray,  # [H, W] float person mask in [0, 1]
    keypoints: np.ndarray,  # [17, 3] (x, y, confidence), COCO order, pixels
    *,
    steps: int = 300,
    progress: Callable[[int, int], None] | None = None,
    surface_samples: int = 2000,
    silhouette_samples: int = 2000,
    sil_weight: float = 10.0,
) -> FitResult:
    """Fit the body to a photo (module docstring); `progress(done, total)` after every step.

    Runs torch single-threaded (restored afterwards): every tensor here is small, and on 2 cores
    a 2-thread [17, 416] @ [416, 3] product took 5 ms against 13 us on one thread (measured).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit(image, mask, keypoints, steps, progress, surface_samples, silhouette_samples, sil_weight)
    finally:
        torch.set_num_threads(threads)


def _fit(image, mask, keypoints, steps, progress, surface_samples, silhouette_samples, sil_weight):
    img, msk, kp = _check_inputs(image, mask, keypoints)
    if steps < 3:
        raise DlaInputError("steps", f"must be >= 3, got {steps}")
    h, w = img.shape[:2]
    model = get_body_model()
    K = photo_intrinsics(w, h)
    Kt = torch.from_numpy(K).float()

    face_id, bary = sample_surface(surface_samples, seed=0)
    rig = PointRig((model.faces[face_id], bary), free_keys=FREE_PHENOTYPE, model=model)
    bone_ids = torch.tensor([model.bone_index(b) for b in FIT_BONES])
    prior_w = torch.tensor(_BONE_PRIOR)[:, None]  # [B, 1]
    lim = torch.tensor([_LIMITS.get(b, ((-_INF, _INF),) * 3) for b in FIT_BONES])  # [B, 3, 2]

    with torch.no_grad():
        rest_pts, _ = rig(None, torch.zeros(model.num_bones, 3), torch.zeros(3), torch.zeros(3))
    rest_kp = rest_pts[:NUM_KEYPOINTS].numpy()
    t0, rr0, depth0 = _initial_root(kp, K, rest_kp, msk)

    root_t = torch.tensor(t0, dtype=torch.float32, requires_grad=True)  # [3]
    root_r = torch.tensor(rr0, dtype=torch.float32, requires_grad=True)  # [3]
    pose = torch.zeros(len(FIT_BONES), 3, requires_grad=True)  # [B, 3]
    phen_logit = torch.zeros(len(FREE_PHENOTYPE), requires_grad=True)  # [K] sigmoid -> 0.5

    target = torch.from_numpy(kp[:, :2])  # [17, 2]
    conf = torch.from_numpy(kp[:, 2])  # [17]
    ys = np.nonzero(msk > 0.5)[0]
    scale_px = float(max(ys.max() - ys.min() + 1, 16))  # person height in pixels
    torso_w = torch.zeros(NUM_KEYPOINTS)
    torso_w[list(_TORSO)] = 1.0

    sil = _SilhouetteTargets(msk, scale_px, samples=silhouette_samples)

    n_a = max(1, int(0.2 * steps))
    n_b = max(1, int(0.4 * steps))
    n_c = steps - n_a - n_b

    opt = torch.optim.Adam(
        [
            {"params": [root_t], "lr": 0.02 * max(1.0, depth0 / 3.0)},
            {"params": [root_r], "lr": 0.03},
            {"params": [pose], "lr": 0.0},
            {"params": [phen_logit], "lr": 0.0},
        ]
    )
    rotations = torch.zeros(model.num_bones, 3)
    for step in range(steps):
        stage = "A" if step < n_a else ("B" if step < n_a + n_b else "C")
        if step == n_a:
            opt.param_groups[2]["lr"] = 0.03
            with torch.no_grad():
                _init_thighs(rig, kp, K, pose, root_r, root_t, bone_ids)
        if step == n_a + n_b:
            opt.param_groups[3]["lr"] = 0.05
        if stage == "C" and step == n_a + n_b + n_c // 2:
            with torch.no_grad():  # re-linearise the phenotype around the current estimate
                rig.linearise(_phenotype_values(rig, phen_logit))
        opt.zero_grad()
        rot = rotations.index_put((bone_ids,), pose)  # [J, 3]
        phen = torch.sigmoid(phen_logit)  # [K]
        pts, _ = rig(phen if stage == "C" else None, rot, root_r, root_t, keypoints_only=stage == "A")
        uv = _project_fit(pts[:NUM_KEYPOINTS], Kt)  # [17, 2]
        r2 = ((uv - target) ** 2).sum(-1) / scale_px**2  # [17]
        if stage == "A":
            wk = conf * (torso_w + 0.1)
            loss = (wk * geman_mcclure(r2, 0.5)).sum() / wk.sum().clamp(min=1e-6)
        else:
            sigma = SIGMA_C if stage == "C" else SIGMA_B[0 if step < n_a + n_b // 2 else 1]
            loss = (conf * geman_mcclure(r2, sigma)).sum() / conf.sum().clamp(min=1e-6)
            loss = loss + 2e-3 * (prior_w * pose**2).sum()
            over = torch.relu(lim[..., 0] - pose) + torch.relu(pose - lim[..., 1])  # [B, 3]
            loss = loss + (over**2).sum()
            if stage == "C" or step >= n_a + int(SIL_FROM_B * n_b):
                loss = loss + sil_weight * sil(_project_fit(pts[NUM_KEYPOINTS:], Kt))
        if stage == "C":
            loss = loss + 0.01 * ((phen - 0.5) ** 2).sum()
        loss.backward()
        opt.step()
        if progress is not None:
            progress(step + 1, steps)

    with torch.no_grad():
        phenotype = _phenotype_values(rig, phen_logit)
        rot = rotations.index_put((bone_ids,), pose.detach())
        return _finish(img, msk, kp, phenotype, rot, root_r.detach(), root_t.detach())


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
        if kp[hip, 2] < _MIN_CONF or kp[knee, 2] < _MIN_CONF:
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
    conf = kp[:, 2] >= _MIN_CONF
    err = np.linalg.norm(uv - kp[:, :2], axis=1)
    body = BodyParams(
        phenotype={k: float(v) for k, v in phenotype.items()},
        root_rotation=root_r.numpy().astype(np.float64),
        root_translation=np.zeros(3),
        pose={k: v.astype(np.float64) for k, v in rotations_to_pose(rot.numpy(), model).items()},
    )
    iou = silhouette_iou(verts, camera, msk)
    return FitResult(body, camera, verts, kp, float(np.median(err[conf])), iou)


def _project_world(points: np.ndarray, camera: Cameras) -> np.ndarray:
    """World points [N, 3] -> pixels [N, 2] with camera 0 (float64)."""
    return project_to_cameras(points, camera)[0][0]


def silhouette(vertices: np.ndarray, camera: Cameras) -> np.ndarray:
    """[H, W] float32 coverage of the body mesh (vertices [V, 3]) seen by camera 0."""
    from dlacli.render.raster import render_mesh

    model = get_body_model()
    col = np.ones((vertices.shape[0], 3), np.float32)
    cam = Cameras(camera.viewmats[:1], camera.Ks[:1], camera.width, camera.height)
    return render_mesh(vertices, model.faces, col, cam, antialias=1, shading=False)[0, ..., 3]


def silhouette_iou(vertices: np.ndarray, camera: Cameras, mask: np.ndarray) -> float:
    """IoU of the mesh silhouette and mask > 0.5."""
    a = silhouette(vertices, camera) > 0.5
    b = np.asarray(mask) > 0.5
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


# ---------------------------------------------------------------------------------------------
# overlay


def overlay_png(image: np.ndarray, result: FitResult) -> np.ndarray:
    """[H, W, 3] uint8: the fitted silhouette tinted over the photo (with its outline), the given
    keypoints as dots, the fitted ones as crosses and a line from each given to its fitted one."""
    from PIL import Image, ImageDraw

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise DlaInputError("image", f"expected [H, W, 3], got {list(img.shape)}")
    if img.max() > 1.5:
        img = img / 255.0
    h, w = img.shape[:2]
    if (w, h) != (result.camera.width, result.camera.height):
        raise DlaInputError(
            "image", f"size {w}x{h} differs from the fit's {result.camera.width}x{result.camera.height}"
        )
    sil = silhouette(result.vertices, result.camera)  # [H, W]
    tint = np.array([0.2, 0.45, 1.0], np.float32)
    out = img * (1.0 - 0.45 * sil[..., None]) + 0.45 * sil[..., None] * tint
    inside = sil > 0.5
    edge = inside & ~(np.roll(inside, 1, 0) & np.roll(inside, -1, 0) & np.roll(inside, 1, 1) & np.roll(inside, -1, 1))
    out[edge] = (0.1, 0.2, 1.0)
    pil = Image.fromarray(np.clip(out * 255.0 + 0.5, 0, 255).astype(np.uint8))
    draw = ImageDraw.Draw(pil)
    r = max(2, round(max(h, w) / 250))
    given = result.keypoints_2d
    fitted = _project_world(coco_keypoints(result.vertices), result.camera)
    for a, b in COCO_SKELETON:
        draw.line([tuple(fitted[a]), tuple(fitted[b])], fill=(255, 80, 80), width=max(1, r // 2))
    for k in range(NUM_KEYPOINTS):
        fx, fy = fitted[k]
        if given[k, 2] >= _MIN_CONF:
            gx, gy = given[k, :2]
            draw.line([(gx, gy), (fx, fy)], fill=(255, 255, 0), width=1)
            draw.ellipse([gx - r, gy - r, gx + r, gy + r], fill=(0, 220, 0), outline=(0, 0, 0))
        draw.line([(fx - r, fy - r), (fx + r, fy + r)], fill=(255, 0, 0), width=max(1, r // 2))
        draw.line([(fx - r, fy + r), (fx + r, fy - r)], fill=(255, 0, 0), width=max(1, r // 2))
    return np.asarray(pil, dtype=np.uint8)
