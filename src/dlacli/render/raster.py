"""Triangle rasterisation on the CPU (numba): UV-space maps, perspective z-buffer, mesh renders.

Conventions
- Images are row-major, y down; pixel (row y, column x) has its centre at (x + 0.5, y + 0.5) and
  is covered when that centre is inside the projected triangle. Centres exactly on an edge go to
  exactly one of the triangles sharing it (top-left rule, see `dlacli.triangle_kernels`).
- Cameras are `dlacli.types.Cameras`: world-to-camera in OpenCV axes (+Z forward), pinhole
  intrinsics fx, fy > 0, cx, cy (skew K[0, 1] is ignored).
- UV space: u to the right, v UP. Texel (row i, column j) of an R x R map has its centre at
  u = (j + 0.5) / R, v = 1 - (i + 0.5) / R, so row 0 is the top of the image (v near 1), as in
  any image file of the texture.
- Barycentrics b [..., 3] weight the face's corners faces[f, 0..2] and sum to 1; in the
  perspective rasteriser they are perspective-correct (they are those of the 3D point where the
  pixel's ray meets the triangle), so `interpolate` of world positions gives that 3D point.
- Empty pixels: face_id -1, bary 0, depth +inf.
- Near plane: points of a triangle closer than `near` (camera z) are clipped away per pixel,
  which equals clipping the triangle at z = near; triangles wholly behind it are skipped.
- Overlaps: the z-buffer keeps the nearest surface (equal depth: the lower face id). In UV
  space, where a layout's triangles overlap, the lowest face id wins.
- Degenerate (zero-area, or seen exactly edge-on) triangles cover nothing.

Outputs of the rasterisers are numpy arrays (this is a CPU, non-differentiable stage);
`interpolate` keeps torch inputs torch, so it is differentiable with respect to the attributes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dlacli import geometry
from dlacli.errors import DlaInputError
from dlacli.render import raster_kernels as rk
from dlacli.triangle_kernels import UVRaster, rasterize_uv  # noqa: F401  (re-exported: the UV raster)
from dlacli.triangle_kernels import as_array as _np
from dlacli.triangle_kernels import check_faces as _check_faces
from dlacli.triangle_kernels import is_int as _is_int
from dlacli.triangle_kernels import rasterize_triangles as _rasterize_triangles
from dlacli.types import Cameras

NEAR = 0.01  # metres


@dataclass
class Raster:
    """Per-camera visibility: the nearest face at each pixel centre."""

    face_id: np.ndarray  # [C, H, W] int32, -1 where empty
    bary: np.ndarray  # [C, H, W, 3] float32 perspective-correct barycentrics, 0 where empty
    depth: np.ndarray  # [C, H, W] float32 camera z (metres along the optical axis), +inf empty

    @property
    def mask(self) -> np.ndarray:
        return self.face_id >= 0  # [C, H, W] bool


# ----------------------------------------------------------------------------------- validation


def _check_points(x, name: str, dims: int) -> np.ndarray:
    arr = _np(x, name, np.float64)
    if arr.ndim not in (2, 3) or arr.shape[-1] != dims:
        want = f"[V, {dims}] or [C, V, {dims}]"
        raise DlaInputError(name, f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise DlaInputError(name, "contains NaN or infinite values")
    return arr


def _check_cameras(cameras) -> tuple[np.ndarray, np.ndarray]:
    """-> viewmats [C, 4, 4] float64, intr [C, 4] float64 (fx, fy, cx, cy)."""
    if not isinstance(cameras, Cameras):
        got = type(cameras).__name__
        raise DlaInputError("cameras", f"expected dlacli.types.Cameras, got {got}")
    if cameras.width < 1 or cameras.height < 1:
        size = f"{cameras.width}x{cameras.height}"
        raise DlaInputError("cameras", f"image size must be >= 1, got {size}")
    vm = _np(cameras.viewmats, "cameras.viewmats", np.float64)
    ks = _np(cameras.Ks, "cameras.Ks", np.float64)
    intr = np.stack([ks[:, 0, 0], ks[:, 1, 1], ks[:, 0, 2], ks[:, 1, 2]], axis=1)
    if not (np.all(np.isfinite(vm)) and np.all(np.isfinite(intr))):
        raise DlaInputError("cameras", "contains NaN or infinite values")
    if np.any(intr[:, :2] <= 0):
        raise DlaInputError("cameras.Ks", f"focal lengths must be > 0, got {intr[:, :2].tolist()}")
    return vm, np.ascontiguousarray(intr)


# ----------------------------------------------------------------------------------- core


def rasterize_camera_space(verts_cam, faces, Ks, width: int, height: int, *, near: float = NEAR) -> Raster:
    """Rasterise camera-space vertices (OpenCV axes) with pinhole intrinsics.

    verts_cam [C, V, 3] (or [V, 3] for one camera), faces [F, 3], Ks [C, 3, 3] (or [3, 3]).
    """
    verts_cam = _check_points(verts_cam, "verts_cam", 3)
    if verts_cam.ndim == 2:
        verts_cam = verts_cam[None]
    ks = _np(Ks, "Ks", np.float64)
    if ks.ndim == 2:
        ks = ks[None]
    if ks.ndim != 3 or ks.shape[1:] != (3, 3):
        raise DlaInputError("Ks", f"expected shape [C, 3, 3], got {list(ks.shape)}")
    if verts_cam.shape[0] != ks.shape[0]:
        if verts_cam.shape[0] != 1:
            raise DlaInputError("verts_cam", f"{verts_cam.shape[0]} vertex sets for {ks.shape[0]} cameras")
        verts_cam = np.broadcast_to(verts_cam, (ks.shape[0],) + verts_cam.shape[1:])
    intr = np.ascontiguousarray(np.stack([ks[:, 0, 0], ks[:, 1, 1], ks[:, 0, 2], ks[:, 1, 2]], 1))
    if np.any(intr[:, :2] <= 0):
        raise DlaInputError("Ks", f"focal lengths must be > 0, got {intr[:, :2].tolist()}")
    if int(width) < 1 or int(height) < 1:
        raise DlaInputError("width/height", f"image size must be >= 1, got {width}x{height}")
    if not near > 0:
        raise DlaInputError("near", f"must be > 0, got {near}")
    faces = _check_faces(faces, verts_cam.shape[1])
    face_id, bary, depth = _rasterize_triangles(verts_cam, faces, intr, int(width), int(height), float(near), False)
    return Raster(face_id, bary, depth)


def world_to_camera(vertices, viewmats) -> np.ndarray:
    """vertices [V, 3] or [C, V, 3] world, viewmats [C, 4, 4] -> [C, V, 3] float64 camera space
    (`dlacli.geometry.world_to_camera` in float64)."""
    return geometry.world_to_camera(np.asarray(vertices, np.float64), np.asarray(viewmats, np.float64))


def _camera_vertices(vertices, cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    vm, intr = _check_cameras(cameras)
    v = _check_points(vertices, "vertices", 3)
    if v.ndim == 3 and v.shape[0] != vm.shape[0]:
        raise DlaInputError("vertices", f"{v.shape[0]} vertex sets [C, V, 3] for {vm.shape[0]} cameras")
    return world_to_camera(v, vm), intr


def rasterize(vertices, faces, cameras: Cameras, *, near: float = NEAR) -> Raster:
    """Perspective z-buffer of a triangle mesh seen by C cameras (numba, parallel).

    vertices [V, 3] world (or [C, V, 3]: a different posed mesh per camera), faces [F, 3] int,
    cameras: dlacli.types.Cameras. Returns face_id [C, H, W], bary [C, H, W, 3], depth [C, H, W].
    """
    verts_cam, intr = _camera_vertices(vertices, cameras)
    if not near > 0:
        raise DlaInputError("near", f"must be > 0, got {near}")
    faces = _check_faces(faces, verts_cam.shape[1])
    face_id, bary, depth = _rasterize_triangles(
        verts_cam, faces, intr, int(cameras.width), int(cameras.height), float(near), False
    )
    return Raster(face_id, bary, depth)


def interpolate(attr, faces, face_id, bary):
    """Barycentric interpolation of per-vertex attributes at rasterised pixels.

    attr [V, D] (shared) or [C, V, D] (per camera), faces [F, 3], face_id [C, H, W] (or [H, W]),
    bary [C, H, W, 3] (or [H, W, 3]) -> [C, H, W, D] (or [H, W, D]); zero where face_id < 0.
    A torch `attr` gives a torch result (its dtype and device, differentiable in attr); numpy
    gives numpy (float64 for float64 input, else float32), computed by a numba kernel.
    """
    shape = lambda x: tuple(x.shape) if hasattr(x, "shape") else np.shape(x)  # noqa: E731
    a_shape, f_shape, b_shape = shape(attr), shape(face_id), shape(bary)
    if len(a_shape) not in (2, 3):
        raise DlaInputError("attr", f"expected shape [V, D] or [C, V, D], got {list(a_shape)}")
    if len(f_shape) not in (2, 3):
        raise DlaInputError("face_id", f"expected shape [C, H, W] or [H, W], got {list(f_shape)}")
    if b_shape != f_shape + (3,):
        raise DlaInputError("bary", f"expected shape {list(f_shape) + [3]}, got {list(b_shape)}")
    single = len(f_shape) == 2
    if len(a_shape) == 3 and a_shape[0] != (1 if single else f_shape[0]):
        raise DlaInputError("attr", f"{a_shape[0]} attribute sets for {f_shape[0]} cameras")
    fcs = _np(faces, "faces").astype(np.int64).reshape(-1, 3)
    fid = _np(face_id, "face_id").astype(np.int32)
    if fid.size and fid.max() >= fcs.shape[0]:
        raise DlaInputError("face_id", f"face id {fid.max()} >= {fcs.shape[0]} faces")
    fid = fid[None] if single else fid  # [C, H, W]
    if isinstance(attr, torch.Tensor):
        bar = torch.as_tensor(bary).reshape(fid.shape + (3,))
        out = _interpolate_torch(attr, fcs, fid, bar)
    else:
        bar = _np(bary, "bary", np.float32).reshape(fid.shape + (3,))
        out = _interpolate_numpy(_np(attr, "attr"), fcs, fid, bar)
    return out[0] if single else out


def _interpolate_torch(attr, faces, face_id, bary):
    """attr [V, D] or [C, V, D] tensor, faces [F, 3], face_id [C, H, W] -> [C, H, W, D] tensor."""
    dev = attr.device
    out = attr.new_zeros(face_id.shape + (attr.shape[-1],))
    if faces.shape[0] == 0:
        return out
    fid = torch.from_numpy(face_id).to(dev).long()
    valid = fid >= 0  # [C, H, W]
    corner = torch.from_numpy(faces).to(dev)[fid.clamp(min=0)]  # [C, H, W, 3] vertex ids
    w = bary.to(device=dev, dtype=attr.dtype) * valid[..., None]  # [C, H, W, 3]
    if attr.ndim == 2:
        vals = attr[corner]  # [C, H, W, 3, D]
    else:
        cam = torch.arange(fid.shape[0], device=dev)[:, None, None, None] % attr.shape[0]
        vals = attr[cam, corner]  # [C, H, W, 3, D]
    return (vals * w[..., None]).sum(dim=-2)


def _interpolate_numpy(attr, faces, face_id, bary):
    """attr [V, D] or [C, V, D], faces [F, 3], face_id [C, H, W] int32 -> [C, H, W, D]."""
    dtype = np.float64 if attr.dtype == np.float64 else np.float32
    a = np.ascontiguousarray(attr if attr.ndim == 3 else attr[None], dtype=dtype)
    out = np.zeros(face_id.shape + (a.shape[2],), dtype)
    if faces.shape[0]:
        rk.interpolate_np(
            a,
            np.ascontiguousarray(faces),
            np.ascontiguousarray(face_id),
            np.ascontiguousarray(bary),
            out,
        )
    return out


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals: vertices [V, 3] or [C, V, 3], faces [F, 3] -> same."""
    v = np.asarray(vertices, np.float64)
    batched = v.ndim == 3
    if not batched:
        v = v[None]
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    tri = v[:, faces]  # [C, F, 3, 3]
    fn = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])  # [C, F, 3], 2 x area
    out = np.zeros_like(v)  # [C, V, 3]
    for c in range(v.shape[0]):
        for k in range(3):
            np.add.at(out[c], faces[:, k], fn[c])
    norm = np.linalg.norm(out, axis=-1, keepdims=True)
    out = out / np.where(norm > 0, norm, 1.0)
    return out if batched else out[0]


