"""Calibration harness of `dla motion from-video`'s fit (issue 24; docs/motion.md, "How well").

Renders synthetic clips of known motions (data.video.render_motion_video, 320 px, as the tests do),
caches MediaPipe's detections per clip, and reruns only the fit on them, printing PA-MPJPE per clip
and per joint (the test's 14 joints on the default body, per-frame similarity), the jitter ratio and
the fit's CPU seconds. Sets: `cal` the built-in motions x subject seeds 0-2; `shrug` idle and
turnaround with the clavicles lifted 0.15-0.55 rad; `rand` idle plus smooth random flexions of the
limbs, clavicles and spine (pose-diverse); `test` the held-out CMU clips of the tests (report only,
never tune on them); `val` eight clips of CMU subject 6 (held out of the pose lifter's training;
BVH files in $DLA_LIFTER_MOTIONS); `bn` twelve clips of the Bandai Namco Research Motion dataset
(CC BY-NC 4.0: evaluation only; `bash scripts/fetch-bandai-namco.sh DIR` and DLA_BANDAI=DIR),
each 2.5 s from the middle of the clip. `fit` prints PA-MPJPE, the jitter ratio and foot skating
(the fit's horizontal foot speed where the truth's foot is planted, against the truth's own).

  PYTHONPATH=src python scripts/video_fit_calibration.py prep cal
  PYTHONPATH=src python scripts/video_fit_calibration.py fit cal TAG

LANDMARKS=lite|full|heavy picks MediaPipe's landmark model (default full; each has its own cache of
detections, the rendered clips are shared).
"""

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

CACHE = Path(os.environ.get("DLA_CALIB_CACHE", "/tmp/dla-video-calib"))
CACHE.mkdir(parents=True, exist_ok=True)
LANDMARKS = os.environ.get("LANDMARKS", "full")
SUFFIX = "" if LANDMARKS == "full" else f"_{LANDMARKS}"  # the detections of each landmark model
TP = Path(__file__).resolve().parents[1] / "tests/data/third_party/motion"
MAJOR = (
    "upperleg01.L",
    "upperleg01.R",
    "lowerleg01.L",
    "lowerleg01.R",
    "foot.L",
    "foot.R",
    "upperarm01.L",
    "upperarm01.R",
    "lowerarm01.L",
    "lowerarm01.R",
    "wrist.L",
    "wrist.R",
    "neck01",
    "head",
)
SHORT = ("hipL", "hipR", "kneeL", "kneeR", "ankL", "ankR", "shL", "shR", "elbL", "elbR", "wrL", "wrR", "neck", "head")
CAL = [(m, s) for m in ("idle", "walk", "turnaround", "wave") for s in (0, 1, 2)]
RAND = [("rand1", 1), ("rand2", 2), ("rand3", 0), ("rand4", 1)]
SHRUG = [("idle_shrug", 3), ("turnaround_shrug", 5)]
TEST = [("131_01", 0), ("131_02", 0), ("01_01", 0)]
# the Bandai Namco clips (dataset-1_{content}_normal_001.bvh): motions that stay in the camera's view
BN_CLIPS = ("walk", "walk-back", "bow", "bye", "byebye", "call", "guide", "respond", "kick", "punch", "slash")
BN = [(f"bn_{c}", k % 3) for k, c in enumerate((*BN_CLIPS, "dance-short"))]
# CMU subject 006 (basketball dribbling), held out of the lifter's training motions: its validation
# set (BVH files from $DLA_LIFTER_MOTIONS, 2.5 s from the middle of each clip)
VAL = [
    ("cc006_02", 0), ("cc006_06", 1), ("cc006_14", 2), ("cc006_15", 0),
    ("cc006_03", 1), ("cc006_08", 2), ("cc006_10", 0), ("cc006_12", 1),
]  # fmt: skip


