"""The LBS rig of an avatar (stages/rig.py): weights, skinning against analytic cases, joint
matrices of the zero pose, and how far LBS departs from dla's own surface-frame skinning."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dlacli.avatar.codec import Decoder, register_decoder
from dlacli.body.builtin_motions import builtin_motion
from dlacli.body.model import get_body_model
from dlacli.stages.animate import pose_avatar
from dlacli.stages.rig import build_rig, polar_rotation, skin, skinning_matrices
from dlacli.types import Avatar, BodyParams, Motion

N = 4096
R = 64  # map resolution: small and fast; the rig does not depend on it


def synthetic_avatar(seed: int = 0, offset_sigma: float = 0.01, decoder: str = "identity") -> Avatar:
    """An identity-decoder avatar with a random map: opaque, random colours, offsets ~N(0, 1 cm)
    clipped to 3 cm per axis (the demo avatar's 1-99 % range is about +-2.5 cm), random small
    rotations, flat scales as lift makes them."""
    rng = np.random.default_rng(seed)
    z = np.zeros((14, R, R), np.float32)
    z[0] = 4.0
    z[1:4] = rng.uniform(0.1, 0.9, (3, R, R))
    z[4:7] = np.clip(rng.normal(0.0, offset_sigma, (3, R, R)), -0.03, 0.03)
    z[7] = 1.0
    z[8:11] = rng.normal(0.0, 0.2, (3, R, R))
    z[11:13], z[13] = -0.5, -1.6
    body = BodyParams(
        phenotype={"gender": 0.3, "age": 0.6, "muscle": 0.5, "weight": 0.6, "height": 0.4, "proportions": 0.5}
    )
    return Avatar(
        z=z,
        encoder="unproject",
        decoder=decoder,
        body=body,
        uv_layout="anny",
        extra={"samples": {"count": N, "seed": 3}},
    )


def short_walk(step: int = 22) -> Motion:
    m = builtin_motion("walk")
    sel = slice(0, None, step)
    return Motion(list(m.bone_labels), m.rotations[sel], m.root_rotation[sel], m.root_translation[sel], m.fps)


@pytest.fixture(scope="module")
def avatar():
    return synthetic_avatar()


@pytest.fixture(scope="module")
def rig(avatar):
    return build_rig(avatar)


def test_rig_shapes_and_weights(rig, avatar, tol):
    model = get_body_model()
    j = model.num_bones
    assert rig.joint_names == model.bone_labels and len(rig) == N
    assert rig.parents.dtype == np.int64 and rig.parents[0] == -1 and np.all(rig.parents[1:] < np.arange(1, j))
    assert rig.bind_transforms.shape == (j, 4, 4) and rig.bind_transforms.dtype == np.float64
    assert rig.joint_indices.dtype == np.int32 and rig.joint_weights.dtype == np.float32
    assert rig.joint_indices.shape == rig.joint_weights.shape == (N, model.vertex_bone_weights[0].shape[1])
    assert np.all((rig.joint_indices >= 0) & (rig.joint_indices < j))
    assert np.all(rig.joint_weights >= 0)
    # rows sum to 1: a float32 sum of K terms, each rounded once (K ops)
    k = rig.joint_weights.shape[1]
    np.testing.assert_allclose(rig.joint_weights.sum(axis=1), 1.0, atol=tol(np.float32, 1.0, ops=2 * k))
    # no joint twice in a row among the weighted slots
    for row_i, row_w in zip(rig.joint_indices[:200], rig.joint_weights[:200]):
        used = row_i[row_w > 0]
        assert len(set(used.tolist())) == used.size
    # the bind transforms are the zero pose's joints: rigid, heads at anny's rest joints
    rot = rig.bind_transforms[:, :3, :3]
    np.testing.assert_allclose(np.swapaxes(rot, 1, 2) @ rot, np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)
    np.testing.assert_allclose(rig.bind_transforms[:, :3, 3], model.rest_bone_heads(avatar.body.phenotype), atol=1e-6)
    assert np.all((rig.opacities >= 0) & (rig.opacities <= 1)) and np.all((rig.rgb >= 0) & (rig.rgb <= 1))
    np.testing.assert_allclose(np.linalg.norm(rig.quats, axis=1), 1.0, atol=1e-5)


def test_rig_rest_is_dla_zero_pose(avatar, rig, tol):
    """The rest Gaussians are what dla's own skinning gives in the zero pose."""
    j = get_body_model().num_bones
    zero = Motion(
        get_body_model().bone_labels, np.zeros((1, j, 3), np.float32), np.zeros((1, 3)), np.zeros((1, 3)), 30.0
    )
    anim = pose_avatar(avatar, zero)
    np.testing.assert_allclose(rig.positions, anim.positions[0], atol=tol(np.float32, 2.0, ops=8))
    np.testing.assert_allclose(rig.scales, anim.scales[0], rtol=1e-6)


def test_skin_identity_returns_rest(rig, tol):
    eye = np.broadcast_to(np.eye(4, dtype=np.float32), (rig.num_joints, 4, 4))
    pos, quats = skin(rig, eye)
    # K products and sums of magnitude ~1 m in float64, rounded to float32 once
    np.testing.assert_allclose(pos, rig.positions, atol=tol(np.float32, 2.0, ops=2))
    np.testing.assert_allclose(np.abs(np.sum(quats * rig.quats, axis=1)), 1.0, atol=tol(np.float32, 1.0, ops=8))


@pytest.mark.parametrize("seed", [0, 1])
def test_skin_one_rigid_transform_is_that_transform(rig, seed, tol):
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=seed)
    g = np.eye(4)
    g[:3, :3] = rot.as_matrix()
    g[:3, 3] = rng.normal(0.0, 1.0, 3)
    pos, quats = skin(rig, np.broadcast_to(g.astype(np.float32), (rig.num_joints, 4, 4)))
    want = rig.positions.astype(np.float64) @ g[:3, :3].T + g[:3, 3]
    # float32 matrix entries (rel. eps) times ~3 m, a dozen rounding steps
    np.testing.assert_allclose(pos, want, atol=tol(np.float32, 3.0, ops=16))
    got_m = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix()
    want_m = rot.as_matrix()[None] @ Rotation.from_quat(rig.quats[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(got_m, want_m, atol=tol(np.float32, 1.0, ops=16))


def test_polar_rotation_matches_svd():
    """Newton's polar iteration against the SVD definition U = W V^T (det > 0)."""
    rng = np.random.default_rng(4)
    a = np.concatenate(
        [
            Rotation.random(200, random_state=1).as_matrix() * rng.uniform(0.5, 1.0, (200, 1, 1)),  # blended-like
            rng.normal(size=(200, 3, 3)),  # generic
        ]
    )
    a[np.linalg.det(a) < 0] *= -1.0  # det > 0, as blends of rotations with weights >= 0 have in practice
    w, _, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(w @ vt))
    w[..., :, 2] *= d[..., None]
    np.testing.assert_allclose(polar_rotation(a), w @ vt, atol=1e-9)


def test_skinning_matrices_of_the_zero_pose_are_identity(avatar, tol):
    model = get_body_model()
    j = model.num_bones
    zero = Motion(model.bone_labels, np.zeros((3, j, 3), np.float32), np.zeros((3, 3)), np.zeros((3, 3)), 30.0)
    mats = skinning_matrices(avatar, zero)
    assert mats.shape == (3, j, 4, 4) and mats.dtype == np.float32
    # the same float32 anny transforms on both sides; their product with an inverse: ~64 roundings of ~1
    np.testing.assert_allclose(mats, np.broadcast_to(np.eye(4), mats.shape), atol=tol(np.float32, 1.0, ops=64))


def test_skinning_matrices_move_the_joints(avatar):
    """M_t,j applied to the rest joint heads gives the posed joint heads (anny's kinematics)."""
    motion = short_walk(40)
    mats = skinning_matrices(avatar, motion).astype(np.float64)
    model = get_body_model()
    heads = model.forward_motion(avatar.body.phenotype, motion).bone_heads.double().numpy()  # [T, J, 3]
    rest = model.rest_bone_heads(avatar.body.phenotype).astype(np.float64)
    moved = np.einsum("tjab,jb->tja", mats[..., :3, :3], rest) + mats[..., :3, 3]
    np.testing.assert_allclose(moved, heads, atol=2e-5)  # float32 transforms, metres: ~100 eps x 2 m


def test_lbs_stays_close_to_dla_skinning(avatar, rig):
    """LBS of the Gaussians vs dla's surface-frame skinning (pose_avatar) on 7 frames of the walk.

    Measured (demo avatar, 131,072 Gaussians, whole walk; docs/rig.md): median 0.04 mm, p99
    4.7 mm, max 35 mm; on this synthetic avatar, the same order. The anchor point on the surface
    moves the same under both up to ~2 mm (max measured 1.8 mm); the offset dx turns with the
    posed tangent frame in dla and with the blended bone rotation in LBS, so per Gaussian
    |error| <= 2 |dx| + 2 mm (both rotations are rigid). Bounds: that analytic one with 3 mm
    for the anchor, and median < 0.5 mm, p99 < 10 mm (over 10x / 2x the measurements)."""
    motion = short_walk()
    anim = pose_avatar(avatar, motion)
    mats = skinning_matrices(avatar, motion)
    errors, angles = [], []
    from dlacli.avatar import gaussian_map as gm
    from dlacli.avatar.posed import sample_settings

    samples = gm.make_samples(*sample_settings(avatar))
    dx = gm.lookup(torch.from_numpy(avatar.z), samples.uv)[:, gm.OFFSET].numpy()
    bound = 2.0 * np.linalg.norm(dx, axis=1) + 0.003
    for t in range(motion.num_frames):
        pos, quats = skin(rig, mats[t])
        err = np.linalg.norm(pos - anim.positions[t], axis=1)
        assert np.all(err <= bound), f"frame {t}: {np.sum(err > bound)} Gaussians beyond 2|dx| + 3 mm"
        errors.append(err)
        angles.append(2 * np.degrees(np.arccos(np.clip(np.abs(np.sum(quats * anim.quats[t], axis=1)), 0, 1))))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.5e-3
    assert np.percentile(errors, 99) < 10e-3
    assert np.median(np.concatenate(angles)) < 2.0  # degrees; measured 0.2 on the demo avatar


class _PoseConditioned(Decoder):
    name = "test-rig-pose-conditioned"
    pose_conditioned = True

    def __init__(self, checkpoint: str = "", where: str = "avatar"):
        pass

    def canonical(self, z):
        return z


def test_pose_conditioned_decoder_warns_one_line(capsys):
    register_decoder(_PoseConditioned.name, _PoseConditioned)
    rig = build_rig(synthetic_avatar(1, decoder=_PoseConditioned.name), n_gaussians=64, where="av.npz")
    err = capsys.readouterr().err.strip().splitlines()
    assert len(rig) == 64
    assert len(err) == 1 and err[0].startswith("warning: av.npz:") and "F_c" in err[0]
