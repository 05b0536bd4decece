"""numba kernels for triangle rasterisation (used by `dlacli.render.raster`; no validation here).

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

import numba as nb
import numpy as np

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
def raster_bands(
    normals, det_abs, bbox, intr, offsets, items, near, first_wins, face_id, bary, depth
):
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


@nb.njit(cache=True, parallel=True)
def interpolate_np(attr, faces, face_id, bary, out):
    """out[c, y, x] = sum_k bary[c, y, x, k] attr[c or 0, faces[f, k]], 0 where face_id < 0.

    attr [C' , V, D] with C' = 1 (shared) or C, faces [F, 3], face_id [C, H, W],
    bary [C, H, W, 3], out [C, H, W, D] (zero-filled by the caller).
    """
    n_cam, height, width = face_id.shape
    shared = attr.shape[0] == 1
    for row in nb.prange(n_cam * height):
        c = row // height
        y = row % height
        a = attr[0] if shared else attr[c]
        for x in range(width):
            f = face_id[c, y, x]
            if f < 0:
                continue
            for k in range(3):
                w = bary[c, y, x, k]
                v = faces[f, k]
                for d in range(attr.shape[2]):
                    out[c, y, x, d] += w * a[v, d]


@nb.njit(cache=True, parallel=True)
def shade_downsample(
    colors, normals, verts, faces, face_id, bary, background, ambient, shading, aa, out
):
    """Fused colour interpolation, headlight Lambert shading, background and box downsampling.

    colors [C' , V, 3] (C' = 1 or C), normals / verts [C, V, 3] camera space, faces [F, 3],
    face_id [C, aa H, aa W], bary [C, aa H, aa W, 3], background [3], out [C, H, W, 4].
    """
    n_cam, height, width, _ = out.shape
    shared = colors.shape[0] == 1
    inv = 1.0 / (aa * aa)
    for row in nb.prange(n_cam * height):
        c = row // height
        y = row % height
        col = colors[0] if shared else colors[c]
        for x in range(width):
            acc = np.zeros(4)
            for sy in range(y * aa, y * aa + aa):
                for sx in range(x * aa, x * aa + aa):
                    f = face_id[c, sy, sx]
                    if f < 0:
                        for j in range(3):
                            acc[j] += background[j]
                        continue
                    rgb = np.zeros(3)
                    nrm = np.zeros(3)
                    pos = np.zeros(3)
                    for k in range(3):
                        w = bary[c, sy, sx, k]
                        v = faces[f, k]
                        for j in range(3):
                            rgb[j] += w * col[v, j]
                            nrm[j] += w * normals[c, v, j]
                            pos[j] += w * verts[c, v, j]
                    lam = 1.0
                    if shading:
                        nn = math.sqrt(nrm[0] ** 2 + nrm[1] ** 2 + nrm[2] ** 2)
                        pn = math.sqrt(pos[0] ** 2 + pos[1] ** 2 + pos[2] ** 2)
                        cosine = 0.0
                        if nn > 0.0 and pn > 0.0:
                            dot = nrm[0] * pos[0] + nrm[1] * pos[1] + nrm[2] * pos[2]
                            cosine = abs(dot) / (nn * pn)
                        lam = ambient + (1.0 - ambient) * cosine
                    for j in range(3):
                        acc[j] += rgb[j] * lam
                    acc[3] += 1.0
            for j in range(4):
                out[c, y, x, j] = min(1.0, max(0.0, acc[j] * inv))
