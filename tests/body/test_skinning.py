"""Gaussian skinning in the UV tangent frame, against explicit per-Gaussian math (scipy)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dlacli.body.model import get_body_model
from dlacli.body.skinning import skin_gaussians, skin_gaussians_on_body
from dlacli.body.uv import sample_surface, sample_uv, tangent_frames
from dlacli.geometry import quat_to_matrix


@pytest.fixture(scope="module")
def body():
    return get_body_model()


@pytest.fixture(scope="module")
def samples():
    f1, b1 = sample_surface(500, seed=0)
    f2, b2 = sample_uv(500, seed=0)
    return np.concatenate([f1, f2]), np.concatenate([b1, b2])


def test_identity_offsets_give_surface_points_and_frames(body, samples, tol):
    fid, bary = samples
    n = fid.size
    verts = torch.from_numpy(body.rest_vertices())[None].double()  # [1, V, 3]
    means, quats, scales = skin_gaussians_on_body(
        verts,
        fid,
        bary,
        torch.zeros(n, 3, dtype=torch.float64),
        torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(n, 4),
        torch.ones(n, 3, dtype=torch.float64),
    )
    # the surface points, computed here from the vertices and barycentrics directly
    v = verts[0].numpy()
    expect = np.einsum("nk,nkc->nc", bary.astype(np.float64), v[body.faces[fid]])
    # float64 both sides, a 3-term barycentric sum (1e-6 was ~1e10 float64 ulps)
    np.testing.assert_allclose(means[0].numpy(), expect, atol=tol(np.float64, np.abs(v).max(), 8))
    _, rot, s = tangent_frames(verts, fid, bary)
    np.testing.assert_allclose(quat_to_matrix(quats[0]).numpy(), rot[0].numpy(), atol=1e-9)
    np.testing.assert_allclose(scales[0].numpy(), s[0, :, None].expand(n, 3).numpy(), atol=1e-12)


def test_general_offsets_match_per_gaussian_math():
    rng = np.random.default_rng(1)
    t, n = 3, 40
    frames_R = Rotation.random(t * n, random_state=2).as_matrix().reshape(t, n, 3, 3)
    frames_T = rng.normal(size=(t, n, 3))
    frames_S = rng.uniform(0.001, 0.01, size=(t, n))
    dxyz = rng.normal(size=(n, 3)) * 0.01
    d_rot = Rotation.random(n, random_state=3)
    dquat = d_rot.as_quat()[:, [3, 0, 1, 2]]
    ds = rng.uniform(0.5, 2.0, size=(n, 3))
    means, quats, scales = skin_gaussians(
        *(torch.from_numpy(x) for x in (frames_T, frames_R, frames_S, dxyz, dquat, ds))
    )
    for k in range(t):
        for i in range(n):
            np.testing.assert_allclose(means[k, i].numpy(), frames_T[k, i] + frames_R[k, i] @ dxyz[i], atol=1e-12)
            rg = frames_R[k, i] @ d_rot[i].as_matrix()
            np.testing.assert_allclose(quat_to_matrix(quats[k, i]).numpy(), rg, atol=1e-9)
            np.testing.assert_allclose(scales[k, i].numpy(), frames_S[k, i] * ds[i], atol=1e-15)
    np.testing.assert_allclose(quats.norm(dim=-1).numpy(), 1.0, atol=1e-12)
    # per-frame offsets [T, N, *] broadcast like shared ones
    tiled = skin_gaussians(
        *(torch.from_numpy(x) for x in (frames_T, frames_R, frames_S)),
        *(torch.from_numpy(np.broadcast_to(x, (t, *x.shape)).copy()) for x in (dxyz, dquat, ds)),
    )
    for a, b in zip(tiled, (means, quats, scales)):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-12)


def test_rigid_body_motion_moves_gaussians_rigidly(body, samples):
    """Posing with only a root transform moves every Gaussian (mean and covariance) rigidly."""
    fid, bary = samples
    n = fid.size
    rng = np.random.default_rng(4)
    dxyz = torch.from_numpy(rng.normal(size=(n, 3)) * 0.01)
    dquat = torch.from_numpy(Rotation.random(n, random_state=5).as_quat()[:, [3, 0, 1, 2]])
    ds = torch.from_numpy(rng.uniform(0.5, 2.0, size=(n, 3)))
    rr, rt = np.array([0.4, -1.0, 0.7]), np.array([0.3, 0.1, -0.2])
    out = body.forward(
        {},
        torch.zeros(2, 104, 3),
        torch.from_numpy(np.stack([np.zeros(3), rr])).float(),
        torch.from_numpy(np.stack([np.zeros(3), rt])).float(),
    )
    means, quats, scales = skin_gaussians_on_body(out.vertices.double(), fid, bary, dxyz, dquat, ds)
    r = Rotation.from_rotvec(rr).as_matrix()
    # posed in float32 (anny's forward, ~250 roundings at |x| ~ 1 m: 3e-5), skinned in float64
    np.testing.assert_allclose(means[1].numpy(), means[0].numpy() @ r.T + rt, atol=5e-5)

    def cov(q, s):
        m = quat_to_matrix(q).numpy()
        return m @ (s.numpy()[..., None] ** 2 * np.swapaxes(m, -1, -2))

    c0, c1 = cov(quats[0], scales[0]), cov(quats[1], scales[1])
    size = np.trace(c0, axis1=-2, axis2=-1)[:, None, None]  # float32 posing: compare relatively
    np.testing.assert_allclose(c1 / size, r @ c0 @ r.T / size, atol=2e-3)
    np.testing.assert_allclose(scales[1].numpy(), scales[0].numpy(), rtol=1e-3)


def test_skinning_gradcheck():
    rng = np.random.default_rng(6)
    t, n = 2, 3
    args = [
        torch.from_numpy(rng.normal(size=(t, n, 3))),
        torch.from_numpy(Rotation.random(t * n, random_state=7).as_matrix().reshape(t, n, 3, 3)),
        torch.from_numpy(rng.uniform(0.5, 1.0, size=(t, n))),
        torch.from_numpy(rng.normal(size=(n, 3))),
        torch.from_numpy(Rotation.random(n, random_state=8).as_quat()[:, [3, 0, 1, 2]]),
        torch.from_numpy(rng.uniform(0.5, 2.0, size=(n, 3))),
    ]
    for a in args:
        a.requires_grad_(True)
    # frames_R enters through its quaternion: keep the check on the other inputs plus dquat
    fn = lambda T, S, dx, dq, ds: skin_gaussians(T, args[1].detach(), S, dx, dq, ds)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (args[0], args[2], args[3], args[4], args[5]))


def test_shape_validation():
    with pytest.raises(ValueError, match="frames_R"):
        skin_gaussians(
            torch.zeros(1, 2, 3),
            torch.zeros(1, 3, 3, 3),
            torch.zeros(1, 2),
            torch.zeros(2, 3),
            torch.zeros(2, 4),
            torch.zeros(2, 3),
        )
    with pytest.raises(ValueError, match="dquat"):
        skin_gaussians(
            torch.zeros(1, 2, 3),
            torch.zeros(1, 2, 3, 3),
            torch.zeros(1, 2),
            torch.zeros(2, 3),
            torch.zeros(2, 3),
            torch.zeros(2, 3),
        )