def rand_motion(k):
    """idle plus smooth random flexions of the limbs, spine and clavicles (a pose-diverse calibration clip)."""
    from scipy.spatial.transform import Rotation as R

    from dlacli.stages.motion.source import load_motion
    from dlacli.types import Motion

    m = load_motion("idle", fps=30)
    rng = np.random.default_rng(1000 + k)
    T = m.num_frames
    t = np.arange(T) / 30.0
    labels = list(m.bone_labels)
    rot = {b: R.from_rotvec(np.asarray(m.rotations[:, i], np.float64)) for i, b in enumerate(labels)}

    def osc(lo, hi):
        f = rng.uniform(0.15, 0.5)
        ph = rng.uniform(0, 2 * np.pi)
        return lo + (hi - lo) * 0.5 * (1 + np.sin(2 * np.pi * f * t + ph))

    spec = []
    for side, sg in (("L", 1.0), ("R", -1.0)):
        spec += [
            (f"upperleg01.{side}", osc(-1.0, 0.2), osc(-0.15, 0.15) * sg, osc(-0.2, 0.2)),
            (f"lowerleg01.{side}", osc(0.0, 1.3), 0, 0),
            (f"upperarm01.{side}", osc(-1.2, 0.5), sg * osc(-0.6, 0.5), osc(-0.4, 0.4)),
            (f"lowerarm01.{side}", osc(-0.2, 0.2), sg * osc(-1.3, 0.0), 0),
            (f"clavicle.{side}", 0, -sg * osc(0.0, 0.6), 0),
        ]
    spec += [("spine01", osc(-0.1, 0.4), osc(-0.1, 0.1), osc(-0.2, 0.2)), ("spine05", osc(0.0, 0.3), 0, 0)]
    for b, x, y, z in spec:
        e = np.stack([np.broadcast_to(np.asarray(a, np.float64), (T,)) for a in (x, y, z)], 1)
        r = R.from_euler("ZYX", e[:, ::-1])
        rot[b] = r * rot[b] if b in rot else r
    labels = list(rot)
    rr = np.asarray(m.root_rotation, np.float64).copy()
    rr[:, 2] += osc(-0.8, 0.8)
    return Motion(
        labels,
        np.stack([rot[b].as_rotvec() for b in labels], 1).astype(np.float32),
        rr.astype(np.float32),
        np.asarray(m.root_translation, np.float32),
        m.fps,
    )


