"""The numba skinning path (body/skin_kernels.py, gaussian_map.skinned_params_on_body without
gradients) against the torch path it replaces for playback (tangent_frames, matrix_to_quat,
skin_gaussians, all float32): the same Gaussians to float32 rounding on posed bodies, and the
torch path still taken, with gradients, when one is asked for."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlacli.avatar import gaussian_map as gm
from dlacli.kernel_path import takes_kernels
from dlacli.types import BodyParams

R = 32
N = 20_000
EPS = float(np.finfo(np.float32).eps)


@pytest.fixture(scope="module")
def bodies():
    """Two posed bodies [2, V, 3]: an arm raised and bent, the other leg and the spine turned."""
    from dlacli.body.model import get_body_model

    m = get_body_model()
    a = BodyParams(pose={"upperarm01.L": np.array([0.0, 0.0, 0.9]), "lowerarm01.L": np.array([0.7, 0.0, 0.0])})
    b = BodyParams(pose={"upperleg01.R": np.array([-0.6, 0.2, 0.0]), "spine03": np.array([0.1, 0.5, 0.0])})
    return torch.cat([m.forward_body(a).vertices, m.forward_body(b).vertices])


def _map(seed: int, batch: int | None = None) -> torch.Tensor:
    """A Gaussian map with random offsets (a few centimetres), rotations and scales."""
    g = torch.Generator().manual_seed(seed)
    shape = (gm.CHANNELS, R, R) if batch is None else (batch, gm.CHANNELS, R, R)
    z = torch.randn(shape, generator=g)
    z[..., gm.OFFSET, :, :] *= 0.03
    z[..., gm.LOG_SCALE, :, :] *= 0.5
    return z


def _torch_path(fmap, samples, verts):
    """The torch path's Gaussians and the frame quaternions' w."""
    frames = gm.sample_frames(verts, samples)
    return gm.skinned_params(fmap, samples, frames), frames[3][..., 0]


def _close(fast, ref, frame_w):
    """Within float32 rounding of the torch path: a few ulps of each quantity's magnitude (means:
    a sum of ~6 float32 products; quaternions: ~30 chained float32 operations, normalised; the
    kernel rounds once, at the store). frame_w [P, N]: w of each sample's frame quaternion."""
    means, quats, scales = fast[:3]
    want_means, want_quats, want_scales = ref[:3]
    assert means.dtype == quats.dtype == scales.dtype == torch.float32
    assert (means - want_means).abs().max() <= 8 * EPS * want_means.abs().max()
    # q and -q are one rotation; the frame's quaternion is taken with w >= 0, so the sign of a
    # Gaussian's may differ between the paths only where that w is ~0
    flip = (frame_w.abs() < 1e-4)[..., None] & ((quats + want_quats).abs() < (quats - want_quats).abs()).all(-1)[
        ..., None
    ]
    dq = torch.where(flip, quats + want_quats, quats - want_quats).abs()
    assert dq.max() <= 32 * EPS
    assert ((scales - want_scales).abs() <= 8 * EPS * want_scales.abs()).all()
    for a, b in zip(fast[3:], ref[3:]):  # opacities and colours: the same lookup
        assert torch.equal(a, b)


def test_the_kernels_give_the_torch_paths_gaussians(bodies):
    samples = gm.make_samples(N, 5)
    fmap = _map(1)
    assert takes_kernels(fmap, bodies)
    fast = gm.skinned_params_on_body(fmap, samples, bodies)
    assert fast[0].shape == (2, N, 3) and fast[1].shape == (2, N, 4)
    _close(fast, *_torch_path(fmap, samples, bodies))
    # every pivot of Shepperd's method occurs among the frames (each branch of the kernel is used)
    rot = gm.sample_frames(bodies, samples)[1]
    diag = rot.diagonal(dim1=-2, dim2=-1)
    sq = torch.stack([1 + diag.sum(-1), *(1 + 2 * diag[..., i] - diag.sum(-1) for i in range(3))], -1)
    assert set(sq.argmax(-1).unique().tolist()) == {0, 1, 2, 3}


