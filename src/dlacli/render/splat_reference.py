"""Slow, obviously correct Gaussian splatting: the test oracle for the numba kernels.

Everything is dense torch (float64 in the tests, any float dtype works): every pixel looks at
every Gaussian, so autograd gives the gradients and there is no tiling, sorting per tile or
hand-written backward. It implements the conventions of docs/rendering.md directly:

- covariance R diag(s^2) R^T (R from the unit quaternion by the Euler-Rodrigues form),
  camera frame W Sigma W^T, pinhole Jacobian at the mean (x/z, y/z clamped to 1.3 x the half
  field of view, as gsplat), + eps2d I; conic = the matrix inverse;
- radius = ceil(3 sqrt(b + sqrt(max(b^2 - det, 0.01)))), b = trace / 2; culled when depth < near,
  depth > far, det <= 0 or off-image; a Gaussian is seen only by pixels whose 16 x 16 tile lies
  in [floor((m - r) / 16), ceil((m + r) / 16)) on both axes (gsplat's tile membership);
- per pixel, Gaussians front to back by depth (stable: ties by index); alpha = min(0.999,
  o exp(-sigma)); skipped when sigma < 0 or alpha < 1/255; a Gaussian counts while the
  transmittance after it stays > 1e-4 (the first one that would bring it to <= 1e-4 and all behind
  it are dropped);
- rgb = sum w_i c_i + (1 - alpha) background, alpha = 1 - prod (1 - alpha_i),
  depth = sum w_i z_i / alpha (0 where alpha = 0).
"""

from __future__ import annotations

import torch

from dlacli.render.sh import eval_sh_colors
from dlacli.render.splat import EPS2D, FAR, NEAR, TILE, RenderOutput
from dlacli.types import Cameras, Gaussians


def _rotation(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z) -> [N, 3, 3], R = (w^2 - v.v) I + 2 v v^T + 2 w [v]x."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device).expand(q.shape[0], 3, 3)
    zero = torch.zeros_like(w)
    cross = torch.stack([zero, -v[:, 2], v[:, 1], v[:, 2], zero, -v[:, 0], -v[:, 1], v[:, 0], zero], dim=-1).reshape(
        -1, 3, 3
    )
    vv = (v * v).sum(-1)
    return (w * w - vv)[:, None, None] * eye + 2.0 * v[:, :, None] * v[:, None, :] + 2.0 * w[:, None, None] * cross


def reference_project(means, quats, scales, viewmat, K, width, height, eps2d=EPS2D):
    """One camera. means [N, 3], quats [N, 4], scales [N, 3], viewmat [4, 4], K [3, 3] ->
    means2d [N, 2], conic matrices [N, 2, 2], depths [N], radii [N] (float, 0 = culled)."""
    R = _rotation(quats)
    cov = R @ torch.diag_embed(scales * scales) @ R.transpose(1, 2)  # [N, 3, 3]
    W, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ W.T + t  # [N, 3]
    cov_c = W @ cov @ W.T  # [N, 3, 3]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x = (cx / fx + 0.3 * 0.5 * width / fx, (width - cx) / fx + 0.3 * 0.5 * width / fx)
    lim_y = (cy / fy + 0.3 * 0.5 * height / fy, (height - cy) / fy + 0.3 * 0.5 * height / fy)
    tx = z * torch.clamp(x / z, -lim_x[0], lim_x[1])
    ty = z * torch.clamp(y / z, -lim_y[0], lim_y[1])
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / z**2, zero, fy / z, -fy * ty / z**2], -1)
    J = J.reshape(-1, 2, 3)
    cov2d = J @ cov_c @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=p.dtype, device=p.device)
    det = torch.linalg.det(cov2d)
    ok = det > 0
    safe = torch.where(ok[:, None, None], cov2d, torch.eye(2, dtype=p.dtype, device=p.device))
    conic = torch.linalg.inv(safe)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    with torch.no_grad():
        b = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
        radius = torch.ceil(3.0 * torch.sqrt(b + torch.sqrt(torch.clamp(b * b - det, min=0.01))))
        m = means2d
        keep = ok & (z >= NEAR) & (z <= FAR)
        keep &= (m[:, 0] + radius > 0) & (m[:, 0] - radius < width)
        keep &= (m[:, 1] + radius > 0) & (m[:, 1] - radius < height)
        radius = torch.where(keep, radius, torch.zeros_like(radius))
    return means2d, conic, z, radius


def _setup(g: Gaussians, cameras: Cameras, background, sh_degree):
    """Camera count, image size, SH degree, viewmats, Ks and background [C, 3] in g's dtype."""
    dtype, device = g.means.dtype, g.means.device
    ncam = len(cameras)
    degree = g.sh_degree if sh_degree is None else int(sh_degree)
    viewmats = cameras.viewmats.to(dtype=dtype, device=device)
    Ks = cameras.Ks.to(dtype=dtype, device=device)
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else background
    bg = torch.as_tensor(bg, dtype=dtype, device=device).expand(ncam, 3)
    return ncam, int(cameras.width), int(cameras.height), degree, viewmats, Ks, bg


