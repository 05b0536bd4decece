"""The rigged USD (formats/usd-rig.md) read back by pxr: UsdSkel's own skinning of the mesh
against our LBS and against anny's posed body, joints, time samples, material, texture, colours."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from dlacli.body.builtin_motions import builtin_motion
from dlacli.body.model import get_body_model
from dlacli.body.uv import uv_raster
from dlacli.errors import DlaInputError
from dlacli.io.usd_read import validate_usd
from dlacli.io.usd_rig import FORMAT, joint_token, texture_path
from dlacli.stages.rig import skinning_matrices, write_rigged_usd
from dlacli.types import Avatar, BodyParams, Motion

pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom, UsdShade, UsdSkel, Vt  # noqa: E402

R = 64
PHENOTYPE = {"gender": 0.8, "age": 0.5, "muscle": 0.3, "weight": 0.4, "height": 0.6, "proportions": 0.5}


def avatar_with(offset: float = 0.0, rgb=None, seed: int = 0) -> Avatar:
    """An identity-decoder avatar: constant normal offset `offset` (metres), colours `rgb`
    (constant [3]) or random."""
    rng = np.random.default_rng(seed)
    z = np.zeros((14, R, R), np.float32)
    z[0] = 4.0
    z[1:4] = rng.uniform(0.1, 0.9, (3, R, R)) if rgb is None else np.asarray(rgb, np.float32)[:, None, None]
    z[6] = offset  # the normal component of dxyz in the tangent frame
    z[7] = 1.0
    z[11:14] = -0.5
    return Avatar(
        z=z, encoder="unproject", decoder="identity", body=BodyParams(phenotype=dict(PHENOTYPE)), uv_layout="anny"
    )


def short_walk() -> Motion:
    m = builtin_motion("walk")
    sel = slice(0, 40, 13)  # 4 frames
    return Motion(list(m.bone_labels), m.rotations[sel], m.root_rotation[sel], m.root_translation[sel], m.fps)


@pytest.fixture(scope="module")
def walk_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("rig") / "avatar.usdc"
    avatar, motion = avatar_with(), short_walk()
    write_rigged_usd(avatar, path, motion=motion)
    return path, avatar, motion


def _skinned(path, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(rest points [V, 3], UsdSkel's skinned points at time t [V, 3]) through UsdSkel.Cache."""
    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Avatar"))
    cache.Populate(root, Usd.PrimDefaultPredicate)
    (binding,) = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
    skel_query = cache.GetSkelQuery(binding.GetSkeleton())
    (target,) = binding.GetSkinningTargets()
    rest = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get()
    points = Vt.Vec3fArray(rest)
    xforms = skel_query.ComputeSkinningTransforms(Usd.TimeCode(t))
    assert target.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(t))
    return np.asarray(rest, np.float64), np.asarray(points, np.float64)


def test_pxr_skinning_matches_our_lbs_and_anny(walk_file):
    path, avatar, motion = walk_file
    model = get_body_model()
    mats = skinning_matrices(avatar, motion).astype(np.float64)  # [T, J, 4, 4]
    idx, w = model.vertex_bone_weights
    body = model.forward_motion(avatar.body.phenotype, motion).vertices.double().numpy()
    for t in range(motion.num_frames):
        rest, skinned = _skinned(path, t)
        blended = np.einsum("vk,vkab->vab", w.astype(np.float64), mats[t][idx])  # [V, 4, 4]
        ours = np.einsum("vab,vb->va", blended[:, :3, :3], rest) + blended[:, :3, 3]
        # pxr skins in float32 from float32 points and float32-stored local transforms: ~30
        # roundings of quantities ~2 m (measured: 4e-7 m)
        np.testing.assert_allclose(skinned, ours, atol=30 * np.finfo(np.float32).eps * 2.0)
        # with zero offsets the mesh is anny's body: UsdSkel reproduces anny's own posed vertices up
        # to re-basing LBS at the zero pose instead of anny's bind pose (docs/rig.md; measured on
        # this phenotype over the whole walk: max 1.38 mm) -> 3 mm
        assert np.abs(skinned - body[t]).max() < 3e-3
    assert np.abs(_skinned(path, motion.num_frames - 1)[1] - rest).max() > 0.05  # the walk moves


