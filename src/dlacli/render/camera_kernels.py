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
        qw = np.float64(quats[g, 0])
        qx = np.float64(quats[g, 1])
        qy = np.float64(quats[g, 2])
        qz = np.float64(quats[g, 3])
        qn = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if qn < 1e-12:  # F.normalize's floor (a NaN stays NaN)
            qn = 1e-12
        w = qw / qn
        x = qx / qn
        y = qy / qn
        z = qz / qn
        s0 = np.float64(scales[g, 0])
        s1 = np.float64(scales[g, 1])
        s2 = np.float64(scales[g, 2])
        # M = rotation(q) diag(s): columns R_i s_i
        m00 = (1 - 2 * (y * y + z * z)) * s0
        m01 = (2 * (x * y - w * z)) * s1
        m02 = (2 * (x * z + w * y)) * s2
        m10 = (2 * (x * y + w * z)) * s0
        m11 = (1 - 2 * (x * x + z * z)) * s1
        m12 = (2 * (y * z - w * x)) * s2
        m20 = (2 * (x * z - w * y)) * s0
        m21 = (2 * (y * z + w * x)) * s1
        m22 = (1 - 2 * (x * x + y * y)) * s2
        mu0 = np.float64(means[g, 0])
        mu1 = np.float64(means[g, 1])
        mu2 = np.float64(means[g, 2])
        for c in range(ncam):
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
            u = px * rz
            lo = -(cx / fx + 0.3 * tanx)
            hi = (width - cx) / fx + 0.3 * tanx
            if u < lo:
                u = lo
            if u > hi:
                u = hi
            v = py * rz
            lo = -(cy / fy + 0.3 * tany)
            hi = (height - cy) / fy + 0.3 * tany
            if v < lo:
                v = lo
            if v > hi:
                v = hi
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
            out_con[c, g, 0] = cyy / dsafe
            out_con[c, g, 1] = -cxy / dsafe
            out_con[c, g, 2] = cxx / dsafe
            mx = fx * px * rz + cx
            my = fy * py * rz + cy
            out_m2[c, g, 0] = mx
            out_m2[c, g, 1] = my
            out_z[c, g] = pz
            b = 0.5 * (cxx + cyy)
            disc = b * b - det
            if disc < 0.01:
                disc = 0.01
            lam = b + np.sqrt(disc)
            radius = np.ceil(3.0 * np.sqrt(lam))
            keep = pz >= near and pz <= far and det > 0 and np.isfinite(radius)
            keep = keep and mx + radius > 0 and mx - radius < width and my + radius > 0 and my - radius < height
            out_r[c, g] = np.int32(min(radius, 2.0**30)) if keep else 0