def truth_motion(name):
    from dlacli.stages.motion.source import load_motion

    if name.startswith("rand"):
        return rand_motion(int(name[4:]))
    if name.endswith("_shrug"):
        from dlacli.types import Motion

        m = load_motion(name[:-6], fps=30)
        labels = list(m.bone_labels)
        rot = np.asarray(m.rotations, np.float32).copy()
        T = rot.shape[0]
        ph = np.linspace(0, 2 * np.pi, T)
        lift = (0.35 + 0.2 * np.sin(ph)).astype(np.float32)  # 0.15-0.55 rad, slowly varying
        for side, sg in (("L", -1.0), ("R", 1.0)):
            c = np.zeros((T, 1, 3), np.float32)
            c[:, 0, 1] = sg * lift
            labels.append(f"clavicle.{side}")
            rot = np.concatenate([rot, c], 1)
            ua = f"upperarm01.{side}"
            if ua in labels:
                rot[:, labels.index(ua), 1] -= sg * lift
            else:
                u = np.zeros((T, 1, 3), np.float32)
                u[:, 0, 1] = -sg * lift
                labels.append(ua)
                rot = np.concatenate([rot, u], 1)
        return Motion(labels, rot, m.root_rotation, m.root_translation, m.fps)
    if name in ("idle", "walk", "turnaround", "wave"):
        return load_motion(name, fps=30)
    if name.startswith(("cc", "bn_")):
        from dlacli.types import Motion

        if name.startswith("bn_"):
            m = load_motion(Path(os.environ["DLA_BANDAI"]) / f"dataset-1_{name[3:]}_normal_001.bvh", fps=30)
        else:
            m = load_motion(Path(os.environ["DLA_LIFTER_MOTIONS"]) / f"{name[2:]}.bvh", fps=30)
        lo = max(0, (m.num_frames - 75) // 2)
        sl = slice(lo, lo + 75)
        return Motion(list(m.bone_labels), m.rotations[sl], m.root_rotation[sl], m.root_translation[sl], m.fps)
    f = {"131_01": "131_01.bvh", "131_02": "131_02.bvh", "01_01": "cmu_01_01.bvh"}[name]
    return load_motion(TP / f, fps=30)


def prep(name, seed):
    out = CACHE / f"{name}_s{seed}{SUFFIX}.npz"
    if out.exists():
        return
    from dlacli.data.video import render_motion_video
    from dlacli.io.video import open_video
    from dlacli.stages.motion import video as mv

    truth = truth_motion(name)
    video = CACHE / f"{name}_s{seed}.mp4"
    t0 = time.process_time()
    if not video.exists():
        render_motion_video(truth, video, res=320, seed=seed)
    t1 = time.process_time()
    # detection, also keeping MediaPipe's raw 33 landmarks (image x,y,z,vis,pres and world)
    from dlacli.io import detect as D

    raw_img, raw_world = [], []
    orig = D._detection

    def spy(result, h, w):
        if result.pose_landmarks is not None:
            raw_img.append([(lk.x, lk.y, lk.z, lk.visibility, lk.presence) for lk in result.pose_landmarks.landmark])
        else:
            raw_img.append(np.zeros((33, 5)).tolist())
        if getattr(result, "pose_world_landmarks", None) is not None:
            wl = result.pose_world_landmarks.landmark
            raw_world.append([(lk.x, lk.y, lk.z, lk.visibility, lk.presence) for lk in wl])
        else:
            raw_world.append(np.zeros((33, 5)).tolist())
        return orig(result, h, w)

    D._detection = spy
    det = mv.detect_clip(open_video(video), landmarks=LANDMARKS)
    D._detection = orig
    t2 = time.process_time()
    np.savez(
        out,
        keypoints=det.keypoints,
        landmarks=det.landmarks,
        found=det.found,
        width=det.width,
        height=det.height,
        fps=det.fps,
        times=det.times,
        raw_img=np.array(raw_img),
        raw_world=np.array(raw_world),
    )
    print(
        f"prep {name} s{seed} {LANDMARKS}: {truth.num_frames} frames render {t1 - t0:.1f}s detect {t2 - t1:.1f}s",
        flush=True,
    )


def load_det(name, seed):
    from dlacli.stages.motion.video import ClipDetections, unswap_left_right

    z = np.load(CACHE / f"{name}_s{seed}{SUFFIX}.npz")
    # the cache holds the tracked, cleaned detections; what `detect_clip` does after them:
    kps, lms, unswapped = unswap_left_right(z["keypoints"], z["landmarks"], z["found"], float(z["fps"]))
    det = ClipDetections(
        kps, lms, z["found"], int(z["width"]), int(z["height"]), float(z["fps"]), z["times"], [], unswapped
    )
    return det, z


def major_joints(motion):
    from dlacli.body.model import get_body_model

    model = get_body_model()
    return model.forward_motion({}, motion).bone_heads.numpy()[:, [model.bone_index(b) for b in MAJOR]]


def pa_err(fit, truth):
    from dlacli.geometry import similarity_fit

    out = []
    for a, b in zip(fit, truth):
        s, r, t = similarity_fit(a, b)
        out.append(np.linalg.norm(s * a @ r.T + t - b, axis=1))
    return np.array(out)  # [T, J]


def jitter(j):
    return float(np.linalg.norm(j[2:] - 2 * j[1:-1] + j[:-2], axis=-1).mean())


def skating(jf, jt, fps=30.0):
    """(fit, truth) mean horizontal speed (m/s) of the feet where the truth's foot is planted
    (slower than 0.3 m/s, within 5 cm of its lowest height), as the tests measure it."""
    ft, ff = jt[:, [4, 5]], jf[:, [4, 5]]
    planted = (np.linalg.norm(ft[1:] - ft[:-1], axis=-1) * fps < 0.3) & (ft[:-1, :, 2] < ft[..., 2].min() + 0.05)
    if not planted.any():
        return float("nan"), float("nan")
    speed = lambda f: float((np.linalg.norm(f[1:, :, :2] - f[:-1, :, :2], axis=-1) * fps)[planted].mean())  # noqa: E731
    return speed(ff), speed(ft)


def run_fit(name, seed, steps=None):
    from dlacli.nn import lifter
    from dlacli.stages.motion import fit as mf
    from dlacli.stages.motion import video as mv

    mf.LIMB_SOURCE = os.environ.get("LIMB_SOURCE", mf.LIMB_SOURCE)
    if os.environ.get("LIFTER"):
        lifter.WEIGHTS = Path(os.environ["LIFTER"])

    det, z = load_det(name, seed)
    orig = mv.detect_clip
    mv.detect_clip = lambda clip, progress=None, landmarks=None: det
    try:
        t0 = time.process_time()
        res = mv.video_to_motion(None, steps=steps)
        cpu = time.process_time() - t0
    finally:
        mv.detect_clip = orig
    truth = truth_motion(name)
    jt, jf = major_joints(truth), major_joints(res.motion)
    e = pa_err(jf, jt)
    return e, (jitter(jf), jitter(jt)), cpu, skating(jf, jt)


def main():
    cmd = sys.argv[1]
    sets = {
        "cal": CAL,
        "test": TEST,
        "all": CAL + TEST,
        "shrug": SHRUG,
        "cal2": CAL + SHRUG,
        "rand": RAND,
        "cal3": CAL + SHRUG + RAND,
        "val": VAL,
        "bn": BN,
    }
    which = sets[sys.argv[2]] if len(sys.argv) > 2 else CAL
    if cmd == "prep":
        for n, s in which:
            prep(n, s)
    elif cmd == "fit":
        import torch

        torch.set_num_threads(1)
        tag = sys.argv[3] if len(sys.argv) > 3 else "run"
        steps = int(os.environ.get("STEPS", "0")) or None
        rows, per = [], []
        for n, s in which:
            e, (jit_f, jit_t), cpu, skate = run_fit(n, s, steps)
            jr = jit_f / jit_t
            rows.append((n, s, e.mean(), jr, cpu, *skate, float(np.percentile(e.mean(1), 90)), jit_f, jit_t))
            per.append(e.mean(0))
            print(
                f"{n:10s} s{s} {1000 * e.mean():6.1f} mm  p90 {1000 * rows[-1][-3]:5.1f}  jitter x{jr:.2f} "
                f"({1000 * jit_f:.1f}/{1000 * jit_t:.1f} mm/frame²)  "
                f"skate {skate[0]:.2f}/{skate[1]:.2f} m/s  cpu {cpu:.1f}s  | "
                + " ".join(f"{k}:{1000 * v:.0f}" for k, v in zip(SHORT, e.mean(0))),
                flush=True,
            )
        m = np.mean([r[2] for r in rows])
        print(
            f"== {tag}: mean {1000 * m:.1f} mm, max jitter x{max(r[3] for r in rows):.2f}, per joint: "
            + " ".join(f"{k}:{1000 * v:.0f}" for k, v in zip(SHORT, np.mean(per, 0))),
            flush=True,
        )
        with open(CACHE / "log.jsonl", "a") as f:
            f.write(
                json.dumps(
                    {
                        "tag": tag,
                        "set": sys.argv[2],
                        "rows": [(r[0], r[1], *(float(x) for x in r[2:])) for r in rows],
                    }
                )
                + "\n"
            )


if __name__ == "__main__":
    main()
