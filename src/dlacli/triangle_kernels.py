"""Triangle coverage (numba): which triangle covers each pixel centre, and where.

Bottom layer (beside `dlacli.geometry`): the scan-conversion core that both the camera rasterisers
(`dlacli.render.raster`) and the body's UV-layout raster (`dlacli.body.uv.uv_raster`, through
`rasterize_uv` below) use, so that body does not import render. Pixel, UV and barycentric
conventions are those of `dlacli.render.raster` (its module docstring).

One kernel serves both the perspective z-buffer and the UV-space rasteriser. It works in
homogeneous 2D ("2DH", Olano & Greer 1997): for a triangle with camera-space corners a, b, c
(the columns of M) and the ray d = K^-1 (x, y, 1) through a pixel centre, the point where the ray
meets the triangle's plane has barycentrics b_k = q_k / (q_0 + q_1 + q_2) with

    q_0 = d . (b x c),   q_1 = d . (c x a),   q_2 = d . (a x b)

and camera depth z = det(M) / (q_0 + q_1 + q_2). These are perspective-correct by construction
(it is a ray-plane intersection), need no division per vertex and no clipping for coverage:
multiplying the edge normals by sign(det M) makes "all q_k >= 0" mean "the ray hits the triangle
in front of the camera". The near plane is applied per pixel (z < near is rejected), which is the
same set of pixels a geometric clip at z = near would give; the near clip is only used to bound
the triangle's screen rectangle.

Watertightness. Shared corners are transformed once, so the edge normal of a shared edge is
bit-for-bit the negation in the two triangles (a x b vs b x a), and so are the q values: a pixel
centre is never on the inside of both or of neither (in floating point, up to the usual caveat
of points within ~1e-12 relative of a shared vertex). A pixel centre exactly on an edge
(q_k == 0) is decided as if it were moved by (eps, eps^2) pixels: the edge owns it when its inward
normal has x > 0, or x == 0 and y > 0. This is the classic top-left rule (for y-down images) and
gives every centre on a shared edge or vertex to exactly one triangle.

The UV rasteriser uses the same kernel with corners (x, y, 1), x = u R, y = (1 - v) R, and the
identity intrinsics, so q_k are the 2D edge functions and all depths are 1.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numba as nb
import numpy as np

from dlacli.errors import DlaInputError

BAND = 8  # rows per work item in the raster pass


@nb.njit(cache=True, parallel=True)
def setup_triangles(verts, faces, intr, width, height, near, normals, det_abs, bbox):
    """Per (camera, face): inward edge normals, |det M| and the clipped pixel rectangle.

    verts   [C, V, 3] float64 camera-space corners (OpenCV axes, z forward)
    faces   [F, 3] int64
    intr    [C, 4] float64 fx, fy, cx, cy (fx, fy > 0)
    normals [C, F, 3, 3] float64 out: row k = sign(det) * (corner k+1 x corner k+2)
    det_abs [C, F] float64 out: |det M|, 0 for a triangle that is skipped
    bbox    [C, F, 4] int64 out: x0, x1, y0, y1 inclusive pixel ranges (x0 > x1 if skipped)
    """
    n_cam = verts.shape[0]
    n_face = faces.shape[0]
    for item in nb.prange(n_cam * n_face):
        c = item // n_face
        f = item % n_face
        bbox[c, f, 0] = 1
        bbox[c, f, 1] = 0
        bbox[c, f, 2] = 1
        bbox[c, f, 3] = 0
        det_abs[c, f] = 0.0
        p = np.empty((3, 3))
        for k in range(3):
            for j in range(3):
                p[k, j] = verts[c, faces[f, k], j]
        for k in range(3):
            a = p[(k + 1) % 3]
            b = p[(k + 2) % 3]
            normals[c, f, k, 0] = a[1] * b[2] - a[2] * b[1]
            normals[c, f, k, 1] = a[2] * b[0] - a[0] * b[2]
            normals[c, f, k, 2] = a[0] * b[1] - a[1] * b[0]
        det = 0.0
        for j in range(3):
            det += p[0, j] * normals[c, f, 0, j]
        if det == 0.0 or not math.isfinite(det):
            continue  # degenerate, or its plane passes through the camera centre (edge-on)
        if det < 0.0:
            for k in range(3):
                for j in range(3):
                    normals[c, f, k, j] = -normals[c, f, k, j]
        # Clip the triangle against z >= near (Sutherland-Hodgman, one plane), project, bound.
        fx = intr[c, 0]
        fy = intr[c, 1]
        cx = intr[c, 2]
        cy = intr[c, 3]
        xmin = math.inf
        xmax = -math.inf
        ymin = math.inf
        ymax = -math.inf
        count = 0
        for k in range(3):
            a = p[k]
            b = p[(k + 1) % 3]
            ina = a[2] >= near
            inb = b[2] >= near
            for emit in range(2):
                if emit == 0:
                    if not ina:
                        continue
                    x = a[0]
                    y = a[1]
                    z = a[2]
                else:
                    if ina == inb:
                        continue
                    t = (near - a[2]) / (b[2] - a[2])
                    x = a[0] + t * (b[0] - a[0])
                    y = a[1] + t * (b[1] - a[1])
                    z = near
                sx = fx * x / z + cx
                sy = fy * y / z + cy
                xmin = min(xmin, sx)
                xmax = max(xmax, sx)
                ymin = min(ymin, sy)
                ymax = max(ymax, sy)
                count += 1
        if count == 0 or not (math.isfinite(xmin) and math.isfinite(xmax)):
            continue
        if not (math.isfinite(ymin) and math.isfinite(ymax)):
            continue
        # Pixel centres x + 0.5 inside [xmin, xmax], widened by one pixel against rounding.
        x0 = max(0.0, math.floor(xmin - 0.5) - 1.0)
        x1 = min(width - 1.0, math.ceil(xmax - 0.5) + 1.0)
        y0 = max(0.0, math.floor(ymin - 0.5) - 1.0)
        y1 = min(height - 1.0, math.ceil(ymax - 0.5) + 1.0)
        if x0 > x1 or y0 > y1:
            continue
        det_abs[c, f] = abs(det)
        bbox[c, f, 0] = int(x0)
        bbox[c, f, 1] = int(x1)
        bbox[c, f, 2] = int(y0)
        bbox[c, f, 3] = int(y1)


@nb.njit(cache=True)
def bin_triangles(det_abs, bbox, n_bands):
    """CSR lists of the faces touching each (camera, band of BAND rows), ascending face id.

    Returns offsets [C * n_bands + 1] int64 and items [total] int64 (face ids).
    """
    n_cam, n_face = det_abs.shape
    counts = np.zeros(n_cam * n_bands + 1, np.int64)
    for c in range(n_cam):
        for f in range(n_face):
            if det_abs[c, f] > 0.0:
                for b in range(bbox[c, f, 2] // BAND, bbox[c, f, 3] // BAND + 1):
                    counts[c * n_bands + b + 1] += 1
    offsets = np.cumsum(counts)
    items = np.empty(offsets[-1], np.int64)
    fill = offsets[:-1].copy()
    for c in range(n_cam):
        for f in range(n_face):
            if det_abs[c, f] > 0.0:
                for b in range(bbox[c, f, 2] // BAND, bbox[c, f, 3] // BAND + 1):
                    slot = c * n_bands + b
                    items[fill[slot]] = f
                    fill[slot] += 1
    return offsets, items


@nb.njit(inline="always")
def _edge_ok(q, nx, ny):
    """Inside test for one edge, with the (eps, eps^2) tie rule for centres on the edge."""
    if q > 0.0:
        return True
    if q < 0.0:
        return False
    return nx > 0.0 or (nx == 0.0 and ny > 0.0)


@nb.njit(cache=True, parallel=True)
def raster_bands(normals, det_abs, bbox, intr, offsets, items, near, first_wins, face_id, bary, depth):
    """Fill face_id / bary / depth; parallel over (camera, band), each band owned by one thread.

    face_id [C, H, W] int32 (pre-filled with -1), bary [C, H, W, 3] float32 (zeros),
    depth [C, H, W] float32 (+inf). With first_wins (UV mode) the lowest face id covering a
    pixel keeps it; otherwise the nearest (strictly smaller depth, so ties keep the lower id).
    """
    n_cam, height, width = face_id.shape
    n_bands = (height + BAND - 1) // BAND
    for work in nb.prange(n_cam * n_bands):
        c = work // n_bands
        band = work % n_bands
        row0 = band * BAND
        row1 = min(height, row0 + BAND) - 1
        fx = intr[c, 0]
        fy = intr[c, 1]
        cx = intr[c, 2]
        cy = intr[c, 3]
        for it in range(offsets[work], offsets[work + 1]):
            f = items[it]
            n = normals[c, f]
            da = det_abs[c, f]
            y0 = max(row0, bbox[c, f, 2])
            y1 = min(row1, bbox[c, f, 3])
            for y in range(y0, y1 + 1):
                dy = (y + 0.5 - cy) / fy
                # q_k = n_k0 * dx + (n_k1 * dy + n_k2), linear in dx along the row
                r0 = n[0, 1] * dy + n[0, 2]
                r1 = n[1, 1] * dy + n[1, 2]
                r2 = n[2, 1] * dy + n[2, 2]
                for x in range(bbox[c, f, 0], bbox[c, f, 1] + 1):
                    dx = (x + 0.5 - cx) / fx
                    q0 = n[0, 0] * dx + r0
                    if not _edge_ok(q0, n[0, 0], n[0, 1]):
                        continue
                    q1 = n[1, 0] * dx + r1
                    if not _edge_ok(q1, n[1, 0], n[1, 1]):
                        continue
                    q2 = n[2, 0] * dx + r2
                    if not _edge_ok(q2, n[2, 0], n[2, 1]):
                        continue
                    s = q0 + q1 + q2
                    if not s > 0.0:
                        continue
                    z = da / s
                    if z < near:
                        continue
                    if first_wins:
                        if face_id[c, y, x] >= 0:
                            continue
                    elif not z < depth[c, y, x]:
                        continue
                    face_id[c, y, x] = f
                    depth[c, y, x] = z
                    bary[c, y, x, 0] = q0 / s
                    bary[c, y, x, 1] = q1 / s
                    bary[c, y, x, 2] = q2 / s


# ------------------------------------------------------------------------------ numpy side


@dataclass
class UVRaster:
    """Which face covers each texel of an R x R UV map (axes: `dlacli.render.raster`)."""

    face_id: np.ndarray  # [R, R] int32, -1 where no triangle covers the texel centre
    bary: np.ndarray  # [R, R, 3] float32 barycentrics of the texel centre, 0 where empty
    mask: np.ndarray  # [R, R] bool, face_id >= 0


def as_array(x, name: str, dtype=None) -> np.ndarray:
    """`x` (array-like or torch tensor) as a numpy array; a DlaInputError naming `name` if not."""
    torch = sys.modules.get("torch")  # a tensor exists only once torch is imported
    if torch is not None and isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        arr = np.asarray(x) if dtype is None else np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise DlaInputError(name, f"not an array ({exc})") from None
    return arr


def is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def check_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    """faces [F, 3] integer indices into n_vertices -> contiguous int64, or a DlaInputError."""
    arr = as_array(faces, name)
    if arr.size == 0:
        return np.zeros((0, 3), np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise DlaInputError(name, f"expected shape [F, 3], got {list(arr.shape)}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise DlaInputError(name, f"expected integer indices, got {arr.dtype}")
    if arr.min() < 0 or arr.max() >= n_vertices:
        raise DlaInputError(name, f"indices must be in [0, {n_vertices}), got range [{arr.min()}, {arr.max()}]")
    return np.ascontiguousarray(arr, dtype=np.int64)


def rasterize_triangles(verts_cam, faces, intr, width, height, near, first_wins):
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
    setup_triangles(verts_cam, faces, intr, width, height, near, normals, det_abs, bbox)
    n_bands = (height + BAND - 1) // BAND
    offsets, items = bin_triangles(det_abs, bbox, n_bands)
    raster_bands(normals, det_abs, bbox, intr, offsets, items, near, first_wins, face_id, bary, depth)
    return face_id, bary, depth


def rasterize_uv(uv, faces, resolution: int) -> UVRaster:
    """Rasterise a UV layout into an R x R texel map.

    uv    [Vt, 2] texture coordinates in [0, 1] (u right, v up; see `dlacli.render.raster`)
    faces [F, 3] int indices into uv
    A texel is covered when its centre is inside a triangle (top-left rule on edges; where
    triangles overlap, the lowest face id wins, so no texel is ever claimed twice).
    """
    if not is_int(resolution) or resolution < 1:
        raise DlaInputError("resolution", f"expected an integer >= 1, got {resolution!r}")
    r = int(resolution)
    uv = as_array(uv, "uv", np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise DlaInputError("uv", f"expected shape [Vt, 2], got {list(uv.shape)}")
    if not np.all(np.isfinite(uv)):
        raise DlaInputError("uv", "contains NaN or infinite values")
    faces = check_faces(faces, uv.shape[0])
    # Corners (x, y, 1) in texel units with y down; identity intrinsics make the rays (x, y, 1).
    pts = np.empty((1, uv.shape[0], 3))
    pts[0, :, 0] = uv[:, 0] * r
    pts[0, :, 1] = (1.0 - uv[:, 1]) * r
    pts[0, :, 2] = 1.0
    intr = np.array([[1.0, 1.0, 0.0, 0.0]])
    face_id, bary, _ = rasterize_triangles(pts, faces, intr, r, r, 0.5, True)
    return UVRaster(face_id[0], bary[0], face_id[0] >= 0)
