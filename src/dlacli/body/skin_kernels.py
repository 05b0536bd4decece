"""Numba kernels of Gaussian skinning without gradients (avatar/gaussian_map.py `skinned_params`
takes them when nothing asks for a gradient): the tangent frames of the posed surface samples
(body/uv.py `tangent_frames`), the frame's quaternion (geometry.py `matrix_to_quat`) and the
skinning of body/skinning.py `skin_gaussians`, fused, in float64, stored as float32.

Per body: the area-weighted vertex normals and each face's dP/du and metres-per-texel scale once
(one thread, a fixed order), then one thread per Gaussian; so the results do not depend on the
thread count (docs/rendering.md "Determinism"). The torch code stays the reference and the path
for gradients; the two agree to float32 rounding (tests/body/test_skin_kernels.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True)
def face_frames(verts, faces, uv_d, inv_det, abs_inv_det, resolution, vn, dpdu, scale):
    """For one body: verts [V, 3], faces [F, 3], uv_d [F, 4] = (d1u, d1v, d2u, d2v) of each UV
    triangle's edges, inv_det [F] = 1 / det (det clamped away from 0 as in uv.py), abs_inv_det [F]
    = 1 / |det| -> vn [V, 3] unit area-weighted vertex normals, dpdu [F, 3], scale [F]."""
    nv, nf = verts.shape[0], faces.shape[0]
    for i in range(nv):
        vn[i, 0] = 0.0
        vn[i, 1] = 0.0
        vn[i, 2] = 0.0
    for f in range(nf):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e10 = np.float64(verts[b, 0]) - np.float64(verts[a, 0])
        e11 = np.float64(verts[b, 1]) - np.float64(verts[a, 1])
        e12 = np.float64(verts[b, 2]) - np.float64(verts[a, 2])
        e20 = np.float64(verts[c, 0]) - np.float64(verts[a, 0])
        e21 = np.float64(verts[c, 1]) - np.float64(verts[a, 1])
        e22 = np.float64(verts[c, 2]) - np.float64(verts[a, 2])
        n0 = e11 * e22 - e12 * e21
        n1 = e12 * e20 - e10 * e22
        n2 = e10 * e21 - e11 * e20
        for k in range(3):
            v = faces[f, k]
            vn[v, 0] += n0
            vn[v, 1] += n1
            vn[v, 2] += n2
        d1v, d2v = uv_d[f, 1], uv_d[f, 3]
        dpdu[f, 0] = (e10 * d2v - e20 * d1v) * inv_det[f]
        dpdu[f, 1] = (e11 * d2v - e21 * d1v) * inv_det[f]
        dpdu[f, 2] = (e12 * d2v - e22 * d1v) * inv_det[f]
        scale[f] = np.sqrt(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2) * abs_inv_det[f]) / resolution
    for i in range(nv):
        norm = max(np.sqrt(vn[i, 0] ** 2 + vn[i, 1] ** 2 + vn[i, 2] ** 2), 1e-12)
        vn[i, 0] /= norm
        vn[i, 1] /= norm
        vn[i, 2] /= norm


@njit(cache=True, inline="always")
def _point_and_normal(verts, faces, vn, f, bary, g):
    """Sample g's point (p0, p1, p2) on face f and its interpolated vertex normal (n0, n1, n2),
    not normalised, with that normal's length floored at 1e-12 (float64)."""
    p0 = p1 = p2 = 0.0
    n0 = n1 = n2 = 0.0
    for k in range(3):
        v = faces[f, k]
        w = np.float64(bary[g, k])
        p0 += w * verts[v, 0]
        p1 += w * verts[v, 1]
        p2 += w * verts[v, 2]
        n0 += w * vn[v, 0]
        n1 += w * vn[v, 1]
        n2 += w * vn[v, 2]
    return p0, p1, p2, n0, n1, n2, max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), 1e-12)


