"""dlacli.geometry against analytic cases and independent oracles (scipy rotations, a per-pixel
loop over camera-to-world matrices), in float32 and float64 with per-dtype tolerances."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dlacli import geometry as G
from dlacli.types import Cameras

F32, F64 = torch.float32, torch.float64
# Absolute tolerances for O(1) quantities (rotation entries, unit vectors, angles) after a few
# dozen float operations: ~100 ulp of 1 (float32 eps 1.2e-7, float64 eps 2.2e-16), with room
# for the sqrt / atan2 conditioning of the log map away from its singular points.
TOL = {F32: 2e-5, F64: 1e-12}
NP = {F32: np.float32, F64: np.float64}


def _random_rotvecs(n: int, seed: int) -> np.ndarray:
    """[n, 3] axis-angles: random ones plus the edge cases (zero, tiny, near a half turn)."""
    aa = Rotation.random(n, random_state=seed).as_rotvec()
    axis = np.array([0.48, -0.6, 0.64])  # unit
    extra = np.stack([0.0 * axis, 1e-9 * axis, 1e-4 * axis, (math.pi - 1e-3) * axis, 2.5 * axis])
    return np.concatenate([aa, extra])


# ------------------------------------------------------------------------------- rotations


@pytest.mark.parametrize("dtype", [F32, F64])
def test_rotations_match_scipy_and_round_trip(dtype):
    tol = TOL[dtype]
    aa_np = _random_rotvecs(200, seed=1)
    ref_m = Rotation.from_rotvec(aa_np).as_matrix()  # float64 oracle
    ref_q = Rotation.from_rotvec(aa_np).as_quat()[:, [3, 0, 1, 2]]  # scipy is (x, y, z, w)
    ref_q *= np.where(ref_q[:, :1] < 0, -1.0, 1.0)
    aa = torch.from_numpy(aa_np).to(dtype)

    m = G.axis_angle_to_matrix(aa)
    assert m.dtype == dtype and m.shape == (205, 3, 3)
    np.testing.assert_allclose(m.double().numpy(), ref_m, atol=tol)
    eye = torch.eye(3, dtype=F64).expand(205, 3, 3).numpy()
    np.testing.assert_allclose((m @ m.transpose(-1, -2)).double().numpy(), eye, atol=tol)
    np.testing.assert_allclose(torch.linalg.det(m.double()).numpy(), 1.0, atol=tol)

    q = G.matrix_to_quat(m)
    np.testing.assert_allclose(q.double().numpy(), ref_q, atol=tol)
    np.testing.assert_allclose(G.axis_angle_to_quat(aa).double().numpy(), ref_q, atol=tol)
    np.testing.assert_allclose(G.quat_to_matrix(q).double().numpy(), ref_m, atol=tol)
    # the log map: compare rotations (at the half turn aa and -aa are the same rotation)
    back = G.matrix_to_axis_angle(m).double().numpy()
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), ref_m, atol=10 * tol)
    np.testing.assert_allclose(back[:200], aa_np[:200], atol=10 * tol)  # angles < pi: unique
    back_q = G.quat_to_axis_angle(q).double().numpy()
    np.testing.assert_allclose(Rotation.from_rotvec(back_q).as_matrix(), ref_m, atol=10 * tol)


@pytest.mark.parametrize("dtype", [F32, F64])
def test_quaternion_algebra(dtype):
    tol = TOL[dtype]
    q = torch.from_numpy(Rotation.random(100, random_state=2).as_quat()[:, [3, 0, 1, 2]]).to(dtype)
    a, b = q[:50], q[50:]
    ma, mb = G.quat_to_matrix(a), G.quat_to_matrix(b)
    # Hamilton product = matrix product (b first, then a)
    np.testing.assert_allclose(
        G.quat_to_matrix(G.quat_multiply(a, b)).double().numpy(), (ma @ mb).double().numpy(), atol=tol
    )
    ident = torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(50, 4)
    prod = G.quat_multiply(a, G.quat_conjugate(a))
    np.testing.assert_allclose(prod.double().numpy(), ident.double().numpy(), atol=tol)
    n = G.quat_normalize(3.0 * a)
    np.testing.assert_allclose(n.norm(dim=-1).double().numpy(), 1.0, atol=tol)
    # q and -q are the same rotation; quat_to_matrix normalises
    np.testing.assert_allclose(G.quat_to_matrix(-2.0 * a).double().numpy(), ma.double().numpy(), atol=tol)


@pytest.mark.parametrize("dtype", [F32, F64])
def test_rotations_numpy_in_numpy_out(dtype):
    aa = _random_rotvecs(20, seed=3).astype(NP[dtype])
    m = G.axis_angle_to_matrix(aa)
    assert isinstance(m, np.ndarray) and m.dtype == NP[dtype]
    np.testing.assert_array_equal(m, G.axis_angle_to_matrix(torch.from_numpy(aa)).numpy())
    q = G.matrix_to_quat(m)
    assert isinstance(q, np.ndarray) and q.dtype == NP[dtype]
    np.testing.assert_array_equal(
        G.quat_multiply(q, q), G.quat_multiply(torch.from_numpy(q), torch.from_numpy(q)).numpy()
    )
    np.testing.assert_array_equal(G.skew(aa[0]), G.skew(torch.from_numpy(aa[0])).numpy())
    with pytest.raises(TypeError, match="not both"):
        G.quat_multiply(q, torch.from_numpy(q))


def test_rotation_gradients_are_finite_at_zero_and_near_pi():
    aa = torch.tensor(
        [[0.0, 0.0, 0.0], [1e-8, -2e-8, 0.0], [0.3, -0.2, 0.5], [0.0, 0.0, math.pi - 1e-4]],
        dtype=F64,
        requires_grad=True,
    )
    assert torch.autograd.gradcheck(G.axis_angle_to_matrix, (aa,))
    assert torch.autograd.gradcheck(G.axis_angle_to_quat, (aa,))
    m = G.axis_angle_to_matrix(aa.detach()).requires_grad_(True)
    G.matrix_to_axis_angle(m).sum().backward()
    assert torch.isfinite(m.grad).all()
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2], [1.0, 0.0, 0.0, 0.0]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(G.quat_to_matrix, (q,))
    assert torch.autograd.gradcheck(G.quat_to_axis_angle, (q,))


# ---------------------------------------------------------------------- rotations in numpy


def test_quat_rotation_rows_are_the_matrix_of_the_quaternion_as_given():
    """The same entries in numpy and torch; for a unit q they are quat_to_matrix's (scipy's),
    for q scaled by s every entry of R - I scales by s^2 (no normalisation)."""
    q = Rotation.random(50, random_state=3).as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    rows = G.quat_rotation_rows(q)
    m = np.stack([np.stack(row, -1) for row in rows], -2)
    np.testing.assert_allclose(m, Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(m, G.quat_to_matrix(torch.from_numpy(q)).numpy(), rtol=0, atol=1e-15)
    scaled = np.stack([np.stack(row, -1) for row in G.quat_rotation_rows(2.0 * q)], -2)
    np.testing.assert_allclose(scaled - np.eye(3), 4.0 * (m - np.eye(3)), atol=1e-12)


def test_quat_normalize_in_numpy_and_torch():
    q = np.array([[3.0, 0.0, 4.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1e-18, 0.0, 0.0, 0.0]], np.float32)
    out = G.quat_normalize(q, float(np.finfo(np.float32).tiny))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, [[0.6, 0.0, 0.8, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]], rtol=1e-6)
    np.testing.assert_allclose(G.quat_normalize(torch.from_numpy(q[:1])).numpy(), out[:1], rtol=1e-6)


def test_quat_order_conversions():
    q = np.arange(8.0).reshape(2, 4)
    np.testing.assert_array_equal(G.quat_wxyz_to_xyzw(q), q[:, [1, 2, 3, 0]])
    np.testing.assert_array_equal(G.quat_xyzw_to_wxyz(G.quat_wxyz_to_xyzw(q)), q)


def test_quat_slerp_against_scipy():
    """Unit-speed interpolation on the arc: scipy's Slerp (shortest path) is the oracle."""
    from scipy.spatial.transform import Slerp

    ends = Rotation.random(2 * 40, random_state=7)
    a = ends[:40].as_quat()[:, [3, 0, 1, 2]]
    b = ends[40:].as_quat()[:, [3, 0, 1, 2]]
    b[::2] *= -1  # the same rotations, half of them on the far side of a
    for t in (0.0, 0.3, 0.5, 1.0):
        got = G.quat_slerp(a, b, t, shortest=True)
        np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=1e-12)
        for k in range(40):
            ref = Slerp([0.0, 1.0], ends[[k, 40 + k]])(t)
            angle = (ref.inv() * Rotation.from_quat(got[k, [1, 2, 3, 0]])).magnitude()
            assert angle < 1e-9, (t, k, angle)
    # without `shortest`, the arc from a to b with <a, b> < 0 is the long one (GfSlerp's)
    one = np.array([1.0, 0.0, 0.0, 0.0])
    turn = np.array([np.cos(0.1), 0.0, 0.0, np.sin(0.1)])  # 0.2 rad about +Z
    half = [G.quat_slerp(one, -turn, 0.5, shortest=s) for s in (True, False)]
    angles = [Rotation.from_quat(h[[1, 2, 3, 0]]).magnitude() for h in half]
    assert angles[0] == pytest.approx(0.1, abs=1e-12) and angles[1] == pytest.approx(np.pi - 0.1, abs=1e-9)
    tiny = G.quat_slerp(a, a, np.full((40, 1), 0.25))  # below 1e-6 rad: linear weights, exact
    np.testing.assert_allclose(tiny, a, atol=1e-15)


