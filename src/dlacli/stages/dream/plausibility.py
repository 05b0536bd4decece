"""Plausibility of dreamed views: sheets (mask beyond body + clothing) and streaks (colours
stretched along the photo camera's rays). docs/dream.md "Plausibility".

Both numbers compare a novel view with what the photo (view 0) itself shows, so clothes, hair and
striped fabric that the photo has are allowed and only what the views add is counted:

- `silhouette_excess` (sheets): the photo's mask spill beyond the fitted body's silhouette is
  measured per body part (the part of the nearest body pixel), as a robust percentile of the
  distance in metres at that part's depth; in view a, a pixel outside the body is allowed when it
  is within its nearest body part's allowance (converted back to pixels at that body pixel's depth
  in view a) plus an antialiasing margin. Excess = the view's mask area not allowed / the body's
  silhouette area in that view.
- `streak_fractions` (streaks): from the structure tensor of the view's luminance inside the person
  mask, the share of textured pixels whose texture is coherent (one dominant orientation) and runs
  along the photo camera's rays as seen from view a (the epipolar lines through the photo camera's
  centre), minus the photo's own share of coherent texture across that direction, floored at 0
  and weighted by how much of a ray view a sees (0 for the back view).
- `plausibility`: both per view and one number, the worst novel view's excess + streak (0 = plausible).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from dlacli.types import Cameras

ALLOWANCE_PERCENTILE = 97.0  # robust extent of the photo's clothing spill per body part
AA_MARGIN_PX = 2.0  # mask outlines are antialiased and the body raster samples pixel centres
ANALYSIS_RES = 256  # views are measured block-averaged to about this size (cost, fixed scales)
GRADIENT_SIGMA = 1.0  # px (at ANALYSIS_RES): luminance smoothing before differencing
TENSOR_SIGMA = 2.0  # px: integration scale of the structure tensor
TEXTURED = 0.01  # rms luminance gradient per pixel above which a pixel counts as textured
COHERENT = 0.6  # (l1 - l2) / (l1 + l2) above which the texture has one dominant orientation
BAND_DEG = 20.0  # the dominant gradient within this angle of the rays' normal: along the rays
MIN_TEXTURED = 0.1  # shares are taken over at least this fraction of the person's pixels
LUMA = np.array([0.299, 0.587, 0.114])


# ------------------------------------------------------------------------------- sheets


def _reduce(x: np.ndarray, k: int) -> np.ndarray:
    """[H, W, ...] -> block means over k x k (H, W cut to multiples of k)."""
    if k == 1:
        return x
    h, w = (x.shape[0] // k) * k, (x.shape[1] // k) * k
    x = np.asarray(x[:h, :w], np.float32)
    cols = x.reshape(h, w // k, k, *x.shape[2:]).sum(axis=2)
    return cols.reshape(h // k, k, w // k, *x.shape[2:]).sum(axis=1) / (k * k)


def to_analysis(images, masks, cameras: Cameras):
    """Views at about ANALYSIS_RES: images [A, H, W, 3] (or None), masks [A, H, W], cameras ->
    the same block-averaged by k = round(H / ANALYSIS_RES) (masks: covered fraction), with
    cameras for the k x k blocks (k = 1: unchanged). Bounds the cost and fixes the scales."""
    k = max(1, int(round(np.shape(masks)[1] / ANALYSIS_RES)))
    if k == 1:
        return images, np.asarray(masks), cameras
    m = np.stack([_reduce(x, k) for x in masks])
    im = None if images is None else np.stack([_reduce(x, k) for x in images])
    return im, m, cameras.resized(m.shape[2], m.shape[1], scale=1.0 / k)


def _body_raster(vertices: np.ndarray, cameras: Cameras):
    """-> (part [A, H, W] int, -1 off the body; depth [A, H, W] camera z, inf off the body)."""
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import face_parts
    from dlacli.render.raster import rasterize

    r = rasterize(vertices, get_body_model().faces, cameras)
    part = np.where(r.face_id >= 0, face_parts()[np.maximum(r.face_id, 0)], -1)
    return part, r.depth.astype(np.float64)


def _nearest_body(part: np.ndarray, depth: np.ndarray):
    """One view: -> (distance in px to the nearest body pixel [H, W], its part, its depth)."""
    body = part >= 0
    if not body.any():
        return np.full(part.shape, np.inf), np.full(part.shape, -1), np.full(part.shape, np.inf)
    d, (iy, ix) = ndimage.distance_transform_edt(~body, return_indices=True)
    return d, part[iy, ix], depth[iy, ix]


def part_allowance(
    mask: np.ndarray, part: np.ndarray, depth: np.ndarray, focal: float, n_parts: int, nearest=None
) -> np.ndarray:
    """The clothing the photo shows around each body part, in metres.

    mask [H, W] the photo's person mask (bool), part [H, W] body part of the fitted body's nearest
    surface (-1 off the body), depth [H, W] its camera z, focal fx in px -> [n_parts] metres: per
    part, the ALLOWANCE_PERCENTILE of the distance of the mask's pixels outside the body to their
    nearest body pixel of that part, times that pixel's depth / focal (0 where no spill)."""
    d, near, z = _nearest_body(part, depth) if nearest is None else nearest
    spill = mask & (part < 0) & (near >= 0)
    metres = d[spill] * z[spill] / focal
    owner = near[spill]
    out = np.zeros(n_parts)
    for k in np.unique(owner):
        out[k] = float(np.percentile(metres[owner == k], ALLOWANCE_PERCENTILE))
    return out