def reference_render(
    gaussians: Gaussians,
    cameras: Cameras,
    *,
    background=None,  # [3] or [C, 3]
    sh_degree: int | None = None,
    chunk: int = 1 << 30,  # pixels per dense block (memory ~ chunk * N * a few tensors)
) -> RenderOutput:
    """Dense per-pixel rendering; dtype and device follow gaussians.means."""
    g = gaussians
    dtype, device = g.means.dtype, g.means.device
    ncam, w, h, degree, viewmats, Ks, bg = _setup(g, cameras, background, sh_degree)
    colors = eval_sh_colors(g.sh, g.means, viewmats, degree)  # [C, N, 3]
    ys, xs = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 2).to(dtype) + 0.5  # [P, 2]
    ptile = torch.div(torch.stack([xs, ys], -1).reshape(-1, 2), TILE, rounding_mode="floor")
    rgbs, alphas, depths = [], [], []
    for c in range(ncam):
        m2, conic, z, radius = reference_project(g.means, g.quats, g.scales, viewmats[c], Ks[c], w, h)
        with torch.no_grad():
            lo = torch.floor(m2.detach() / TILE - radius[:, None] / TILE)  # [N, 2]
            hi = torch.ceil(m2.detach() / TILE + radius[:, None] / TILE)
            order = torch.sort(z.detach(), stable=True).indices
        # everything below is in depth order along the last axis
        m2, conic, z, col = m2[order], conic[order], z[order], colors[c][order]
        op, lo, hi, rad = g.opacities[order], lo[order], hi[order], radius[order]
        rgb_c, a_c, d_c = [], [], []
        for start in range(0, pix.shape[0], chunk):
            px, pt = pix[start : start + chunk], ptile[start : start + chunk]
            member = ((pt[:, None, :] >= lo[None]) & (pt[:, None, :] < hi[None])).all(-1)
            member &= rad[None] > 0  # [P, N]
            d = m2[None] - px[:, None]  # [P, N, 2]
            sigma = 0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
            alpha = torch.clamp(op[None] * torch.exp(-sigma), max=0.999)
            valid = member & (sigma >= 0) & (alpha >= 1.0 / 255.0)
            with torch.no_grad():
                t_after = torch.cumprod(1.0 - torch.where(valid, alpha, 0.0), dim=-1)
                keep = valid & (t_after > 1e-4)
            a = torch.where(keep, alpha, torch.zeros_like(alpha))
            trans = torch.cumprod(1.0 - a, dim=-1)  # after each
            before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=-1)
            wgt = a * before  # [P, N]
            acc_a = 1.0 - trans[:, -1] if trans.shape[1] else torch.zeros_like(px[:, 0])
            rgb_c.append(wgt @ col + (1.0 - acc_a)[:, None] * bg[c])
            a_c.append(acc_a)
            d_c.append((wgt @ z) / acc_a.clamp(min=1e-10))
        rgbs.append(torch.cat(rgb_c).reshape(h, w, 3))
        alphas.append(torch.cat(a_c).reshape(h, w))
        depths.append(torch.cat(d_c).reshape(h, w))
    return RenderOutput(torch.stack(rgbs), torch.stack(alphas), torch.stack(depths))


