"""Differentiable 3D Gaussian splatting: CPU numba kernels, gsplat on CUDA.

`render_gaussians(gaussians, cameras)` -> RenderOutput(rgb [C, H, W, 3], alpha [C, H, W],
depth [C, H, W]), differentiable w.r.t. means, quats, scales, opacities and SH coefficients.
The conventions (gsplat "classic" mode, eps2d 0.3, tile size 16, ...) are written in
docs/rendering.md. The pieces are plain functions:

- `project_gaussians`: EWA projection to 2D means, conics, depths and integer radii; on CPU
  with the cameras held fixed one numba kernel forward and one backward (`_ProjectCPU`), else
  torch code (where, on CPU, the world-to-camera transform is a numba kernel); both bitwise the
  same for any thread count (docs/rendering.md "Projection", "Determinism");
- `eval_sh_colors` (torch): view-dependent colour from SH, + 0.5, clamped at 0 (as 3DGS);
- `rasterize_projected` (torch.autograd.Function over the numba kernels in binning_kernels.py and
  splat_kernels.py):
  tile binning, front-to-back compositing and its backward pass. Without autograd (no_grad, or
  no input needing a gradient) `render_gaussians` calls the kernels directly and composes the
  images in one numba pass (`splat_kernels.compose`): the same values bit for bit.

On CUDA tensors with gsplat importable, `render_gaussians` calls `gsplat.rasterization` with the
same settings instead; gsplat is imported lazily there and never sees CPU tensors.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from dlacli.errors import DlaInputError
from dlacli.kernel_path import takes_kernels
from dlacli.render import binning_kernels as B
from dlacli.render import camera_kernels
from dlacli.render import fast_kernels as F
from dlacli.render import splat_kernels as K
from dlacli.render.sh import eval_sh_colors
from dlacli.types import Cameras, Gaussians

EPS2D = 0.3
NEAR = 0.01
FAR = 1e10
TILE = B.TILE


class RenderOutput(NamedTuple):
    rgb: torch.Tensor  # [C, H, W, 3] composited over the background
    alpha: torch.Tensor  # [C, H, W] 1 - final transmittance
    depth: torch.Tensor  # [C, H, W] expected z-depth sum(w_i z_i) / alpha, 0 where alpha == 0

    def rgba(self, k: int = 0) -> np.ndarray:
        """Camera k's image as a numpy RGBA [H, W, 4] (a copy, `K.pack_rgba`)."""
        rgb = np.ascontiguousarray(self.rgb[k].detach().cpu().numpy())
        alpha = np.ascontiguousarray(self.alpha[k].detach().cpu().numpy(), dtype=rgb.dtype)
        out = np.empty((*rgb.shape[:2], 4), dtype=rgb.dtype)
        K.pack_rgba(rgb, alpha, out)
        return out


class Projected(NamedTuple):
    means2d: torch.Tensor  # [C, N, 2] pixels
    conics: torch.Tensor  # [C, N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: torch.Tensor  # [C, N] camera z
    radii: torch.Tensor  # [C, N] int32, 0 = culled


def _check_shape(name: str, t: torch.Tensor, shape: tuple) -> None:
    """Raise DlaInputError unless `t` has `shape` (None matches any size)."""
    ok = t.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape))
    if not ok:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise DlaInputError(name, f"expected shape {want}, got {list(t.shape)}")


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), normalised here -> [N, 3, 3] rotation matrices."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


