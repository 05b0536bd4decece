"""Read the input photo of `dla dream`: image, optional person mask, optional COCO keypoints.

`read_photo(path, mask_path=None, keypoints_path=None, notes=None)` ->
(image [H, W, 3] float32 rgb in [0, 1], mask [H, W] float32 in [0, 1] or None,
keypoints [17, 3] float32 (x, y, confidence) or None).

Rules (docs/fit.md):
- Any format Pillow reads; EXIF orientation is applied. Modes: 8- and 16-bit grey (L, I;16),
  grey + alpha (LA), palette (P, with or without a transparent index), RGB, RGBA, CMYK, 32-bit
  integer / float grey (I, F: scaled by the maximum of the type's usual range, 65535 / 1.0).
  Pillow reads 16-bit-per-channel colour PNGs at 8 bits per channel; that precision is kept.
- Colour is returned as stored (not composited over a background).
- Mask: from `mask_path` (any image, read as grey; its alpha channel when it has one) or else from
  the photo's alpha channel; an alpha channel that is entirely opaque (>= 254/255) is "no mask"
  (None). A mask with no pixel above 0.5 is an error ("empty mask"). The mask must have the
  photo's size.
- Size: each side must be >= 64 px (`MIN_SIDE`). Images whose longer side exceeds 8192 px
  (`MAX_SIDE`) are downscaled (Lanczos; the mask by area averaging) to exactly 8192 px on the
  longer side, the keypoints are scaled with them, and a note saying so is appended to `notes`.
  Pillow's decompression-bomb limit (about 179 megapixels) still applies and is reported as
  an error.
- Keypoints JSON (`read_coco_keypoints`): COCO annotation style, either
  {"keypoints": [x1, y1, v1, ..., x17, y17, v17]} or a list of such annotations (the one with
  the most visible points is used; ties: the first). x, y in pixels of the photo as stored on
  disk (continuous coordinates, the image's top-left corner at (0, 0)); v is COCO's visibility:
  0 = not labelled -> confidence 0; 1 (labelled, occluded) and 2 (visible) -> confidence 1.
  Optional "keypoints_3d": 51 numbers (17 x [x, y, z]), metres in MediaPipe's world-landmark
  frame (x right, y down, z away from the camera, origin anywhere, e.g. the hips), read by
  `read_coco_keypoints_3d`. Other keys are ignored.
Every problem raises DlaInputError naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError, one_line
from dlacli.io.files import decoding, open_image
from dlacli.io.validate import load_json

MIN_SIDE = 64
MAX_SIDE = 8192
MAX_KEYPOINT_PX = 1e6  # a keypoint farther off the image than this is a broken file, not a detection
NUM_KEYPOINTS = 17
MAX_LANDMARK_M = 10.0  # a 3D landmark farther than this from the hips is not a person's


def _open_image(path: Path):
    from PIL import ImageOps

    im = open_image(path)  # larger than MAX_SIDE is downscaled below; beyond ~67 MP refused here
    with decoding(path):
        im.load()
        return ImageOps.exif_transpose(im)


def _to_float(im, path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """PIL image -> (rgb [H, W, 3] float32 in [0, 1], alpha [H, W] float32 or None)."""
    mode = im.mode
    if mode == "P":
        im = im.convert("RGBA") if "transparency" in im.info else im.convert("RGB")
        mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        grey = np.asarray(im, dtype=np.float32) / 65535.0
        return np.repeat(grey[..., None], 3, axis=2), None
    if mode == "I":
        grey = np.asarray(im, dtype=np.float64)
        top = 65535.0 if grey.max(initial=0) <= 65535 else float(grey.max())
        grey = (np.clip(grey, 0, None) / top).astype(np.float32)
        return np.repeat(grey[..., None], 3, axis=2), None
    if mode == "F":
        grey = np.clip(np.asarray(im, dtype=np.float32), 0.0, 1.0)
        return np.repeat(grey[..., None], 3, axis=2), None
    if mode in ("1", "L"):
        grey = np.asarray(im.convert("L"), dtype=np.float32) / 255.0
        return np.repeat(grey[..., None], 3, axis=2), None
    if mode in ("LA", "La", "RGBA", "RGBa", "PA"):
        arr = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
        return np.ascontiguousarray(arr[..., :3]), np.ascontiguousarray(arr[..., 3])
    try:
        arr = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (ValueError, OSError) as exc:
        raise DlaInputError(path, f"unsupported image mode {mode!r} ({one_line(exc)})") from None
    return arr, None


def _read_mask_file(path: Path) -> np.ndarray:
    im = _open_image(path)
    rgb, alpha = _to_float(im, path)
    if alpha is not None and float(alpha.min()) < 254.0 / 255.0:
        return alpha
    return rgb.mean(axis=2).astype(np.float32)


def read_coco_keypoints(path: str | Path) -> np.ndarray:
    """COCO keypoints JSON (module docstring) -> [17, 3] float32 (x, y, confidence 0 or 1)."""
    return _read_annotation(Path(path))[0]


def read_coco_keypoints_3d(path: str | Path) -> np.ndarray | None:
    """The optional "keypoints_3d" of the annotation `read_coco_keypoints` picks: 51 numbers
    (17 x [x, y, z]) in metres, MediaPipe's world-landmark frame (x right, y down, z away from the
    camera) -> [17, 4] float32 (x, y, z, confidence of the 2D point), or None without the key."""
    path = Path(path)
    kp, ann, where = _read_annotation(path)
    if "keypoints_3d" not in ann:
        return None
    values = ann["keypoints_3d"]
    if not isinstance(values, list) or len(values) != 3 * NUM_KEYPOINTS:
        n = len(values) if isinstance(values, list) else type(values).__name__
        raise DlaInputError(path, f"{where}'keypoints_3d' must be a list of 51 numbers (17 x [x, y, z]), got {n}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        raise DlaInputError(path, f"{where}'keypoints_3d' must contain numbers only")
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
    except OverflowError:
        raise DlaInputError(path, f"{where}'keypoints_3d' holds a number too large for metres") from None
    if not np.all(np.isfinite(arr)):
        raise DlaInputError(path, f"{where}'keypoints_3d' contains NaN or infinite values")
    if np.abs(arr).max() > MAX_LANDMARK_M:
        raise DlaInputError(path, f"{where}'keypoints_3d' holds a coordinate beyond +-{MAX_LANDMARK_M:g} m")
    out = np.zeros((NUM_KEYPOINTS, 4), np.float32)
    out[:, :3] = arr
    out[:, 3] = kp[:, 2]
    return out


def _read_annotation(path: Path) -> tuple[np.ndarray, dict, str]:
    """-> (keypoints [17, 3], the chosen annotation, its "annotation i: " prefix for messages)."""
    data = load_json(path)
    anns = data if isinstance(data, list) else [data]
    if not anns:
        raise DlaInputError(path, "empty list: no person annotation")
    best, best_visible, best_ann, best_where = None, -1, None, ""
    for i, ann in enumerate(anns):
        where = f"annotation {i}: " if isinstance(data, list) else ""
        if not isinstance(ann, dict) or "keypoints" not in ann:
            raise DlaInputError(path, f"{where}expected an object with a 'keypoints' list")
        values = ann["keypoints"]
        if not isinstance(values, list) or len(values) != 3 * NUM_KEYPOINTS:
            n = len(values) if isinstance(values, list) else type(values).__name__
            raise DlaInputError(path, f"{where}'keypoints' must be a list of 51 numbers (17 x [x, y, v]), got {n}")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            raise DlaInputError(path, f"{where}'keypoints' must contain numbers only")
        try:
            arr = np.asarray(values, dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
        except OverflowError:  # a JSON integer of hundreds of digits
            raise DlaInputError(path, f"{where}'keypoints' holds a number too large for a pixel coordinate") from None
        if not np.all(np.isfinite(arr)):
            raise DlaInputError(path, f"{where}'keypoints' contains NaN or infinite values")
        if np.abs(arr[:, :2]).max() > MAX_KEYPOINT_PX:
            raise DlaInputError(path, f"{where}'keypoints' holds a coordinate beyond +-{MAX_KEYPOINT_PX:g} px")
        if not np.all(np.isin(arr[:, 2], (0, 1, 2))):
            raise DlaInputError(path, f"{where}visibility values must be 0, 1 or 2")
        visible = int((arr[:, 2] > 0).sum())
        if visible > best_visible:
            best, best_visible, best_ann, best_where = arr, visible, ann, where
    out = best.astype(np.float32)
    out[:, 2] = (best[:, 2] > 0).astype(np.float32)
    return out, best_ann, best_where


def _downscale(rgb, alpha, mask, keypoints, path: Path, notes):
    from PIL import Image

    h, w = rgb.shape[:2]
    s = MAX_SIDE / max(h, w)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))

    def resize(arr, resample):
        im = Image.fromarray(np.ascontiguousarray(arr, dtype=np.float32))
        return np.asarray(im.resize((nw, nh), resample), dtype=np.float32)

    rgb = np.clip(np.stack([resize(rgb[..., c], Image.LANCZOS) for c in range(3)], -1), 0.0, 1.0)
    if alpha is not None:
        alpha = np.clip(resize(alpha, Image.BOX), 0.0, 1.0)
    if mask is not None:
        mask = np.clip(resize(mask, Image.BOX), 0.0, 1.0)
    if keypoints is not None:
        keypoints = keypoints.copy()
        keypoints[:, 0] *= nw / w
        keypoints[:, 1] *= nh / h
    if notes is not None:
        notes.append(
            f"{path}: {w}x{h} px is larger than {MAX_SIDE} px: downscaled to {nw}x{nh} "
            "(mask and keypoints scaled with it)"
        )
    return rgb, alpha, mask, keypoints


def read_photo(
    path: str | Path,
    mask_path: str | Path | None = None,
    keypoints_path: str | Path | None = None,
    notes: list[str] | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """-> (image [H, W, 3] float32, mask [H, W] float32 or None, keypoints [17, 3] or None).

    See the module docstring for the rules; notes (e.g. downscaling) are appended to `notes`.
    """
    path = Path(path)
    rgb, alpha = _to_float(_open_image(path), path)
    h, w = rgb.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise DlaInputError(path, f"image is {w}x{h} px: need at least {MIN_SIDE} px on each side")
    mask = None
    if mask_path is not None:
        mask_path = Path(mask_path)
        mask = _read_mask_file(mask_path)
        if mask.shape != (h, w):
            raise DlaInputError(mask_path, f"mask is {mask.shape[1]}x{mask.shape[0]} px, the photo {w}x{h} px")
        where = mask_path
    else:
        if alpha is not None and float(alpha.min()) < 254.0 / 255.0:
            mask = alpha
        where = path
    if mask is not None and not np.any(mask > 0.5):
        raise DlaInputError(where, "empty mask: no person pixels (no mask/alpha value above 0.5)")
    keypoints = None
    if keypoints_path is not None:
        keypoints = read_coco_keypoints(keypoints_path)
        big = keypoints[:, 2] > 0
        span = 2.0 * max(h, w)
        if np.any(np.abs(keypoints[big, :2]) > span):
            raise DlaInputError(keypoints_path, f"keypoints lie far outside the {w}x{h} px photo (wrong image?)")
    if max(h, w) > MAX_SIDE:
        rgb, _, mask, keypoints = _downscale(rgb, None, mask, keypoints, path, notes)
    return rgb.astype(np.float32), mask, keypoints
