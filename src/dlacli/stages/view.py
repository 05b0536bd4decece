"""View: an avatar (and a motion) -> one self-contained HTML page that splats and plays it.

The page (assets/viewer/viewer.html + viewer.js, docs/view.md) carries the avatar as an LBS rig
(stages/rig.py): rest-pose Gaussians, per-Gaussian joint weights and the joint matrices of every
frame, so its size is O(N) + O(J x T), never per-frame Gaussians. It skins, sorts and splats in
the browser (WebGL2). Everything is inline: the data is one gzip blob, base64 in a <script>
element, described by a JSON header ("dla.view/1"):

| array           | dtype    | shape        | stored as                                   | error bound           |
|-----------------|----------|--------------|---------------------------------------------|-----------------------|
| positions       | u16      | [N, 3]       | (x - min) / step, step = (max - min) / 65535 | step / 2 per axis     |
| quats           | i16      | [N, 4]       | round(32767 q), (w, x, y, z), renormalised   | 0.5 / 32767 per comp. |
| scales          | f16      | [N, 3]       | IEEE half                                   | 2^-11 rel. (normal range) |
| opacities       | u8       | [N]          | round(255 o)                                | 1 / 510               |
| rgb             | u8       | [N, 3]       | round(255 c)                                | 1 / 510               |
| joint_indices   | u8       | [N, K]       | into the used joints (meta.joint_names)     | exact                 |
| joint_weights   | u8       | [N, K]       | integers summing to 255 per row             | 1 / 255 per weight    |
| matrices        | f32      | [T, J, 3, 4] | top three rows of M_t,j (world from rest)    | exact (float32)       |

K is the rig's weights per Gaussian less the trailing slots that are zero everywhere; J counts
only the joints some Gaussian depends on. Without a motion the page holds one frame: the
avatar's own pose (body.json's pose, the pose `dla render` shows by default).
"""

from __future__ import annotations

import base64
import gzip
import json
import os
from importlib import resources

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.types import Avatar, Motion

FORMAT = "dla.view/1"
MAX_FRAMES = 36_000  # 20 minutes at 30 fps: T x J x 48 bytes of matrices (~180 MB for 104 joints)
CAMERA_AZIMUTH = 25.0  # degrees: the first view, as `dla animate`'s preview (three-quarter front)
CAMERA_ELEVATION = 8.0
CAMERA_FOV = 40.0  # vertical, degrees
FOLLOW_SECONDS = 0.5  # the orbit target follows the pelvis smoothed over this window
BACKGROUND = (0.1, 0.1, 0.1)
WEIGHT_SCALE = 255  # u8 weights: measured on the demo walk, skinned means move <= 0.37 mm (median 0.003)
ALIGN = 4  # every array starts at a multiple of 4 bytes (Float32Array views)


def pose_motion(avatar: Avatar, fps: float = 30.0) -> Motion:
    """The avatar's own pose (body.json) as a one-frame motion."""
    from dlacli.body.model import get_body_model, pose_to_rotations

    model = get_body_model()
    rot = pose_to_rotations(avatar.body.pose, "pose", model)[None]
    return Motion(
        bone_labels=list(model.bone_labels),
        rotations=rot,
        root_rotation=np.asarray(avatar.body.root_rotation, np.float32).reshape(1, 3),
        root_translation=np.asarray(avatar.body.root_translation, np.float32).reshape(1, 3),
        fps=float(fps),
    )


def _largest_remainder(weights: np.ndarray, total: int) -> np.ndarray:
    """Rows of non-negative weights [N, K] (rows sum to ~1) -> integers [N, K] summing to `total`
    per row, each within 1 of weight * total (largest-remainder rounding)."""
    w = np.clip(np.asarray(weights, np.float64), 0.0, None)
    w = w / w.sum(axis=1, keepdims=True)
    scaled = w * total
    base = np.floor(scaled).astype(np.int64)
    short = total - base.sum(axis=1)  # [N] units still to hand out, 0 <= short < K
    order = np.argsort(-(scaled - base), axis=1, kind="stable")
    ranks = np.empty_like(order)
    np.put_along_axis(ranks, order, np.arange(w.shape[1])[None].repeat(w.shape[0], 0), axis=1)
    return base + (ranks < short[:, None])