def test_joints_bind_and_time_samples(walk_file):
    path, avatar, motion = walk_file
    model = get_body_model()
    stage = Usd.Stage.Open(str(path))
    assert stage.GetRootLayer().customLayerData["dla:format"] == FORMAT
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == motion.fps and stage.GetFramesPerSecond() == motion.fps
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, motion.num_frames - 1.0)
    assert stage.GetDefaultPrim().GetPath() == "/Avatar" and stage.GetDefaultPrim().IsA(UsdSkel.Root)
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Avatar/Skeleton"))
    joints = list(skel.GetJointsAttr().Get())
    assert len(joints) == model.num_bones
    # order = anny's bones; each path ends in the bone's sanitised label and extends its parent's
    assert [j.rsplit("/", 1)[-1] for j in joints] == [joint_token(b) for b in model.bone_labels]
    for j, parent in enumerate(model.bone_parents):
        assert joints[j] == (
            joint_token(model.bone_labels[j]) if parent < 0 else f"{joints[parent]}/{joint_token(model.bone_labels[j])}"
        )
    assert list(skel.GetJointNamesAttr().Get()) == model.bone_labels
    topo = UsdSkel.Topology(skel.GetJointsAttr().Get())
    assert topo.Validate()[0]
    np.testing.assert_array_equal(np.asarray(topo.GetParentIndices()), model.bone_parents)
    # bindTransforms (row-vector USD matrices) = the zero pose's joint poses
    bind = np.asarray(skel.GetBindTransformsAttr().Get()).transpose(0, 2, 1)
    np.testing.assert_allclose(bind, model.zero_pose(avatar.body.phenotype).bone_poses[0].double().numpy(), atol=1e-7)
    # restTransforms compose back to the bind transforms
    query = UsdSkel.Cache().GetSkelQuery(skel)
    rest_world = np.asarray(query.ComputeJointWorldTransforms(UsdGeom.XformCache(), True)).transpose(0, 2, 1)
    np.testing.assert_allclose(rest_world, bind, atol=1e-6)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Motion"))
    assert list(anim.GetJointsAttr().Get()) == joints
    assert UsdSkel.BindingAPI(skel.GetPrim()).GetAnimationSourceRel().GetTargets() == [anim.GetPath()]
    for attr in (anim.GetTranslationsAttr(), anim.GetRotationsAttr()):
        assert attr.GetTimeSamples() == [float(t) for t in range(motion.num_frames)]
    # the animated joint world transforms at frame t are anny's bone poses
    poses = get_body_model().forward_motion(avatar.body.phenotype, motion).bone_poses.double().numpy()
    for t in range(motion.num_frames):
        world = np.asarray(query.ComputeJointWorldTransforms(UsdGeom.XformCache(Usd.TimeCode(t)), False)).transpose(
            0, 2, 1
        )
        np.testing.assert_allclose(world, poses[t], atol=2e-5)  # float32 local translations/quatf, ~40 joints deep


def test_mesh_material_texture_and_colours(tmp_path):
    rgb = (0.5, 0.25, 0.75)
    path = tmp_path / "flat.usda"
    tex = write_rigged_usd(avatar_with(offset=0.01, rgb=rgb), path)
    assert tex == texture_path(path) == tmp_path / "flat.albedo.png"
    assert validate_usd(path) == []
    stage = Usd.Stage.Open(str(path))
    assert not stage.HasAuthoredTimeCodeRange() and not stage.GetPrimAtPath("/Avatar/Motion")
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Body"))
    model = get_body_model()
    points = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    assert points.shape == (model.num_vertices, 3)
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), model.faces)
    # a constant 1 cm outward offset moves every vertex 1 cm along its normal
    moved = np.linalg.norm(points - model.rest_vertices(PHENOTYPE), axis=1)
    np.testing.assert_allclose(moved, 0.01, atol=1e-5)
    # displayColor is linear: sRGB (IEC 61966-2-1) of the avatar's colour, decoded
    color = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor").Get())
    expected = [((c + 0.055) / 1.055) ** 2.4 for c in rgb]
    np.testing.assert_allclose(color, np.broadcast_to(expected, color.shape), atol=1e-6)
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    np.testing.assert_allclose(np.asarray(st.ComputeFlattened()), model.uv[model.face_uv.reshape(-1)], atol=1e-7)
    # material: UsdPreviewSurface.diffuseColor <- UsdUVTexture(file = the PNG beside the USD)
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    source = surface.GetInput("diffuseColor").GetConnectedSources()[0][0].source
    texture = UsdShade.Shader(source.GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    asset = texture.GetInput("file").Get()
    assert asset.path == "./flat.albedo.png" and asset.resolvedPath == str(tex)
    image = np.asarray(Image.open(tex))
    assert image.shape == (R, R, 3)
    covered = uv_raster(R).mask
    np.testing.assert_allclose(image[covered] / 255.0, np.broadcast_to(rgb, (covered.sum(), 3)), atol=0.5 / 255 + 1e-9)
    # skinning primvars: anny's own weights, 9 per vertex
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    idx, w = model.vertex_bone_weights
    assert binding.GetJointIndicesPrimvar().GetElementSize() == idx.shape[1]
    np.testing.assert_array_equal(np.asarray(binding.GetJointIndicesPrimvar().Get()).reshape(idx.shape), idx)
    np.testing.assert_allclose(np.asarray(binding.GetJointWeightsPrimvar().Get()).reshape(w.shape), w, atol=1e-6)


def test_texture_rows_follow_v_up(tmp_path):
    """Row 0 of the PNG is v near 1: a map whose colour depends on v comes out in that order."""
    avatar = avatar_with()
    v = 1.0 - (np.arange(R) + 0.5) / R  # texel centre v per row
    avatar.z[1:4] = v[None, :, None]
    tex = write_rigged_usd(avatar, tmp_path / "v.usdc")
    image = np.asarray(Image.open(tex), np.float64)[..., 0] / 255.0
    covered = uv_raster(R).mask
    rows = np.nonzero(covered)[0]
    np.testing.assert_allclose(image[covered], v[rows], atol=0.5 / 255 + 1e-9)


def test_bad_outputs_are_refused_before_writing(tmp_path):
    with pytest.raises(DlaInputError, match="usdc"):
        write_rigged_usd(avatar_with(), tmp_path / "a.glb")
    (tmp_path / "b.albedo.png").mkdir()  # the texture's place is taken by a folder
    with pytest.raises(DlaInputError, match="albedo"):
        write_rigged_usd(avatar_with(), tmp_path / "b.usdc")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.albedo.png"]
