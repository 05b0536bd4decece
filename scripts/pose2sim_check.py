"""`dla motion from-video` on a real recording with a reference (issue 40; docs/motion.md, "A real
four-camera check"): Pose2Sim's Demo_SinglePerson, one person filmed by four calibrated cameras
(1088 x 1920, 60 fps, Qualisys calibration; the pip package pose2sim, BSD-3-Clause). Nothing of it
is vendored and no test needs it; fetch it as a package:

  pip download --no-deps pose2sim==0.10.49 -d DIR
  unzip -q DIR/pose2sim-0.10.49-py3-none-any.whl 'Pose2Sim/Demo_SinglePerson/*' -d DIR
  PYTHONPATH=src python scripts/pose2sim_check.py DIR/Pose2Sim/Demo_SinglePerson [--landmarks full,heavy]

The reference: MediaPipe's COCO keypoints of the four videos (the tracker `motion from-video`
uses, with the heavy landmark model unless --reference says otherwise), undistorted and
triangulated per frame (weighted DLT over the cameras that see a joint with confidence >= 0.5,
at least three). The calibration file's conventions (which way its
rotation goes, the camera's axes) and each video's frame offset are not assumed: the choice with
the smallest reprojection error is taken and printed with that error. Then each camera alone:
`video_to_motion` on its video, the fitted motion posed on the default body, its COCO keypoints
(anny's regressor, the ones the fit matches) against the reference, per frame after a similarity
(PA-MPJPE) over shoulders, elbows, wrists, hips, knees and ankles; and the jitter (mean
acceleration) against the reference's. The reference carries MediaPipe's own errors, so this
measures how far one camera is from four, not from the truth.
"""

from __future__ import annotations

import argparse
import itertools
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

JOINTS = (5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16)  # COCO shoulders .. ankles
MIN_CONF = 0.5
MAX_OFFSET = 6  # frames searched for each video's offset against the first


def read_qca(path: Path) -> list[dict]:
    """Qualisys .qca.txt -> per camera: name, K [3, 3], distortion (k1, k2, k3, p1, p2), the
    transform's matrix R [3, 3] and position c [3] in metres, image size."""
    cams = []
    for cam in ET.parse(path).getroot().iter("camera"):
        fov = cam.find("fov_video").attrib
        tr = cam.find("transform").attrib
        it = cam.find("intrinsic").attrib
        left, top = float(fov["left"]), float(fov["top"])
        k = np.array(
            [
                [float(it["focalLengthU"]) / 64.0, 0.0, float(it["centerPointU"]) / 64.0 - left],
                [0.0, float(it["focalLengthV"]) / 64.0, float(it["centerPointV"]) / 64.0 - top],
                [0.0, 0.0, 1.0],
            ]
        )
        r = np.array([[float(tr[f"r{i}{j}"]) for j in (1, 2, 3)] for i in (1, 2, 3)])
        c = np.array([float(tr[a]) for a in "xyz"]) / 1000.0
        dist = [float(it[n]) for n in ("radialDistortion1", "radialDistortion2", "radialDistortion3")]
        dist += [float(it["tangentalDistortion1"]), float(it["tangentalDistortion2"])]
        size = (int(float(fov["right"]) - left + 1), int(float(fov["bottom"]) - top + 1))
        cams.append({"name": cam.attrib["serial"], "K": k, "dist": np.array(dist), "R": r, "c": c, "size": size})
    return cams