class _CameraPoints(torch.autograd.Function):
    """p[c, n] = R[c] mu[n] + t[c] on CPU tensors, by numba kernels whose results do not depend
    on the thread count (`camera_kernels.camera_points`).

    torch's einsum / matmul hands these shapes to MKL's gemm, whose results change with the
    number of threads, forward (C = 3, N = 3,000: 1 vs 2 threads, up to 8e-6 px in the 2D
    means) and backward (d mu, an [N, 3C] x [3C, 3] product: 1 vs 3 threads at C = 7 or 12).
    d R and d t (only when the cameras themselves are optimised) are torch sums over N, one
    output per thread (also independent of the thread count).
    """

    @staticmethod
    def forward(ctx, R, t, means):  # R [C, 3, 3], t [C, 3], means [N, 3] -> [C, N, 3]
        ctx.save_for_backward(R, means)
        dtype = torch.promote_types(R.dtype, means.dtype)

        def arr(x):
            return x.detach().to(dtype).contiguous().numpy()

        out = torch.empty((R.shape[0], means.shape[0], 3), dtype=dtype)
        camera_kernels.camera_points(arr(R), arr(t), arr(means), out.numpy())
        return out

    @staticmethod
    def backward(ctx, g):  # g [C, N, 3]
        R, means = ctx.saved_tensors
        g = g.contiguous()
        g_R = g_t = g_means = None
        if ctx.needs_input_grad[2]:
            out = torch.empty(means.shape, dtype=g.dtype)
            camera_kernels.camera_points_grad(R.detach().to(g.dtype).contiguous().numpy(), g.numpy(), out.numpy())
            g_means = out.to(means.dtype)
        if ctx.needs_input_grad[0]:
            g_R = (g[:, :, :, None] * means[None, :, None, :].to(g.dtype)).sum(dim=1).to(R.dtype)
        if ctx.needs_input_grad[1]:
            g_t = g.sum(dim=1).to(R.dtype)
        return g_R, g_t, g_means