def test_quat_continuous_signs():
    q = Rotation.random(30, random_state=2).as_quat()[:, [3, 0, 1, 2]].reshape(10, 3, 4)
    flips = np.where(np.random.default_rng(0).uniform(size=(10, 3, 1)) < 0.5, -1.0, 1.0)
    out = G.quat_continuous_signs(q * flips)
    assert np.all(np.einsum("tnd,tnd->tn", out[1:], out[:-1]) >= 0)
    np.testing.assert_array_equal(np.abs(out), np.abs(q))  # only signs change
    np.testing.assert_array_equal(out[0], (q * flips)[0])


def test_rotation_between_directions():
    rng = np.random.default_rng(4)
    for a, b in [
        *(rng.normal(size=(2, 3)) for _ in range(20)),
        (np.array([0.0, 0, 2]), np.array([0.0, 0, -1])),
        (np.array([1.0, 0, 0]), np.array([-3.0, 0, 0])),
        (np.array([0.0, 1, 0]), np.array([0.0, 5, 0])),
    ]:
        r = G.rotation_between(a, b)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(r @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
        axis = np.cross(a, b)
        if np.linalg.norm(axis) > 1e-6:  # the shortest turn: about a x b, which it keeps
            np.testing.assert_allclose(r @ axis, axis, atol=1e-9)


def test_rigid_motion_recovers_a_known_motion():
    rng = np.random.default_rng(5)
    shape = rng.normal(size=(50, 3))
    rots = Rotation.random(6, random_state=6)
    shift = rng.normal(size=(6, 3))
    rots = Rotation.concatenate([Rotation.identity(), rots])
    shift = np.vstack([np.zeros(3), shift])
    frames = np.stack([rots[t].apply(shape) + shift[t] for t in range(7)])  # [T, n, 3]
    r, c = G.rigid_motion(frames)
    np.testing.assert_allclose(r, rots.as_matrix() @ rots[0].as_matrix().T, atol=1e-9)
    np.testing.assert_allclose(c, frames.mean(axis=1), atol=1e-12)


# ------------------------------------------------------------------------------ projection


@pytest.mark.parametrize("dtype", [F32, F64])
def test_projection_of_known_points(dtype):
    vm = torch.eye(4, dtype=dtype)  # camera at the origin looking down +Z
    k = torch.tensor([[100.0, 0, 32], [0, 80.0, 24], [0, 0, 1]], dtype=dtype)
    pts = torch.tensor([[1.0, 2.0, 4.0], [0.0, 0.0, 2.0], [-0.5, 0.25, 0.5]], dtype=dtype)
    px, depth = G.project_points(pts, vm, k)
    assert px.dtype == dtype and px.shape == (3, 2) and depth.shape == (3,)
    want = [[100 * 1 / 4 + 32, 80 * 2 / 4 + 24], [32, 24], [100 * -0.5 / 0.5 + 32, 80 * 0.25 / 0.5 + 24]]
    np.testing.assert_allclose(px.double().numpy(), want, rtol=TOL[dtype])
    np.testing.assert_allclose(depth.double().numpy(), [4, 2, 0.5], rtol=TOL[dtype])
    # a translated camera: world = camera + (0, 0, -1)
    vm2 = vm.clone()
    vm2[2, 3] = 1.0
    px2, depth2 = G.project_points(pts - torch.tensor([0, 0, 1.0], dtype=dtype), vm2, k)
    np.testing.assert_allclose(px2.double().numpy(), want, rtol=10 * TOL[dtype])
    np.testing.assert_allclose(depth2.double().numpy(), [4, 2, 0.5], rtol=10 * TOL[dtype])


def test_projection_of_an_orbit_camera_follows_the_conventions():
    """Azimuth 0 is on -Y looking at the front: +X (the person's left) is on the image right, +Z
    up is up in the image; the target projects to the principal point at depth = distance."""
    w, h, fov, dist = 64, 48, 40.0, 3.0
    cams = G.look_at_orbit_cameras([0.0, 0.0, 0.0], dist, [0.0, 90.0], 0.0, fov, w, h)
    f = 0.5 * h / math.tan(math.radians(fov) / 2)
    pts = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1.0]])
    px, depth = G.project_to_cameras(pts, cams)
    assert px.dtype == np.float64 and px.shape == (2, 3, 2) and depth.shape == (2, 3)
    np.testing.assert_allclose(px[0], [[w / 2, h / 2], [w / 2 + f / dist, h / 2], [w / 2, h / 2 - f / dist]], atol=1e-4)
    np.testing.assert_allclose(depth[0], [dist, dist, dist], atol=1e-6)
    np.testing.assert_allclose(depth[1, 1], dist - 1.0, atol=1e-6)  # the camera at azimuth 90 is on +X
    np.testing.assert_allclose(
        G.camera_centers(cams.viewmats.double()).numpy(), [[0, -dist, 0], [dist, 0, 0]], atol=1e-6
    )
    np.testing.assert_allclose(
        G.camera_centers(cams.viewmats.double()).numpy(), cams.c2w_opengl()[:, :3, 3], atol=1e-12
    )


