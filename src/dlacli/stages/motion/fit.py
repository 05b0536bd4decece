"""One temporal fit of anny's pose to a clip's per-frame detections (`dla motion from-video`).

Input: for the N frames where a person was detected (`frames` [N]: their indices in the clip,
increasing), COCO-17 keypoints [N, 17, 3] (pixels, confidence) and MediaPipe's 3D landmarks
[N, 17, 4] (docs/motion.md, "from a video"). Output: one phenotype for the clip and, per detected
frame, the rotations of `FIT_BONES` (the photo fit's bones), the root rotation and the root
translation, in the photo fit's world: a static pinhole camera at the origin looking along +Y,
+Z up, vertical field of view `fit.FOV_Y_DEG` (a focal length guess, as for a photo).

The unknowns of all frames of a window (`VIDEO_FIT_WINDOW` frames; longer clips are fitted window
by window, overlapping, the shape from the first) are optimised together by Adam, batched through
`PointRig` (one bone-chain call for all frames a step). The objective, a mean over the frames:
- reprojection: Geman-McClure of the keypoints' pixel error over the person's height in pixels,
  weighted by confidence (keypoints below `MIN_CONF` or outside the image count 0);
- the photo fit's limb-direction prior (`fit.limb_loss`), per frame, toward the mean of two 3D
  estimates of each limb's direction: MediaPipe's 3D landmarks and the pose lifter's 3D keypoints
  (`nn.lifter`, trained on CMU motion capture; docs/motion.md has how the two were chosen), and
  for a segment neither sees MediaPipe's guess at a low weight (`UNSEEN_LIMB_CONF`);
- the photo fit's pose prior and joint limits;
- temporal smoothness: squared accelerations (second differences over consecutive detected
  frames) of the 3D keypoints, of the bone rotations and of the root;
- foot contact: where an ankle is still in the image (`foot_contacts`), the squared frame-to-frame
  displacement of that ankle's 3D keypoint (no skating);
- a prior of the phenotype to 0.5 (it is shared by the clip).
Initialisation per frame: the root's facing from the landmarks (`fit.facing_from_landmarks`),
its depth from the torso's pixel length, the limbs by inverse kinematics on the prior's
directions. Coarse to fine: the root alone on the torso keypoints first (`ROOT_STAGE` of the
steps), then everything; the phenotype from half-way.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from dlacli.body.keypoints import HIPS, MIN_CONF, NUM_KEYPOINTS, SHOULDERS, TORSO, PointRig
from dlacli.body.model import get_body_model
from dlacli.body.moving_rig import MovingRig
from dlacli.limits import VIDEO_FIT_STEPS, VIDEO_FIT_WINDOW
from dlacli.stages.fit.photo import (
    BONE_PRIOR,
    FIT_BONES,
    FREE_PHENOTYPE,
    JOINT_LIMITS,
    LIMB_SEGMENTS,
    LIMB_SIGMA,
    NO_LIMIT,
    facing_from_landmarks,
    geman_mcclure,
    photo_intrinsics,
    project_fit,
)

if TYPE_CHECKING:
    from dlacli.nn.lifter import PoseLifter

ROOT_STAGE = 0.2  # fraction of the steps that fit the root alone
SIGMA = (0.1, 0.04)  # Geman-McClure scales (fractions of the person's height): first half, second half
ACC_WEIGHT = 100.0  # keypoint accelerations (in person heights per frame^2, squared)
LIMB_W = 0.7  # the 3D-landmark limb-direction prior (14 x the photo fit's: on the synthetic CMU clip 0.05 gave
# 84 mm PA-MPJPE, 0.2 69 mm, 0.5-1.0 60-61 mm, 2-4 62-63 mm with more jitter)
ROT_ACC_WEIGHT = 1.0  # bone and root rotation accelerations (radians per frame^2, squared)
CONTACT_WEIGHT = 300.0  # ankle displacement during a contact (person heights per frame, squared)
BODY_HEIGHT_M = 1.7  # the metres that the temporal terms divide by (a person's height)
CONTACT_SPEED = 0.25  # an ankle slower than this (person heights per second, in the image) is in contact
CONTACT_MIN_FRAMES = 3  # shorter runs of slow frames are not contacts
CONTACT_CONF = 0.5
# the bones a video fits: the photo fit's, and the clavicles, the upper spine and the lower neck,
# which carry the shoulders and the head (without them the shoulders of a retargeted CMU clip sit
# 70 mm off on the default body); their "near the zero pose" prior weights and joint limits
VIDEO_BONES = (*FIT_BONES, "clavicle.L", "clavicle.R", "spine05", "neck02")
_VIDEO_PRIOR = (*BONE_PRIOR, 0.5, 0.5, 4.0, 2.0)
_VIDEO_LIMITS = {
    **JOINT_LIMITS,
    "clavicle.L": ((-0.6, 0.6), (-1.0, 1.0), (-0.8, 0.8)),
    "clavicle.R": ((-0.6, 0.6), (-1.0, 1.0), (-0.8, 0.8)),
    "spine05": ((-0.5, 0.8), (-0.5, 0.5), (-0.6, 0.6)),
    "neck02": ((-0.6, 0.8), (-0.6, 0.6), (-0.8, 0.8)),
}
ANKLES = (15, 16)  # COCO left, right ankle
LR = (0.02, 0.03, 0.05, 0.05)  # Adam: root translation (x depth / 3 m), root rotation, bones, phenotype
IK_ITERS = 30
OVERLAP = 24  # frames two neighbouring windows share (cross-faded)


@dataclass
class MotionFit:
    """The fit of the detected frames (module doc): world of the photo fit (camera at the origin)."""

    phenotype: dict[str, float]
    rotations: np.ndarray  # [N, B, 3] axis-angle of VIDEO_BONES, local-ref
    root_rotation: np.ndarray  # [N, 3]
    root_translation: np.ndarray  # [N, 3] metres, camera at the origin looking along +Y
    reprojection_px: np.ndarray  # [N] median pixel error of the confident keypoints (NaN: none)
    contacts: np.ndarray  # [N, 2] bool: left, right ankle in contact (`foot_contacts`)


def person_height_px(keypoints: np.ndarray) -> float:
    """A clip's person height in pixels from keypoints [N, 17, 3]: the median over frames of the
    confident keypoints' vertical extent (nose to ankles is ~0.87 of the height), at least 16."""
    ext = []
    for kp in keypoints:
        ok = kp[:, 2] >= MIN_CONF
        if ok.sum() >= 4 and ok[[15, 16]].any() and ok[0]:
            ext.append((kp[ok, 1].max() - kp[ok, 1].min()) / 0.87)
    if not ext:  # no frame shows head and feet: the torso (~0.3 of the height)
        for kp in keypoints:
            if (kp[list(TORSO), 2] >= MIN_CONF).all():
                ext.append(np.linalg.norm(kp[[5, 6], :2].mean(0) - kp[[11, 12], :2].mean(0)) / 0.3)
    return float(max(np.median(ext), 16.0)) if ext else 16.0


