"""numba kernels for attribute interpolation and mesh shading (used by `dlacli.render.raster`;
no validation here). The coverage kernel itself (which triangle covers each pixel centre: 2DH edge
functions, the top-left rule, bands) is in `dlacli.triangle_kernels`, shared with the body's UV raster.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


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
def shade_downsample(colors, normals, verts, faces, face_id, bary, background, ambient, shading, aa, out):
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