def test_a_map_per_body_and_one_body_alone(bodies):
    samples = gm.make_samples(4000, 2)
    fmaps = _map(7, batch=2)  # a pose-conditioned decoder's F per body
    _close(gm.skinned_params_on_body(fmaps, samples, bodies), *_torch_path(fmaps, samples, bodies))
    whole = gm.skinned_params_on_body(fmaps[1], samples, bodies)
    alone = gm.skinned_params_on_body(fmaps[1], samples, bodies[1:])
    for a, b in zip(whole[:3], alone[:3]):  # each body on its own: batching changes no bit
        assert torch.equal(a[1:], b)


def test_gradients_take_the_torch_path(bodies):
    samples = gm.make_samples(2000, 3)
    fmap = _map(4).requires_grad_(True)
    verts = bodies[:1].clone().requires_grad_(True)
    assert not takes_kernels(fmap, verts)
    means, quats, scales, opacity, rgb = gm.skinned_params_on_body(fmap, samples, verts)
    (means.sum() + quats[..., 1].sum() + scales.sum()).backward()
    assert fmap.grad is not None and fmap.grad[gm.OFFSET].abs().sum() > 0 and fmap.grad[gm.ROTATION].abs().sum() > 0
    assert verts.grad is not None and verts.grad.abs().sum() > 0
    with torch.no_grad():  # the same values as the kernels give
        assert takes_kernels(fmap, verts)
        frame_w = gm.sample_frames(verts, samples)[3][..., 0]
        _close(gm.skinned_params_on_body(fmap, samples, verts), (means, quats, scales, opacity, rgb), frame_w)


def test_texel_maps_without_gradients_match_the_torch_path(bodies):
    """position_map and normal_map (what pose and view conditioning see) by the kernels."""
    from dlacli.body import uv as U

    assert takes_kernels(bodies)
    grad = bodies.clone().requires_grad_(True)
    assert not takes_kernels(grad)
    for fn in (U.position_map, U.normal_map):
        fast, ref = fn(bodies, R), fn(grad, R).detach()
        assert fast.shape == ref.shape == (2, R, R, 3)
        assert ((fast == 0) == (ref == 0)).all()  # the same empty texels
        assert (fast - ref).abs().max() <= 8 * EPS * ref.abs().max()
    both = U.surface_maps(bodies, R)  # one pass for the two maps: the same numbers as each alone
    assert torch.equal(both[0], U.position_map(bodies, R)) and torch.equal(both[1], U.normal_map(bodies, R))


def test_kept_face_frames_follow_the_vertices_values(bodies):
    """`uv.body_face_frames` keeps the last bodies' frames and finds them by the vertices' values: a
    body changed in place (the same array) gets its own frames, never the kept ones, and every
    answer equals the kernel's own, at resolution 1 (the skinning divides scale by R)."""
    from dlacli.body import skin_kernels as sk
    from dlacli.body import uv as U

    faces, uv_d, inv_det, abs_inv_det = U.face_uv_terms()

    def direct(verts):
        vn = np.empty((verts.shape[0], 3))
        dpdu, scale = np.empty((faces.shape[0], 3)), np.empty(faces.shape[0])
        sk.face_frames(verts, faces, uv_d, inv_det, abs_inv_det, 1.0, vn, dpdu, scale)
        return vn, dpdu, scale

    verts = np.ascontiguousarray(bodies[0].numpy(), np.float32)
    first = U.body_face_frames(verts)
    assert U.body_face_frames(verts.copy()) is first  # the same values: kept
    verts[:50] += np.float32(0.05)  # moved in place: the same object, other values
    moved = U.body_face_frames(verts)
    assert moved is not first
    for got, want in zip(moved, direct(verts)):
        assert np.array_equal(got, want)
    other = np.ascontiguousarray(bodies[1].numpy(), np.float32)
    for body in (other, verts, other):  # more bodies than are kept: still right
        for got, want in zip(U.body_face_frames(body), direct(body)):
            assert np.array_equal(got, want)