def foot_contacts(keypoints: np.ndarray, frames: np.ndarray, fps: float, height_px: float) -> np.ndarray:
    """[N, 2] bool: which ankle (left, right) stands still in the image: confident, and its pixel
    speed (central difference over detected neighbours one frame apart, after a 3-frame mean)
    below `CONTACT_SPEED` person heights per second, for at least `CONTACT_MIN_FRAMES` frames in a
    row. keypoints [N, 17, 3], frames [N] increasing clip indices."""
    n = keypoints.shape[0]
    out = np.zeros((n, 2), bool)
    frames = np.asarray(frames, np.int64)
    for side, a in enumerate(ANKLES):
        xy = keypoints[:, a, :2].astype(np.float64)
        conf = keypoints[:, a, 2] >= CONTACT_CONF
        smooth = xy.copy()
        for i in range(n):  # a 3-frame mean over consecutive, confident neighbours
            sel = [j for j in (i - 1, i, i + 1) if 0 <= j < n and abs(frames[j] - frames[i]) <= 1 and conf[j]]
            if sel:
                smooth[i] = xy[sel].mean(0)
        speed = np.full(n, np.inf)
        for i in range(n):
            lo = i - 1 if i > 0 and frames[i] - frames[i - 1] == 1 and conf[i - 1] else i
            hi = i + 1 if i + 1 < n and frames[i + 1] - frames[i] == 1 and conf[i + 1] else i
            if hi > lo and conf[i]:
                speed[i] = np.linalg.norm(smooth[hi] - smooth[lo]) / (hi - lo) * fps / height_px
        slow = speed < CONTACT_SPEED
        i = 0
        while i < n:  # keep runs of consecutive slow frames long enough
            if not slow[i]:
                i += 1
                continue
            j = i
            while j + 1 < n and slow[j + 1] and frames[j + 1] - frames[j] == 1:
                j += 1
            if j - i + 1 >= CONTACT_MIN_FRAMES:
                out[i : j + 1, side] = True
            i = j + 1
    return out


