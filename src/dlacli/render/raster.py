"""Triangle rasterisation on the CPU (numba): UV-space maps, perspective z-buffer, mesh renders.

Conventions
- Images are row-major, y down; pixel (row y, column x) has its centre at (x + 0.5, y + 0.5) and
  is covered when that centre is inside the projected triangle. Centres exactly on an edge go to
  exactly one of the triangles sharing it (top-left rule, see `raster_kernels`).
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
from dlacli.types import Cameras

NEAR = 0.01  # metres


@dataclass
class UVRaster:
    """Which face covers each texel of an R x R UV map (see module docstring for the axes)."""

    face_id: np.ndarray  # [R, R] int32, -1 where no triangle covers the texel centre
    bary: np.ndarray  # [R, R, 3] float32 barycentrics of the texel centre, 0 where empty
    mask: np.ndarray  # [R, R] bool, face_id >= 0


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


def _np(x, name: str, dtype=None) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        arr = np.asarray(x) if dtype is None else np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise DlaInputError(name, f"not an array ({exc})") from None
    return arr


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _check_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    arr = _np(faces, name)
    if arr.size == 0:
        return np.zeros((0, 3), np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise DlaInputError(name, f"expected shape [F, 3], got {list(arr.shape)}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise DlaInputError(name, f"expected integer indices, got {arr.dtype}")
    if arr.min() < 0 or arr.max() >= n_vertices:
        raise DlaInputError(
            name, f"indices must be in [0, {n_vertices}), got range [{arr.min()}, {arr.max()}]"
        )
    return np.ascontiguousarray(arr, dtype=np.int64)


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


def _raster_core(verts_cam, faces, intr, width, height, near, first_wins):
    """verts_cam [C, V, 3] float64, faces [F, 3] int64, intr [C, 4] -> (face_id, bary, depth)."""
    n_cam = intr.shape[0]
    n_face = faces.shape[0]
    face_id = np.full((n_cam, height, width), -1, np.int32)
    bary = np.zeros((n_cam, height, width, 3), np.float32)
    depth = np.full((n_cam, height, width), np.inf, np.float32)
    if n_face == 0 or n_cam == 0:
        return face_id, bary, depth
    normals = np.empty((n_cam, n_face, 3, 3))
    det_abs = np.empty((n_cam, n_face))
    bbox = np.empty((n_cam, n_face, 4), np.int64)
    verts_cam = np.ascontiguousarray(verts_cam, dtype=np.float64)
    rk.setup_triangles(verts_cam, faces, intr, width, height, near, normals, det_abs, bbox)
    n_bands = (height + rk.BAND - 1) // rk.BAND
    offsets, items = rk.bin_triangles(det_abs, bbox, n_bands)
    rk.raster_bands(
        normals, det_abs, bbox, intr, offsets, items, near, first_wins, face_id, bary, depth
    )
    return face_id, bary, depth


def rasterize_uv(uv, faces, resolution: int) -> UVRaster:
    """Rasterise a UV layout into an R x R texel map.

    uv    [Vt, 2] texture coordinates in [0, 1] (u right, v up; see module docstring)
    faces [F, 3] int indices into uv
    A texel is covered when its centre is inside a triangle (top-left rule on edges; where
    triangles overlap, the lowest face id wins, so no texel is ever claimed twice).
    """
    if not _is_int(resolution) or resolution < 1:
        raise DlaInputError("resolution", f"expected an integer >= 1, got {resolution!r}")
    r = int(resolution)
    uv = _np(uv, "uv", np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise DlaInputError("uv", f"expected shape [Vt, 2], got {list(uv.shape)}")
    if not np.all(np.isfinite(uv)):
        raise DlaInputError("uv", "contains NaN or infinite values")
    faces = _check_faces(faces, uv.shape[0])
    # Corners (x, y, 1) in texel units with y down; identity intrinsics make the rays (x, y, 1).
    pts = np.empty((1, uv.shape[0], 3))
    pts[0, :, 0] = uv[:, 0] * r
    pts[0, :, 1] = (1.0 - uv[:, 1]) * r
    pts[0, :, 2] = 1.0
    intr = np.array([[1.0, 1.0, 0.0, 0.0]])
    face_id, bary, _ = _raster_core(pts, faces, intr, r, r, 0.5, True)
    return UVRaster(face_id[0], bary[0], face_id[0] >= 0)


def rasterize_camera_space(
    verts_cam, faces, Ks, width: int, height: int, *, near: float = NEAR
) -> Raster:
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
            raise DlaInputError(
                "verts_cam", f"{verts_cam.shape[0]} vertex sets for {ks.shape[0]} cameras"
            )
        verts_cam = np.broadcast_to(verts_cam, (ks.shape[0],) + verts_cam.shape[1:])
    intr = np.ascontiguousarray(np.stack([ks[:, 0, 0], ks[:, 1, 1], ks[:, 0, 2], ks[:, 1, 2]], 1))
    if np.any(intr[:, :2] <= 0):
        raise DlaInputError("Ks", f"focal lengths must be > 0, got {intr[:, :2].tolist()}")
    if int(width) < 1 or int(height) < 1:
        raise DlaInputError("width/height", f"image size must be >= 1, got {width}x{height}")
    if not near > 0:
        raise DlaInputError("near", f"must be > 0, got {near}")
    faces = _check_faces(faces, verts_cam.shape[1])
    face_id, bary, depth = _raster_core(
        verts_cam, faces, intr, int(width), int(height), float(near), False
    )
    return Raster(face_id, bary, depth)


def world_to_camera(vertices, viewmats) -> np.ndarray:
    """vertices [V, 3] or [C, V, 3] world, viewmats [C, 4, 4] -> [C, V, 3] float64 camera space
    (`dlacli.geometry.world_to_camera` in float64)."""
    return geometry.world_to_camera(np.asarray(vertices, np.float64), np.asarray(viewmats, np.float64))


def _camera_vertices(vertices, cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    vm, intr = _check_cameras(cameras)
    v = _check_points(vertices, "vertices", 3)
    if v.ndim == 3 and v.shape[0] != vm.shape[0]:
        raise DlaInputError(
            "vertices", f"{v.shape[0]} vertex sets [C, V, 3] for {vm.shape[0]} cameras"
        )
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
    face_id, bary, depth = _raster_core(
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
            a, np.ascontiguousarray(faces), np.ascontiguousarray(face_id),
            np.ascontiguousarray(bary), out,
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


def _scaled(cameras: Cameras, factor: int) -> Cameras:
    """The same cameras with an image `factor` times larger (pixel centres stay consistent)."""
    ks = cameras.Ks.clone()
    ks[:, :2, :] *= factor
    return Cameras(cameras.viewmats, ks, cameras.width * factor, cameras.height * factor)


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
        raise DlaInputError(
            "vertex_colors", f"expected shape [{verts.shape[-2]}, 3], got {list(col.shape)}"
        )
    if col.ndim == 3 and col.shape[0] != len(cameras):
        raise DlaInputError(
            "vertex_colors", f"{col.shape[0]} colour sets for {len(cameras)} cameras"
        )
    if not 0.0 <= ambient <= 1.0:
        raise DlaInputError("ambient", f"must be in [0, 1], got {ambient}")
    _check_cameras(cameras)
    hi = _scaled(cameras, aa)
    verts_cam, intr = _camera_vertices(verts, hi)
    faces = _check_faces(faces, verts_cam.shape[1])
    fid, bary, _ = _raster_core(verts_cam, faces, intr, hi.width, hi.height, float(near), False)
    normals = vertex_normals(verts_cam, faces)  # [C, V, 3] camera space
    colors = np.ascontiguousarray(col if col.ndim == 3 else col[None], dtype=np.float64)
    rgba = np.empty((len(cameras), cameras.height, cameras.width, 4), np.float32)
    rk.shade_downsample(
        colors, normals, verts_cam, faces, fid, bary, bg.astype(np.float64), float(ambient),
        bool(shading), aa, rgba,
    )
    if as_uint8:
        return np.round(rgba * 255.0).astype(np.uint8)
    return rgba


def visible_vertices(
    vertices, faces, cameras: Cameras, tol: float = 0.01, *, raster: Raster | None = None,
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
        _, _, depth = _raster_core(
            verts_cam, faces, intr, cameras.width, cameras.height, float(near), False
        )
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
