"""View folders: transforms.json (nerfstudio / instant-ngp convention) + images + body.json
(formats/views.md).

Cameras: pinhole, no distortion; transform_matrix is camera-to-world in OpenGL axes and is
converted with `Cameras.from_c2w_opengl`. Images: RGBA (alpha = person mask) or RGB/gray plus a
`mask_path`; 8- and 16-bit PNGs are scaled to [0, 1]. A frame's optional `trust_path` is a gray
image of its colour trust (`ViewSet.trust`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, one_line
from dlacli.io.atomic import atomic_dir
from dlacli.io.body import body_from_dict, body_to_dict
from dlacli.io.files import MAX_IMAGE_PIXELS, inside, open_image
from dlacli.io.validate import MAX_DISTANCE, as_array, as_float, check_format, check_magnitude, dump_json, load_json
from dlacli.types import BodyParams, Cameras, ViewSet

FORMAT = "dla.views/1"
TRANSFORMS = "transforms.json"
BODY = "body.json"
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")  # all read as a pinhole without distortion
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
INTRINSIC_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy")
LAYOUT = (TRANSFORMS, BODY, "images", "images/view_*.png", "images/trust_*.png")  # what write_views puts in a folder
MAX_FRAMES = 4096
MAX_TOTAL_PIXELS = 1 << 27  # all views together: 128 MP (2 GiB as float32 RGB + mask)
RIGID_TOL = 1e-3  # max |R^T R - I| and |det R - 1| accepted for a camera-to-world rotation


def _folder_of(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".json":
        return path.parent
    if not path.is_dir():
        raise DlaInputError(path, "not a view folder" if path.exists() else "no such view folder")
    return path


def read_transforms(folder: str | os.PathLike) -> dict[str, Any]:
    """Parse and check transforms.json without reading images.

    Returns {"c2w": [V, 4, 4] float64, "fx"/"fy"/"cx"/"cy": [V] float64, "width", "height",
    "file_paths": [V] str, "mask_paths": [V] str | None, "trust_paths": [V] str | None,
    "times": [V] int | None,
    "dla": the "dla" object without its format, "format": the dla.format found or None}.
    """
    folder = _folder_of(folder)
    where = folder / TRANSFORMS
    meta = load_json(where)
    if not isinstance(meta, dict):
        raise DlaInputError(where, f"expected a JSON object, found {type(meta).__name__}")
    dla = meta.get("dla", {})
    if not isinstance(dla, dict):
        raise DlaInputError(where, "'dla' must be an object")
    if "format" in dla:
        check_format(dla["format"], FORMAT, f"{where}:dla")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DlaInputError(where, "'frames' must be a non-empty list")
    _check_camera(meta, where, "top level")

    c2w, intr, file_paths, mask_paths, trust_paths, times = [], {k: [] for k in INTRINSIC_KEYS}, [], [], [], []
    for i, frame in enumerate(frames):
        at = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise DlaInputError(where, f"{at} is not an object")
        _check_camera(frame, where, at)
        for key in INTRINSIC_KEYS:
            if key not in frame and key not in meta:
                raise DlaInputError(where, f"{at}: missing '{key}' (neither in the frame nor at the top level)")
            value = as_float(frame.get(key, meta.get(key)), where, f"{at}.{key}")
            if value <= 0 and key not in ("cx", "cy"):
                raise DlaInputError(where, f"{at}.{key} = {value} must be > 0")
            if key in ("w", "h") and value != int(value):
                raise DlaInputError(where, f"{at}.{key} = {value} is not a whole number of pixels")
            intr[key].append(value)
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DlaInputError(where, f"{at}: missing '{key}'")
        file_paths.append(_rel_path(frame["file_path"], where, f"{at}.file_path"))
        mask_paths.append(_rel_path(frame["mask_path"], where, f"{at}.mask_path") if "mask_path" in frame else None)
        trust_paths.append(_rel_path(frame["trust_path"], where, f"{at}.trust_path") if "trust_path" in frame else None)
        c2w.append(_rigid(frame["transform_matrix"], where, f"{at}.transform_matrix"))
        times.append(_time(frame.get("time"), where, f"{at}.time"))

    sizes = sorted({(int(w), int(h)) for w, h in zip(intr["w"], intr["h"])})
    if len(sizes) > 1:
        raise DlaInputError(
            where,
            f"frames have different image sizes {one_line(', '.join(f'{w}x{h}' for w, h in sizes))}; all must be "
            "the same",
        )
    width, height = sizes[0]
    if width * height > MAX_IMAGE_PIXELS:
        raise DlaInputError(
            where,
            f"images of {width}x{height} pixels are larger than dla reads ({MAX_IMAGE_PIXELS / 1e6:.0f} megapixels)",
        )
    if len(frames) > MAX_FRAMES or len(frames) * width * height > MAX_TOTAL_PIXELS:
        raise DlaInputError(
            where,
            f"{len(frames)} frames of {width}x{height} are more than dla reads at once "
            f"(at most {MAX_FRAMES} frames and {MAX_TOTAL_PIXELS / 1e6:.0f} megapixels in all)",
        )
    return {
        "c2w": np.stack(c2w),
        "fx": np.array(intr["fl_x"]),
        "fy": np.array(intr["fl_y"]),
        "cx": np.array(intr["cx"]),
        "cy": np.array(intr["cy"]),
        "width": width,
        "height": height,
        "file_paths": file_paths,
        "mask_paths": mask_paths,
        "trust_paths": trust_paths,
        "times": times,
        "dla": {k: v for k, v in dla.items() if k != "format"},
        "format": dla.get("format"),
    }


def _check_camera(obj: dict, where: Path, at: str) -> None:
    model = obj.get("camera_model")
    if model is not None and model not in CAMERA_MODELS:
        raise DlaInputError(
            where,
            f"{at}: camera_model {excerpt(model)} is not supported (supported: {', '.join(CAMERA_MODELS)}, no "
            "distortion)",
        )
    for key in DISTORTION_KEYS:
        if key in obj and as_float(obj[key], where, f"{at}.{key}") != 0.0:
            raise DlaInputError(
                where, f"{at}: lens distortion {key} = {obj[key]} is not supported (undistort the images first)"
            )


def _rel_path(value: Any, where: Path, name: str) -> str:
    if not isinstance(value, str) or not value:
        raise DlaInputError(where, f"{name} must be a non-empty path string")
    return value


def _rigid(value: Any, where: Path, name: str) -> np.ndarray:
    m = as_array(value, (4, 4), where, name, np.float64)
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DlaInputError(where, f"{name} last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    r = m[:3, :3]
    det = float(np.linalg.det(r))
    if abs(det) < 1e-9:
        raise DlaInputError(where, f"{name} is not invertible (its rotation part has determinant {det:.3g})")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > RIGID_TOL or abs(det - 1.0) > RIGID_TOL:
        raise DlaInputError(
            where,
            f"{name} is not a rigid camera pose (rotation part: determinant {det:.4g}, max |R^T R - I| = {err:.3g})",
        )
    check_magnitude(m[:3, 3], MAX_DISTANCE, where, f"{name} translation", "m")
    return m


def _time(value: Any, where: Path, name: str) -> int | None:
    if value is None:
        return None
    t = as_float(value, where, name)
    if t != int(t) or t < 0:
        raise DlaInputError(where, f"{name} = {value} must be a non-negative integer motion frame index")
    return int(t)


def _resolve(folder: Path, rel: str, where: Path, name: str, allow_outside: bool = False) -> Path:
    """The image file `rel` names, inside `folder` (files.inside) unless `allow_outside`."""
    path = inside(folder, rel, where, name, allow_outside)
    if not os.path.lexists(path) and not Path(rel).suffix and os.path.lexists(folder / (rel + ".png")):
        path = inside(folder, rel + ".png", where, name, allow_outside)  # instant-ngp style paths without extension
    if not os.path.lexists(path):
        raise DlaInputError(path, f"image file not found ({name} in {where})")
    return path


def _decode(path: Path, width: int, height: int) -> tuple[np.ndarray, np.ndarray | None]:
    """An image file of `width` x `height` (checked before decoding) -> ([H, W, C] float32 in
    [0, 1] colour or gray, [H, W] alpha or None)."""
    try:
        with open_image(path) as im:
            if im.size != (width, height):
                raise DlaInputError(
                    path, f"image is {im.size[0]}x{im.size[1]} but transforms.json declares {width}x{height}"
                )
            im.load()
            mode = im.mode
            if (mode == "P" and "transparency" in im.info) or mode == "PA":
                im, mode = im.convert("RGBA"), "RGBA"
            elif mode in ("P", "1"):
                im, mode = im.convert("RGB" if mode == "P" else "L"), "RGB" if mode == "P" else "L"
            arr = np.asarray(im)
    except (OSError, ValueError, SyntaxError) as err:  # Pillow reports truncation and junk as OSError
        raise DlaInputError(path, f"not a readable image ({one_line(err)})") from None
    if mode in ("L", "LA", "RGB", "RGBA"):
        arr = arr.astype(np.float32) / 255.0
    elif mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grayscale PNG
        if mode == "I" and arr.size and (int(arr.min()) < 0 or int(arr.max()) > 65535):  # e.g. a 32-bit TIFF
            low, high = int(arr.min()), int(arr.max())
            raise DlaInputError(
                path,
                f"32-bit integer image with values {low} to {high}, outside the 16-bit range "
                "0-65535 that dla scales to [0, 1]",
            )
        arr = arr.astype(np.float32) / 65535.0
    else:
        raise DlaInputError(path, f"unsupported image mode {mode!r} (use 8- or 16-bit RGB(A), gray or gray+alpha)")
    if arr.ndim == 2:
        arr = arr[..., None]
    if mode in ("LA", "RGBA"):
        return arr[..., :-1], arr[..., -1]
    return arr, None


def _load_view(folder: Path, t: dict, i: int, where: Path, allow_outside: bool):
    """([H, W, 3] rgb, [H, W] mask, [H, W] colour trust or None) of frame i."""
    w, h = t["width"], t["height"]
    image_path = _resolve(folder, t["file_paths"][i], where, f"frames[{i}].file_path", allow_outside)
    colour, alpha = _decode(image_path, w, h)
    rgb = np.repeat(colour, 3, axis=-1) if colour.shape[-1] == 1 else colour
    mask_file = image_path
    if t["mask_paths"][i] is not None:
        mask_file = _resolve(folder, t["mask_paths"][i], where, f"frames[{i}].mask_path", allow_outside)
        gray, mask_alpha = _decode(mask_file, w, h)
        if mask_alpha is not None:
            alpha = mask_alpha
        elif gray.shape[-1] == 1:
            alpha = gray[..., 0]
        else:
            raise DlaInputError(mask_file, "a mask must be grayscale or carry an alpha channel, found RGB")
    if alpha is None:
        raise DlaInputError(
            image_path, "image has no alpha channel and its frame has no mask_path: the person mask is missing"
        )
    if not np.any(alpha > 0):
        raise DlaInputError(mask_file, "the person mask is empty (all zero)")
    trust = None
    if t["trust_paths"][i] is not None:
        trust_file = _resolve(folder, t["trust_paths"][i], where, f"frames[{i}].trust_path", allow_outside)
        gray, trust_alpha = _decode(trust_file, w, h)
        if trust_alpha is not None or gray.shape[-1] != 1:
            raise DlaInputError(trust_file, "a colour trust image must be grayscale without alpha")
        trust = gray[..., 0]
    return rgb, alpha, trust


def read_views(folder: str | os.PathLike, require_body: bool = True, allow_outside: bool = False) -> ViewSet:
    """Read a view folder (or its transforms.json path) into a ViewSet.

    With require_body=False a missing body.json is allowed and `ViewSet.body` is None; a body.json
    that is present is always validated. Image and mask paths must stay inside the folder
    (no absolute paths, no `..`, no links out of it) unless `allow_outside`.
    """
    return _read(folder, require_body, allow_outside)[1]


def view_files(folder: str | os.PathLike, allow_outside: bool = False) -> list[Path]:
    """Every file a view folder's reader opens (transforms.json, body.json, images, masks): the
    inputs that no output of the same command may replace."""
    folder = _folder_of(folder)
    t = read_transforms(folder)
    where = folder / TRANSFORMS
    files = [where, folder / BODY]
    if os.path.lexists(folder / BODY):
        inside(folder, BODY, folder / BODY, "the link", allow_outside)
    for i, rel in enumerate(t["file_paths"]):
        files.append(_resolve(folder, rel, where, f"frames[{i}].file_path", allow_outside))
    for key in ("mask_path", "trust_path"):
        for i, rel in enumerate(t[f"{key}s"]):
            if rel is not None:
                files.append(_resolve(folder, rel, where, f"frames[{i}].{key}", allow_outside))
    return files


def _load(folder: Path, require_body: bool, allow_outside: bool):
    """(transforms, body or None, images [V, H, W, 3] float32, masks [V, H, W] float32, colour trust
    [V, H, W] float32 or None when no frame has one): everything but the Cameras (whose tensors
    need torch; `summarize_views` does without them)."""
    where = folder / TRANSFORMS
    t = read_transforms(folder)
    body = _read_body(folder, require_body, allow_outside)
    images, masks, trusts = zip(*(_load_view(folder, t, i, where, allow_outside) for i in range(len(t["file_paths"]))))
    trust = None
    if any(x is not None for x in trusts):
        trust = np.stack([np.ones_like(m) if x is None else x for x, m in zip(trusts, masks)]).astype(np.float32)
    return t, body, np.stack(images).astype(np.float32), np.stack(masks).astype(np.float32), trust


def _read(folder: str | os.PathLike, require_body: bool, allow_outside: bool = False) -> tuple[dict[str, Any], ViewSet]:
    folder = _folder_of(folder)
    t, body, images, masks, trust = _load(folder, require_body, allow_outside)
    cameras = Cameras.from_c2w_opengl(t["c2w"], t["fx"], t["fy"], t["cx"], t["cy"], t["width"], t["height"])
    views = ViewSet(
        images=images,  # [V, H, W, 3]
        masks=masks,  # [V, H, W]
        cameras=cameras,
        body=body,
        file_paths=list(t["file_paths"]),
        times=list(t["times"]),
        extra=t["dla"],
        trust=trust,
    )
    return t, views


def _read_body(folder: Path, require: bool, allow_outside: bool = False) -> BodyParams | None:
    path = folder / BODY
    if os.path.lexists(path):  # a link out of the folder counts as reading outside it
        path = inside(folder, BODY, path, "the link", allow_outside)
    if not path.exists():
        if require:
            raise DlaInputError(path, "missing: a view folder needs the body parameters beside transforms.json")
        return None
    return body_from_dict(load_json(path), path)


def write_views(views: ViewSet, folder: str | os.PathLike) -> None:
    """Write `views` as a view folder (atomic as a whole): images/view_{i:03d}.png (RGBA, 8-bit,
    alpha = mask), images/trust_{i:03d}.png (8-bit gray) for each view whose colour trust is not 1
    everywhere, transforms.json, and body.json when `views.body` is set."""
    from PIL import Image

    images = np.asarray(views.images)  # [V, H, W, 3]
    masks = np.asarray(views.masks)  # [V, H, W]
    cams = views.cameras
    v, h, w = len(cams), cams.height, cams.width
    if v == 0:
        raise DlaInputError("views", "has no views")
    if images.shape != (v, h, w, 3):
        raise DlaInputError("views.images", f"has shape {images.shape}, expected ({v}, {h}, {w}, 3) from the cameras")
    if masks.shape != (v, h, w):
        raise DlaInputError("views.masks", f"has shape {masks.shape}, expected ({v}, {h}, {w})")
    trust = None if views.trust is None else np.asarray(views.trust)
    if trust is not None and trust.shape != (v, h, w):
        raise DlaInputError("views.trust", f"has shape {trust.shape}, expected ({v}, {h}, {w})")
    arrays = (("views.images", images), ("views.masks", masks), ("views.trust", trust))
    for name, arr in (a for a in arrays if a[1] is not None):
        if not np.all(np.isfinite(arr)):
            raise DlaInputError(name, "has non-finite values")
    for i in range(v):
        if not np.any(np.round(np.clip(masks[i], 0, 1) * 255) > 0):
            raise DlaInputError("views.masks", f"view {i} is empty (all zero after 8-bit rounding)")
    times = list(views.times) if views.times is not None else [None] * v
    if len(times) != v:
        raise DlaInputError("views.times", f"has {len(times)} entries for {v} views")

    ks = cams.Ks.detach().cpu().double().numpy()  # [V, 3, 3]
    c2w = cams.c2w_opengl()  # [V, 4, 4]
    for i in range(v):
        _rigid(c2w[i], "views.cameras", f"camera {i} camera-to-world")
    if not np.all(np.isfinite(ks)) or np.any(ks[:, [0, 1], [0, 1]] <= 0):
        raise DlaInputError("views.cameras", "intrinsics must be finite with positive focal lengths")
    intr = np.stack([ks[:, 0, 0], ks[:, 1, 1], ks[:, 0, 2], ks[:, 1, 2]], axis=1)  # [V, 4]
    names = ("fl_x", "fl_y", "cx", "cy")
    shared = bool(np.all(intr == intr[0]))
    meta: dict[str, Any] = {"camera_model": "OPENCV", "w": w, "h": h}
    if shared:
        meta.update({k: _f32(x) for k, x in zip(names, intr[0])})
    meta.update({"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    trust8 = None if trust is None else np.round(np.clip(trust, 0.0, 1.0) * 255.0).astype(np.uint8)
    frames = []
    for i in range(v):
        frame: dict[str, Any] = {"file_path": f"images/view_{i:03d}.png"}
        if trust8 is not None and (trust8[i] < 255).any():
            frame["trust_path"] = f"images/trust_{i:03d}.png"
        if not shared:
            frame.update({k: _f32(x) for k, x in zip(names, intr[i])})
        frame["transform_matrix"] = [[_f32(x) for x in row] for row in c2w[i]]
        if times[i] is not None:
            frame["time"] = int(times[i])
        frames.append(frame)
    meta["frames"] = frames
    meta["dla"] = {"format": FORMAT, **{k: val for k, val in (views.extra or {}).items() if k != "format"}}
    body = None
    if views.body is not None:
        body = body_to_dict(views.body)
        body_from_dict(body, "views.body")
    try:
        text = dump_json(meta) + "\n"
    except (TypeError, ValueError) as err:
        raise DlaInputError("views.extra", f"is not JSON-serialisable ({err})") from None

    with atomic_dir(folder) as tmp:
        (tmp / "images").mkdir()
        for i in range(v):
            rgba = np.concatenate([images[i], masks[i][..., None]], axis=-1)  # [H, W, 4]
            u8 = np.round(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8)
            Image.fromarray(u8, "RGBA").save(tmp / frames[i]["file_path"])
            if "trust_path" in frames[i]:
                Image.fromarray(trust8[i], "L").save(tmp / frames[i]["trust_path"])
        (tmp / TRANSFORMS).write_text(text, encoding="utf-8")
        if body is not None:
            (tmp / BODY).write_text(dump_json(body) + "\n", encoding="utf-8")


def _f32(x: float) -> float:
    """The shortest decimal that reads back as the same float32 (the cameras are float32)."""
    return float(str(np.float32(x)))


def summarize_views(folder: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of a view folder (works without body.json and says so; no torch)."""
    t, body, _, masks, trust = _load(_folder_of(folder), require_body=False, allow_outside=False)
    centres = t["c2w"][:, :3, 3]  # [V, 3]
    dist = np.linalg.norm(centres, axis=1)
    same = all(np.all(t[k] == t[k][0]) for k in ("fx", "fy", "cx", "cy"))
    intr = {k: (float(t[k][0]) if same else t[k].tolist()) for k in ("fx", "fy", "cx", "cy")}
    # per view, the share of the person's pixels whose colour is trusted (1 without trust images)
    trusted = [1.0] * len(masks)
    if trust is not None:
        trusted = [round(float((m * x).sum() / m.sum()), 4) for m, x in zip(masks, trust)]
    return {
        "kind": "views",
        "format": t["format"] or "nerfstudio transforms.json (no dla.format)",
        "views": len(masks),
        "width": t["width"],
        "height": t["height"],
        "intrinsics": intr,
        "shared_intrinsics": same,
        "camera_distance_min": float(dist.min()),
        "camera_distance_max": float(dist.max()),
        "times": t["times"],
        "mask_coverage": [round(float(m.mean()), 4) for m in masks],
        "colour_trust": trusted,
        "body": "present" if body is not None else "missing (body.json is required by dla lift)",
        "phenotype": None if body is None else dict(body.phenotype),
        "file_paths": t["file_paths"],
    }
