"""Body model wrapper: rotation helpers, pose conversion, agreement with anny, pose semantics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dlacli.body.model import (
    BodyModel,
    axis_angle_to_pose_params,
    get_body_model,
    pose_params_to_axis_angle,
    pose_to_rotations,
    rotations_to_pose,
)
from dlacli.errors import DlaInputError
from dlacli.geometry import (
    axis_angle_to_matrix,
    axis_angle_to_quat,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_multiply,
    quat_to_axis_angle,
    quat_to_matrix,
)
from dlacli.types import BodyParams, Motion

# Rounding steps along anny's float32 forward, for tolerances tol(float32, |x|, FORWARD_OPS):
# 136 phenotype blend shapes summed, a bone chain up to 17 deep of 4x4 products (4 terms each),
# a 9-bone linear blend of 4x4 transforms applied to a point: ~136 + 68 + 45 ~ 250.
FORWARD_OPS = 250


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return get_body_model()


def _random_axis_angles(n: int, seed: int) -> np.ndarray:
    """Random rotations with angles over [0, pi], plus angles at 0, tiny, and within 1e-6 of pi."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, np.pi, size=n)
    special = np.concatenate([[0.0, 1e-9, 1e-4, np.pi], np.pi - np.logspace(-9, -2, 8)])
    angle[: min(n, special.size)] = special[:n]
    return axis * angle[:, None]


# ---------------------------------------------------------------------------------------------
# rotation helpers against scipy


def test_axis_angle_to_matrix_matches_scipy():
    aa = _random_axis_angles(500, 0)
    ours = axis_angle_to_matrix(torch.from_numpy(aa)).numpy()
    np.testing.assert_allclose(ours, Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)


def test_log_map_round_trip_including_near_pi():
    aa = _random_axis_angles(500, 1)
    mats = Rotation.from_rotvec(aa).as_matrix()
    back = matrix_to_axis_angle(torch.from_numpy(mats)).numpy()
    assert np.all(np.linalg.norm(back, axis=1) <= np.pi + 1e-9)
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), mats, atol=1e-9)
    # away from pi the axis-angle itself comes back (at pi, +-axis are the same rotation)
    far = np.linalg.norm(aa, axis=1) < np.pi - 1e-3
    np.testing.assert_allclose(back[far], aa[far], atol=1e-9)


def test_quaternions_match_scipy():
    aa = _random_axis_angles(300, 2)
    mats = Rotation.from_rotvec(aa).as_matrix()
    ref = Rotation.from_rotvec(aa).as_quat()[:, [3, 0, 1, 2]]  # scipy is (x, y, z, w)
    ref *= np.where(ref[:, :1] < 0, -1.0, 1.0)
    q = matrix_to_quat(torch.from_numpy(mats)).numpy()
    q_dist = np.minimum(np.abs(q - ref).max(1), np.abs(q + ref).max(1))  # w = 0 is sign-ambiguous
    assert q_dist.max() < 1e-9
    q2 = axis_angle_to_quat(torch.from_numpy(aa)).numpy()
    np.testing.assert_allclose(quat_to_matrix(torch.from_numpy(q2)).numpy(), mats, atol=1e-12)
    np.testing.assert_allclose(
        Rotation.from_rotvec(quat_to_axis_angle(torch.from_numpy(q2)).numpy()).as_matrix(), mats, atol=1e-9
    )
    # the Hamilton product composes rotations like matrix products (b first, then a)
    a, b = torch.from_numpy(q2[:150]), torch.from_numpy(q2[150:])
    np.testing.assert_allclose(quat_to_matrix(quat_multiply(a, b)).numpy(), mats[:150] @ mats[150:], atol=1e-12)