@pytest.mark.parametrize("dtype", [F32, F64])
def test_projection_broadcasts_and_matches_numpy(dtype):
    rng = np.random.default_rng(4)
    cams = G.look_at_orbit_cameras([0.1, 0.0, 0.2], 3.0, [10.0, 100.0, 250.0], [5.0, -10.0, 30.0], 45.0, 40, 30)
    pts = rng.normal(size=(7, 3)) * 0.5
    vm, ks = cams.viewmats.to(dtype), cams.Ks.to(dtype)
    px, depth = G.project_points(torch.from_numpy(pts).to(dtype), vm, ks)  # [7, 3] with [C, 4, 4]
    assert px.shape == (3, 7, 2) and depth.shape == (3, 7) and px.dtype == dtype
    px_np, depth_np = G.project_points(pts.astype(NP[dtype]), vm.numpy(), ks.numpy())
    assert px_np.dtype == NP[dtype]
    np.testing.assert_allclose(px_np, px.numpy(), rtol=TOL[dtype], atol=TOL[dtype] * 100)
    # per camera, one at a time, with an explicit loop (the oracle)
    for c in range(3):
        r, t = vm[c, :3, :3].double().numpy(), vm[c, :3, 3].double().numpy()
        pc = pts @ r.T + t
        k = ks[c].double().numpy()
        want = np.stack([k[0, 0] * pc[:, 0] / pc[:, 2] + k[0, 2], k[1, 1] * pc[:, 1] / pc[:, 2] + k[1, 2]], 1)
        np.testing.assert_allclose(px[c].double().numpy(), want, atol=1e-3 if dtype == F32 else 1e-9)
        np.testing.assert_allclose(depth[c].double().numpy(), pc[:, 2], atol=1e-5 if dtype == F32 else 1e-12)
    # one point set per camera: [C, N, 3] with [C, 4, 4]
    per_cam = torch.from_numpy(np.stack([pts, pts + 0.1, pts - 0.1])).to(dtype)
    px3, _ = G.project_points(per_cam, vm, ks)
    np.testing.assert_allclose(px3[0].numpy(), px[0].numpy(), rtol=0, atol=0)


