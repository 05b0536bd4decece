"""Gaussian splatting: the numba CPU path against the dense float64 reference, analytic cases,
edge cases, and (on CUDA with gsplat only) against gsplat.

Relative gradient error is ||g - g_ref|| / max(||g_ref||, 1e-6) over each whole parameter tensor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dlacli.errors import DlaInputError
from dlacli.render.sh import sh_basis
from dlacli.render.splat import (
    project_gaussians,
    rasterize_projected,
    render_gaussians,
)
from dlacli.render.splat_reference import pairs_render, reference_render
from dlacli.types import Cameras, Gaussians

F64 = torch.float64
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def look_at_cameras(eyes, w, h, f, dtype=F64, cx=None, cy=None) -> Cameras:
    """Cameras at `eyes` looking at the origin with +Z up (via the OpenGL c2w convention)."""
    c2ws = []
    for eye in eyes:
        eye = np.asarray(eye, dtype=np.float64)
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -fwd, eye
        c2ws.append(c2w)
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    cams = Cameras.from_c2w_opengl(np.stack(c2ws), f, f * 1.1, cx, cy, w, h)
    return Cameras(cams.viewmats.to(dtype), cams.Ks.to(dtype), w, h)


def random_gaussians(n, degree, seed, extent=1.0, scale=(0.01, 0.2), opacity=(0.05, 1.0)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * extent
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    lo, hi = math.log(scale[0]), math.log(scale[1])
    scales = torch.exp(torch.empty(n, 3, dtype=F64).uniform_(lo, hi, generator=g))
    opac = torch.empty(n, dtype=F64).uniform_(*opacity, generator=g)
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=F64) * 0.4
    return Gaussians(means, quats, scales, opac, sh)


def with_grad(g: Gaussians) -> Gaussians:
    return Gaussians(*(getattr(g, p).detach().clone().requires_grad_(True) for p in PARAMS))


def rel_err(a, b):
    return ((a.double() - b.double()).norm() / b.double().norm().clamp(min=1e-6)).item()


def test_reference_gradcheck():
    g = random_gaussians(3, 1, seed=3, extent=0.3, scale=(0.05, 0.15), opacity=(0.3, 0.8))
    cams = look_at_cameras([(0.4, -2.5, 0.3), (-2.0, -1.0, 0.5)], 6, 5, 5.0)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    gen = torch.Generator().manual_seed(0)
    proj = [torch.randn(2, 6 * 5 * 5, generator=gen, dtype=F64) for _ in range(3)]

    def f(*ps):
        out = reference_render(Gaussians(*ps), cams, background=bg)
        flat = torch.cat([out.rgb, out.alpha[..., None], out.depth[..., None]], -1).reshape(2, -1)
        return torch.stack([(p * flat).sum() for p in proj])

    inputs = [getattr(g, p).clone().requires_grad_(True) for p in PARAMS]
    alpha = reference_render(g, cams).alpha
    assert alpha.max() > 0.3  # the scene is actually seen
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


SCENES = [(seed, deg) for seed in range(3) for deg in (0, 3)]


@pytest.mark.parametrize("seed,degree", SCENES)
def test_cpu_kernel_matches_reference(seed, degree):
    g = random_gaussians(70, degree, seed)
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3)], 40, 27, 36.0, cx=21.3, cy=12.9)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    ref_g, out_g = with_grad(g), with_grad(g.to(torch.float32))
    ref = reference_render(ref_g, cams, background=bg)
    out = render_gaussians(out_g, cams.to(torch.float32), background=bg.float())
    assert ref.alpha.max() > 0.5 and (ref.alpha == 0).any()
    for name, a, b in zip(("rgb", "alpha", "depth"), out, ref):
        assert a.shape == b.shape
        # float32 kernel vs float64 reference: a front-to-back composite of up to 70 Gaussians
        # (~10 roundings each) of values <= 3; ~300 float32 ulps of 3 (measured <= 1e-6)
        assert (a.double() - b).abs().max() < 1e-4, name
    gen = torch.Generator().manual_seed(100 + seed)
    weights = [torch.randn(t.shape, generator=gen, dtype=F64) for t in ref]
    loss_ref = sum((w * t).sum() for w, t in zip(weights, ref))
    loss_out = sum((w.float() * t).sum() for w, t in zip(weights, out))
    grads_ref = torch.autograd.grad(loss_ref, [getattr(ref_g, p) for p in PARAMS])
    grads_out = torch.autograd.grad(loss_out, [getattr(out_g, p) for p in PARAMS])
    for name, a, b in zip(PARAMS, grads_out, grads_ref):
        assert b.norm() > 0, name
        assert rel_err(a, b) < 1e-3, name  # float32 backward: sums over pixels (measured <= 3e-6)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_no_grad_render_equals_autograd_render(dtype):
    """Without autograd the images are composed by one numba pass (splat_kernels.compose) instead
    of torch operations on the rasteriser's outputs: the same formulas in the same precision and
    order, so the same values bit for bit (background, alpha, depth and the empty pixels)."""
    g = random_gaussians(90, 2, seed=5).to(dtype)
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3)], 41, 29, 36.0, dtype=dtype)
    bg = torch.tensor([[0.2, 0.5, 0.9], [0.7, 0.1, 0.3]], dtype=dtype)
    tracked = render_gaussians(with_grad(g), cams, background=bg)
    assert tracked.rgb.requires_grad
    with torch.no_grad():
        plain = render_gaussians(g, cams, background=bg)
    assert not plain.rgb.requires_grad
    assert (tracked.alpha == 0).any() and tracked.alpha.max() > 0.5
    for name, a, b in zip(("rgb", "alpha", "depth"), plain, tracked):
        assert a.dtype == dtype and torch.equal(a, b.detach()), name
    for k in range(2):  # the RGBA image a preview or a render writes
        rgba = tracked.rgba(k)
        assert rgba.shape == (29, 41, 4) and rgba.dtype == (np.float64 if dtype == torch.float64 else np.float32)
        assert np.array_equal(rgba, torch.cat([plain.rgb[k], plain.alpha[k][..., None]], dim=-1).numpy())


def test_pairs_render_matches_reference():
    """The pure-torch pair renderer used as the benchmark baseline renders the same images."""
    g = random_gaussians(120, 2, seed=11, extent=0.7, scale=(0.02, 0.3), opacity=(0.3, 1.0))
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3)], 37, 22, 33.0)
    a_g, b_g = with_grad(g), with_grad(g)
    ref = reference_render(a_g, cams, background=[0.3, 0.2, 0.1])
    out = pairs_render(b_g, cams, background=[0.3, 0.2, 0.1])
    for a, b in zip(out, ref):
        assert (a - b).abs().max() < 1e-9
    loss_a = ref.rgb.sum() + ref.alpha.sum() + 0.3 * ref.depth.sum()
    loss_b = out.rgb.sum() + out.alpha.sum() + 0.3 * out.depth.sum()
    for p in PARAMS:
        ga = torch.autograd.grad(loss_a, getattr(a_g, p), retain_graph=True)[0]
        gb = torch.autograd.grad(loss_b, getattr(b_g, p), retain_graph=True)[0]
        assert rel_err(gb, ga) < 1e-8, p


def test_cpu_kernel_matches_reference_dense_scene():
    """Many overlapping opaque Gaussians: saturated pixels, early termination, alpha cap."""
    g = random_gaussians(250, 1, seed=7, extent=0.6, scale=(0.05, 0.3), opacity=(0.6, 1.0))
    cams = look_at_cameras([(0.3, -2.0, 0.2), (2.0, 0.5, 0.5)], 35, 21, 30.0)
    ref_g, out_g = with_grad(g), with_grad(g.to(torch.float32))
    ref = reference_render(ref_g, cams)
    out = render_gaussians(out_g, cams.to(torch.float32))
    assert (ref.alpha > 1 - 1e-3).sum() > 50  # deep enough for the 1e-4 stop to matter
    for a, b in zip(out, ref):
        assert (a.double() - b).abs().max() < 1e-4  # float32 vs float64, as above
    loss_ref = ref.rgb.sum() + 0.3 * ref.depth.sum() - ref.alpha.sum()
    loss_out = out.rgb.sum() + 0.3 * out.depth.sum() - out.alpha.sum()
    for p in PARAMS:
        a = torch.autograd.grad(loss_out, getattr(out_g, p), retain_graph=True)[0]
        b = torch.autograd.grad(loss_ref, getattr(ref_g, p), retain_graph=True)[0]
        assert rel_err(a, b) < 1e-3, p


def test_cpu_kernel_gradcheck_float64():
    """The hand-written backward against finite differences, straight through the kernels."""
    g = random_gaussians(4, 1, seed=1, extent=0.3, scale=(0.02, 0.2), opacity=(0.2, 0.8))
    cams = look_at_cameras([(0.5, -2.5, 0.3), (-2.0, -1.5, 0.2)], 7, 6, 6.3)
    inputs = [getattr(g, p).clone().requires_grad_(True) for p in PARAMS]
    gen = torch.Generator().manual_seed(1)
    proj = [torch.randn(2 * 6 * 7 * 5, generator=gen, dtype=F64) for _ in range(3)]

    def f(*ps):
        out = render_gaussians(Gaussians(*ps), cams, background=torch.tensor([0.3, 0.1, 0.6]))
        flat = torch.cat([out.rgb, out.alpha[..., None], out.depth[..., None]], -1).reshape(-1)
        return torch.stack([(p * flat).sum() for p in proj])

    assert render_gaussians(g, cams).alpha.max() > 0.3
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def _head_on_camera(w, h, f, dtype=F64):
    viewmat = torch.eye(4, dtype=dtype)[None]
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=dtype)[None]
    return Cameras(viewmat, K, w, h)


@pytest.mark.parametrize("render", [render_gaussians, reference_render], ids=["cpu", "reference"])
def test_isotropic_gaussian_head_on(render, tol):
    f, z, s, opacity = 40.0, 2.0, 0.12, 0.8
    w = h = 16  # one tile, so every pixel is a member of the Gaussian's tile range
    g = Gaussians(
        torch.tensor([[0.0, 0.0, z]], dtype=F64),
        torch.tensor([[0.3, -0.5, 0.2, 0.7]], dtype=F64),  # rotation is irrelevant: isotropic
        torch.full((1, 3), s, dtype=F64),
        torch.tensor([opacity], dtype=F64),
        torch.tensor([[[0.7, -0.2, 0.1]]], dtype=F64),
    )
    out = render(g, _head_on_camera(w, h, f))
    var = (f * s / z) ** 2 + 0.3
    ys, xs = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    r2 = (xs - w / 2) ** 2 + (ys - h / 2) ** 2
    expect = opacity * np.exp(-r2 / (2 * var))
    expect[expect < 1 / 255] = 0.0
    # float64 throughout (was 1e-6 and 1e-9: ~1e10 and ~1e7 ulps). The exponent (<= 5.3 where
    # alpha >= 1/255) carries the 2D covariance's rounding (J W S W^T J^T, ~30 steps): <= ~160
    # roundings relative, on values <= 1; the depth is a normalised weighted mean of z = 2
    atol = tol(torch.float64, 1.0, 256)
    assert np.abs(out.alpha[0].numpy() - expect).max() < atol
    rgb = 0.5 + 0.28209479177387814 * np.array([0.7, -0.2, 0.1])
    assert np.abs(out.rgb[0].numpy() - expect[..., None] * rgb).max() < atol
    seen = expect > 0
    assert np.abs(out.depth[0].numpy()[seen] - z).max() < tol(torch.float64, z, 256)
    assert (out.depth[0].numpy()[~seen] == 0).all()


@pytest.mark.parametrize("render", [render_gaussians, reference_render], ids=["cpu", "reference"])
def test_stop_rule_and_alpha_cap(render):
    """Stacked Gaussians with alpha 0.95 at the centre: after three T = 0.05^3 = 1.25e-4 > 1e-4;
    the fourth would bring it to 6.25e-6 <= 1e-4, so the pixel stops before it (gsplat)."""
    f, n = 40.0, 5
    depths = torch.arange(n, dtype=F64) + 2.0
    means = torch.stack([torch.zeros(n, dtype=F64), torch.zeros(n, dtype=F64), depths], -1)
    scales = (depths * 0.2)[:, None].expand(n, 3).clone()  # equal footprint on screen
    colors = torch.eye(3, dtype=F64)[torch.arange(n) % 3] * 0.9 + 0.05
    sh = ((colors - 0.5) / 0.28209479177387814)[:, None, :]
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=F64).expand(n, 4)
    opac = torch.full((n,), 0.95, dtype=F64)
    cam = _head_on_camera(2, 2, f)  # pixel centres at +-0.5 px from the principal point
    out = render(Gaussians(means, quats, scales, opac, sh), cam)
    var = (f * 0.2) ** 2 + 0.3
    a = 0.95 * math.exp(-0.5 / (2 * var))  # same alpha for every Gaussian at every pixel
    kept = 0
    t = 1.0
    rgb = torch.zeros(3, dtype=F64)
    for i in range(n):
        if t * (1 - a) <= 1e-4:
            break
        rgb += colors[i] * a * t
        t *= 1 - a
        kept += 1
    assert kept == 3
    assert torch.allclose(out.rgb[0], rgb.expand(2, 2, 3), atol=1e-9)
    assert torch.allclose(out.alpha[0], torch.full((2, 2), 1 - t, dtype=F64), atol=1e-12)
    # opacity 1 at the very centre: alpha is capped at 0.999
    one = Gaussians(means[:1], quats[:1], torch.full((1, 3), 1e-4, dtype=F64), torch.ones(1, dtype=F64), sh[:1])
    single = render(one, _head_on_camera(1, 1, f))
    assert abs(single.alpha.item() - 0.999) < 1e-12
    # opacity below 1/255 never shows
    faint = Gaussians(means[:1], quats[:1], scales[:1], torch.full((1,), 0.003, dtype=F64), sh[:1])
    assert render(faint, cam).alpha.abs().max() == 0


def test_sh_basis_matches_scipy():
    special = pytest.importorskip("scipy.special")
    rng = np.random.default_rng(0)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    basis = sh_basis(3, torch.from_numpy(d)).numpy()
    for deg in range(4):
        for m in range(-deg, deg + 1):
            y = special.sph_harm_y(deg, abs(m), theta, phi)  # Condon-Shortley phase included
            want = y.real if m == 0 else math.sqrt(2) * (y.real if m > 0 else y.imag)
            assert np.abs(basis[:, deg * deg + deg + m] - want).max() < 1e-12, (deg, m)


def test_projection_culls():
    cams = _head_on_camera(32, 24, 30.0)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.005], [50.0, 0.0, 2.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]]).expand(4, 4)
    scales = torch.full((4, 3), 0.01)
    p = project_gaussians(means, quats, scales, cams.viewmats.float(), cams.Ks.float(), 32, 24)
    assert p.radii[0].tolist() == [p.radii[0, 0].item(), 0, 0, 0]
    assert p.radii[0, 0] == math.ceil(3 * math.sqrt((30 * 0.01 / 2) ** 2 + 0.3 + 0.1))
    assert torch.allclose(p.means2d[0, 0], torch.tensor([16.0, 12.0]))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_projection_matches_torch_path(dtype):
    """On CPU with the cameras held fixed, project_gaussians is two numba kernels (float64
    inside); with a gradient asked for the view matrices it is the torch code. Same culling,
    same radii, the same 2D means, conics and depths within the rounding of the dtype, and the
    same gradients w.r.t. means, quaternions and scales, on a scene with Gaussians behind the
    cameras, across the near plane, off screen and with zero scales."""
    g = random_gaussians(400, 0, seed=5, extent=6.0, scale=(1e-3, 0.5))
    g.scales[:10] = 0.0  # degenerate: only eps2d keeps the 2D covariance positive
    cams = look_at_cameras([(3.0, -2.0, 1.0), (0.5, 2.5, 0.4), (-2.0, 0.1, 2.5)], 48, 32, 40.0, dtype=dtype)
    gen = torch.Generator().manual_seed(2)
    upstream = [torch.randn(3, 400, k, generator=gen, dtype=dtype) for k in (2, 3, 1)]
    runs = []
    for cameras_grad in (False, True):
        ps = [t.to(dtype).clone().requires_grad_(True) for t in (g.means, g.quats, g.scales)]
        viewmats = cams.viewmats.clone().requires_grad_(cameras_grad)
        proj = project_gaussians(*ps, viewmats, cams.Ks, 48, 32)
        assert (proj.conics.grad_fn is not None) and (
            "ProjectCPU" in type(proj.conics.grad_fn).__name__
        ) != cameras_grad
        keep = (proj.radii > 0)[..., None]  # the rasteriser sends no gradient to culled pairs
        loss = sum((u * keep * x).sum() for u, x in zip(upstream, (proj.means2d, proj.conics, proj.depths[..., None])))
        loss.backward()
        runs.append((proj, [p.grad for p in ps]))
    (fused, fused_grads), (ref, ref_grads) = runs
    keep = ref.radii > 0
    assert 0 < keep.sum() < keep.numel()  # some culled, some kept
    if dtype == torch.float64:
        assert torch.equal(fused.radii, ref.radii)
    else:  # a radius is a ceil: float32 rounding may move one that sits on an integer by 1
        assert (fused.radii != ref.radii).sum() <= 2 and (fused.radii - ref.radii).abs().max() <= 1
    eps = torch.finfo(dtype).eps
    z = ref.depths.detach()
    assert ((fused.depths - z).abs() <= 8 * eps * z.abs()).all()
    m = ref.means2d.detach()[keep]
    assert ((fused.means2d.detach()[keep] - m).abs() <= 64 * eps * (m.abs() + 48)).all()
    c = ref.conics.detach()[keep]  # error relative to the conic's size (b may cancel to ~0)
    size = c[:, [0, 2]].abs().amax(-1, keepdim=True)
    assert ((fused.conics.detach()[keep] - c).abs() <= 1e3 * eps * size).all()
    for name, a, b in zip(("means", "quats", "scales"), fused_grads, ref_grads):
        scale = b.abs().amax(-1, keepdim=True) + b.abs().max() * 1e-6  # per Gaussian, floored
        assert ((a - b).abs() <= 1e3 * eps * scale).all(), (name, ((a - b).abs() / scale).max())


EDGE_CASES = {
    "behind_camera": dict(z=(-3.0, -0.5)),
    "zero_scales": dict(scale=0.0),
    "huge_scales": dict(scale=100.0),
    "opacity_0_and_1": dict(opacity=(0.0, 1.0)),
    "camera_inside": dict(z=(-1.0, 1.0), spread=2.0),
}


@pytest.mark.parametrize("case", sorted(EDGE_CASES))
@pytest.mark.parametrize("size", [(23, 9), (1, 1)], ids=["23x9", "1x1"])
def test_edge_cases_finite(case, size):
    opts = EDGE_CASES[case]
    n = 40
    gen = torch.Generator().manual_seed(0)
    spread = opts.get("spread", 0.5)
    zlo, zhi = opts.get("z", (1.0, 3.0))
    means = torch.cat(
        [(torch.rand(n, 2, generator=gen) - 0.5) * spread, torch.rand(n, 1, generator=gen) * (zhi - zlo) + zlo], -1
    )
    quats = torch.randn(n, 4, generator=gen)
    scales = torch.full((n, 3), opts["scale"]) if "scale" in opts else torch.rand(n, 3, generator=gen) * 0.1
    if "opacity" in opts:
        opac = torch.tensor(opts["opacity"]).repeat(n // 2)
    else:
        opac = torch.rand(n, generator=gen)
    g = with_grad(Gaussians(means, quats, scales, opac, torch.randn(n, 4, 3, generator=gen)))
    w, h = size
    out = render_gaussians(g, _head_on_camera(w, h, 0.8 * w + 2, dtype=torch.float32), background=[0.2, 0.3, 0.4])
    assert out.rgb.shape == (1, h, w, 3) and out.alpha.shape == out.depth.shape == (1, h, w)
    for t in out:
        assert torch.isfinite(t).all()
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()
    if case == "behind_camera":
        assert (out.alpha == 0).all()
    loss = out.rgb.sum() + out.alpha.sum() + out.depth.sum()
    loss.backward()
    for p in PARAMS:
        assert torch.isfinite(getattr(g, p).grad).all(), p
    with torch.no_grad():  # the fused projection (no autograd) culls the same Gaussians
        plain = render_gaussians(g, _head_on_camera(w, h, 0.8 * w + 2, dtype=torch.float32), background=[0.2, 0.3, 0.4])
    for t, u in zip(plain, out):
        assert torch.isfinite(t).all() and (t - u.detach()).abs().max() <= 1e-4


def test_empty_scene_renders_background():
    g = with_grad(
        Gaussians(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 1, 3))
    )
    cams = look_at_cameras([(0, -3, 0), (3, 0, 0)], 5, 3, 4.0, dtype=torch.float32)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    out = render_gaussians(g, cams, background=bg)
    assert torch.equal(out.rgb, bg[:, None, None, :].expand(2, 3, 5, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    out.rgb.sum().backward()
    assert g.means.grad.shape == (0, 3)


def test_rasterize_projected_direct():
    """The autograd.Function on hand-made 2D Gaussians: one disc in the middle of 20x20."""
    means2d = torch.tensor([[[10.0, 10.0]]], requires_grad=True)
    conics = torch.tensor([[[0.25, 0.0, 0.25]]], requires_grad=True)  # variance 4 px^2
    colors = torch.tensor([[[1.0, 0.5, 0.0, 3.0]]], requires_grad=True)
    opac = torch.tensor([[0.5]], requires_grad=True)
    radii = torch.tensor([[6]], dtype=torch.int32)
    acc, alpha = rasterize_projected(means2d, conics, colors, opac, radii, torch.ones(1, 1), 20, 20)
    ys, xs = torch.meshgrid(torch.arange(20) + 0.5, torch.arange(20) + 0.5, indexing="ij")
    want = 0.5 * torch.exp(-((xs - 10) ** 2 + (ys - 10) ** 2) / 8)
    # membership: tiles overlapped by [10 - 6, 10 + 6] -> tile 0 only (16 px) on both axes
    want = torch.where((want >= 1 / 255) & (xs < 16) & (ys < 16), want, torch.zeros_like(want))
    assert torch.allclose(alpha[0], want, atol=1e-6)
    assert torch.allclose(acc[0, ..., 3], 3.0 * want, atol=1e-5)
    alpha.sum().backward()
    # a float32 sum over <= 256 pixels totalling 25: <= 256 eps32 * 25 = 7.6e-4
    assert abs(opac.grad.item() - (want / 0.5).sum().item()) < 1e-3
    assert abs(means2d.grad[0, 0, 0].item()) < 1e-4  # symmetric: no pull sideways


def test_bad_inputs_raise():
    g = random_gaussians(3, 0, seed=0).to(torch.float32)
    cams = look_at_cameras([(0, -3, 0)], 8, 8, 8.0, dtype=torch.float32)
    with pytest.raises(DlaInputError, match="background"):
        render_gaussians(g, cams, background=torch.zeros(2, 3))
    with pytest.raises(DlaInputError, match="sh_degree"):
        render_gaussians(g, cams, sh_degree=2)
    m2, z = torch.zeros(1, 3, 2), torch.ones(1, 3)
    with pytest.raises(DlaInputError, match=r"colors: expected shape \[1, 3, 4\], got \[1, 3, 3\]"):
        rasterize_projected(m2, torch.zeros(1, 3, 3), torch.zeros(1, 3, 3), z, z.int(), z, 4, 4)
    with pytest.raises(DlaInputError, match="quats"):
        project_gaussians(g.means, g.quats[:2], g.scales, cams.viewmats, cams.Ks, 8, 8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_matches_gsplat_on_cuda():
    pytest.importorskip("gsplat")
    g = random_gaussians(2000, 3, seed=0, extent=1.0, scale=(0.005, 0.05), opacity=(0.1, 1.0))
    g = g.to(torch.float32)
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3)], 96, 64, 80.0, dtype=torch.float32)
    cpu = render_gaussians(g, cams, background=[0.1, 0.2, 0.3])
    cuda = render_gaussians(g.to("cuda"), cams.to("cuda"), background=[0.1, 0.2, 0.3])
    for a, b in zip(cpu, cuda):
        diff = (a - b.cpu()).abs()
        # gsplat >= 1.5 uses per-axis 3.33-sigma boxes for tile membership where this module
        # uses gsplat 1.4's 3-sigma radius, so a few fringe pixels may differ by <~ 1e-2
        assert diff.mean() < 1e-3
        assert diff.max() < 5e-2


@pytest.mark.parametrize("nthreads", [1, 2, 3])
def test_tile_lists_match_a_direct_listing(nthreads):
    """The parallel tile lists (bands of tile rows per thread, each list sorted by depth) against a
    plain listing: for every tile of every camera, the pairs whose tile rectangle covers it, by
    depth key, ties in pair order (numpy's stable argsort); lists short and long (insertion and
    radix sort), depths with many ties and depths that share their top bits or not."""
    from dlacli.render.binning_kernels import TILE, _tile_lists

    rng = np.random.default_rng(3)
    ncam, n, width, height = 3, 400, 70, 45  # 5 x 3 tiles per camera, the last ones partial
    tw, th = -(-width // TILE), -(-height // TILE)
    trect = np.zeros((ncam * n, 4), dtype=np.int32)
    visible = rng.random(ncam * n) < 0.8
    for i in np.flatnonzero(visible):
        x0, y0 = rng.integers(0, tw), rng.integers(0, th)
        trect[i] = (x0, rng.integers(x0, tw + 1), y0, rng.integers(y0, th + 1))  # some empty
    depths = np.concatenate(
        [
            rng.choice(np.float32([0.5, 2.0, 2.0001, 3.0]), n),  # ties
            rng.uniform(2.0, 2.5, n).astype(np.float32),  # one exponent: the top digits alike
            rng.uniform(0.01, 500.0, n).astype(np.float32),
        ]
    ).reshape(ncam, n)
    keys = depths.view(np.uint32)
    offsets, lists = _tile_lists(keys, trect, width, height, nthreads)
    order = np.concatenate([c * n + np.argsort(depths[c], kind="stable") for c in range(ncam)])
    sizes = []
    for c in range(ncam):
        for ty in range(th):
            for tx in range(tw):
                t = c * tw * th + ty * tw + tx
                want = [
                    i
                    for i in order
                    if i // n == c and trect[i, 0] <= tx < trect[i, 1] and trect[i, 2] <= ty < trect[i, 3]
                ]
                assert lists[offsets[t] : offsets[t + 1]].tolist() == want, (c, tx, ty)
                sizes.append(len(want))
    assert offsets[-1] == lists.shape[0]
    assert min(sizes) <= 24 < max(sizes)  # both sorts were used


@pytest.mark.parametrize("degree", [0, 2])
def test_appearance_per_camera_equals_each_camera_alone(degree):
    """Opacities [C, N] and SH [C, N, K, 3] per camera in one call: each camera's image is the
    one it renders alone with its row as the Gaussians' own, bit for bit without autograd and
    with it; the per-camera gradients are that camera's alone (bit for bit), those of the shared
    geometry the sum over the cameras (to float32 summation order)."""
    g = random_gaussians(80, degree, seed=11).to(torch.float32)
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3), (0.1, 2.5, 0.6)], 37, 31, 34.0, dtype=torch.float32)
    gen = torch.Generator().manual_seed(3)
    opac = torch.rand(3, len(g), generator=gen) * 0.95 + 0.02
    sh = (torch.randn(3, *g.sh.shape, generator=gen) * 0.4).float()
    alone = [Gaussians(g.means, g.quats, g.scales, opac[c], sh[c]) for c in range(3)]
    with torch.no_grad():
        joint = render_gaussians(g, cams, opacities=opac, sh=sh)
        for c in range(3):
            one = render_gaussians(alone[c], cams.select(c))
            for a, b in zip(joint, one):
                assert torch.equal(a[c], b[0])
        # a camera's row matters: another camera's appearance draws another image
        assert not torch.equal(joint.rgb[0], render_gaussians(alone[1], cams.select(0)).rgb[0])
    means = g.means.detach().clone().requires_grad_(True)
    op_t, sh_t = opac.clone().requires_grad_(True), sh.clone().requires_grad_(True)
    out = render_gaussians(Gaussians(means, g.quats, g.scales, g.opacities, g.sh), cams, opacities=op_t, sh=sh_t)
    weights = torch.randn(out.rgb.shape, generator=gen)
    gm, go, gs = torch.autograd.grad((weights * out.rgb).sum(), [means, op_t, sh_t])
    total = torch.zeros_like(means)
    for c in range(3):
        m = g.means.detach().clone().requires_grad_(True)
        o, s = opac[c].clone().requires_grad_(True), sh[c].clone().requires_grad_(True)
        one = render_gaussians(Gaussians(m, g.quats, g.scales, o, s), cams.select(c))
        assert torch.equal(one.rgb[0], out.rgb[c].detach())
        dm, do, ds = torch.autograd.grad((weights[c : c + 1] * one.rgb).sum(), [m, o, s])
        assert torch.equal(go[c], do) and torch.equal(gs[c], ds)
        total += dm
    assert gm.norm() > 0 and rel_err(gm, total) < 1e-5  # three float32 terms, summed in another order


def test_appearance_per_camera_bad_shapes():
    g = random_gaussians(10, 0, seed=1)
    cams = look_at_cameras([(0.8, -2.4, 0.4), (-2.2, 1.0, -0.3)], 9, 7, 8.0)
    with pytest.raises(DlaInputError, match="opacities"):
        render_gaussians(g, cams, opacities=torch.ones(3, 10, dtype=F64))
    with pytest.raises(DlaInputError, match="sh"):
        render_gaussians(g, cams, sh=torch.zeros(2, 10, 4, 3, dtype=F64))