@njit(parallel=True, cache=True)
def skin_samples(verts, faces, vn, dpdu, scale, face_id, bary, dxyz, dquat, ds, means, quats, scales):
    """One body's Gaussians: verts [V, 3], faces [F, 3], `face_frames`' vn, dpdu, scale, the
    samples face_id [N], bary [N, 3], the map's dxyz [N, 3], unit dquat [N, 4] (w, x, y, z),
    ds [N, 3] -> means [N, 3], quats [N, 4], scales [N, 3] (float32): mean = T + R dxyz,
    quat = normalise(q(R) dquat), scale = S ds, with (T, R, S) the sample's tangent frame."""
    n = face_id.shape[0]
    for g in prange(n):
        f = face_id[g]
        p0, p1, p2, n0, n1, n2, norm = _point_and_normal(verts, faces, vn, f, bary, g)
        inv = 1.0 / norm  # one division, then products (float64: far below float32 rounding)
        n0, n1, n2 = n0 * inv, n1 * inv, n2 * inv
        # tangent: dP/du orthonormalised against n; a unit vector orthogonal to n if degenerate
        d = dpdu[f, 0] * n0 + dpdu[f, 1] * n1 + dpdu[f, 2] * n2
        t0, t1, t2 = dpdu[f, 0] - d * n0, dpdu[f, 1] - d * n1, dpdu[f, 2] - d * n2
        tn = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        if not tn > 1e-12:
            if abs(n0) < 0.9:
                t0, t1, t2 = 1.0 - n0 * n0, -n0 * n1, -n0 * n2
            else:
                t0, t1, t2 = -n1 * n0, 1.0 - n1 * n1, -n1 * n2
            tn = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        inv = 1.0 / tn
        t0, t1, t2 = t0 * inv, t1 * inv, t2 * inv
        b0 = n1 * t2 - n2 * t1
        b1 = n2 * t0 - n0 * t2
        b2 = n0 * t1 - n1 * t0
        # R = [t | b | n] (columns): m_ij = row i, column j
        m00, m01, m02 = t0, b0, n0
        m10, m11, m12 = t1, b1, n1
        m20, m21, m22 = t2, b2, n2
        # Shepperd's method, the pivot chosen as in geometry.matrix_to_quat (first largest)
        s0 = 1.0 + m00 + m11 + m22
        s1 = 1.0 + m00 - m11 - m22
        s2 = 1.0 - m00 + m11 - m22
        s3 = 1.0 - m00 - m11 + m22
        best, top = 0, s0
        if s1 > top:
            best, top = 1, s1
        if s2 > top:
            best, top = 2, s2
        if s3 > top:
            best, top = 3, s3
        piv = np.sqrt(max(top, 0.1))
        pp = piv * piv
        # the pivot's quaternion picked by selects, not branches: which one varies from Gaussian
        # to Gaussian, and mispredicted branches cost more than the sums of all four
        a01, s01 = m10 - m01, m10 + m01
        a02, s02 = m02 - m20, m02 + m20
        a12, s12 = m21 - m12, m21 + m12
        qw = pp if best == 0 else (a12 if best == 1 else (a02 if best == 2 else a01))
        qx = a12 if best == 0 else (pp if best == 1 else (s01 if best == 2 else s02))
        qy = a02 if best == 0 else (s01 if best == 1 else (pp if best == 2 else s12))
        qz = a01 if best == 0 else (s02 if best == 1 else (s12 if best == 2 else pp))
        inv = 1.0 / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        inv = -inv if qw < 0 else inv
        qw, qx, qy, qz = qw * inv, qx * inv, qy * inv, qz * inv
        # skinning
        x0, x1, x2 = np.float64(dxyz[g, 0]), np.float64(dxyz[g, 1]), np.float64(dxyz[g, 2])
        means[g, 0] = p0 + m00 * x0 + m01 * x1 + m02 * x2
        means[g, 1] = p1 + m10 * x0 + m11 * x1 + m12 * x2
        means[g, 2] = p2 + m20 * x0 + m21 * x1 + m22 * x2
        bw, bx = np.float64(dquat[g, 0]), np.float64(dquat[g, 1])
        by, bz = np.float64(dquat[g, 2]), np.float64(dquat[g, 3])
        rw = qw * bw - qx * bx - qy * by - qz * bz
        rx = qw * bx + qx * bw + qy * bz - qz * by
        ry = qw * by - qx * bz + qy * bw + qz * bx
        rz = qw * bz + qx * by - qy * bx + qz * bw
        inv = 1.0 / max(np.sqrt(rw * rw + rx * rx + ry * ry + rz * rz), 1e-12)
        quats[g, 0] = rw * inv
        quats[g, 1] = rx * inv
        quats[g, 2] = ry * inv
        quats[g, 3] = rz * inv
        s = scale[f]
        scales[g, 0] = s * ds[g, 0]
        scales[g, 1] = s * ds[g, 1]
        scales[g, 2] = s * ds[g, 2]


@njit(parallel=True, cache=True)
def surface_points_normals(verts, faces, vn, face_id, bary, dest, pos, nrm):
    """Points and unit interpolated vertex normals (float32) at the surface samples face_id [N],
    bary [N, 3] of one body (verts [V, 3], `face_frames`' vn), written to rows dest[g] of pos and
    nrm [M, 3] (M >= N; other rows untouched: a UV map's covered texels, or dest = arange(N)):
    body/uv.py `surface_points` and `tangent_frames`' normal."""
    for g in prange(face_id.shape[0]):
        f = face_id[g]
        p0, p1, p2, n0, n1, n2, norm = _point_and_normal(verts, faces, vn, f, bary, g)
        row = dest[g]
        pos[row, 0] = p0
        pos[row, 1] = p1
        pos[row, 2] = p2
        nrm[row, 0] = n0 / norm
        nrm[row, 1] = n1 / norm
        nrm[row, 2] = n2 / norm