def test_projection_near_guard_and_gradients():
    k = torch.tensor([[50.0, 0, 10], [0, 50.0, 10], [0, 0, 1]], dtype=F64)
    pts = torch.tensor([[0.3, 0.1, 0.0], [0.3, 0.1, -1.0], [0.3, 0.1, 1e-3]], dtype=F64)
    px, depth = G.project_points(pts, torch.eye(4, dtype=F64), k, near=1e-2)
    assert torch.isfinite(px).all()
    np.testing.assert_allclose(depth.numpy(), [0.0, -1.0, 1e-3])  # depth is not guarded
    np.testing.assert_allclose(px[0].numpy(), [50 * 0.3 / 1e-2 + 10, 50 * 0.1 / 1e-2 + 10])  # divisor = near
    np.testing.assert_allclose(px[2].numpy(), px[0].numpy())  # z < near: clamped the same way
    x = torch.tensor([[0.3, -0.2, 2.0], [-0.1, 0.4, 1.5]], dtype=F64, requires_grad=True)
    vm = torch.eye(4, dtype=F64)
    vm[:3, 3] = torch.tensor([0.1, 0.0, 0.5], dtype=F64)
    assert torch.autograd.gradcheck(lambda p: G.project_points(p, vm, k)[0], (x,))
    with pytest.raises(TypeError, match="not both"):
        G.project_points(x.detach().numpy(), vm, k)