def pack_rig(rig, mats: np.ndarray) -> tuple[dict, bytes]:
    """Quantise a rig and its joint matrices [T, J, 4, 4] -> (JSON-able header, raw payload).

    See the module docstring for the layout and the error bounds."""
    n = len(rig)
    mats = np.asarray(mats, np.float32)
    if mats.ndim != 4 or mats.shape[1:] != (rig.num_joints, 4, 4):
        raise DlaInputError("mats", f"expected [T, {rig.num_joints}, 4, 4], got {list(mats.shape)}")
    weights_int = _largest_remainder(rig.joint_weights, WEIGHT_SCALE)  # [N, K]
    used_slots = np.nonzero(np.any(weights_int > 0, axis=0))[0]
    k = int(used_slots.max()) + 1 if used_slots.size else 1
    weights_int = weights_int[:, :k]
    indices = np.where(weights_int > 0, rig.joint_indices[:, :k], -1)
    used = np.unique(indices[indices >= 0])
    if used.size > 255:
        raise DlaInputError(
            "rig", f"{used.size} joints carry weight; the page stores joint indices in 8 bits (at most 255)"
        )
    remap = np.zeros(rig.num_joints, np.int64)
    remap[used] = np.arange(used.size)
    local = np.where(indices >= 0, remap[np.clip(indices, 0, None)], 0).astype(np.uint8)

    lo = rig.positions.min(axis=0).astype(np.float64)
    hi = rig.positions.max(axis=0).astype(np.float64)
    step = np.where(hi > lo, (hi - lo) / 65535.0, 1.0)
    positions = np.clip(np.rint((rig.positions - lo) / step), 0, 65535).astype(np.uint16)
    quats = rig.quats / np.linalg.norm(rig.quats, axis=1, keepdims=True)
    arrays = {
        "positions": positions,
        "quats": np.rint(np.clip(quats, -1, 1) * 32767).astype(np.int16),
        "scales": np.clip(rig.scales, 0, 65504).astype(np.float16),
        "opacities": np.rint(np.clip(rig.opacities, 0, 1) * 255).astype(np.uint8),
        "rgb": np.rint(np.clip(rig.rgb, 0, 1) * 255).astype(np.uint8),
        "joint_indices": local,
        "joint_weights": weights_int.astype(np.uint8),
        "matrices": np.ascontiguousarray(mats[:, used, :3, :]),  # [T, J, 3, 4]
    }
    dtypes = {np.uint8: "u8", np.uint16: "u16", np.int16: "i16", np.float16: "f16", np.float32: "f32"}
    specs, parts, offset = {}, [], 0
    for name, arr in arrays.items():
        arr = np.ascontiguousarray(arr)
        data = arr.astype(arr.dtype.newbyteorder("<"), copy=False).tobytes()
        specs[name] = {"dtype": dtypes[arr.dtype.type], "shape": list(arr.shape), "offset": offset}
        pad = (-len(data)) % ALIGN
        parts.append(data + b"\0" * pad)
        offset += len(data) + pad
    header = {
        "format": FORMAT,
        "gaussians": n,
        "k": k,
        "joints": int(used.size),
        "frames": int(mats.shape[0]),
        "joint_names": [rig.joint_names[j] for j in used],
        "position_min": lo.tolist(),
        "position_step": step.tolist(),
        "weight_scale": WEIGHT_SCALE,
        "arrays": specs,
    }
    return header, b"".join(parts)