def render_mesh(
    vertices,
    faces,
    vertex_colors,
    cameras: Cameras,
    *,
    antialias: int = 2,
    background=(0.0, 0.0, 0.0),
    shading: bool = True,
    ambient: float = 0.3,
    as_uint8: bool = False,
    near: float = NEAR,
) -> np.ndarray:
    """Render a vertex-coloured triangle mesh: -> RGBA [C, H, W, 4] (float32 in [0, 1] or uint8).

    vertices [V, 3] or [C, V, 3] world, faces [F, 3], vertex_colors [V, 3] (or [C, V, 3]) rgb in
    [0, 1] (uint8 is divided by 255), background rgb. Antialiasing: the image is rasterised at
    `antialias` x the resolution and box-filtered down, so edge pixels get fractional coverage;
    alpha is the covered fraction and rgb is composited over `background`. With shading, colours
    are scaled by a two-sided headlight Lambert term ambient + (1 - ambient) |n . l| with smooth
    (area-weighted vertex) normals n and l the direction to the camera.
    """
    if not _is_int(antialias) or antialias < 1:
        raise DlaInputError("antialias", f"expected an integer >= 1, got {antialias!r}")
    aa = int(antialias)
    bg = _np(background, "background", np.float32).reshape(-1)
    if bg.shape != (3,):
        raise DlaInputError("background", f"expected 3 values (rgb), got {bg.shape[0]}")
    col = _np(vertex_colors, "vertex_colors")
    col = col.astype(np.float32) / 255.0 if col.dtype == np.uint8 else col.astype(np.float32)
    verts = _check_points(vertices, "vertices", 3)
    if col.shape[-2:] != (verts.shape[-2], 3) or col.ndim not in (2, 3):
        raise DlaInputError("vertex_colors", f"expected shape [{verts.shape[-2]}, 3], got {list(col.shape)}")
    if col.ndim == 3 and col.shape[0] != len(cameras):
        raise DlaInputError("vertex_colors", f"{col.shape[0]} colour sets for {len(cameras)} cameras")
    if not 0.0 <= ambient <= 1.0:
        raise DlaInputError("ambient", f"must be in [0, 1], got {ambient}")
    _check_cameras(cameras)
    hi = cameras.resized(cameras.width * aa, cameras.height * aa)
    verts_cam, intr = _camera_vertices(verts, hi)
    faces = _check_faces(faces, verts_cam.shape[1])
    fid, bary, _ = _rasterize_triangles(verts_cam, faces, intr, hi.width, hi.height, float(near), False)
    normals = vertex_normals(verts_cam, faces)  # [C, V, 3] camera space
    colors = np.ascontiguousarray(col if col.ndim == 3 else col[None], dtype=np.float64)
    rgba = np.empty((len(cameras), cameras.height, cameras.width, 4), np.float32)
    rk.shade_downsample(
        colors,
        normals,
        verts_cam,
        faces,
        fid,
        bary,
        bg.astype(np.float64),
        float(ambient),
        bool(shading),
        aa,
        rgba,
    )
    if as_uint8:
        return np.round(rgba * 255.0).astype(np.uint8)
    return rgba


