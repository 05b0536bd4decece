"""What the photo shows beyond the body (dream's body backend, docs/dream.md "Beyond the body").

The body backend displaces the fitted body along its normals by at most a part's clothing bound
(`texture.vertex_bounds`), so a hair bun, a hat's tip, curls or a skirt's hem that reach further
would be cut off in views 1-3. Those person pixels of the photo that the displaced body does not
cover become a layer: a thin 2.5D shell over just those pixels (`shell.shell_depths`: the mid
depth of the nearest body pixel, a round profile of thickness from the mask's local width),
reaching `JOIN_DIV` pixels into the body's silhouette so the two meet without a crack, coloured
from the photo in front and behind (as the shell backend colours what lies off the body), and
rendered together with the body in one z-buffer (`render_with_layer`).

The displaced body never matches the mask to the pixel, so a fringe one or two pixels wide runs
along most of the outline; an opening of radius max(1, res / OPEN_DIV) removes it, and what is
left must touch the body and hold at least (res / MIN_AREA_DIV)^2 pixels, or it is mask noise
(a shadow, a speck of background), and at most MAX_SHARE of the body's silhouette, or the mask
took the background (a rectangle, a wall): a bun or a hat's tip is small beside the body, and a
dress is already mostly within the clothing bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from dlacli.types import Cameras

OPEN_DIV = 256  # opening radius (px) = max(1, res // OPEN_DIV): 2 px at 512
MIN_AREA_DIV = 64  # a piece of the layer holds at least (res // MIN_AREA_DIV)^2 px: 64 at 512
JOIN_DIV = 256  # the layer reaches max(1, res // JOIN_DIV) px into the body's silhouette
MAX_SHARE = 0.25  # nor more than this share of the body's silhouette: a mask that took the background
MAX_HALF = 0.12  # metres: a layer is at most twice this deep
BLUR_DIV = 64  # its colours: the photo blurred by res / BLUR_DIV px (8 at 512)


@dataclass
class Layer:
    """The layer beyond the body of one photo."""

    pixels: np.ndarray  # [H, W] bool: the photo's person pixels it stands for (beyond the body)
    cover: np.ndarray  # [H, W] bool: the pixels its mesh covers (those and the join into the body)
    vertices: np.ndarray  # [2N, 3] world: front layer, then back layer (shell.shell_mesh)
    faces: np.ndarray  # [M, 3]
    uv: np.ndarray  # [2N, 2] where each vertex takes its colour in the photo (u right, v up)


def _disk(radius: int) -> np.ndarray:
    y, x = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return x * x + y * y <= radius * radius


def beyond_pixels(person: np.ndarray, body: np.ndarray) -> np.ndarray:
    """[H, W] bool: the person pixels (person [H, W] bool) beyond the body's silhouette (body
    [H, W] bool) that make the layer: the difference opened (the outline's fringe goes), each
    connected piece kept when it touches the body and is large enough (module docstring)."""
    res = person.shape[0]
    beyond = person & ~body
    beyond = ndimage.binary_opening(beyond, structure=_disk(max(1, res // OPEN_DIV)))
    if not beyond.any():
        return beyond
    labels, n = ndimage.label(beyond, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    touching = np.zeros(n + 1, bool)
    touching[labels[ndimage.binary_dilation(body, structure=np.ones((3, 3), bool)) & beyond]] = True
    keep = touching & (sizes >= max(1, res // MIN_AREA_DIV) ** 2) & (sizes <= MAX_SHARE * body.sum())
    keep[0] = False
    return keep[labels]


def layer_depths(person, pixels, cover, fid, fdepth, bdepth, focal: float):
    """Front and back camera depths [H, W] of the layer over `cover` (inf elsewhere).

    person / pixels / cover [H, W] bool: the mask, the layer's pixels beyond the body, and those
    with the join into the body; fid / fdepth / bdepth: the body's nearest face id and its nearest
    and farthest depths (`shell.body_depth_layers`); focal: fx in pixels. Each connected piece of
    the layer stands at one mid depth, the median mid depth of the body pixels it touches, so
    no piece is stretched in depth between two parts (a sheet); its half thickness is the
    shell's round profile (`shell.round_profile`), sqrt(d (2 r - d)) x INFLATE with d the distance
    to the mask's outline and r the largest d on the layer nearby (not on the body, whose
    inside would make a thin curl as thick as the torso), at most MAX_HALF."""
    from dlacli.stages.dream.shell import round_profile

    body = fid >= 0
    body_mid = np.where(body, (fdepth + bdepth) / 2.0, np.nan)
    labels, n = ndimage.label(cover, structure=np.ones((3, 3), bool))
    ring = ndimage.binary_dilation(pixels, structure=np.ones((3, 3), bool), iterations=2) & body & cover
    mid = np.full(person.shape, np.nan)
    for k in range(1, n + 1):
        piece = labels == k
        touch = body_mid[piece & ring]
        mid[piece] = np.median(touch if touch.size else body_mid[body])  # (a kept piece touches the body)
    half = np.minimum(round_profile(person, pixels, mid, focal), MAX_HALF)
    front = np.where(cover, mid - half, np.inf)
    back = np.where(cover, mid + half, np.inf)
    return front, back


def layer_mesh(alpha: np.ndarray, camera: Cameras, vertices: np.ndarray) -> Layer | None:
    """The layer of a framed photo: alpha [R, R] its mask, camera (the crop's), vertices [V, 3]
    the displaced body. None when nothing lies beyond the body."""
    from dlacli.body.model import get_body_model
    from dlacli.stages.dream.shell import body_depth_layers, shell_mesh

    person = alpha > 0.5
    fid, fdepth, _, bdepth = body_depth_layers(vertices, get_body_model().faces, camera)
    pixels = beyond_pixels(person, fid >= 0)
    if not pixels.any():
        return None
    join = max(1, person.shape[0] // JOIN_DIV)
    cover = person & ndimage.binary_dilation(pixels, structure=_disk(join + 1))
    front, back = layer_depths(person, pixels, cover, fid, fdepth, bdepth, float(camera.Ks[0, 0, 0]))
    verts, faces, ys, xs = shell_mesh(cover, front, back, camera)
    h, w = person.shape
    uv = np.stack([(xs + 0.5) / w, 1.0 - (ys + 0.5) / h], axis=1)
    return Layer(pixels=pixels, cover=cover, vertices=verts, faces=faces, uv=np.concatenate([uv, uv]))


def layer_colours(photo: np.ndarray, layer: Layer) -> np.ndarray:
    """[H, W, 3] the photo [H, W, 3] blurred over the layer's pixels beyond the body (sigma
    res / BLUR_DIV px, normalised, so neither the background nor the body's colour bleeds in),
    on the pixels its mesh covers: views 1-3 see the layer from angles the photo does not, where
    its detail would be stretched into streaks."""
    sigma = max(1.0, photo.shape[0] / BLUR_DIV)
    w = ndimage.gaussian_filter(layer.pixels.astype(np.float64), sigma)
    out = np.stack([ndimage.gaussian_filter(photo[..., c] * layer.pixels, sigma) for c in range(3)], -1)
    return np.where(layer.cover[..., None], out / np.maximum(w, 1e-12)[..., None], 0.0)


def render_with_layer(body: dict, layer: Layer, photo: np.ndarray, cameras: Cameras) -> np.ndarray:
    """RGBA [C, H, W, 4] (premultiplied) of a `texture.textured_body` and its layer from the
    cameras, in one z-buffer. The layer's colours come from the photo [R, R, 3], placed beside the
    body's UV map in one texture; the body's own lookups land on the same texels as in
    `texture.render_body`."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import render_textured

    m = get_body_model()
    tex = np.asarray(body["texture"], np.float32)
    r = tex.shape[0]
    img = layer_colours(np.asarray(photo, np.float64), layer).astype(np.float32)
    if img.shape[:2] != (r, r):
        img = ndimage.zoom(img, (r / img.shape[0], r / img.shape[1], 1), order=1, grid_mode=True, mode="nearest")
    texture = np.concatenate([tex, np.clip(img, 0.0, 1.0)], axis=1)  # [R, 2R, 3]: body map | photo
    nv, nt = len(body["vertices"]), len(m.uv)
    verts = np.concatenate([np.asarray(body["vertices"], np.float64), layer.vertices])
    faces = np.concatenate([m.faces, layer.faces + nv])
    uv = np.concatenate([np.asarray(m.uv, np.float64) * (0.5, 1.0), layer.uv * (0.5, 1.0) + (0.5, 0.0)])
    face_uv = np.concatenate([m.face_uv, layer.faces + nt])
    return render_textured(verts, faces, uv, face_uv, texture, cameras, antialias=2)