# ---------------------------------------------------------------------------- look-at cameras


def test_look_at_and_orbit_cameras():
    eyes = np.array([[2.0, -3.0, 1.0], [-1.0, 0.5, 4.0], [0.2, 3.0, -1.0]])
    target = np.array([0.1, 0.2, 0.3])
    c2w = G.look_at_c2w(eyes, target)
    rot = c2w[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (3, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    fwd = -rot[:, :, 2]  # OpenGL cameras look down -Z
    to_target = (target - eyes) / np.linalg.norm(target - eyes, axis=1, keepdims=True)
    np.testing.assert_allclose(fwd, to_target, atol=1e-12)
    assert np.all(rot[:, 2, 0] == 0)  # the camera's right axis is horizontal (up = +Z)
    e = G.orbit_eyes(target, 2.5, [0.0, 90.0, 180.0], [0.0, 0.0, 90.0])
    np.testing.assert_allclose(e - target, [[0, -2.5, 0], [2.5, 0, 0], [0, 0, 2.5]], atol=1e-12)
    cams = G.pinhole_cameras(c2w, 60.0, 40, 30)
    assert (cams.width, cams.height) == (40, 30)
    np.testing.assert_allclose(
        cams.Ks[0].numpy(),
        [[15 / math.tan(math.radians(30)), 0, 20], [0, 15 / math.tan(math.radians(30)), 15], [0, 0, 1]],
        rtol=1e-6,
    )
    assert G.framing_distance(2.0, 90.0, margin=1.0) == pytest.approx(1.0)
    path = np.stack([np.full(10, 2.0), np.arange(10.0)], axis=1)
    sm = G.smooth_path(path, fps=10.0, seconds=0.3)
    np.testing.assert_allclose(sm[:, 0], 2.0)
    np.testing.assert_allclose(sm[1:-1, 1], path[1:-1, 1])  # a 3-tap mean keeps a straight line


# ---------------------------------------------------------------------------- Plucker rays


def _cameras(dtype) -> Cameras:
    """Two non-square cameras with fx != fy and an off-centre principal point."""
    base = G.look_at_orbit_cameras([0.0, 0.1, 0.2], 3.0, [30.0, 200.0], [10.0, -20.0], 50.0, 9, 7)
    ks = torch.tensor([[[11.0, 0, 4.1], [0, 9.0, 3.3], [0, 0, 1]], [[8.0, 0, 5.2], [0, 12.0, 2.9], [0, 0, 1]]])
    return Cameras(base.viewmats, ks, 9, 7).to(dtype)


def _slow_plucker(cams: Cameras) -> np.ndarray:
    """Per-pixel loop over camera-to-world matrices (OpenGL axes, looking down -Z), float64."""
    c2w = cams.c2w_opengl()
    ks = cams.Ks.double().numpy()
    out = np.zeros((len(cams), cams.height, cams.width, 6))
    for c in range(len(cams)):
        fx, fy, cx, cy = ks[c, 0, 0], ks[c, 1, 1], ks[c, 0, 2], ks[c, 1, 2]
        o = c2w[c, :3, 3]
        for i in range(cams.height):
            for j in range(cams.width):
                d_gl = np.array([(j + 0.5 - cx) / fx, -(i + 0.5 - cy) / fy, -1.0])
                d = c2w[c, :3, :3] @ d_gl
                d /= np.linalg.norm(d)
                out[c, i, j] = np.concatenate([d, np.cross(o, d)])
    return out


@pytest.mark.parametrize("dtype", [F32, F64])
def test_plucker_rays_image_space(dtype):
    cams = _cameras(dtype)
    rays = G.plucker_rays(cams)
    assert rays.shape == (2, 7, 9, 6) and rays.dtype == dtype
    d, m = rays[..., :3].double(), rays[..., 3:].double()
    tol = TOL[dtype]
    np.testing.assert_allclose(d.norm(dim=-1).numpy(), 1.0, atol=tol)  # unit directions
    np.testing.assert_allclose((d * m).sum(-1).numpy(), 0.0, atol=10 * tol)  # moment orthogonal to d
    # moment equation: any point p = o + t d on the ray has p x d = m
    o, _ = G.pixel_rays(cams)
    for t in (0.5, 2.0, 7.0):
        p = o.double() + t * d
        np.testing.assert_allclose(torch.linalg.cross(p, d, dim=-1).numpy(), m.numpy(), atol=100 * tol)
        # and it projects back onto the pixel centre it came from
        px, depth = G.project_points(p.reshape(2, -1, 3), cams.viewmats.double(), cams.Ks.double())
        jj, ii = np.meshgrid(np.arange(9) + 0.5, np.arange(7) + 0.5)
        want = np.broadcast_to(np.stack([jj, ii], -1).reshape(1, -1, 2), px.shape)
        np.testing.assert_allclose(px.numpy(), want, atol=1e-3 if dtype == F32 else 1e-9)
        assert (depth > 0).all()
    np.testing.assert_allclose(rays.double().numpy(), _slow_plucker(cams), atol=1e-5 if dtype == F32 else 1e-10)


@pytest.mark.parametrize("dtype", [F32, F64])
def test_plucker_rays_uv_space(dtype):
    tol = TOL[dtype]
    gen = torch.Generator().manual_seed(5)
    positions = torch.randn(6, 5, 3, generator=gen, dtype=dtype) * 0.4  # a UV position map [R, R, 3]
    centers = torch.tensor([[0.0, -3.0, 0.2], [2.5, 1.0, 0.5]], dtype=dtype)  # [C, 3]
    rays = G.plucker_rays_uv(positions, centers)
    assert rays.shape == (2, 6, 5, 6) and rays.dtype == dtype
    d, m = rays[..., :3].double(), rays[..., 3:].double()
    np.testing.assert_allclose(d.norm(dim=-1).numpy(), 1.0, atol=tol)
    np.testing.assert_allclose((d * m).sum(-1).numpy(), 0.0, atol=10 * tol)
    # the texel's own point and the camera centre are both on its ray
    p = positions.double().expand(2, 6, 5, 3)
    np.testing.assert_allclose(torch.linalg.cross(p, d, dim=-1).numpy(), m.numpy(), atol=10 * tol)
    want_d = p - centers.double()[:, None, None, :]
    np.testing.assert_allclose(d.numpy(), (want_d / want_d.norm(dim=-1, keepdim=True)).numpy(), atol=tol)
    # a texel at the centre itself: zeros, no NaN
    at_centre = G.plucker_rays_uv(centers[:1, None, None, :].expand(1, 2, 2, 3), centers[:1])
    assert torch.equal(at_centre, torch.zeros_like(at_centre))
    # numpy in, numpy out
    rays_np = G.plucker_rays_uv(positions.numpy(), centers.numpy())
    assert isinstance(rays_np, np.ndarray) and rays_np.dtype == NP[dtype]
    np.testing.assert_allclose(rays_np, rays.numpy(), atol=0)


def test_plucker_uv_of_points_on_pixel_rays_equals_the_image_ray_map():
    """A 'position map' made of points on each pixel's ray gives the image-space map exactly."""
    cams = _cameras(F64)
    o, d = G.pixel_rays(cams)
    positions = o + torch.linspace(1.0, 4.0, 9, dtype=F64)[None, None, :, None] * d  # [C, H, W, 3]
    centers = G.camera_centers(cams.viewmats)  # [C, 3]
    np.testing.assert_allclose(G.plucker_rays_uv(positions, centers).numpy(), G.plucker_rays(cams).numpy(), atol=1e-12)