def _camera_points(R: torch.Tensor, t: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    """R [C, 3, 3] @ means [N, 3] + t [C, 3] -> [C, N, 3]; thread-count independent on CPU."""
    if R.device.type == "cpu" and means.device.type == "cpu":
        return _CameraPoints.apply(R, t, means)
    return torch.einsum("cij,nj->cni", R, means) + t[:, None, :]


def project_gaussians(
    means: torch.Tensor,  # [N, 3] world
    quats: torch.Tensor,  # [N, 4] (w, x, y, z), any norm
    scales: torch.Tensor,  # [N, 3] linear
    viewmats: torch.Tensor,  # [C, 4, 4] world-to-camera, OpenCV axes
    Ks: torch.Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    eps2d: float = EPS2D,
    near: float = NEAR,
    far: float = FAR,
) -> Projected:
    """EWA projection as gsplat's pinhole `fully_fused_projection` (classic mode).

    Covariance R S S^T R^T -> camera frame -> J Sigma J^T with the pinhole Jacobian J evaluated
    at the mean whose x/z, y/z are clamped to 1.3 x the half field of view (gsplat does this to
    keep off-screen Gaussians bounded), + eps2d on the diagonal. radius = ceil(3 sqrt(lambda_max))
    with lambda_max = b + sqrt(max(b^2 - det, 0.01)), b = trace / 2. Culled (radius 0): depth
    < near or > far, det <= 0, or the square of half-side `radius` entirely off the image.
    """
    n = means.shape[0] if means.ndim == 2 else -1
    _check_shape("means", means, (None, 3))
    _check_shape("quats", quats, (n, 4))
    _check_shape("scales", scales, (n, 3))
    _check_shape("viewmats", viewmats, (None, 4, 4))
    _check_shape("Ks", Ks, (viewmats.shape[0], 3, 3))
    if takes_kernels(means, quats, scales, viewmats, Ks, held=(viewmats, Ks), dtype=None):
        return _project_fused(means, quats, scales, viewmats, Ks, width, height, eps2d, near, far)
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3] columns R_i s_i
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    pc = _camera_points(R, t, means)  # [C, N, 3]
    x, y, z = pc.unbind(-1)  # [C, N]
    fx = Ks[:, 0, 0, None]  # [C, 1]
    fy = Ks[:, 1, 1, None]
    cx = Ks[:, 0, 2, None]
    cy = Ks[:, 1, 2, None]
    tanx = 0.5 * width / fx
    tany = 0.5 * height / fy
    rz = 1.0 / z
    u = torch.minimum(torch.maximum(x * rz, -(cx / fx + 0.3 * tanx)), (width - cx) / fx + 0.3 * tanx)
    v = torch.minimum(torch.maximum(y * rz, -(cy / fy + 0.3 * tany)), (height - cy) / fy + 0.3 * tany)
    # rows of J R (camera Jacobian times view rotation): [C, 3] broadcast with [C, N]
    j0 = (fx * rz)[..., None] * (R[:, None, 0, :] - u[..., None] * R[:, None, 2, :])  # [C, N, 3]
    j1 = (fy * rz)[..., None] * (R[:, None, 1, :] - v[..., None] * R[:, None, 2, :])  # [C, N, 3]
    # per Gaussian [C, 3] x [3, 3] products: torch's plain loop kernel (bmm with < 400
    # multiply-adds per matrix, i.e. C <= 44), the same for any thread count
    a0 = torch.einsum("cnj,njk->cnk", j0, M)  # [C, N, 3] row 0 of J R M
    a1 = torch.einsum("cnj,njk->cnk", j1, M)
    cov_xx = (a0 * a0).sum(-1) + eps2d  # [C, N]
    cov_xy = (a0 * a1).sum(-1)
    cov_yy = (a1 * a1).sum(-1) + eps2d
    det = cov_xx * cov_yy - cov_xy * cov_xy
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([cov_yy / det_safe, -cov_xy / det_safe, cov_xx / det_safe], dim=-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C, N, 2]
    with torch.no_grad():
        b = 0.5 * (cov_xx + cov_yy)
        lam = b + torch.sqrt(torch.clamp(b * b - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        mx, my = means2d.unbind(-1)
        keep = (z >= near) & (z <= far) & (det > 0) & torch.isfinite(radius)
        keep &= (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(keep, radius.clamp(max=2.0**30), torch.zeros_like(radius)).to(torch.int32)
    return Projected(means2d, conics, z, radii)


class _ProjectCPU(torch.autograd.Function):
    """`project_gaussians` on CPU tensors as two numba kernels (`camera_kernels.project_fused`
    and `project_fused_grad`): one thread per Gaussian, float64 inside, instead of ~60 torch
    operations on [C, N] tensors and their autograd graph. Outputs agree with the torch code
    within the rounding of the input dtype (docs/rendering.md "Projection"); the results do not
    depend on the thread count. Gradients w.r.t. means, quats and scales (cameras fixed)."""

    @staticmethod
    def forward(ctx, means, quats, scales, intr, rot, trans, width, height, eps2d, near, far):
        dtype = means.dtype
        ncam, n = rot.shape[0], means.shape[0]
        means2d = torch.empty((ncam, n, 2), dtype=dtype)
        conics = torch.empty((ncam, n, 3), dtype=dtype)
        depths = torch.empty((ncam, n), dtype=dtype)
        radii = torch.empty((ncam, n), dtype=torch.int32)
        geo = (means, quats, scales, rot, trans, intr, float(width), float(height), float(eps2d))
        ctx.save_for_backward(means, quats, scales, rot, trans, intr)
        ctx.meta = geo[6:]
        camera_kernels.project_fused(
            *(_np(x) for x in geo[:6]),
            *geo[6:],
            float(near),
            float(far),
            means2d.numpy(),
            conics.numpy(),
            depths.numpy(),
            radii.numpy(),
        )
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_m2, g_con, g_z, _g_radii):
        means, quats, scales, rot, trans, intr = ctx.saved_tensors
        ncam, n = rot.shape[0], means.shape[0]
        dtype = means.dtype

        def grad(g, shape):
            return _np(torch.zeros(shape, dtype=dtype) if g is None else g.to(dtype))

        out = [torch.empty((n, k), dtype=dtype) for k in (3, 4, 3)]
        camera_kernels.project_fused_grad(
            *(_np(x) for x in (means, quats, scales, rot, trans, intr)),
            *ctx.meta,
            grad(g_m2, (ncam, n, 2)),
            grad(g_con, (ncam, n, 3)),
            grad(g_z, (ncam, n)),
            *(o.numpy() for o in out),
        )
        g_mu, g_q, g_s = (o.to(t.dtype) for o, t in zip(out, (means, quats, scales)))
        return g_mu, g_q, g_s, None, None, None, None, None, None, None, None


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


def _camera_arrays(viewmats, Ks) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What the numba kernels read of the cameras: intrinsics [C, 4] (fx, fy, cx, cy), rotations
    [C, 3, 3] and translations [C, 3] of the view matrices, detached."""
    intr = torch.stack([Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]], dim=-1).detach()
    return intr, viewmats[:, :3, :3].detach(), viewmats[:, :3, 3].detach()


def _project_fused(means, quats, scales, viewmats, Ks, width, height, eps2d, near, far) -> Projected:
    intr, rot, trans = _camera_arrays(viewmats, Ks)
    return Projected(*_ProjectCPU.apply(means, quats, scales, intr, rot, trans, width, height, eps2d, near, far))


def _raster_cpu(means2d, conics, colors, opacities, radii, depths, width, height):
    """The numba forward pass: binning and compositing -> (acc [C, H, W, 4] numpy in the input's
    precision, t_final [C, H, W] float64, and what the backward pass needs)."""
    dtype = means2d.dtype
    npd = np.float64 if dtype == torch.float64 else np.float32

    def arr(t, np_dtype):
        return np.ascontiguousarray(t.detach().cpu().numpy().astype(np_dtype, copy=False))

    rd = arr(radii, np.int64)
    dk = arr(depths, np.float32)
    dk = np.where(rd > 0, dk, np.float32(1.0)).astype(np.float32).view(np.uint32)
    params, offsets, lists, trect = B.bin_gaussians(
        arr(means2d, npd), arr(conics, npd), arr(opacities, npd), arr(colors, npd), rd, dk, width, height
    )
    acc, tfin, saved = composite_lists(params, offsets, lists, means2d.shape[0], width, height)
    return acc, tfin, (params, offsets, lists, trect, *saved)


def composite_lists(params, offsets, lists, ncam, width, height, exact: bool = True):
    """`K.raster_forward` over the binned pairs -> (acc [C, H, W, 4] in params' dtype, t_final
    [C, H, W] float64, (t_final, last, work) for the backward pass); `exact=False` (float32
    params only): `F.raster_forward_fast`, whose third item is (t_final, None, work)."""
    cost = np.diff(offsets).astype(np.float64)
    wptr, wtiles = B.assign_workers(cost, K.num_threads())
    acc = np.empty((ncam, height, width, 4), dtype=params.dtype)
    tfin = np.empty((ncam, height, width), dtype=np.float64)
    work = np.zeros(cost.shape[0], dtype=np.float64)
    if not exact and params.dtype == np.float32:
        F.raster_forward_fast(params, offsets, lists, wptr, wtiles, ncam, width, height, acc, tfin, work)
        return acc, tfin, (tfin, None, work)
    last = np.empty((ncam, height, width), dtype=np.int64)
    K.raster_forward(params, offsets, lists, wptr, wtiles, ncam, width, height, acc, tfin, last, work)
    return acc, tfin, (tfin, last, work)


def binned_plain(
    g: Gaussians, viewmats, Ks, width, height, degree, opacities=None, sh=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection and packing in one numba pass (`B.project_and_pack`), then the tiles' depth-sorted
    lists (`B.tile_lists`) -> (params [C * N, B.NPARAM], tile offsets, lists): what the compositing
    kernels read (also `dlacli.render.splat_stats`). opacities [C, N] and sh [C, N, K, 3]: each
    camera's own, in place of g's (`render_gaussians`)."""
    dtype = g.means.dtype
    npd = np.float64 if dtype == torch.float64 else np.float32
    ncam, n = viewmats.shape[0], len(g)
    rgb = eval_sh_colors(g.sh if sh is None else sh, g.means, viewmats, degree).to(dtype)  # [C, N, 3]
    if opacities is None:
        opacities = g.opacities[None].expand(ncam, -1)
    params = np.empty((ncam * n, B.NPARAM), dtype=npd)
    trect = np.empty((ncam * n, 4), dtype=np.int32)
    radii = np.empty((ncam, n), dtype=np.int32)
    keys = np.empty((ncam, n), dtype=np.float32)
    intr, rot, trans = _camera_arrays(viewmats, Ks)
    B.project_and_pack(
        *(_np(t) for t in (g.means, g.quats, g.scales, opacities)),
        rgb.numpy(),
        *(_np(t) for t in (rot, trans, intr)),
        float(width),
        float(height),
        float(EPS2D),
        float(NEAR),
        float(FAR),
        params,
        trect,
        radii,
        keys,
    )
    offsets, lists = B.tile_lists(keys.view(np.uint32), trect, width, height)
    return params, offsets, lists


def _render_plain_cpu(
    g: Gaussians, viewmats, Ks, width, height, bg, degree, exact: bool = True, opacities=None, sh=None
) -> RenderOutput:
    """`render_gaussians` without autograd on the CPU: `binned_plain`, then the same compositing
    and `K.compose` as the autograd route, whose images it equals bit for bit
    (tests/render/test_splat.py); `exact=False` composites with `F.raster_forward_fast` (float32;
    tests/render/test_splat_fast.py)."""
    dtype = g.means.dtype
    ncam = viewmats.shape[0]
    params, offsets, lists = binned_plain(g, viewmats, Ks, width, height, degree, opacities, sh)
    acc, tfin, _ = composite_lists(params, offsets, lists, ncam, width, height, exact)
    out = RenderOutput(*(torch.empty(s, dtype=dtype) for s in ((ncam, height, width, 3), *[(ncam, height, width)] * 2)))
    K.compose(acc, tfin, bg.detach().contiguous().numpy(), *(t.numpy() for t in out))
    return out


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, radii, depths, width, height):
        dtype = means2d.dtype
        acc, tfin, ctx.saved = _raster_cpu(means2d, conics, colors, opacities, radii, depths, width, height)
        ctx.meta = (width, height, means2d.shape, dtype, means2d.device)
        alpha = torch.from_numpy(1.0 - tfin).to(dtype=dtype, device=means2d.device)
        return torch.from_numpy(acc).to(means2d.device), alpha

    @staticmethod
    def backward(ctx, g_acc, g_alpha):
        params, offsets, lists, trect, tfin, last, work = ctx.saved
        width, height, shape, dtype, device = ctx.meta
        ncam, n = shape[0], shape[1]
        if g_acc is None:
            g_acc = torch.zeros((ncam, height, width, 4), dtype=dtype)
        if g_alpha is None:
            g_alpha = torch.zeros((ncam, height, width), dtype=dtype)
        ga = np.ascontiguousarray(g_acc.detach().cpu().numpy())
        gl = np.ascontiguousarray(g_alpha.detach().cpu().numpy())
        nw = K.num_threads()
        wptr, wtiles = B.assign_workers(work, nw)
        # one gradient row per (Gaussian, tile), summed per Gaussian in a fixed order: the same
        # gradients, bit for bit, for any thread count (docs/rendering.md "Determinism"); rows
        # are stored in the input's precision, like the parameters, and summed in float64
        sptr = B.isect_rows(trect)
        isect_grad = np.empty((lists.shape[0], K.NGRAD), dtype=params.dtype)
        isect_hit = np.zeros(lists.shape[0], dtype=np.uint8)
        K.raster_backward(
            params,
            offsets,
            lists,
            trect,
            sptr,
            wptr,
            wtiles,
            ncam,
            width,
            height,
            tfin,
            last,
            ga,
            gl,
            isect_grad,
            isect_hit,
        )
        full = np.empty((ncam * n, K.NGRAD), dtype=np.float32 if dtype != torch.float64 else np.float64)
        K.reduce_grads(isect_grad, isect_hit, sptr, full)
        full_t = torch.from_numpy(full).to(dtype=dtype, device=device).reshape(ncam, n, K.NGRAD)
        return (full_t[..., 0:2], full_t[..., 2:5], full_t[..., 6:10], full_t[..., 5], None, None, None, None)


def rasterize_projected(
    means2d: torch.Tensor,  # [C, N, 2]
    conics: torch.Tensor,  # [C, N, 3]
    colors: torch.Tensor,  # [C, N, 4] composited channels (rgb + z-depth)
    opacities: torch.Tensor,  # [C, N]
    radii: torch.Tensor,  # [C, N] int, 0 = skip
    depths: torch.Tensor,  # [C, N] sort key (front to back); not differentiated
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """CPU tile rasteriser: ([C, H, W, 4] sum_i w_i colour_i, [C, H, W] alpha), no background.

    w_i = alpha_i prod_{j<i} (1 - alpha_j) over the Gaussians that count at the pixel
    (docs/rendering.md). Differentiable w.r.t. means2d, conics, colors and opacities. `depths`
    must be positive where radii > 0 (true for `project_gaussians` output).
    """
    _check_shape("means2d", means2d, (None, None, 2))
    c, n = means2d.shape[:2]
    _check_shape("conics", conics, (c, n, 3))
    _check_shape("colors", colors, (c, n, 4))
    _check_shape("opacities", opacities, (c, n))
    _check_shape("radii", radii, (c, n))
    _check_shape("depths", depths, (c, n))
    if width < 1 or height < 1:
        raise DlaInputError("rasterize_projected", f"image size must be >= 1, got {width}x{height}")
    return _RasterizeCPU.apply(means2d, conics, colors, opacities, radii, depths, width, height)


def check_render_inputs(g: Gaussians, cameras: Cameras, background, sh_degree, opacities=None, sh=None):
    n, ncam = len(g), len(cameras)
    for name, t, shape in (
        ("gaussians.means", g.means, (n, 3)),
        ("gaussians.quats", g.quats, (n, 4)),
        ("gaussians.scales", g.scales, (n, 3)),
        ("gaussians.opacities", g.opacities, (n,)),
        ("opacities", opacities, (ncam, n)),
    ):
        if t is None:
            continue
        if tuple(t.shape) != shape:
            raise DlaInputError(name, f"expected shape {list(shape)}, got {list(t.shape)}")
        if not t.is_floating_point():
            raise DlaInputError(name, f"expected a floating-point tensor, got {t.dtype}")
    if g.sh.ndim != 3 or g.sh.shape[0] != n or g.sh.shape[2] != 3:
        raise DlaInputError("gaussians.sh", f"expected shape [N, K, 3], got {list(g.sh.shape)}")
    if sh is not None and tuple(sh.shape) != (ncam, *g.sh.shape):
        raise DlaInputError("sh", f"expected shape {[ncam, *g.sh.shape]}, got {list(sh.shape)}")
    if cameras.width < 1 or cameras.height < 1:
        raise DlaInputError("cameras", f"image size must be >= 1, got {cameras.width}x{cameras.height}")
    if len(cameras) < 1:
        raise DlaInputError("cameras", "no cameras")
    degree = g.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= g.sh_degree:
        raise DlaInputError("sh_degree", f"must be in 0..{g.sh_degree} for {g.sh.shape[1]} coefficients, got {degree}")
    if background is None:
        bg = torch.zeros((ncam, 3), dtype=g.means.dtype, device=g.means.device)
    else:
        bg = torch.as_tensor(background, dtype=g.means.dtype, device=g.means.device)
        if tuple(bg.shape) == (3,):
            bg = bg[None].expand(ncam, 3)
        elif tuple(bg.shape) != (ncam, 3):
            raise DlaInputError("background", f"expected shape [3] or [{ncam}, 3], got {list(bg.shape)}")
    return degree, bg


def render_gaussians(
    gaussians: Gaussians,
    cameras: Cameras,
    *,
    background=None,  # [3] or [C, 3], default black
    sh_degree: int | None = None,
    exact: bool = True,
    opacities: torch.Tensor | None = None,
    sh: torch.Tensor | None = None,
) -> RenderOutput:
    """Render C views of N Gaussians; differentiable w.r.t. every Gaussian parameter.

    Appearance per camera (as gsplat's `rasterization` takes it): opacities [C, N] and SH
    coefficients sh [C, N, K, 3] (K as the Gaussians'), where given, replace the Gaussians' own,
    camera c seeing row c; each camera's image equals rendering it alone with those values.

    Leading batch dimensions B... of the Gaussians (`Gaussians.batch_shape`: several avatars,
    poses or training items) give outputs [B..., C, H, W(, 3)], every set seen by the same C
    cameras; item b equals rendering `gaussians.item(b)` alone, values and gradients.
    Device and dtype follow `gaussians.means`; cameras are moved there. float32 CUDA tensors with
    gsplat installed -> gsplat; otherwise the numba CPU path (CUDA tensors without gsplat, or
    not float32, are rendered on the CPU and the results moved back). `exact=False`: where no
    gradient is asked for, float32 on the CPU composites with the fast kernel
    (`fast_kernels.raster_forward_fast`: a polynomial exponential, float32 state; images within
    the tolerance docs/rendering.md states of the exact ones, the same bits run to run); ignored
    elsewhere.
    """
    lead = gaussians.batch_shape
    if lead:
        assert opacities is None and sh is None, "appearance per camera is for one set of Gaussians"
        flat = Gaussians(*(t.reshape(-1, *t.shape[len(lead) :]) for t in gaussians._tensors()))
        outs = [
            render_gaussians(flat.item(b), cameras, background=background, sh_degree=sh_degree, exact=exact)
            for b in range(flat.means.shape[0])
        ]
        return RenderOutput(*(torch.stack(parts).reshape(*lead, *parts[0].shape) for parts in zip(*outs)))
    degree, bg = check_render_inputs(gaussians, cameras, background, sh_degree, opacities, sh)
    device, dtype = gaussians.means.device, gaussians.means.dtype
    viewmats = cameras.viewmats.to(device=device, dtype=dtype)
    Ks = cameras.Ks.to(device=device, dtype=dtype)
    w, h = int(cameras.width), int(cameras.height)
    if device.type == "cuda" and dtype == torch.float32 and _gsplat_available():
        return _render_gsplat(gaussians, viewmats, Ks, w, h, bg, degree, opacities, sh)
    g = gaussians
    if device.type != "cpu":
        cpu = torch.device("cpu")
        g = gaussians.to(cpu)
        viewmats, Ks, bg = viewmats.to(cpu), Ks.to(cpu), bg.to(cpu)
        opacities, sh = (None if t is None else t.to(cpu) for t in (opacities, sh))
    grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad
        for t in (g.means, g.quats, g.scales, g.opacities, g.sh, viewmats, Ks, opacities, sh)
    )
    if grad:
        proj = project_gaussians(g.means, g.quats, g.scales, viewmats, Ks, w, h)
        rgb = eval_sh_colors(g.sh if sh is None else sh, g.means, viewmats, degree)  # [C, N, 3]
        colors = torch.cat([rgb, proj.depths[..., None]], dim=-1)  # [C, N, 4]
        opac = g.opacities[None].expand(viewmats.shape[0], -1) if opacities is None else opacities
        acc, alpha = rasterize_projected(
            proj.means2d, proj.conics, colors, opac, proj.radii, proj.depths.detach(), w, h
        )
        out_rgb = acc[..., :3] + (1.0 - alpha)[..., None] * bg[:, None, None, :]
        depth = acc[..., 3] / alpha.clamp(min=1e-10)
        out = RenderOutput(out_rgb, alpha, depth)
    else:  # no autograd: the same images without the torch intermediates
        with torch.no_grad():
            out = _render_plain_cpu(g, viewmats, Ks, w, h, bg, degree, exact, opacities, sh)
    if device.type != "cpu":
        out = RenderOutput(*(t.to(device) for t in out))
    return out


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def _render_gsplat(g: Gaussians, viewmats, Ks, width, height, bg, degree, opacities=None, sh=None) -> RenderOutput:
    """gsplat.rasterization with this module's conventions (CUDA tensors only); opacities [C, N]
    and sh [C, N, K, 3] per camera where given."""
    import gsplat

    assert g.means.device.type == "cuda", "gsplat must only be called with CUDA tensors"
    colors, alphas, _ = gsplat.rasterization(
        means=g.means,
        quats=g.quats,
        scales=g.scales,
        opacities=g.opacities if opacities is None else opacities,
        colors=g.sh if sh is None else sh,
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
        near_plane=NEAR,
        far_plane=FAR,
        eps2d=EPS2D,
        sh_degree=degree,
        packed=False,
        tile_size=TILE,
        backgrounds=bg.contiguous(),
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    alpha = alphas[..., 0]
    depth = torch.where(alpha > 0, colors[..., 3], torch.zeros_like(alpha))
    return RenderOutput(colors[..., :3], alpha, depth)