def pairs_render(
    gaussians: Gaussians,
    cameras: Cameras,
    *,
    background=None,  # [3] or [C, 3]
    sh_degree: int | None = None,
) -> RenderOutput:
    """Tile-free pure-torch renderer over an explicit list of (Gaussian, pixel) pairs.

    Same conventions as `reference_render`, but only the pairs that can count are built: pixels
    inside both the Gaussian's member tiles and the box where alpha can reach 1/255
    (|dx| <= sqrt(2 log(255 o) cov_xx), same for y, + a small margin). Pairs are sorted by
    (pixel, depth); transmittance is a segmented cumulative sum of log(1 - alpha) in float64.
    Autograd does the backward. Used as the pure-torch baseline of `dla bench speed --suite splat`.
    """
    from dlacli.render.splat import project_gaussians  # same projection as the CPU kernel path

    g = gaussians
    dtype, device = g.means.dtype, g.means.device
    ncam, w, h, degree, viewmats, Ks, bg = _setup(g, cameras, background, sh_degree)
    proj = project_gaussians(g.means, g.quats, g.scales, viewmats, Ks, w, h)
    colors = eval_sh_colors(g.sh, g.means, viewmats, degree)  # [C, N, 3]
    outs = []
    for c in range(ncam):
        m2, conic, z = proj.means2d[c], proj.conics[c], proj.depths[c]
        with torch.no_grad():
            rad = proj.radii[c].to(dtype)
            ca, cb, cc = conic.detach().double().unbind(-1)
            op = g.opacities.detach().double()
            det = ca * cc - cb * cb
            thr = torch.log(op.clamp(min=1e-30) * 255.0) + 0.05
            ok = (rad > 0) & (det > 0) & (op * 255.0 >= 1.0)
            ex = torch.sqrt((2.0 * thr * cc / det).clamp(min=0.0)).nan_to_num(0.0)
            ey = torch.sqrt((2.0 * thr * ca / det).clamp(min=0.0)).nan_to_num(0.0)
            md = m2.detach().double()
            tx0 = torch.floor(md[:, 0] / TILE - rad / TILE).clamp(0, (w + TILE - 1) // TILE)
            tx1 = torch.ceil(md[:, 0] / TILE + rad / TILE).clamp(0, (w + TILE - 1) // TILE)
            ty0 = torch.floor(md[:, 1] / TILE - rad / TILE).clamp(0, (h + TILE - 1) // TILE)
            ty1 = torch.ceil(md[:, 1] / TILE + rad / TILE).clamp(0, (h + TILE - 1) // TILE)
            x0 = torch.maximum(torch.ceil(md[:, 0] - ex - 0.5).clamp(-1, w), tx0 * TILE)
            x1 = torch.minimum(torch.floor(md[:, 0] + ex - 0.5).clamp(-1, w), (tx1 * TILE - 1).clamp(max=w - 1))
            y0 = torch.maximum(torch.ceil(md[:, 1] - ey - 0.5).clamp(-1, h), ty0 * TILE)
            y1 = torch.minimum(torch.floor(md[:, 1] + ey - 0.5).clamp(-1, h), (ty1 * TILE - 1).clamp(max=h - 1))
            nx = (x1 - x0 + 1).clamp(min=0).long()
            ny = (y1 - y0 + 1).clamp(min=0).long()
            cnt = torch.where(ok, nx * ny, torch.zeros_like(nx))
            order = torch.sort(z.detach(), stable=True).indices  # depth order, ties by index
            cnt_o = cnt[order]
            gid = torch.repeat_interleave(order, cnt_o)  # [P] Gaussian of each pair
            first = torch.cumsum(cnt_o, 0) - cnt_o
            local = torch.arange(gid.shape[0], device=device) - torch.repeat_interleave(first, cnt_o)
            px = x0.long()[gid] + local % nx[gid]
            py = y0.long()[gid] + torch.div(local, nx[gid], rounding_mode="floor")
            pix = py * w + px
            perm = torch.sort(pix, stable=True).indices  # pixel-major, depth order inside
            gid, px, py, pix = gid[perm], px[perm], py[perm], pix[perm]
            _, seg = torch.unique_consecutive(pix, return_counts=True)
            seg_first = torch.repeat_interleave(torch.cumsum(seg, 0) - seg, seg)  # [P]
        dx = m2[gid, 0] - (px.to(dtype) + 0.5)
        dy = m2[gid, 1] - (py.to(dtype) + 0.5)
        cg = conic[gid]
        sigma = 0.5 * (cg[:, 0] * dx * dx + cg[:, 2] * dy * dy) + cg[:, 1] * dx * dy
        alpha = torch.clamp(g.opacities[gid] * torch.exp(-sigma), max=0.999)
        valid = (sigma >= 0) & (alpha >= 1.0 / 255.0)
        with torch.no_grad():
            lv = torch.log1p(-torch.where(valid, alpha, 0.0).double())
            cs = torch.cumsum(lv, 0)
            after = cs - (cs[seg_first] - lv[seg_first])  # log T after each pair, per pixel
            keep = valid & (torch.exp(after) > 1e-4)
        a = torch.where(keep, alpha, torch.zeros_like(alpha))
        la = torch.log1p(-a.double())
        cs = torch.cumsum(la, 0)
        before = cs - la - (cs[seg_first] - la[seg_first])  # log T in front of each pair
        wgt = (a.double() * torch.exp(before)).to(dtype)  # [P]
        feats = torch.cat([colors[c][gid], z[gid, None]], -1) * wgt[:, None]  # [P, 4]
        acc = torch.zeros(h * w, 4, dtype=dtype, device=device).index_add(0, pix, feats)
        acc_a = torch.zeros(h * w, dtype=dtype, device=device).index_add(0, pix, wgt)
        rgb = acc[:, :3] + (1.0 - acc_a)[:, None] * bg[c]
        depth = acc[:, 3] / acc_a.clamp(min=1e-10)
        outs.append((rgb.reshape(h, w, 3), acc_a.reshape(h, w), depth.reshape(h, w)))
    return RenderOutput(*(torch.stack(t) for t in zip(*outs)))
