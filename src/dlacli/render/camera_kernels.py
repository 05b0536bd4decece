"""Numba kernels of the splatter's camera transform (render/splat.py `_CameraPoints`): the
Gaussians' means in each camera's frame and the gradient back to the means, each output element
written by one thread in a fixed order of operations, so the results do not depend on the thread
count (docs/rendering.md "Determinism")."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def camera_points(rot, trans, means, out):
    """out[c, n] = rot[c] @ means[n] + trans[c]: rot [C, 3, 3], trans [C, 3], means [N, 3],
    out [C, N, 3]. One thread per Gaussian, a fixed order of operations (float64)."""
    ncam, n = rot.shape[0], means.shape[0]
    for g in prange(n):
        m0 = np.float64(means[g, 0])
        m1 = np.float64(means[g, 1])
        m2 = np.float64(means[g, 2])
        for c in range(ncam):
            for i in range(3):
                out[c, g, i] = (
                    np.float64(rot[c, i, 0]) * m0
                    + np.float64(rot[c, i, 1]) * m1
                    + np.float64(rot[c, i, 2]) * m2
                    + np.float64(trans[c, i])
                )


@njit(parallel=True, cache=True)
def camera_points_grad(rot, grad, out):
    """out[n, j] = sum over c, i (in that order) of grad[c, n, i] rot[c, i, j]: the gradient of
    `camera_points` w.r.t. the means. rot [C, 3, 3], grad [C, N, 3], out [N, 3]."""
    ncam, n = grad.shape[0], grad.shape[1]
    for g in prange(n):
        for j in range(3):
            v = 0.0
            for c in range(ncam):
                for i in range(3):
                    v += np.float64(grad[c, g, i]) * np.float64(rot[c, i, j])
            out[g, j] = v


@njit(cache=True, inline="always")
def _scaled_rotation(quats, scales, g):
    """M = rotation(q) diag(s) of Gaussian g, row-major (columns R_i s_i), float64; q of any norm
    (F.normalize's floor: a NaN stays NaN)."""
    qw = np.float64(quats[g, 0])
    qx = np.float64(quats[g, 1])
    qy = np.float64(quats[g, 2])
    qz = np.float64(quats[g, 3])
    qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qn < 1e-12:
        qn = 1e-12
    w = qw / qn
    x = qx / qn
    y = qy / qn
    z = qz / qn
    s0 = np.float64(scales[g, 0])
    s1 = np.float64(scales[g, 1])
    s2 = np.float64(scales[g, 2])
    return (
        (1 - 2 * (y * y + z * z)) * s0,
        (2 * (x * y - w * z)) * s1,
        (2 * (x * z + w * y)) * s2,
        (2 * (x * y + w * z)) * s0,
        (1 - 2 * (x * x + z * z)) * s1,
        (2 * (y * z - w * x)) * s2,
        (2 * (x * z - w * y)) * s0,
        (2 * (y * z + w * x)) * s1,
        (1 - 2 * (x * x + y * y)) * s2,
    )


@njit(cache=True, inline="always")
def _clamp(x, lo, hi):
    """x clamped to [lo, hi] by comparisons, so a NaN stays NaN (as torch's minimum / maximum)."""
    if x < lo:
        x = lo
    if x > hi:
        x = hi
    return x


@njit(cache=True, inline="always")
def _project_one(m, mu0, mu1, mu2, rot, trans, intr, c, width, height, eps2d, near, far):
    """Gaussian (M = `_scaled_rotation`, mean mu) seen by camera c: (mean x, mean y, conic a, b, c,
    depth, radius int, 0 = culled), float64, the torch code's formulas in its order."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    r00 = np.float64(rot[c, 0, 0])
    r01 = np.float64(rot[c, 0, 1])
    r02 = np.float64(rot[c, 0, 2])
    r10 = np.float64(rot[c, 1, 0])
    r11 = np.float64(rot[c, 1, 1])
    r12 = np.float64(rot[c, 1, 2])
    r20 = np.float64(rot[c, 2, 0])
    r21 = np.float64(rot[c, 2, 1])
    r22 = np.float64(rot[c, 2, 2])
    px = r00 * mu0 + r01 * mu1 + r02 * mu2 + np.float64(trans[c, 0])
    py = r10 * mu0 + r11 * mu1 + r12 * mu2 + np.float64(trans[c, 1])
    pz = r20 * mu0 + r21 * mu1 + r22 * mu2 + np.float64(trans[c, 2])
    fx = np.float64(intr[c, 0])
    fy = np.float64(intr[c, 1])
    cx = np.float64(intr[c, 2])
    cy = np.float64(intr[c, 3])
    tanx = 0.5 * width / fx
    tany = 0.5 * height / fy
    rz = 1.0 / pz
    u = _clamp(px * rz, -(cx / fx + 0.3 * tanx), (width - cx) / fx + 0.3 * tanx)
    v = _clamp(py * rz, -(cy / fy + 0.3 * tany), (height - cy) / fy + 0.3 * tany)
    # rows of J R (pinhole Jacobian at the clamped point times the view rotation)
    j00 = fx * rz * (r00 - u * r20)
    j01 = fx * rz * (r01 - u * r21)
    j02 = fx * rz * (r02 - u * r22)
    j10 = fy * rz * (r10 - v * r20)
    j11 = fy * rz * (r11 - v * r21)
    j12 = fy * rz * (r12 - v * r22)
    a00 = j00 * m00 + j01 * m10 + j02 * m20
    a01 = j00 * m01 + j01 * m11 + j02 * m21
    a02 = j00 * m02 + j01 * m12 + j02 * m22
    a10 = j10 * m00 + j11 * m10 + j12 * m20
    a11 = j10 * m01 + j11 * m11 + j12 * m21
    a12 = j10 * m02 + j11 * m12 + j12 * m22
    cxx = a00 * a00 + a01 * a01 + a02 * a02 + eps2d
    cxy = a00 * a10 + a01 * a11 + a02 * a12
    cyy = a10 * a10 + a11 * a11 + a12 * a12 + eps2d
    det = cxx * cyy - cxy * cxy
    dsafe = det if det > 0 else 1.0
    mx = fx * px * rz + cx
    my = fy * py * rz + cy
    b = 0.5 * (cxx + cyy)
    disc = b * b - det
    if disc < 0.01:
        disc = 0.01
    lam = b + np.sqrt(disc)
    radius = np.ceil(3.0 * np.sqrt(lam))
    keep = pz >= near and pz <= far and det > 0 and np.isfinite(radius)
    keep = keep and mx + radius > 0 and mx - radius < width and my + radius > 0 and my - radius < height
    r = np.int32(min(radius, 2.0**30)) if keep else np.int32(0)
    return mx, my, cyy / dsafe, -cxy / dsafe, cxx / dsafe, pz, r


@njit(parallel=True, cache=True)
def project_fused(
    means, quats, scales, rot, trans, intr, width, height, eps2d, near, far, out_m2, out_con, out_z, out_r
):
    """The whole EWA projection and culling of `splat.project_gaussians`, one thread per Gaussian,
    float64 inside (inputs and outputs may be float32): the forward pass without autograd, the
    same formulas in the same order as the torch code. means [N, 3], quats [N, 4] (w, x, y, z,
    any norm), scales [N, 3], rot [C, 3, 3], trans [C, 3], intr [C, 4] (fx, fy, cx, cy) ->
    out_m2 [C, N, 2], out_con [C, N, 3], out_z [C, N], out_r [C, N] int32 (0 = culled). NaNs
    propagate as in torch (the clamps of the Jacobian point are written as comparisons)."""
    ncam, n = rot.shape[0], means.shape[0]
    for g in prange(n):
        m = _scaled_rotation(quats, scales, g)
        mu0 = np.float64(means[g, 0])
        mu1 = np.float64(means[g, 1])
        mu2 = np.float64(means[g, 2])
        for c in range(ncam):
            mx, my, ca, cb, cc, z, r = _project_one(
                m, mu0, mu1, mu2, rot, trans, intr, c, width, height, eps2d, near, far
            )
            out_con[c, g, 0] = ca
            out_con[c, g, 1] = cb
            out_con[c, g, 2] = cc
            out_m2[c, g, 0] = mx
            out_m2[c, g, 1] = my
            out_z[c, g] = z
            out_r[c, g] = r


@njit(parallel=True, cache=True)
def project_fused_grad(
    means, quats, scales, rot, trans, intr, width, height, eps2d, g_m2, g_con, g_z, out_mu, out_q, out_s
):
    """The gradient of `project_fused` w.r.t. the means, quaternions and scales (the cameras held
    fixed): g_m2 [C, N, 2], g_con [C, N, 3], g_z [C, N] -> out_mu [N, 3], out_q [N, 4], out_s
    [N, 3]. Recomputes the forward per Gaussian, float64, cameras summed in order (the same bits
    for any thread count). Where a clamp of the Jacobian point is active its gradient is 0, and
    where det <= 0 the conic is the unnormalised adjugate, as in torch's where/minimum/maximum."""
    ncam, n = rot.shape[0], means.shape[0]
    nblocks = (n + 255) // 256
    for blk in prange(nblocks):  # scratch arrays once per block of Gaussians, not per Gaussian
        s = np.empty(3)
        rq = np.empty((3, 3))  # rotation of q
        m = np.empty((3, 3))
        mu = np.empty(3)
        gm = np.empty((3, 3))  # d M
        gmu = np.empty(3)
        r = np.empty((3, 3))
        p = np.empty(3)
        j0 = np.empty(3)
        j1 = np.empty(3)
        a0 = np.empty(3)
        a1 = np.empty(3)
        ga0 = np.empty(3)
        ga1 = np.empty(3)
        gr = np.empty((3, 3))
        for g in range(blk * 256, min(blk * 256 + 256, n)):
            qw = np.float64(quats[g, 0])
            qx = np.float64(quats[g, 1])
            qy = np.float64(quats[g, 2])
            qz = np.float64(quats[g, 3])
            qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            floor = qn < 1e-12
            if floor:
                qn = 1e-12
            w = qw / qn
            x = qx / qn
            y = qy / qn
            z = qz / qn
            s[0] = np.float64(scales[g, 0])
            s[1] = np.float64(scales[g, 1])
            s[2] = np.float64(scales[g, 2])
            rq[0, 0] = 1 - 2 * (y * y + z * z)
            rq[0, 1] = 2 * (x * y - w * z)
            rq[0, 2] = 2 * (x * z + w * y)
            rq[1, 0] = 2 * (x * y + w * z)
            rq[1, 1] = 1 - 2 * (x * x + z * z)
            rq[1, 2] = 2 * (y * z - w * x)
            rq[2, 0] = 2 * (x * z - w * y)
            rq[2, 1] = 2 * (y * z + w * x)
            rq[2, 2] = 1 - 2 * (x * x + y * y)
            for i in range(3):
                for k in range(3):
                    m[i, k] = rq[i, k] * s[k]
            for i in range(3):
                mu[i] = np.float64(means[g, i])
            gm[:] = 0.0
            gmu[:] = 0.0
            for c in range(ncam):
                for i in range(3):
                    for k in range(3):
                        r[i, k] = np.float64(rot[c, i, k])
                for i in range(3):
                    p[i] = r[i, 0] * mu[0] + r[i, 1] * mu[1] + r[i, 2] * mu[2] + np.float64(trans[c, i])
                fx = np.float64(intr[c, 0])
                fy = np.float64(intr[c, 1])
                cx = np.float64(intr[c, 2])
                cy = np.float64(intr[c, 3])
                tanx = 0.5 * width / fx
                tany = 0.5 * height / fy
                rz = 1.0 / p[2]
                u = p[0] * rz
                v = p[1] * rz
                lo = -(cx / fx + 0.3 * tanx)
                hi = (width - cx) / fx + 0.3 * tanx
                u_free = u >= lo and u <= hi
                u = min(max(u, lo), hi) if not np.isnan(u) else u
                lo = -(cy / fy + 0.3 * tany)
                hi = (height - cy) / fy + 0.3 * tany
                v_free = v >= lo and v <= hi
                v = min(max(v, lo), hi) if not np.isnan(v) else v
                for k in range(3):
                    j0[k] = fx * rz * (r[0, k] - u * r[2, k])
                    j1[k] = fy * rz * (r[1, k] - v * r[2, k])
                for k in range(3):
                    a0[k] = j0[0] * m[0, k] + j0[1] * m[1, k] + j0[2] * m[2, k]
                    a1[k] = j1[0] * m[0, k] + j1[1] * m[1, k] + j1[2] * m[2, k]
                cxx = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2] + eps2d
                cxy = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2]
                cyy = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2] + eps2d
                det = cxx * cyy - cxy * cxy
                gc0 = np.float64(g_con[c, g, 0])
                gc1 = np.float64(g_con[c, g, 1])
                gc2 = np.float64(g_con[c, g, 2])
                if det > 0:  # conic = (cyy, -cxy, cxx) / det
                    gdet = -(gc0 * cyy - gc1 * cxy + gc2 * cxx) / (det * det)
                    gxx = gc2 / det + gdet * cyy
                    gxy = -gc1 / det - 2.0 * gdet * cxy
                    gyy = gc0 / det + gdet * cxx
                else:
                    gxx = gc2
                    gxy = -gc1
                    gyy = gc0
                # d a0, d a1, then d J rows and d M
                for k in range(3):
                    ga0[k] = 2.0 * gxx * a0[k] + gxy * a1[k]
                    ga1[k] = 2.0 * gyy * a1[k] + gxy * a0[k]
                grz = 0.0
                gu = 0.0
                gv = 0.0
                for j in range(3):
                    gj0 = ga0[0] * m[j, 0] + ga0[1] * m[j, 1] + ga0[2] * m[j, 2]
                    gj1 = ga1[0] * m[j, 0] + ga1[1] * m[j, 1] + ga1[2] * m[j, 2]
                    for k in range(3):
                        gm[j, k] += j0[j] * ga0[k] + j1[j] * ga1[k]
                    grz += fx * gj0 * (r[0, j] - u * r[2, j]) + fy * gj1 * (r[1, j] - v * r[2, j])
                    gu -= fx * rz * gj0 * r[2, j]
                    gv -= fy * rz * gj1 * r[2, j]
                gpx = 0.0
                gpy = 0.0
                gpz = np.float64(g_z[c, g])
                if u_free:
                    gpx += gu * rz
                    grz += gu * p[0]
                if v_free:
                    gpy += gv * rz
                    grz += gv * p[1]
                gmx = np.float64(g_m2[c, g, 0])
                gmy = np.float64(g_m2[c, g, 1])
                gpx += gmx * fx * rz
                gpy += gmy * fy * rz
                grz += gmx * fx * p[0] + gmy * fy * p[1]
                gpz -= grz * rz * rz
                for i in range(3):
                    gmu[i] += r[0, i] * gpx + r[1, i] * gpy + r[2, i] * gpz
            for i in range(3):
                out_mu[g, i] = gmu[i]
            # M = rotation(q) diag(s)
            for k in range(3):
                gsk = 0.0
                for j in range(3):
                    gsk += gm[j, k] * rq[j, k]
                    gr[j, k] = gm[j, k] * s[k]
                out_s[g, k] = gsk
            gw = 2 * (-z * gr[0, 1] + y * gr[0, 2] + z * gr[1, 0] - x * gr[1, 2] - y * gr[2, 0] + x * gr[2, 1])
            gx = (
                2
                * (
                    y * gr[0, 1]
                    + z * gr[0, 2]
                    + y * gr[1, 0]
                    - 2 * x * gr[1, 1]
                    - w * gr[1, 2]
                    + z * gr[2, 0]
                    + w * gr[2, 1]
                )
                - 4 * x * gr[2, 2]
            )
            gy = (
                2
                * (
                    -2 * y * gr[0, 0]
                    + x * gr[0, 1]
                    + w * gr[0, 2]
                    + x * gr[1, 0]
                    + z * gr[1, 2]
                    - w * gr[2, 0]
                    + z * gr[2, 1]
                )
                - 4 * y * gr[2, 2]
            )
            gz = (
                2
                * (
                    -2 * z * gr[0, 0]
                    - w * gr[0, 1]
                    + x * gr[0, 2]
                    + w * gr[1, 0]
                    - 2 * z * gr[1, 1]
                    + y * gr[1, 2]
                    + x * gr[2, 0]
                )
                + 2 * y * gr[2, 1]
            )
            if floor:  # x / eps: no gradient through the norm
                dot = 0.0
            else:
                dot = w * gw + x * gx + y * gy + z * gz
            out_q[g, 0] = (gw - w * dot) / qn
            out_q[g, 1] = (gx - x * dot) / qn
            out_q[g, 2] = (gy - y * dot) / qn
            out_q[g, 3] = (gz - z * dot) / qn
