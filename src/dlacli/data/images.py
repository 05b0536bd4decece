"""RGBA images of a posed synthetic subject (docs/synth.md).

The dressed mesh (dlacli.data.garments) is rasterised with dlacli.render.raster at `SUPERSAMPLE` x
the resolution; every covered sub-pixel gets its procedural colour (dlacli.data.appearance), then a
shading term; sub-pixels are box-filtered down. Alpha is the covered fraction; rgb is the straight
(not premultiplied) colour, 0 where alpha is 0. Overlapping garment layers are ordered with a small
per-layer z-buffer bias (see `_render`).
"""

from __future__ import annotations

import numpy as np

from dlacli.data.appearance import Lighting, lit_terms, shade_colors
from dlacli.data.garments import DressedBody
from dlacli.types import Cameras

SUPERSAMPLE = 2
AMBIENT = 0.35


def render(
    body: DressedBody,
    verts: np.ndarray,
    cameras: Cameras,
    seed: int,
    chunk: int = 4,
    *,
    lighting: Lighting | None = None,
    ao: np.ndarray | None = None,
    light_view: np.ndarray | None = None,
) -> np.ndarray:
    """verts [V, 3] or [C, V, 3] -> RGBA [C, H, W, 4] float32 (straight alpha, see module doc),
    `chunk` cameras at a time (bounds the memory of the supersampled z-buffers). Appearance
    "albedo" when `lighting` is None, else "lit" with the per-vertex ao [V] or [C, V].
    `light_view` [3, 3] (lit only): a world-to-camera rotation; every camera then sees the lights
    as that camera sees them (they turn with the camera), instead of fixed in the world."""
    if lighting is not None and ao is None:
        raise ValueError("the lit appearance needs the ambient occlusion of the posed vertices")
    parts = []
    for s in range(0, len(cameras), chunk):
        cams = Cameras(cameras.viewmats[s : s + chunk], cameras.Ks[s : s + chunk], cameras.width, cameras.height)
        sub_ao = None if ao is None else (ao if ao.ndim == 1 else ao[s : s + chunk])
        sub_verts = verts if verts.ndim == 2 else verts[s : s + chunk]
        parts.append(_render(body, sub_verts, cams, seed, lighting, sub_ao, light_view))
    return np.concatenate(parts)


def _render(
    body: DressedBody,
    verts: np.ndarray,
    cameras: Cameras,
    seed: int,
    lighting: Lighting | None = None,
    ao: np.ndarray | None = None,
    light_view: np.ndarray | None = None,
) -> np.ndarray:
    from dlacli.render.raster import rasterize_camera_space, vertex_normals, world_to_camera

    light_view = None if light_view is None else np.asarray(light_view, np.float64)

    ss = SUPERSAMPLE
    ks = cameras.Ks.clone()
    ks[:, :2, :] *= ss
    hi = Cameras(cameras.viewmats, ks, cameras.width * ss, cameras.height * ss)
    c, h, w = len(cameras), hi.height, hi.width
    vcam = world_to_camera(verts, cameras.viewmats.double().numpy())  # [C, V, 3]
    normals = vertex_normals(vcam, body.faces)  # [C, V, 3]
    # Garment layers overlap by millimetres (a shoe's collar inside the trousers, the tights
    # under a suit): outer layers win the z-buffer within their bias. Sliding a vertex along
    # its camera ray changes its depth but not where it projects, so silhouettes are exact.
    dist = np.linalg.norm(vcam, axis=-1, keepdims=True)  # [C, V, 1]
    biased = vcam * (1.0 - body.depth_bias[None, :, None] / np.maximum(dist, 1e-9))
    ras = rasterize_camera_space(biased, body.faces, hi.Ks, hi.width, hi.height)
    out = np.zeros((c, cameras.height, cameras.width, 4), np.float32)
    for k in range(c):
        fid = ras.face_id[k].reshape(-1)
        cov = fid >= 0
        f, bary = fid[cov], ras.bary[k].reshape(-1, 3)[cov].astype(np.float64)
        corners = body.faces[f]  # [N, 3]
        rest = np.einsum("nk,nkd->nd", bary, body.rest[corners])
        uv = np.einsum("nk,nkd->nd", bary, body.face_uv[f])
        albedo = shade_colors(body, body.face_material[f], rest, uv, seed)
        n = np.einsum("nk,nkd->nd", bary, normals[k][corners])
        pt = np.einsum("nk,nkd->nd", bary, vcam[k][corners])
        norms = np.linalg.norm(n, axis=1) * np.linalg.norm(pt, axis=1)
        rgb = np.zeros((h * w, 3))
        if lighting is None:  # "albedo": a two-sided headlight
            lam = np.abs((n * pt).sum(1)) / np.maximum(norms, 1e-12)  # |cos| normal vs view ray
            rgb[cov] = albedo * (AMBIENT + (1.0 - AMBIENT) * lam)[:, None]
        else:  # "lit": camera-space normals, eye at the origin, the world's lights turned into the camera
            unit = lambda a: a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)  # noqa: E731
            occlusion = np.einsum("nk,nk->n", bary, (ao if ao.ndim == 1 else ao[k])[corners])
            turn = cameras.viewmats[k, :3, :3].double().numpy() if light_view is None else light_view
            diffuse, spec = lit_terms(
                body.face_material[f], unit(n), unit(-pt), occlusion, lighting, lighting.directions @ turn.T
            )
            rgb[cov] = np.clip(albedo * diffuse + spec, 0.0, 1.0)
        cover = cov.astype(np.float64).reshape(h, w)
        rgb = rgb.reshape(h, w, 3)
        pool = lambda a: a.reshape(cameras.height, ss, cameras.width, ss, -1).mean(axis=(1, 3))  # noqa: E731
        alpha = pool(cover[..., None])[..., 0]
        col = pool(rgb) / np.maximum(alpha, 1e-12)[..., None]
        out[k, ..., :3] = np.where(alpha[..., None] > 0, col, 0.0)
        out[k, ..., 3] = alpha
    return out