def visible_vertices(
    vertices,
    faces,
    cameras: Cameras,
    tol: float = 0.01,
    *,
    raster: Raster | None = None,
    near: float = NEAR,
) -> np.ndarray:
    """Which vertices each camera sees: -> [C, V] bool.

    vertices [V, 3] or [C, V, 3] world, faces [F, 3]. A vertex is visible when it is in front of
    the near plane, projects inside the image, and its camera depth is at most the z-buffer depth
    at the pixel containing it plus `tol` (metres). A pixel the mesh does not cover (depth +inf,
    e.g. a vertex on the silhouette) hides nothing. Pass `raster` to reuse a z-buffer computed
    with the same vertices, faces and cameras.
    """
    if not tol >= 0:
        raise DlaInputError("tol", f"must be >= 0, got {tol}")
    verts_cam, intr = _camera_vertices(vertices, cameras)
    if raster is None:
        faces = _check_faces(faces, verts_cam.shape[1])
        _, _, depth = _rasterize_triangles(verts_cam, faces, intr, cameras.width, cameras.height, float(near), False)
    else:
        depth = raster.depth
        if depth.shape != (len(cameras), cameras.height, cameras.width):
            raise DlaInputError("raster", f"depth shape {list(depth.shape)} does not match cameras")
    z = verts_cam[..., 2]  # [C, V]
    ks = _np(cameras.Ks, "cameras.Ks", np.float64)
    px = np.floor(geometry.camera_to_pixels(verts_cam, ks, max(float(near), geometry.DEPTH_EPS)))
    x, y = px[..., 0], px[..., 1]  # [C, V]; meaningless where z < near (masked below)
    inside = (z >= near) & (x >= 0) & (x < cameras.width) & (y >= 0) & (y < cameras.height)
    xi = np.where(inside, x, 0).astype(np.int64)
    yi = np.where(inside, y, 0).astype(np.int64)
    cam = np.arange(z.shape[0])[:, None]
    zbuf = depth[cam, yi, xi].astype(np.float64)  # [C, V]
    return inside & (z <= zbuf + tol)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a UV map: texture [R, R, D], uv [..., 2] (u right, v up; texel centres at
    u = (j + 0.5) / R, v = 1 - (i + 0.5) / R) -> [..., D]. Outside the map the border texel holds."""
    tex = np.asarray(texture)
    r = tex.shape[0]
    x = np.asarray(uv[..., 0], np.float64) * tex.shape[1] - 0.5
    y = (1.0 - np.asarray(uv[..., 1], np.float64)) * r - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    xa, xb = np.clip(x0, 0, tex.shape[1] - 1).astype(np.int64), np.clip(x0 + 1, 0, tex.shape[1] - 1).astype(np.int64)
    ya, yb = np.clip(y0, 0, r - 1).astype(np.int64), np.clip(y0 + 1, 0, r - 1).astype(np.int64)
    top = tex[ya, xa] * (1.0 - fx) + tex[ya, xb] * fx
    bottom = tex[yb, xa] * (1.0 - fx) + tex[yb, xb] * fx
    return (top * (1.0 - fy) + bottom * fy).astype(np.float32)


def render_textured(
    vertices,
    faces,
    uv,
    face_uv,
    texture,
    cameras: Cameras,
    *,
    antialias: int = 2,
    background=(0.0, 0.0, 0.0),
    near: float = NEAR,
) -> np.ndarray:
    """Render a UV-textured triangle mesh without shading: -> RGBA [C, H, W, 4] float32.

    vertices [V, 3] (or [C, V, 3]) world, faces [F, 3], uv [Vt, 2] texture coordinates, face_uv
    [F, 3] their indices per face corner (corner k of faces[f] has uv[face_uv[f, k]]), texture
    [R, R, 3] rgb in [0, 1] (row 0 = top = v near 1). Each covered sample of the `antialias` x
    supersampled image takes the bilinear texture value at its perspective-correct UV; the image
    is box-filtered down, alpha = the covered fraction, rgb composited over `background` (so with
    a black background rgb is premultiplied), as in `render_mesh`.
    """
    if not _is_int(antialias) or antialias < 1:
        raise DlaInputError("antialias", f"expected an integer >= 1, got {antialias!r}")
    tex = _np(texture, "texture", np.float32)
    if tex.ndim != 3 or tex.shape[2] != 3 or min(tex.shape[:2]) < 1:
        raise DlaInputError("texture", f"expected shape [R, R, 3], got {list(tex.shape)}")
    bg = _np(background, "background", np.float32).reshape(-1)
    if bg.shape != (3,):
        raise DlaInputError("background", f"expected 3 values (rgb), got {bg.shape[0]}")
    uvs = _check_points(uv, "uv", 2)
    fuv = _check_faces(face_uv, uvs.shape[0])
    aa = int(antialias)
    _check_cameras(cameras)
    hi = cameras.resized(cameras.width * aa, cameras.height * aa)
    verts_cam, intr = _camera_vertices(vertices, hi)
    faces = _check_faces(faces, verts_cam.shape[1])
    if fuv.shape != faces.shape:
        raise DlaInputError("face_uv", f"expected shape {list(faces.shape)}, got {list(fuv.shape)}")
    fid, bary, _ = _rasterize_triangles(verts_cam, faces, intr, hi.width, hi.height, float(near), False)
    covered = fid >= 0  # [C, Hh, Wh]
    px_uv = _interpolate_numpy(uvs.astype(np.float32), fuv, fid, bary)  # [C, Hh, Wh, 2]
    col = np.zeros(fid.shape + (3,), np.float32)
    col[covered] = sample_texture(tex, px_uv[covered])
    cov = covered.astype(np.float32)
    col = sum(col[:, i::aa, j::aa] for i in range(aa) for j in range(aa)) / float(aa * aa)  # box filter
    alpha = sum(cov[:, i::aa, j::aa] for i in range(aa) for j in range(aa)) / float(aa * aa)
    rgb = col + (1.0 - alpha[..., None]) * bg
    return np.concatenate([rgb, alpha[..., None]], axis=-1).astype(np.float32)
