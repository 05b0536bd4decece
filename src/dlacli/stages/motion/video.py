"""`dla motion from-video`: a video of a person -> an anny motion (docs/motion.md, "from a video").

1. `detect_clip`: the clip is streamed (`io.video.open_video`, one frame in memory at a time)
   through MediaPipe Pose in video mode (`io.detect.PoseTracker`); per frame it keeps the COCO-17
   keypoints and 3D landmarks only. Keypoints outside the image or below the confidence floor
   count as unseen; a frame with too few confident keypoints (no shoulder or no hip) has no
   person; so has a frame whose person jumped away from the tracked one (`keep_tracked`: another
   person was picked up), until the tracked one is back or `TRACK_RESET_S` passed. Left and
   right labels that change sides at once are swapped back (`unswap_left_right`).
2. `stages.motion.fit.fit_motion`: one temporal fit over the detected frames.
3. `fill_missing`: frames with no person are interpolated (rotations slerped, translations
   linear between the nearest fitted frames; held before the first and after the last).
4. The motion's world: the fit's (camera at the origin, looking along +Y, +Z up, level), moved so
   that the first frame's pelvis is above the origin and the ankles' lowest 5 % rest at the
   default body's ankle height in the zero pose (the feet on z = ground).
5. `preview_frames`: the fitted body over the clip's frames, for `--preview`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from dlacli.body.keypoints import COCO_MIRROR, HIPS, MIN_CONF, SHOULDERS, TORSO
from dlacli.errors import DlaInputError
from dlacli.io.video import VideoClip
from dlacli.limits import DEFAULT_LANDMARKS
from dlacli.types import Motion

if TYPE_CHECKING:
    from dlacli.nn.lifter import PoseLifter
    from dlacli.stages.motion.fit import MotionFit

MIN_KEYPOINTS = 6  # confident keypoints a frame needs (with a shoulder and a hip) to count as seen
TRACK_JUMP = 0.3  # a torso centre this far (person heights) from the last tracked one ...
TRACK_SPEED = 3.0  # ... plus this many person heights per second since then: another person
TRACK_RESET_S = 1.0  # after this long without the tracked person, whoever is found is tracked
# shoulders or hips this wide (torso lengths; ~0.6 facing the camera) on both sides of a change of
# sides within this many seconds (two frame intervals at 25-30 fps) are a label swap: a turn that
# fast would be ~800 degrees a second
SWAP_WIDTH = 0.35
SWAP_GAP_S = 0.085
PREVIEW_ALPHA = 0.6  # opacity of the body drawn over the clip
PREVIEW_FILLED = (0.6, 0.6, 0.6)  # colour of the body in frames with no person (interpolated)
PREVIEW_FITTED = (0.45, 0.62, 0.90)


@dataclass
class ClipDetections:
    """What the detector found in each frame of a clip (small: ~300 bytes a frame)."""

    keypoints: np.ndarray  # [T, 17, 3] pixels + confidence (0 where unseen)
    landmarks: np.ndarray  # [T, 17, 4] MediaPipe world landmarks + confidence
    found: np.ndarray  # [T] bool: a (tracked) person in this frame
    width: int
    height: int
    fps: float
    times: np.ndarray  # [T] seconds in the file
    switched: list[int] = field(default_factory=list)  # frames dropped as another person (keep_tracked)
    unswapped: list[int] = field(default_factory=list)  # frames whose left and right were swapped back

    @property
    def num_frames(self) -> int:
        return int(self.found.shape[0])


def _torso_centre(kp: np.ndarray) -> np.ndarray:
    c = kp[:, 2] >= MIN_CONF
    sel = [k for k in TORSO if c[k]]
    return kp[sel, :2].mean(0)


def clean_keypoints(kp: np.ndarray, width: int, height: int) -> tuple[np.ndarray, bool]:
    """Keypoints [17, 3] with confidence 0 for those outside the image or below the floor, and
    whether the frame shows enough of a person (`MIN_KEYPOINTS`, a shoulder and a hip)."""
    kp = np.asarray(kp, np.float32).copy()
    x, y = kp[:, 0], kp[:, 1]
    outside = (x < 0) | (y < 0) | (x > width - 1) | (y > height - 1) | ~np.isfinite(kp).all(1)
    kp[outside | (kp[:, 2] < MIN_CONF), 2] = 0.0
    kp[~np.isfinite(kp)] = 0.0
    c = kp[:, 2] > 0
    return kp, bool(c.sum() >= MIN_KEYPOINTS and c[[5, 6]].any() and c[[11, 12]].any())


def keep_tracked(keypoints: np.ndarray, found: np.ndarray, fps: float) -> tuple[np.ndarray, list[int]]:
    """Which frames keep their person (module doc, step 1): keypoints [T, 17, 3] (cleaned), found
    [T] -> (found [T] without the frames whose torso centre is further than `TRACK_JUMP` + `TRACK_SPEED`
    x the time since the last kept frame (person heights) from that frame's, within
    `TRACK_RESET_S`; those frames' indices)."""
    keep = np.asarray(found, bool).copy()
    switched = []
    last_centre, last_frame, scale = None, -(10**9), 16.0
    reset = max(1, int(round(TRACK_RESET_S * fps)))
    for k in np.nonzero(keep)[0]:
        kp = keypoints[k]
        centre = _torso_centre(kp)
        ys = kp[kp[:, 2] > 0, 1]
        size = max(float(ys.max() - ys.min()), 16.0)
        gap = k - last_frame
        if last_centre is not None and gap <= reset:
            if np.linalg.norm(centre - last_centre) > max(scale, size) * (TRACK_JUMP + TRACK_SPEED * gap / fps):
                keep[k] = False
                switched.append(int(k))
                continue
        last_centre, last_frame, scale = centre, k, size
    return keep, switched


def _pair_widths(kp: np.ndarray) -> dict[tuple[int, int], float]:
    """Signed image widths (x of the left minus x of the right, torso lengths) of the shoulders and
    hips seen in a frame's keypoints [17, 3]."""
    c = kp[:, 2] >= MIN_CONF
    if not (c[list(SHOULDERS)].any() and c[list(HIPS)].any()):
        return {}
    sh = kp[[k for k in SHOULDERS if c[k]], :2].mean(0)
    hp = kp[[k for k in HIPS if c[k]], :2].mean(0)
    torso = max(float(np.linalg.norm(sh - hp)), 1.0)
    return {(a, b): float(kp[a, 0] - kp[b, 0]) / torso for a, b in (SHOULDERS, HIPS) if c[a] and c[b]}


def unswap_left_right(keypoints: np.ndarray, landmarks: np.ndarray, found: np.ndarray, fps: float):
    """Undo the detector's left-right label swaps (module doc, step 1). A frame whose shoulders or
    hips are at least `SWAP_WIDTH` torso lengths wide in the image shows which way the person
    faces; between two such frames at most `SWAP_GAP_S` apart (narrower frames between them
    skipped), the wide pairs seen in both changing sides is no turn (a turn passes through a side
    view, where they are narrow): the labels swapped. Each swap flips the labelling of the frames
    after it; the frames of the less frequent labelling get their left and right exchanged, and
    MediaPipe's 3D landmarks are mirrored in depth as well (the other reading of the same image: a
    body seen from the front instead of the back). Returns (keypoints, landmarks, the frames
    changed)."""
    seen = np.nonzero(found)[0]
    parity = np.zeros(len(seen), bool)
    prev = None  # (frame, its wide pairs) of the last frame that showed the facing
    for j, k in enumerate(seen):
        if j > 0:
            parity[j] = parity[j - 1]
        wide = {p: w for p, w in _pair_widths(keypoints[k]).items() if abs(w) >= SWAP_WIDTH}
        if not wide:
            continue
        if prev is not None and (k - prev[0]) / fps <= SWAP_GAP_S:
            common = [p for p in wide if p in prev[1]]
            if common and all(wide[p] * prev[1][p] < 0 for p in common):
                parity[j] = not parity[j]
        prev = (k, wide)
    fix = seen[parity] if parity.sum() * 2 < len(seen) else seen[~parity]
    kps, lms = keypoints.copy(), landmarks.copy()
    mirror = list(COCO_MIRROR)
    kps[fix] = keypoints[fix][:, mirror]
    lms[fix] = landmarks[fix][:, mirror] * np.array([1.0, 1.0, -1.0, 1.0], np.float32)
    return kps, lms, [int(k) for k in fix]


def detect_clip(
    clip: VideoClip, progress: Callable[[int, int | None], None] | None = None, landmarks: str = DEFAULT_LANDMARKS
) -> ClipDetections:
    """Stream the clip through the tracker (module doc, step 1) with the landmark model `landmarks`."""
    from dlacli.io.detect import PoseTracker

    kps, lms, found, times = [], [], [], []
    with PoseTracker(landmarks) as tracker:
        for k, t, frame in clip:
            det = tracker(frame)
            kp = np.zeros((17, 3), np.float32)
            lm = np.zeros((17, 4), np.float32)
            ok = False
            if det is not None:
                kp, ok = clean_keypoints(det.keypoints, clip.width, clip.height)
                if det.world is not None:
                    lm = det.world.copy()
                    lm[:, 3] = kp[:, 2]
            kps.append(kp)
            lms.append(lm)
            found.append(ok)
            times.append(t)
            if progress is not None:
                progress(k + 1, clip.expected_frames)
    if not found:
        raise DlaInputError(clip.path, "holds no frames in the chosen span (--start/--end)")
    kps, lms = np.stack(kps), np.stack(lms)
    keep, switched = keep_tracked(kps, np.array(found), clip.fps)
    kps[~keep] = 0.0
    lms[~keep] = 0.0
    kps, lms, unswapped = unswap_left_right(kps, lms, keep, clip.fps)
    return ClipDetections(kps, lms, keep, clip.width, clip.height, clip.fps, np.array(times), switched, unswapped)


def missing_ranges(found: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive (first, last) frame ranges where `found` [T] is False."""
    out, t, n = [], 0, len(found)
    while t < n:
        if found[t]:
            t += 1
            continue
        s = t
        while t < n and not found[t]:
            t += 1
        out.append((s, t - 1))
    return out


def fill_missing(
    frames: np.ndarray, rotations: np.ndarray, root_rotation: np.ndarray, root_translation: np.ndarray, total: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Values at `frames` [N] (increasing) -> the same for all `total` frames: a missing frame
    between two fitted ones is slerped (rotations [N, B, 3] and root_rotation [N, 3], axis-angle)
    or linearly interpolated (root_translation [N, 3]) at its time; before the first and after the
    last fitted frame the nearest is held."""
    from dlacli.geometry import axis_angle_to_quat, quat_slerp, quat_to_axis_angle

    frames = np.asarray(frames, np.int64)
    t = np.arange(total)
    hi = np.clip(np.searchsorted(frames, t), 0, len(frames) - 1)  # first fitted frame >= t
    lo = np.clip(hi - 1, 0, len(frames) - 1)
    lo = np.where(frames[hi] == t, hi, lo)
    span = (frames[hi] - frames[lo]).astype(np.float64)
    w = np.where(span > 0, (t - frames[lo]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)  # before the first / after the last: 0 or 1 -> held

    def slerp(aa: np.ndarray) -> np.ndarray:
        q = axis_angle_to_quat(np.asarray(aa, np.float64))
        shape = (-1,) + (1,) * (q.ndim - 1)
        out = quat_to_axis_angle(quat_slerp(q[lo], q[hi], w.reshape(shape), shortest=True))
        exact = (w == 0).reshape(shape)  # fitted frames (and held ends) keep their values exactly
        return np.where(exact, np.asarray(aa, np.float64)[lo], np.where((w == 1).reshape(shape), aa[hi], out))

    rt = root_translation[lo] * (1 - w[:, None]) + root_translation[hi] * w[:, None]
    return slerp(rotations), slerp(root_rotation), rt


def to_motion(fit, found: np.ndarray, fps: float, ground_ankle_z: float, ankle_z: np.ndarray) -> Motion:
    """The fitted detected frames -> a Motion over all frames (module doc, steps 3-4); `ankle_z`
    [N, 2] the fitted ankles' heights in the fit world, `ground_ankle_z` the default body's."""
    from dlacli.stages.motion.fit import VIDEO_BONES

    frames = np.nonzero(found)[0]
    rot, rr, rt = fill_missing(frames, fit.rotations, fit.root_rotation, fit.root_translation, len(found))
    low = float(np.percentile(ankle_z.min(axis=1), 5))
    offset = np.array([rt[frames[0], 0], rt[frames[0], 1], low - ground_ankle_z])
    return Motion(
        list(VIDEO_BONES), rot.astype(np.float32), rr.astype(np.float32), (rt - offset).astype(np.float32), fps
    )


@dataclass
class VideoMotion:
    """What `video_to_motion` made: the motion and what the run found."""

    motion: Motion
    detections: ClipDetections
    fit: MotionFit  # the detected frames only
    missing: list[tuple[int, int]]  # inclusive frame ranges with no person (filled)
    seconds: dict[str, float]  # wall time of "detect" and "fit"


def video_to_motion(
    clip: VideoClip,
    *,
    steps: int | None = None,
    detect_progress: Callable[[int, int | None], None] | None = None,
    fit_progress: Callable[[int, int], None] | None = None,
    lifter: PoseLifter | None = None,
    landmarks: str = DEFAULT_LANDMARKS,
) -> VideoMotion:
    """Steps 1-4 of the module doc; `lifter` a `nn.lifter.PoseLifter` (None: the shipped weights),
    `landmarks` MediaPipe's landmark model (io.detect). DlaInputError when no frame shows a person."""
    import time

    import torch

    from dlacli.body.keypoints import coco_keypoints
    from dlacli.body.model import get_body_model
    from dlacli.limits import VIDEO_FIT_STEPS
    from dlacli.stages.motion.fit import ANKLES, VIDEO_BONES, fit_motion

    t0 = time.perf_counter()
    det = detect_clip(clip, detect_progress, landmarks)
    t1 = time.perf_counter()
    frames = np.nonzero(det.found)[0]
    if len(frames) == 0:
        raise DlaInputError(clip.path, "no person found in any frame (MediaPipe Pose)")
    fit = fit_motion(
        det.keypoints[frames],
        det.landmarks[frames],
        frames,
        det.width,
        det.height,
        det.fps,
        steps=VIDEO_FIT_STEPS if steps is None else steps,
        progress=fit_progress,
        lifter=lifter,
    )
    model = get_body_model()
    with torch.no_grad():
        full = np.zeros((len(frames), model.num_bones, 3), np.float32)
        full[:, [model.bone_index(b) for b in VIDEO_BONES]] = fit.rotations
        ankle_z = []
        for s in range(0, len(frames), 64):
            out = model.forward(
                fit.phenotype,
                torch.from_numpy(full[s : s + 64]),
                torch.from_numpy(fit.root_rotation[s : s + 64]).float(),
                torch.from_numpy(fit.root_translation[s : s + 64]).float(),
            )
            ankle_z.append(coco_keypoints(out.vertices)[:, list(ANKLES), 2].numpy())
        ground = float(coco_keypoints(model.zero_pose().vertices)[0, list(ANKLES), 2].min())
    motion = to_motion(fit, det.found, det.fps, ground, np.concatenate(ankle_z))
    t2 = time.perf_counter()
    return VideoMotion(motion, det, fit, missing_ranges(det.found), {"detect": t1 - t0, "fit": t2 - t1})


def preview_frames(clip: VideoClip, result: VideoMotion, batch: int = 16) -> Iterator[np.ndarray]:
    """The clip's frames with the fitted body drawn over them (blue; grey where the frame had no
    person and the pose is interpolated), from the fit's camera; frames padded to multiples of 16."""
    import torch

    from dlacli.body.model import get_body_model
    from dlacli.render.raster import render_mesh
    from dlacli.stages.fit.photo import photo_camera
    from dlacli.stages.motion.fit import VIDEO_BONES

    model = get_body_model()
    fit, det = result.fit, result.detections
    frames = np.nonzero(det.found)[0]
    rot, rr, rt = fill_missing(frames, fit.rotations, fit.root_rotation, fit.root_translation, det.num_frames)
    full = np.zeros((det.num_frames, model.num_bones, 3), np.float32)
    full[:, [model.bone_index(b) for b in VIDEO_BONES]] = rot
    cam = photo_camera(det.width, det.height)
    pad_h, pad_w = -det.height % 16, -det.width % 16
    pending: list[np.ndarray] = []

    def flush() -> Iterator[np.ndarray]:
        s = start[0]
        sel = slice(s, s + len(pending))
        with torch.no_grad():
            verts = model.forward(
                fit.phenotype,
                torch.from_numpy(full[sel]),
                torch.from_numpy(rr[sel]).float(),
                torch.from_numpy(rt[sel]).float(),
            ).vertices.numpy()
        for j, frame in enumerate(pending):
            colour = PREVIEW_FITTED if det.found[s + j] else PREVIEW_FILLED
            rgba = render_mesh(verts[j], model.faces, np.tile(colour, (model.num_vertices, 1)), cam)[0]
            a = PREVIEW_ALPHA * rgba[..., 3:]
            out = frame.astype(np.float32) / 255.0 * (1 - a) + rgba[..., :3] * a
            yield np.pad(out, ((0, pad_h), (0, pad_w), (0, 0)))
        start[0] += len(pending)
        pending.clear()

    start = [0]
    for k, _, frame in clip:
        if k >= det.num_frames:
            break
        pending.append(frame)
        if len(pending) == batch:
            yield from flush()
    if pending:
        yield from flush()