def _initial_camera(rig, mats: np.ndarray, fps: float) -> dict:
    """An orbit camera that frames the body (its largest extent over a few sampled frames) around
    its centre at frame 0, and the path `follow` [T, 3] the orbit target moves along when the page
    follows the body: the pelvis (root joint) smoothed over FOLLOW_SECONDS, relative to frame 0,
    height held steady (as `dla animate`'s preview camera)."""
    from dlacli.geometry import framing_distance, smooth_path
    from dlacli.stages.rig import skin

    frames = np.unique(np.linspace(0, mats.shape[0] - 1, min(8, mats.shape[0])).round().astype(int))
    extent, centre = 0.1, None
    for t in frames:
        pos, _ = skin(rig, mats[t])
        lo, hi = pos.min(axis=0).astype(np.float64), pos.max(axis=0).astype(np.float64)
        extent = max(extent, hi[2] - lo[2], float(np.hypot(hi[0] - lo[0], hi[1] - lo[1])))
        if centre is None:
            centre = 0.5 * (lo + hi)
    root = int(np.argmax(rig.parents < 0))
    pelvis = (
        mats[:, root, :3, :3].astype(np.float64) @ rig.bind_transforms[root, :3, 3] + mats[:, root, :3, 3]
    )  # [T, 3]
    path = smooth_path(pelvis, fps, FOLLOW_SECONDS)
    follow = path - path[0]
    follow[:, 2] = 0.0
    return {
        "target": centre.tolist(),
        "distance": float(framing_distance(extent, CAMERA_FOV, margin=1.3)),
        "azimuth": CAMERA_AZIMUTH,
        "elevation": CAMERA_ELEVATION,
        "fov": CAMERA_FOV,
        "follow": np.round(follow, 5).tolist(),
    }


def page_html(header: dict, payload: bytes, title: str, fps: float, camera: dict, background=BACKGROUND) -> str:
    """The whole page: the template with the header, the gzip+base64 payload and the script."""
    assets = resources.files("dlacli") / "assets" / "viewer"
    template = (assets / "viewer.html").read_text(encoding="utf-8")
    script = (assets / "viewer.js").read_text(encoding="utf-8")
    meta = {
        **header,
        "title": title,
        "fps": float(fps),
        "camera": camera,
        "background": list(map(float, background)),
        "autoplay": header["frames"] > 1,
        "compression": "gzip",
    }
    meta_text = json.dumps(meta, separators=(",", ":")).replace("<", "\\u003c")  # never "</script>" inside
    blob = base64.b64encode(gzip.compress(payload, compresslevel=9, mtime=0)).decode("ascii")
    safe_title = title.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    out = template.replace("@@TITLE@@", f"dla view: {safe_title}").replace("@@META@@", meta_text)
    out = out.replace("@@SCRIPT@@", script)
    return out.replace("@@DATA@@", blob)  # last: base64 holds no placeholder


def view_page(
    avatar: Avatar,
    motion: Motion | None,
    n_gaussians: int | None = None,
    seed: int | None = None,
    where: str = "avatar",
    checkpoint: str | None = None,
    title: str = "avatar",
) -> str:
    """The page for an avatar and a motion (None: its own pose, one frame)."""
    from dlacli.stages.rig import build_rig, skinning_matrices

    mot = motion if motion is not None else pose_motion(avatar)
    if mot.num_frames > MAX_FRAMES:
        raise DlaInputError(
            "motion", f"{mot.num_frames} frames is more than a page holds ({MAX_FRAMES}): lower --fps or cut the motion"
        )
    rig = build_rig(avatar, n_gaussians, seed, where=where, checkpoint=checkpoint)
    mats = skinning_matrices(avatar, mot, where="motion")
    header, payload = pack_rig(rig, mats)
    return page_html(header, payload, title, mot.fps, _initial_camera(rig, mats, mot.fps))


def write_page(html: str, path: str | os.PathLike) -> None:
    """Write the page atomically."""
    from dlacli.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(html, encoding="utf-8")
