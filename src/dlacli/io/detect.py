"""Person mask and COCO-17 keypoints from a photo with MediaPipe Pose (optional extra "detect").

The only module that imports mediapipe, lazily inside `detect_person`. mediapipe 0.10.21's wheel
ships the BlazePose detector and the "full" landmark model (model_complexity=1) together with
the segmentation head, so this works offline; the "heavy" model (complexity 2) would be
downloaded at run time and is not used.

BlazePose gives 33 landmarks (normalised x, y, plus `visibility`); COCO-17 takes 17 of them
(`BLAZEPOSE_TO_COCO`), in pixels, with confidence = visibility.
"""

from __future__ import annotations

import numpy as np

from dlacli.errors import DlaInputError

# COCO-17 order -> BlazePose landmark index (nose, eyes, ears, shoulders, elbows, wrists, hips,
# knees, ankles; BlazePose's "left" is the person's left, as COCO's).
BLAZEPOSE_TO_COCO = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)

_MISSING = (
    "mediapipe is not installed: install the detect extra (pip install 'dla[detect]') "
    "or pass --mask / --keypoints"
)


def _import_mediapipe():
    try:
        import mediapipe as mp
    except ImportError:
        raise DlaInputError("--mask/--keypoints", _MISSING) from None
    return mp


def detect_person(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """image [H, W, 3] (float in [0, 1] or uint8) -> (mask [H, W] float32 in [0, 1],
    keypoints [17, 3] float32 (x, y, confidence) in pixels, COCO order).

    Raises DlaInputError when mediapipe is missing or when no person is found.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise DlaInputError("image", f"expected [H, W, 3], got {list(img.shape)}")
    if img.dtype != np.uint8:
        img = np.clip(np.asarray(img, dtype=np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(img)
    mp = _import_mediapipe()
    h, w = img.shape[:2]
    with mp.solutions.pose.Pose(
        static_image_mode=True, model_complexity=1, enable_segmentation=True
    ) as pose:
        result = pose.process(img)
    if result.pose_landmarks is None:
        raise DlaInputError("image", "no person found (pass --mask and --keypoints instead)")
    lms = result.pose_landmarks.landmark
    kp = np.zeros((len(BLAZEPOSE_TO_COCO), 3), np.float32)
    for k, i in enumerate(BLAZEPOSE_TO_COCO):
        kp[k] = (lms[i].x * w, lms[i].y * h, np.clip(lms[i].visibility, 0.0, 1.0))
    if result.segmentation_mask is None:  # pragma: no cover - enable_segmentation is set
        raise DlaInputError("image", "mediapipe returned no person mask")
    mask = np.clip(np.asarray(result.segmentation_mask, dtype=np.float32), 0.0, 1.0)
    return mask, kp