# the photo fit's segments (limbs, shoulder line, hip line) and the two sides of the torso
# (shoulder -> hip): without these the torso's lean toward or away from the camera is free, and
# the fit put the hips ~50 mm in front of the truth's on the synthetic clips
VIDEO_SEGMENTS = (*LIMB_SEGMENTS, (5, 11), (6, 12))
_SEG_A = [s[0] for s in VIDEO_SEGMENTS]
_SEG_B = [s[1] for s in VIDEO_SEGMENTS]


def _limb_targets_batched(lm: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """landmarks [N, 17, 4] -> unit directions [N, S, 3] (camera axes) and confidences [N, S]."""
    a = np.array([s[0] for s in VIDEO_SEGMENTS])
    b = np.array([s[1] for s in VIDEO_SEGMENTS])
    d = lm[:, b, :3].astype(np.float64) - lm[:, a, :3]
    n = np.linalg.norm(d, axis=-1)
    conf = np.minimum(lm[:, a, 3], lm[:, b, 3]) * (n > 1e-3)
    u = d / np.maximum(n, 1e-9)[..., None]
    return torch.from_numpy(u).float(), torch.from_numpy(conf).float()


def _limb_loss(pts17: torch.Tensor, dirs: torch.Tensor, wts: torch.Tensor, sigma: float | None) -> torch.Tensor:
    """Per-frame confidence-weighted mean of rho(|u - v|^2) over `VIDEO_SEGMENTS`: pts17 [N, 17, 3]
    in the fitting world, dirs [N, S, 3] in camera axes, wts [N, S] -> [N] (as `fit.limb_loss`,
    with weights per frame)."""
    d = pts17[..., _SEG_B, :] - pts17[..., _SEG_A, :]
    d = torch.stack([d[..., 0], -d[..., 2], d[..., 1]], dim=-1)  # fitting world -> camera axes
    r2 = ((d / d.norm(dim=-1, keepdim=True).clamp(min=1e-9) - dirs) ** 2).sum(-1)
    rho = r2 if sigma is None else geman_mcclure(r2, sigma)
    return (wts * rho).sum(-1) / wts.sum(-1).clamp(min=1e-6)


def _initial_roots(kp: np.ndarray, lm: np.ndarray, K: np.ndarray, rest_kp: np.ndarray):
    """Per-frame root translation [N, 3] and rotation [N, 3] (camera at the origin): depth from the
    torso's pixel length (median-filtered over 9 frames, bounded to 0.6-1.6 x the clip's median),
    along the ray through the hips; the facing from the landmarks (else from the shoulders' order),
    unwrapped over time."""
    f = float(K[1, 1])
    n = kp.shape[0]
    torso_m = float(np.linalg.norm(rest_kp[list(SHOULDERS)].mean(0) - rest_kp[list(HIPS)].mean(0)))
    depth = np.full(n, np.nan)
    hips = np.zeros((n, 2))
    for i in range(n):
        c = kp[i, :, 2] >= MIN_CONF
        sh = [k for k in SHOULDERS if c[k]]
        hp = [k for k in HIPS if c[k]]
        hips[i] = kp[i, hp, :2].mean(0) if hp else kp[i, c, :2].mean(0) if c.any() else (K[0, 2], K[1, 2])
        if sh and hp:
            px = float(np.linalg.norm(kp[i, sh, :2].mean(0) - kp[i, hp, :2].mean(0)))
            depth[i] = f * torso_m / max(px, 1.0)
    med = float(np.nanmedian(depth)) if np.isfinite(depth).any() else 3.0
    depth = np.where(np.isfinite(depth), depth, med)
    depth = np.array([np.median(depth[max(0, i - 4) : i + 5]) for i in range(n)])
    depth = np.clip(depth, 0.6 * med, 1.6 * med)
    ray = np.stack([(hips[:, 0] - K[0, 2]) / f, np.ones(n), -(hips[:, 1] - K[1, 2]) / f], axis=1)
    hip_rest = rest_kp[[11, 12]].mean(0)
    t = ray * depth[:, None] - hip_rest
    yaw = np.zeros(n)
    for i in range(n):
        facing = facing_from_landmarks(lm[i])
        if facing is not None:
            yaw[i] = facing[2]
        elif kp[i, 5, 2] >= MIN_CONF and kp[i, 6, 2] >= MIN_CONF and kp[i, 5, 0] < kp[i, 6, 0]:
            yaw[i] = math.pi  # the left shoulder on the image left: the back is seen
    yaw = np.unwrap(yaw)
    rr = np.zeros((n, 3))
    rr[:, 2] = yaw
    return t, rr


class _Window:
    """The objective and the unknowns of one window of detected frames (module doc)."""

    def __init__(self, rig: MovingRig, kp, lm, limbs, frames, contacts, K, height_px, phen_logit, fit_shape: bool):
        """limbs: (directions [N, S, 3], confidences [N, S]) of the limb prior (`_limb_directions`)."""
        self.rig = rig
        self.Kt = torch.from_numpy(K).float()
        self.height_px = float(height_px)
        n = kp.shape[0]
        self.n = n
        conf = kp[:, :, 2].astype(np.float32).copy()
        conf[conf < MIN_CONF] = 0.0
        self.target = torch.from_numpy(kp[:, :, :2].astype(np.float32))  # [N, 17, 2]
        self.conf = torch.from_numpy(conf)  # [N, 17]
        self.dirs, self.dir_w = limbs
        frames = np.asarray(frames, np.int64)
        self.triples = torch.from_numpy(np.nonzero(frames[2:] - frames[:-2] == 2)[0])  # i: i, i+1, i+2 consecutive
        pair = frames[1:] - frames[:-1] == 1
        self.contact_pairs = [
            torch.from_numpy(np.nonzero(pair & contacts[:-1, s] & contacts[1:, s])[0]) for s in range(2)
        ]
        self.prior_w = torch.tensor(_VIDEO_PRIOR)[:, None]  # [B, 1]
        self.lim = torch.tensor([_VIDEO_LIMITS.get(b, ((-NO_LIMIT, NO_LIMIT),) * 3) for b in VIDEO_BONES])  # [B, 3, 2]
        torso = torch.zeros(NUM_KEYPOINTS)
        torso[list(TORSO)] = 1.0
        self.torso_w = torso + 0.1
        with torch.no_grad():
            rest = rig(None, torch.zeros(1, len(VIDEO_BONES), 3), torch.zeros(1, 3), torch.zeros(1, 3))[0]
        t0, rr0 = _initial_roots(kp, lm, K, rest.numpy())
        self.root_t = torch.from_numpy(t0).float().requires_grad_(True)  # [N, 3]
        self.root_r = torch.from_numpy(rr0).float().requires_grad_(True)  # [N, 3]
        self.pose = torch.zeros(n, len(VIDEO_BONES), 3, requires_grad=True)  # [N, B, 3]
        self.phen_logit = phen_logit.clone().requires_grad_(fit_shape)  # [K]
        self.fit_shape = fit_shape

    def points(self, phen=None) -> torch.Tensor:
        return self.rig(phen, self.pose, self.root_r, self.root_t)  # [N, 17, 3]

    def pose_prior(self) -> torch.Tensor:  # [N]
        p = self.pose
        over = torch.relu(self.lim[..., 0] - p) + torch.relu(p - self.lim[..., 1])
        return 2e-3 * (self.prior_w * p**2).sum((-2, -1)) + (over**2).sum((-2, -1))

    def initial_ik(self, iters: int = 30) -> None:
        """Bone rotations from the landmark limb directions, root fixed (all frames at once)."""
        wts = self.dir_w.clone()
        wts[:, 8:] = 0.0  # the limbs only: the shoulder and hip lines are the root's
        opt = torch.optim.Adam([self.pose], lr=0.1)
        for _ in range(iters):
            opt.zero_grad()
            loss = _limb_loss(self.points(), self.dirs, wts, None) + self.pose_prior()
            loss.sum().backward()
            opt.step()

    def loss(self, stage_root: bool, sigma: float, use_shape: bool) -> torch.Tensor:
        phen = torch.sigmoid(self.phen_logit) if use_shape else None
        pts = self.points(phen)  # [N, 17, 3]
        uv = project_fit(pts, self.Kt)  # [N, 17, 2]
        r2 = ((uv - self.target) ** 2).sum(-1) / self.height_px**2  # [N, 17]
        if stage_root:
            w = self.conf * self.torso_w
            return ((w * geman_mcclure(r2, 0.5)).sum(-1) / w.sum(-1).clamp(min=1e-6)).mean()
        per_frame = (self.conf * geman_mcclure(r2, sigma)).sum(-1) / self.conf.sum(-1).clamp(min=1e-6)
        per_frame = per_frame + self.pose_prior() + LIMB_W * _limb_loss(pts, self.dirs, self.dir_w, LIMB_SIGMA)
        loss = per_frame.mean()
        i = self.triples
        if len(i):
            h = BODY_HEIGHT_M
            acc = (pts[i + 2] - 2 * pts[i + 1] + pts[i]) / h  # [M, 17, 3]
            loss = loss + ACC_WEIGHT * (acc**2).sum(-1).mean()
            for x in (self.pose, self.root_r[:, None]):
                loss = loss + ROT_ACC_WEIGHT * ((x[i + 2] - 2 * x[i + 1] + x[i]) ** 2).sum((-2, -1)).mean()
            rt = (self.root_t[i + 2] - 2 * self.root_t[i + 1] + self.root_t[i]) / h
            loss = loss + ACC_WEIGHT * (rt**2).sum(-1).mean()
        for side, pairs in enumerate(self.contact_pairs):
            if len(pairs):
                a = ANKLES[side]
                step = (pts[pairs + 1, a] - pts[pairs, a]) / BODY_HEIGHT_M  # [M, 3]
                loss = loss + CONTACT_WEIGHT * (step**2).sum(-1).mean()
        if use_shape:
            loss = loss + 0.01 * ((phen - 0.5) ** 2).sum()
        return loss

    def optimise(self, steps: int, progress: Callable[[int], None] | None = None) -> None:
        n_root = max(1, int(ROOT_STAGE * steps))
        self.initial_ik(IK_ITERS)
        lr_t = LR[0] * max(1.0, float(self.root_t[:, 1].detach().abs().mean()) / 3.0)
        groups = [{"params": [self.root_t], "lr": lr_t}, {"params": [self.root_r], "lr": LR[1]}]
        opt = torch.optim.Adam(groups)
        for _ in range(n_root):
            opt.zero_grad()
            self.loss(True, 0.5, False).backward()
            opt.step()
            if progress is not None:
                progress(1)
        params = [
            {"params": [self.root_t], "lr": lr_t},
            {"params": [self.root_r], "lr": LR[1]},
            {"params": [self.pose], "lr": LR[2]},
        ]
        if self.fit_shape:
            params.append({"params": [self.phen_logit], "lr": 0.0})
        opt = torch.optim.Adam(params)
        rest = steps - n_root
        for step in range(rest):
            half = step >= rest // 2
            if self.fit_shape and half:
                opt.param_groups[3]["lr"] = LR[3]
            opt.zero_grad()
            self.loss(False, SIGMA[1] if half else SIGMA[0], self.fit_shape and half).backward()
            opt.step()
            if progress is not None:
                progress(1)


LIMB_SOURCE = "both"  # where the limb prior's directions come from: lifter, landmarks or both (their mean)
# the weight of MediaPipe's 3D guess for a segment that neither estimate sees (an end keypoint
# below MIN_CONF: hidden behind the body or out of the frame), where it would otherwise have none
# (chosen on the calibration sets: 0.05-0.6 measured, docs/motion.md)
UNSEEN_LIMB_CONF = 0.05


def _limb_directions(
    kp: np.ndarray, lm: np.ndarray, K: np.ndarray, lifter: PoseLifter | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The limb prior's unit directions [N, S, 3] (camera axes) and confidences [N, S]: those of
    the pose lifter's 3D keypoints (`nn.lifter`), of MediaPipe's 3D landmarks, or their mean; a
    segment none of them sees takes MediaPipe's guess at `UNSEEN_LIMB_CONF`."""
    mp = _limb_targets_batched(lm)
    if LIMB_SOURCE == "landmarks":
        return _unseen_from_landmarks(*mp, lm)
    from dlacli.nn.lifter import lift_keypoints

    lifted = _limb_targets_batched(lift_keypoints(kp, K, lifter))
    if LIMB_SOURCE == "lifter":
        return _unseen_from_landmarks(*lifted, lm)
    # the mean where both see the segment; else the one that does (a keypoint out of the frame
    # leaves the lifter without the segment, MediaPipe still guesses it)
    has_l, has_m = (lifted[1] > 0)[..., None], (mp[1] > 0)[..., None]
    mean = torch.nn.functional.normalize(lifted[0] * has_l + mp[0] * has_m, dim=-1)
    conf = torch.where(has_l[..., 0] & has_m[..., 0], torch.minimum(lifted[1], mp[1]), lifted[1] + mp[1])
    return _unseen_from_landmarks(mean, conf, lm)


def _unseen_from_landmarks(dirs: torch.Tensor, conf: torch.Tensor, lm: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Segments with confidence 0 take MediaPipe's direction (its world landmarks are a full
    skeleton wherever it found the person, seen or not) at confidence UNSEEN_LIMB_CONF; frames
    without landmarks (all zero) keep none."""
    guess = _limb_targets_batched(np.concatenate([lm[..., :3], np.ones_like(lm[..., 3:])], -1))
    fill = (conf <= 0) & (guess[1] > 0)
    dirs = torch.where(fill[..., None], guess[0], dirs)
    return dirs, torch.where(fill, torch.full_like(conf, UNSEEN_LIMB_CONF), conf)


def _windows(n: int, size: int, overlap: int) -> list[tuple[int, int]]:
    """[lo, hi) index ranges of at most `size` covering range(n), neighbours sharing `overlap`."""
    if n <= size:
        return [(0, n)]
    out, lo = [], 0
    while True:
        hi = min(lo + size, n)
        out.append((lo, hi))
        if hi == n:
            return out
        lo = hi - overlap


def fit_motion(
    keypoints: np.ndarray,  # [N, 17, 3] pixels + confidence (0: not seen)
    landmarks: np.ndarray,  # [N, 17, 4] MediaPipe world landmarks + confidence
    frames: np.ndarray,  # [N] increasing clip frame indices of the detections
    width: int,
    height: int,
    fps: float,
    *,
    steps: int = VIDEO_FIT_STEPS,
    window: int = VIDEO_FIT_WINDOW,
    progress: Callable[[int, int], None] | None = None,
    lifter: PoseLifter | None = None,
) -> MotionFit:
    """The temporal fit (module doc); `progress(done, total)` counts optimisation steps; `lifter`
    the pose lifter (`nn.lifter.PoseLifter`; None: the shipped one).

    Runs torch single-threaded (restored afterwards), as the photo fit: the tensors are small."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit_motion(keypoints, landmarks, frames, width, height, fps, steps, window, progress, lifter)
    finally:
        torch.set_num_threads(threads)


def _fit_motion(keypoints, landmarks, frames, width, height, fps, steps, window, progress, lifter) -> MotionFit:
    kp = np.asarray(keypoints, np.float32)
    lm = np.asarray(landmarks, np.float32)
    frames = np.asarray(frames, np.int64)
    n = kp.shape[0]
    assert kp.shape == (n, NUM_KEYPOINTS, 3) and lm.shape == (n, NUM_KEYPOINTS, 4) and frames.shape == (n,), (
        kp.shape,
        lm.shape,
        frames.shape,
    )
    K = photo_intrinsics(width, height)
    limbs = _limb_directions(kp, lm, K, lifter)
    height_px = person_height_px(kp)
    contacts = foot_contacts(kp, frames, fps, height_px)
    rig = PointRig(free_keys=FREE_PHENOTYPE, model=get_body_model())
    moving = MovingRig(rig, VIDEO_BONES, NUM_KEYPOINTS)
    spans = _windows(n, max(int(window), 2 * OVERLAP + 1), OVERLAP)
    total = steps * len(spans)
    done = [0]

    def tick(k: int) -> None:
        done[0] += k
        if progress is not None:
            progress(done[0], total)

    rot = np.zeros((n, len(VIDEO_BONES), 3))
    rr = np.zeros((n, 3))
    rt = np.zeros((n, 3))
    phen_logit = torch.zeros(len(FREE_PHENOTYPE))
    for w, (lo, hi) in enumerate(spans):
        win = _Window(
            moving, kp[lo:hi], lm[lo:hi], tuple(x[lo:hi] for x in limbs), frames[lo:hi], contacts[lo:hi], K, height_px,
            phen_logit, w == 0,
        )  # fmt: skip
        win.optimise(steps, tick)
        if w == 0:
            phen_logit = win.phen_logit.detach().clone()
        if w == 0 and len(spans) > 1:  # later windows: the shape fixed, the rigs linearised at it
            rig.linearise(rig.phenotype_dict(torch.sigmoid(phen_logit)))
            moving.linearise(rig.phenotype0)
            phen_logit = torch.logit(torch.tensor([rig.phenotype0[k] for k in FREE_PHENOTYPE]).clamp(1e-4, 1 - 1e-4))
        parts = (win.pose.detach().numpy(), win.root_r.detach().numpy(), win.root_t.detach().numpy())
        # cross-fade the frames this window shares with the previous one
        fade = np.ones(hi - lo)
        if w > 0:
            shared = min(OVERLAP, hi - lo)
            fade[:shared] = (np.arange(shared) + 0.5) / shared
        for dst, src in zip((rot, rr, rt), parts, strict=True):
            shape = (-1,) + (1,) * (src.ndim - 1)
            dst[lo:hi] = dst[lo:hi] * (1 - fade.reshape(shape)) + src * fade.reshape(shape)
    phenotype = rig.phenotype_dict(torch.sigmoid(phen_logit))
    reprojection = _reprojection(moving, torch.sigmoid(phen_logit), kp, rot, rr, rt, K)
    return MotionFit(phenotype, rot, rr, rt, reprojection, contacts)


@torch.no_grad()
def _reprojection(rig: MovingRig, phen: torch.Tensor, kp, rot, rr, rt, K) -> np.ndarray:
    """[N] median pixel error of each frame's confident keypoints (NaN where none)."""
    as_t = lambda x: torch.from_numpy(np.asarray(x, np.float32))  # noqa: E731
    pts = rig(phen, as_t(rot), as_t(rr), as_t(rt))
    uv = project_fit(pts, torch.from_numpy(K).float()).numpy()
    err = np.linalg.norm(uv - kp[..., :2], axis=-1)
    err = np.where(kp[..., 2] >= MIN_CONF, err, np.nan)
    out = np.full(len(err), np.nan)
    ok = np.isfinite(err).any(-1)
    out[ok] = np.nanmedian(err[ok], axis=-1)
    return out