def silhouette_excess(masks: np.ndarray, cameras: Cameras, vertices: np.ndarray) -> np.ndarray:
    """How far each view's person mask goes beyond the fitted body plus the clothing the photo shows
    around each body part.

    masks [A, H, W] (view 0 the photo), cameras [A], vertices [V, 3] the fitted body -> [A] floats:
    the area of view a's mask outside the body's silhouette grown per part (each pixel outside the
    body is allowed up to its nearest part's `part_allowance`, in pixels at that body pixel's depth
    in view a, + AA_MARGIN_PX), as a fraction of the body's silhouette area in view a. Body pixels
    are never counted; a view without the body counts its whole mask. A sheet as wide as the body
    beside it scores ~1. Views of 1.5 ANALYSIS_RES or more are measured block-averaged (`to_analysis`).
    """
    from dlacli.body.regions import PARTS

    _, masks, cameras = to_analysis(None, masks, cameras)
    person = np.asarray(masks) > 0.5
    part, depth = _body_raster(vertices, cameras)
    fx = cameras.Ks[:, 0, 0].double().numpy()
    nearest = [_nearest_body(part[a], depth[a]) for a in range(len(person))]
    allowance = part_allowance(person[0], part[0], depth[0], float(fx[0]), len(PARTS), nearest[0])
    out = np.empty(len(person))
    for a in range(len(person)):
        d, near, z = nearest[a]
        limit = np.where(near >= 0, allowance[np.maximum(near, 0)] * fx[a] / z, 0.0) + AA_MARGIN_PX
        out[a] = float((person[a] & (part[a] < 0) & (d > limit)).sum()) / max(int((part[a] >= 0).sum()), 1)
    return out


# ------------------------------------------------------------------------------- streaks


def structure_tensor(lum: np.ndarray, person: np.ndarray):
    """Luminance [H, W] inside person [H, W] bool -> (valid [H, W] bool, energy, coherence, angle):
    the structure tensor J = G_TENSOR_SIGMA * (grad L grad L^T) of the luminance smoothed within the
    mask (GRADIENT_SIGMA, normalised convolution), with gradients taken only where both central-
    difference neighbours are person pixels, so the mask's outline adds no edge. energy = trace J
    (mean squared gradient), coherence = (l1 - l2) / (l1 + l2), angle = the dominant gradient's
    direction (radians, image x right, y down)."""
    m = person.astype(np.float64)
    w = ndimage.gaussian_filter(m, GRADIENT_SIGMA)
    smooth = ndimage.gaussian_filter(lum * m, GRADIENT_SIGMA) / np.maximum(w, 1e-9)
    gx = np.zeros_like(smooth)
    gy = np.zeros_like(smooth)
    gx[:, 1:-1] = (smooth[:, 2:] - smooth[:, :-2]) / 2.0
    gy[1:-1, :] = (smooth[2:, :] - smooth[:-2, :]) / 2.0
    ok = np.zeros_like(person)
    ok[1:-1, 1:-1] = person[1:-1, 1:-1] & person[1:-1, 2:] & person[1:-1, :-2] & person[2:, 1:-1] & person[:-2, 1:-1]
    okf = ok.astype(np.float64)
    norm = np.maximum(ndimage.gaussian_filter(okf, TENSOR_SIGMA), 1e-9)
    jxx, jxy, jyy = (ndimage.gaussian_filter(g * okf, TENSOR_SIGMA) / norm for g in (gx * gx, gx * gy, gy * gy))
    energy = jxx + jyy
    coherence = np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy**2) / np.maximum(energy, 1e-12)
    angle = 0.5 * np.arctan2(2.0 * jxy, jxx - jyy)
    return ok, energy, coherence, angle


def ray_normals(camera_a: Cameras, photo_camera: Cameras, shape) -> np.ndarray:
    """[H, W] angle (radians) of the normal to the photo camera's rays as seen from camera a, per
    pixel: the epipolar line through the pixel and the photo camera's centre projected into view a
    (homogeneous, so a centre at infinity or behind camera a works). shape (H, W) of camera a's image."""
    c0 = np.linalg.inv(photo_camera.viewmats[0].double().numpy())[:3, 3]  # photo camera centre, world
    vm = camera_a.viewmats[0].double().numpy()
    k = camera_a.Ks[0].double().numpy()
    e = k @ (vm[:3, :3] @ c0 + vm[:3, 3])  # homogeneous epipole in view a (analysis pixels)
    h, w = shape
    u = np.arange(w)[None, :] + 0.5
    v = np.arange(h)[:, None] + 0.5
    # line through (u, v, 1) and e: l = x cross e; its normal (l0, l1)
    return np.arctan2(e[0] - u * e[2], v * e[2] - e[1])


