"""What the body fit says about itself (docs/fit.md "Result"): its record in transforms.json
(`fit_info`), the worst-joint warning (`fit_warning`) and the overlay of the fitted body on the
photo (`overlay_png`)."""

from __future__ import annotations

import numpy as np

from dlacli.body.keypoints import COCO_NAMES, COCO_SKELETON, MIN_CONF, NUM_KEYPOINTS, coco_keypoints
from dlacli.errors import DlaInputError
from dlacli.geometry import project_to_cameras
from dlacli.stages.fit.photo import FitResult
from dlacli.stages.fit.silhouette import silhouette

WORST_JOINT_WARN = 0.03  # dream warns when a confident keypoint is farther than this x the person's height


# ---------------------------------------------------------------------------------------------
# report


def fit_info(result: FitResult) -> dict:
    """The fit's record in transforms.json (`dream.fit`): reprojection_px, mask_iou and, when the
    per-joint errors are known, joint_error_pct (per COCO name, confident keypoints only, % of the
    person's height), worst_joint {name, pct} and the winning start."""
    info = {"reprojection_px": float(result.reprojection_px), "mask_iou": float(result.mask_iou)}
    if result.joint_error is not None:
        info["joint_error_pct"] = {
            COCO_NAMES[k]: round(100.0 * float(e), 2) for k, e in enumerate(result.joint_error) if np.isfinite(e)
        }
        name, err = result.worst_joint
        info["worst_joint"] = {"name": name, "pct": round(100.0 * err, 2)}
        info["start"] = result.start
    return info


def fit_warning(result: FitResult, threshold: float = WORST_JOINT_WARN) -> str | None:
    """A one-line warning when the worst confident keypoint is farther than `threshold` x the
    person's height from its fitted keypoint, else None."""
    name, err = result.worst_joint
    if not name or err <= threshold:
        return None
    return (
        f"warning: fit: {name} is {100.0 * err:.1f} % of the person's height from the detected keypoint; "
        "see fit_overlay.png"
    )


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
    fitted = project_to_cameras(coco_keypoints(result.vertices), result.camera)[0][0]
    for a, b in COCO_SKELETON:
        draw.line([tuple(fitted[a]), tuple(fitted[b])], fill=(255, 80, 80), width=max(1, r // 2))
    for k in range(NUM_KEYPOINTS):
        fx, fy = fitted[k]
        if given[k, 2] >= MIN_CONF:
            gx, gy = given[k, :2]
            draw.line([(gx, gy), (fx, fy)], fill=(255, 255, 0), width=1)
            draw.ellipse([gx - r, gy - r, gx + r, gy + r], fill=(0, 220, 0), outline=(0, 0, 0))
        draw.line([(fx - r, fy - r), (fx + r, fy + r)], fill=(255, 0, 0), width=max(1, r // 2))
        draw.line([(fx - r, fy + r), (fx + r, fy - r)], fill=(255, 0, 0), width=max(1, r // 2))
    name, err = result.worst_joint
    if name:  # a red ring around the worst detected keypoint, labelled with its name and error
        k = COCO_NAMES.index(name)
        gx, gy = given[k, :2]
        rr = 4 * r
        draw.ellipse([gx - rr, gy - rr, gx + rr, gy + rr], outline=(255, 0, 0), width=max(2, r // 2))
        draw.text((gx + rr + 2, gy - rr), f"{name} {100.0 * err:.1f} %", fill=(255, 0, 0))
    return np.asarray(pil, dtype=np.uint8)