def test_rotation_gradients_finite_and_correct():
    aa = torch.tensor([[0.3, -0.2, 0.5], [0.0, 0.0, 0.0], [1e-8, 0, 0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (aa,))
    aa2 = torch.tensor([[0.3, -0.2, 0.5], [1.0, 2.0, -0.5], [0.0, 0.0, 3.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: matrix_to_axis_angle(axis_angle_to_matrix(x)), (aa2,))
    eye = torch.eye(3, dtype=torch.float64)[None].requires_grad_(True)
    matrix_to_axis_angle(eye).sum().backward()
    assert torch.isfinite(eye.grad).all()


# ---------------------------------------------------------------------------------------------
# pose parameters


def test_pose_params_round_trip():
    t, j = 6, 104
    aa = _random_axis_angles(t * j, 3).reshape(t, j, 3)
    aa[:, 0] = 0.0
    rr = _random_axis_angles(t, 4)
    rt = np.random.default_rng(5).normal(size=(t, 3))
    params = axis_angle_to_pose_params(torch.from_numpy(aa), torch.from_numpy(rr), torch.from_numpy(rt))
    assert params.shape == (t, j, 4, 4)
    np.testing.assert_allclose(params[..., 3, :].numpy(), np.broadcast_to([0, 0, 0, 1.0], (t, j, 4)))
    np.testing.assert_allclose(params[:, 1:, :3, 3].numpy(), 0.0)
    rot, rr2, rt2 = pose_params_to_axis_angle(params)
    assert np.all(rot[:, 0].numpy() == 0.0)
    np.testing.assert_allclose(
        Rotation.from_rotvec(rot.numpy().reshape(-1, 3)).as_matrix(),
        Rotation.from_rotvec(aa.reshape(-1, 3)).as_matrix(),
        atol=1e-9,
    )
    np.testing.assert_allclose(
        Rotation.from_rotvec(rr2.numpy()).as_matrix(), Rotation.from_rotvec(rr).as_matrix(), atol=1e-9
    )
    np.testing.assert_allclose(rt2.numpy(), rt)
    # numpy in, numpy out; a "root" rotation is composed under root_rotation
    aa[:, 0] = _random_axis_angles(t, 6)
    p_np = axis_angle_to_pose_params(aa.astype(np.float32), rr.astype(np.float32), rt.astype(np.float32))
    assert isinstance(p_np, np.ndarray) and p_np.dtype == np.float32
    expect = Rotation.from_rotvec(rr) * Rotation.from_rotvec(aa[:, 0])
    np.testing.assert_allclose(p_np[:, 0, :3, :3], expect.as_matrix(), atol=1e-5)


# ---------------------------------------------------------------------------------------------
# the model against anny itself


def test_empty_pose_matches_anny_forward(body, tol):
    import anny

    phenotype = {"gender": 0.2, "age": 0.7, "muscle": 0.6, "weight": 0.4, "height": 0.55, "proportions": 0.5}
    ref_model = anny.Anny(
        rig="anny", topology="anny", pose_parameterization="local-ref"
    )  # float64, anny's default skinning
    identity = torch.eye(4, dtype=torch.float64).expand(1, 104, 4, 4)
    ref = ref_model(identity, {k: torch.tensor([v], dtype=torch.float64) for k, v in phenotype.items()})
    ours = body.forward_body(BodyParams(phenotype=phenotype))
    atol = tol(torch.float32, ref["vertices"].abs().max(), FORWARD_OPS)  # ours float32, anny float64
    np.testing.assert_allclose(ours.vertices[0].numpy(), ref["vertices"][0].numpy(), atol=atol)
    np.testing.assert_allclose(ours.bone_poses[0].numpy(), ref["bone_poses"][0].numpy(), atol=atol)
    assert body.bone_labels == list(ref_model.bone_labels)
    assert body.faces.shape == (27420, 3) and body.num_vertices == 13718
    np.testing.assert_array_equal(body.face_uv, ref_model.face_texture_coordinate_indices.numpy())
    # LBS with the returned transforms on anny's bind mesh gives the vertices back
    w = torch.zeros(body.num_vertices, 104, dtype=torch.float64)
    idx, wts = body.vertex_bone_weights
    w.scatter_add_(1, torch.from_numpy(idx), torch.from_numpy(wts).double())
    bind = ref["rest_vertices"][0]
    blend = torch.einsum("vj,jab->vab", w, ours.bone_transforms[0].double())
    lbs = (blend[:, :3, :3] @ bind[:, :, None])[..., 0] + blend[:, :3, 3]
    np.testing.assert_allclose(lbs.numpy(), ref["vertices"][0].numpy(), atol=atol)  # float32 transforms


def test_root_transform_is_rigid(body, tol):
    rest = body.zero_pose()
    rr = torch.tensor([[0.3, -1.2, 2.0]])
    rt = torch.tensor([[0.5, -0.25, 1.0]])
    out = body.forward({}, torch.zeros(1, 104, 3), rr, rt)
    r = Rotation.from_rotvec(rr[0].numpy()).as_matrix()
    expect = rest.vertices[0].numpy() @ r.T + rt[0].numpy()
    np.testing.assert_allclose(
        out.vertices[0].numpy(), expect, atol=tol(torch.float32, np.abs(expect).max(), FORWARD_OPS)
    )
    # float32 Rodrigues (~10 roundings per entry) composed with the root's bind rotation (3 terms)
    np.testing.assert_allclose(out.bone_poses[0, 0, :3, :3].numpy(), r, atol=tol(torch.float32, 1.0, 16))
    np.testing.assert_allclose(out.bone_heads[0, 0].numpy(), rt[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(rest.bone_heads[0, 0].numpy(), 0.0, atol=1e-6)


def test_local_ref_turns_subtree_about_bone_head_in_world_axes(body, tol):
    """Rotating one bone by R moves the vertices skinned only to its subtree by x -> h + R (x - h),
    h its head in the zero pose, with R in world axes; vertices with no weight in it stay."""
    c = body.bone_labels.index("lowerarm01.L")
    subtree = {c}
    for j in range(c + 1, body.num_bones):
        if body.bone_parents[j] in subtree:
            subtree.add(j)
    idx, wts = body.vertex_bone_weights
    in_sub = np.isin(idx, sorted(subtree))
    w_sub = (wts * in_sub).sum(1)
    rest = body.zero_pose()
    aa = np.array([0.2, 0.9, -0.4], dtype=np.float32)
    rot = torch.zeros(1, 104, 3)
    rot[0, c] = torch.from_numpy(aa)
    out = body.forward({}, rot, torch.zeros(1, 3), torch.zeros(1, 3))
    h = rest.bone_heads[0, c].numpy()
    x = rest.vertices[0].numpy()
    full = w_sub > 1 - 1e-6
    none = w_sub < 1e-6
    assert full.sum() > 200 and none.sum() > 5000
    expect = h + (x[full] - h) @ Rotation.from_rotvec(aa).as_matrix().T
    atol = tol(torch.float32, np.abs(x).max(), FORWARD_OPS)
    np.testing.assert_allclose(out.vertices[0].numpy()[full], expect, atol=atol)
    np.testing.assert_allclose(out.vertices[0].numpy()[none], x[none], atol=atol)


def test_forward_motion_batches_and_reorders(body, tol):
    rng = np.random.default_rng(7)
    t = 5
    rot = (rng.normal(size=(t, 104, 3)) * 0.2).astype(np.float32)
    rot[:, 0] = 0
    rr = (rng.normal(size=(t, 3)) * 0.3).astype(np.float32)
    rt = rng.normal(size=(t, 3)).astype(np.float32)
    motion = Motion(list(body.bone_labels), rot, rr, rt, fps=30.0)
    whole = body.forward({}, torch.from_numpy(rot), torch.from_numpy(rr), torch.from_numpy(rt))
    batched = body.forward_motion({}, motion, batch=2)
    # the same float32 forward in other batch shapes: BLAS may sum in another order, so allow the
    # forward's rounding budget (1e-6 was ~3 ulps at |x| = 2.5 m)
    atol = tol(torch.float32, whole.vertices.abs().max(), FORWARD_OPS)
    np.testing.assert_allclose(batched.vertices.numpy(), whole.vertices.numpy(), atol=atol)
    perm = rng.permutation(104)
    shuffled = Motion([body.bone_labels[i] for i in perm], rot[:, perm], rr, rt, fps=30.0)
    sel = body.forward_motion({}, shuffled, frames=[4, 1])
    np.testing.assert_allclose(sel.vertices.numpy(), whole.vertices[[4, 1]].numpy(), atol=atol)
    bad = Motion(["root", "no_such_bone"], np.zeros((1, 2, 3)), np.zeros((1, 3)), np.zeros((1, 3)), fps=30.0)
    with pytest.raises(DlaInputError, match="unknown bone 'no_such_bone'"):
        body.forward_motion({}, bad)


def test_pose_dict_conversion(body):
    pose = {"head": np.array([0.1, 0.2, 0.3]), "wrist.R": [0.0, -0.5, 0.0]}
    rot = pose_to_rotations(pose, "body.json")
    assert rot.shape == (104, 3)
    assert np.count_nonzero(np.abs(rot).sum(1)) == 2
    np.testing.assert_allclose(rot[body.bone_labels.index("head")], [0.1, 0.2, 0.3], rtol=1e-6)
    back = rotations_to_pose(rot)
    assert set(back) == {"head", "wrist.R"}
    np.testing.assert_allclose(back["wrist.R"], [0.0, -0.5, 0.0])
    with pytest.raises(DlaInputError) as err:
        pose_to_rotations({"elbow_left": [0, 0, 1]}, "body.json")
    assert str(err.value).startswith("body.json: unknown bone 'elbow_left' (anny rig has 104 bones, e.g.")
    with pytest.raises(DlaInputError, match="3 finite numbers"):
        pose_to_rotations({"head": [0, 1]}, "body.json")
    with pytest.raises(DlaInputError, match="phenotype"):
        body.forward({"gender": 1.5}, torch.zeros(1, 104, 3), torch.zeros(1, 3), torch.zeros(1, 3))


def test_rest_bone_heads_left_is_plus_x(body):
    heads = body.rest_bone_heads()
    assert heads.shape == (104, 3)
    assert body.bone_parents[0] == -1 and body.bone_parents.shape == (104,)
    for name in ("wrist", "foot", "eye", "upperarm01"):
        assert heads[body.bone_labels.index(f"{name}.L"), 0] > 0 > heads[body.bone_labels.index(f"{name}.R"), 0]
    # facing -Y: the eyes are in front of (more negative y than) the head bone
    assert heads[body.bone_labels.index("eye.L"), 1] < heads[body.bone_labels.index("head"), 1]
    assert heads[body.bone_labels.index("head"), 2] > 0.4 > -0.5 > heads[body.bone_labels.index("foot.L"), 2]


def test_forward_is_differentiable(body):
    rot = torch.zeros(1, 104, 3, requires_grad=True)
    out = body.forward({}, rot, torch.zeros(1, 3), torch.zeros(1, 3))
    out.vertices[0, :, 0].sum().backward()
    assert rot.grad is not None and torch.isfinite(rot.grad).all() and rot.grad.abs().sum() > 0


def test_dtype_follows_input(body, tol):
    rng = np.random.default_rng(9)
    rot = torch.from_numpy(rng.normal(size=(2, 104, 3)) * 0.2)
    rr, rt = torch.from_numpy(rng.normal(size=(2, 3))), torch.from_numpy(rng.normal(size=(2, 3)))
    out64 = body.forward({"weight": 0.8}, rot, rr, rt)
    out32 = body.forward({"weight": 0.8}, rot.float(), rr.float(), rt.float())
    assert out64.vertices.dtype == torch.float64 and out32.vertices.dtype == torch.float32
    atol = tol(torch.float32, out64.vertices.abs().max(), FORWARD_OPS)
    np.testing.assert_allclose(out64.vertices.numpy(), out32.vertices.numpy(), atol=atol)