def _shares(valid, energy, coherence, angle, n_person: int):
    """-> (textured & coherent mask, denominator): shares are taken over the textured pixels, or
    MIN_TEXTURED of the person's pixels if fewer are textured."""
    textured = valid & (energy > TEXTURED**2)
    streaky = textured & (coherence > COHERENT)
    return streaky, max(int(textured.sum()), MIN_TEXTURED * n_person, 1.0)


def _streaky(image: np.ndarray, mask: np.ndarray):
    """-> (textured & coherent [H, W] bool, share denominator, dominant gradient angle [H, W])."""
    person = np.asarray(mask) > 0.5
    valid, energy, coherence, angle = structure_tensor(np.asarray(image, np.float64) @ LUMA, person)
    streaky, denom = _shares(valid, energy, coherence, angle, int(person.sum()))
    return streaky, denom, angle


def _within_band(angle: np.ndarray, direction) -> np.ndarray:
    """Axial angles (mod pi) within BAND_DEG of direction (scalar or per pixel)."""
    return np.abs((angle - direction + np.pi / 2) % np.pi - np.pi / 2) <= math.radians(BAND_DEG)


def photo_stripes(image: np.ndarray, mask: np.ndarray, direction: float) -> float:
    """The photo's own coherent texture across one image direction: the share of its textured
    person pixels with coherent texture whose dominant gradient lies within BAND_DEG of `direction`
    (radians): horizontal stripes on a shirt score high for direction pi/2 (a vertical gradient);
    isotropic texture scores about 2 BAND_DEG / 180 of its coherent share."""
    return _band_share(_streaky(image, mask), direction)


def _band_share(streaks, direction) -> float:
    streaky, denom, angle = streaks
    return float((streaky & _within_band(angle, direction)).sum()) / denom


def ray_streak_share(image: np.ndarray, mask: np.ndarray, camera_a: Cameras, photo_camera: Cameras):
    """-> (share, direction): the share of view a's textured person pixels whose coherent texture
    runs along the photo camera's rays (dominant gradient within BAND_DEG of the epipolar lines'
    normal), and the axial mean of that normal over the person (radians)."""
    streaky, denom, angle = _streaky(image, mask)
    normal = ray_normals(camera_a, photo_camera, angle.shape)
    person = np.asarray(mask) > 0.5
    direction = 0.5 * float(np.angle(np.exp(2j * normal[person]).mean())) if person.any() else 0.0
    return float((streaky & _within_band(angle, normal)).sum()) / denom, direction


def streak_fractions(images: np.ndarray, masks: np.ndarray, cameras: Cameras) -> np.ndarray:
    """[A] streak scores: per novel view a, `ray_streak_share` minus the photo's own share across
    the same direction (`photo_stripes`, at the rays' mean normal in view a: stripes a standing
    person's clothes have keep their image orientation under a turn about the vertical), floored at
    0, times the sine of the angle between view a's optical axis and the photo's: a stretch of
    depth d along the photo's rays is seen d sin(angle) long, so the back view (rays seen end-on,
    stretching invisible) scores 0 and the side views count fully. View 0 (the reference) scores 0.

    images [A, H, W, 3] straight colour in [0, 1], masks [A, H, W], cameras [A] (view 0 the photo)."""
    images, masks, cameras = to_analysis(images, masks, cameras)
    photo = Cameras(cameras.viewmats[:1], cameras.Ks[:1], cameras.width, cameras.height)
    axes = cameras.viewmats[:, 2, :3].double().numpy()  # optical axes (world)
    reference = _streaky(images[0], masks[0])
    out = np.zeros(len(images))
    for a in range(1, len(images)):
        seen = math.sqrt(max(0.0, 1.0 - float(axes[0] @ axes[a]) ** 2))  # sin of the angle between the axes
        if seen < 1e-3:
            continue
        cam = Cameras(cameras.viewmats[a : a + 1], cameras.Ks[a : a + 1], cameras.width, cameras.height)
        share, direction = ray_streak_share(images[a], masks[a], cam, photo)
        out[a] = seen * max(0.0, share - _band_share(reference, direction))
    return out


# ------------------------------------------------------------------------------- one number


def plausibility(images: np.ndarray, masks: np.ndarray, cameras: Cameras, vertices: np.ndarray) -> dict:
    """Sheets and streaks of a view set -> {"excess": [A], "streak": [A], "score": float} (rounded to
    4 decimals): score = max over the novel views (1..A-1) of excess + streak; 0 = plausible.

    images [A, H, W, 3], masks [A, H, W] (view 0 the photo), cameras [A], vertices [V, 3] the fitted
    body. Stored in transforms.json as `dla.dream.plausibility`."""
    images, masks, cameras = to_analysis(images, masks, cameras)
    excess = silhouette_excess(masks, cameras, vertices)
    streak = streak_fractions(images, masks, cameras)
    score = max((excess[a] + streak[a] for a in range(1, len(images))), default=0.0)
    return {
        "excess": [round(float(x), 4) for x in excess],
        "streak": [round(float(x), 4) for x in streak],
        "score": round(float(score), 4),
    }