def undistort(px: np.ndarray, k: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Pixels [..., 2] -> normalised undistorted image coordinates [..., 2] (Brown-Conrady,
    radial k1-k3 and tangential p1, p2, inverted by fixed-point iteration)."""
    k1, k2, k3, p1, p2 = dist
    xd = (px[..., 0] - k[0, 2]) / k[0, 0]
    yd = (px[..., 1] - k[1, 2]) / k[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(20):
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2**3
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return np.stack([x, y], -1)


def world_to_camera(cam: dict, convention: tuple[bool, bool]) -> tuple[np.ndarray, np.ndarray]:
    """(R_wc, t) with X_cam = R_wc X + t, under one reading of the transform: its matrix or its
    transpose as the world-to-camera rotation, and the camera's axes flipped in y and z or not."""
    transpose, flip = convention
    r = cam["R"].T if transpose else cam["R"]
    if flip:
        r = np.diag([1.0, -1.0, -1.0]) @ r
    return r, -r @ cam["c"]


def triangulate(rays: np.ndarray, poses: list, weights: np.ndarray) -> np.ndarray:
    """Weighted DLT: normalised image points [C, 2] of cameras (R, t) -> the point [3]."""
    rows = []
    for (x, y), (r, t), w in zip(rays, poses, weights):
        p = np.hstack([r, t[:, None]])
        rows += [w * (x * p[2] - p[0]), w * (y * p[2] - p[1])]
    _, _, vt = np.linalg.svd(np.array(rows))
    return vt[-1, :3] / vt[-1, 3]


def reference(kps: list[np.ndarray], cams: list[dict], convention, offsets):
    """Triangulated COCO keypoints [T, 17, 3] (NaN where fewer than 3 cameras see a joint) and
    the median reprojection error in pixels."""
    poses = [world_to_camera(c, convention) for c in cams]
    t0 = max(0, *(-o for o in offsets))
    frames = min(len(k) - o for k, o in zip(kps, offsets)) - t0
    rays = [undistort(k[..., :2], c["K"], c["dist"]) for k, c in zip(kps, cams)]
    out = np.full((frames, 17, 3), np.nan)
    errs = []
    for f in range(frames):
        for j in range(17):
            idx = [f + t0 + o for o in offsets]
            conf = np.array([k[i, j, 2] for k, i in zip(kps, idx)])
            use = np.nonzero(conf >= MIN_CONF)[0]
            if len(use) < 3:
                continue
            pts = np.array([rays[c][idx[c], j] for c in use])
            x = triangulate(pts, [poses[c] for c in use], conf[use])
            for c in use:
                r, t = poses[c]
                z = r @ x + t
                if z[2] <= 0:
                    break
                errs.append(np.linalg.norm((z[:2] / z[2] - pts[list(use).index(c)]) * cams[c]["K"][0, 0]))
            else:
                out[f, j] = x
    return out, float(np.median(errs)) if errs else np.inf, t0


def pa_mpjpe(ours: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-frame error (metres) after the best similarity, over JOINTS, frames where the
    reference has all of them."""
    from dlacli.geometry import similarity_fit

    out = []
    for a, b in zip(ours, ref):
        a, b = a[list(JOINTS)], b[list(JOINTS)]
        if np.isnan(b).any():
            continue
        s, r, t = similarity_fit(a, b)
        out.append(np.linalg.norm(s * a @ r.T + t - b, axis=1).mean())
    return np.array(out)


def jitter(j: np.ndarray) -> float:
    j = j[:, list(JOINTS)]
    acc = j[2:] - 2 * j[1:-1] + j[:-2]
    return float(np.nanmean(np.linalg.norm(acc, axis=-1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("demo", type=Path, help="the Demo_SinglePerson folder")
    parser.add_argument("--landmarks", default="full", help="models to score, comma-separated (lite, full, heavy)")
    parser.add_argument("--reference", default="heavy", help="the model whose four views make the reference")
    args = parser.parse_args()

    from dlacli.body.keypoints import coco_keypoints
    from dlacli.body.model import get_body_model
    from dlacli.io.video import open_video
    from dlacli.stages.motion.video import detect_clip, video_to_motion

    cams = read_qca(next((args.demo / "calibration").glob("*.qca.txt")))
    videos = [args.demo / "videos" / f"{c['name']}.mp4" for c in cams]
    kps = [detect_clip(open_video(v), landmarks=args.reference).keypoints.astype(np.float64) for v in videos]

    best = None
    for convention in itertools.product((False, True), (False, True)):
        _, err, _ = reference(kps, cams, convention, [0] * len(cams))
        print(f"  transform transposed={convention[0]} axes flipped={convention[1]}: reprojection {err:.1f} px")
        if best is None or err < best[1]:
            best = (convention, err)
    convention = best[0]
    offsets = [0] * len(cams)
    for c in range(1, len(cams)):  # each video's frame offset against the first, one at a time
        trial = []
        for o in range(-MAX_OFFSET, MAX_OFFSET + 1):
            cand = offsets.copy()
            cand[c] = o
            trial.append((reference(kps, cams, convention, cand)[1], o))
        offsets[c] = min(trial)[1]
    ref, err, t0 = reference(kps, cams, convention, offsets)
    seen = ~np.isnan(ref[:, list(JOINTS)]).any(axis=(1, 2))
    print(
        f"reference ({args.reference} landmarks, frames per video {[len(k) for k in kps]}): transposed="
        f"{convention[0]} flipped={convention[1]}, offsets {offsets}, reprojection median {err:.1f} px, "
        f"{seen.sum()} of {len(ref)} frames with all 12 joints"
    )

    model = get_body_model()
    ref_jitter = jitter(ref)
    for landmarks in args.landmarks.split(","):
        for c, (cam, video) in enumerate(zip(cams, videos)):
            result = video_to_motion(open_video(video), landmarks=landmarks)
            verts = model.forward_motion({}, result.motion).vertices.numpy()
            ours = coco_keypoints(verts).astype(np.float64)
            start = t0 + offsets[c]
            n = min(len(ref), len(ours) - start)
            e = pa_mpjpe(ours[start : start + n], ref[:n])
            ratio = jitter(ours[start : start + n]) / ref_jitter
            print(
                f"{landmarks} {cam['name']}: PA-MPJPE mean {1000 * e.mean():.1f} mm, median "
                f"{1000 * np.median(e):.1f}, 90th percentile {1000 * np.percentile(e, 90):.1f} over {len(e)} frames; "
                f"jitter x{ratio:.2f} the reference's; detect {result.seconds['detect']:.1f} s, "
                f"fit {result.seconds['fit']:.1f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
