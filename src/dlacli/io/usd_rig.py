"""A rigged avatar as a UsdSkel asset (formats/usd-rig.md): skeleton, skinned textured mesh and,
optionally, a joint animation. Pure writer: it takes arrays (`RigAsset`); the avatar-level entry
point that computes them is `dlacli.stages.rig.write_rigged_usd`.

Layout (defaultPrim /Avatar):

    /Avatar                      SkelRoot
    /Avatar/Skeleton             Skeleton (joints, bindTransforms, restTransforms; with a motion
                                 skel:animationSource -> /Avatar/Motion)
    /Avatar/Body                 Mesh, skinned (skel:skeleton, skel:jointIndices/jointWeights),
                                 UVs `primvars:st`, vertex colours `primvars:displayColor`,
                                 material:binding -> /Avatar/Materials/Skin
    /Avatar/Materials/Skin       UsdPreviewSurface whose diffuseColor is a UsdUVTexture reading
                                 the PNG written beside the USD file
    /Avatar/Motion               SkelAnimation (with a motion): per joint per frame local
                                 translations / rotations / scales, time-sampled

Matrices: dla uses column vectors (x' = M x, translation in the last column); USD's Gf matrices
use row vectors (translation in the last row), so every matrix is transposed on the way out.
Quaternions: `Vt.QuatfArray.FromNumpy` takes (x, y, z, w); dla's are (w, x, y, z).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.usd import AVATAR, FORMAT_KEY, SUFFIXES, export_layer, pxr_quiet  # one USD convention for both writers
from dlacli.types import srgb_to_linear

FORMAT = "dla.usd-rig/1"
SKELETON = "/Avatar/Skeleton"
BODY = "/Avatar/Body"
MATERIAL = "/Avatar/Materials/Skin"
ANIMATION = "/Avatar/Motion"
TEXTURE_SUFFIX = ".albedo.png"  # avatar.usdc -> avatar.albedo.png beside it
ROUGHNESS = 0.8  # skin and cloth: a matte look; the avatar's colours carry no specular information


@dataclass
class RigAsset:
    """Everything the UsdSkel file holds (numpy; matrices in dla's column-vector convention)."""

    joint_names: list[str]  # [J] anny bone labels
    parents: np.ndarray  # [J] int64, -1 for the root, parents before children
    bind_transforms: np.ndarray  # [J, 4, 4] float64 world transform of each joint in the rest pose
    points: np.ndarray  # [V, 3] float32 rest-pose mesh vertices, metres
    normals: np.ndarray  # [V, 3] float32 unit vertex normals
    faces: np.ndarray  # [F, 3] int64 vertex indices (outward winding, counter-clockwise)
    uv: np.ndarray  # [Vt, 2] float32 texture coordinates (u right, v up)
    face_uv: np.ndarray  # [F, 3] int64 indices into uv, per face corner
    vertex_rgb: np.ndarray  # [V, 3] float32 display colour, sRGB-encoded in [0, 1]
    joint_indices: np.ndarray  # [V, K] int32 into joint_names
    joint_weights: np.ndarray  # [V, K] float32, rows sum to 1
    texture: np.ndarray  # [H, W, 3] uint8 sRGB base colour, row 0 = top (v = 1)
    fps: float | None = None  # frames per second of the animation
    joint_poses: np.ndarray | None = None  # [T, J, 4, 4] float64 world joint transforms per frame


def joint_token(label: str) -> str:
    """An anny bone label as a USD path element: characters other than letters, digits and '_'
    become '_' ("upperarm01.L" -> "upperarm01_L", "toe1-2.L" -> "toe1_2_L")."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", label)
    return name if re.match(r"[A-Za-z_]", name) else f"_{name}"


def joint_paths(labels: list[str], parents: np.ndarray) -> list[str]:
    """UsdSkel joint paths ("root/spine05/spine04/...") from bone labels and parents."""
    paths: list[str] = []
    for j, label in enumerate(labels):
        p = int(parents[j])
        assert p < j, f"joint {label!r}: parent {p} must come before it"
        paths.append(joint_token(label) if p < 0 else f"{paths[p]}/{joint_token(label)}")
    assert len(set(paths)) == len(paths), "joint names collide after sanitising"
    return paths


def local_transforms(world: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """[..., J, 4, 4] world joint transforms -> [..., J, 4, 4] transforms relative to the parent."""
    world = np.asarray(world, np.float64)
    out = world.copy()
    has = parents >= 0
    out[..., has, :, :] = np.linalg.inv(world[..., parents[has], :, :]) @ world[..., has, :, :]
    return out


def texture_path(path: str | os.PathLike) -> Path:
    """The PNG written beside a rigged USD file: avatar.usdc -> avatar.albedo.png."""
    path = Path(path)
    return path.with_name(path.stem + TEXTURE_SUFFIX)


def _check(asset: RigAsset) -> None:
    j, v = len(asset.joint_names), asset.points.shape[0]
    assert asset.parents.shape == (j,) and asset.bind_transforms.shape == (j, 4, 4), (
        asset.parents.shape,
        asset.bind_transforms.shape,
    )
    assert asset.points.shape == (v, 3) and asset.normals.shape == (v, 3), (asset.points.shape, asset.normals.shape)
    assert asset.faces.ndim == 2 and asset.faces.shape[1] == 3 and asset.face_uv.shape == asset.faces.shape
    assert asset.vertex_rgb.shape == (v, 3)
    assert asset.joint_indices.shape == asset.joint_weights.shape and asset.joint_indices.shape[0] == v
    assert asset.texture.ndim == 3 and asset.texture.shape[2] == 3 and asset.texture.dtype == np.uint8
    if asset.joint_poses is not None:
        assert asset.joint_poses.ndim == 4 and asset.joint_poses.shape[1:] == (j, 4, 4), asset.joint_poses.shape
        assert asset.fps is not None and asset.fps > 0, asset.fps


@pxr_quiet()
def write_rig_usd(path: str | os.PathLike, asset: RigAsset) -> Path:
    """Write the UsdSkel asset (binary for .usdc/.usd, text for .usda) and its texture PNG beside
    it, both atomically and together (one output group). Returns the texture's path."""
    from PIL import Image
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

    from dlacli.geometry import matrix_to_quat, quat_wxyz_to_xyzw
    from dlacli.io.atomic import atomic_path, output_group

    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"unknown USD suffix {path.suffix!r} (use {', '.join(SUFFIXES)})")
    _check(asset)
    tex_path = texture_path(path)

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.GetRootLayer().customLayerData = {FORMAT_KEY: FORMAT}
    root = UsdSkel.Root.Define(stage, AVATAR)
    stage.SetDefaultPrim(root.GetPrim())

    # skeleton: joint paths from the parents, bind = rest = the rest pose
    paths = joint_paths(asset.joint_names, asset.parents)
    tokens = Vt.TokenArray(paths)
    bind = np.asarray(asset.bind_transforms, np.float64)
    skel = UsdSkel.Skeleton.Define(stage, SKELETON)
    skel.CreateJointsAttr(tokens)
    skel.CreateJointNamesAttr(Vt.TokenArray(list(asset.joint_names)))  # what DCC tools name bones
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(bind.transpose(0, 2, 1))))
    rest_local = local_transforms(bind, asset.parents)
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(rest_local.transpose(0, 2, 1))))

    # mesh
    mesh = UsdGeom.Mesh.Define(stage, BODY)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(asset.points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(asset.faces.shape[0], 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(asset.faces.reshape(-1), np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(asset.normals, np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    lo, hi = asset.points.min(axis=0), asset.points.max(axis=0)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32)))
    primvars = UsdGeom.PrimvarsAPI(mesh.GetPrim())
    st = primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(asset.uv, np.float32)))
    st.SetIndices(Vt.IntArray.FromNumpy(np.ascontiguousarray(asset.face_uv.reshape(-1), np.int32)))
    color = primvars.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex)
    color.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(srgb_to_linear(asset.vertex_rgb), np.float32)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    k = asset.joint_indices.shape[1]
    binding.CreateJointIndicesPrimvar(False, k).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(asset.joint_indices.reshape(-1), np.int32))
    )
    binding.CreateJointWeightsPrimvar(False, k).Set(
        Vt.FloatArray.FromNumpy(np.ascontiguousarray(asset.joint_weights.reshape(-1), np.float32))
    )
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])

    # material: UsdPreviewSurface <- UsdUVTexture(st) of the PNG beside this file
    material = UsdShade.Material.Define(stage, MATERIAL)
    surface = UsdShade.Shader.Define(stage, f"{MATERIAL}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(ROUGHNESS)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"{MATERIAL}/UV")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    texture = UsdShade.Shader.Define(stage, f"{MATERIAL}/BaseColor")
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{tex_path.name}"))
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(texture.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)

    # animation: local joint transforms per frame
    if asset.joint_poses is not None:
        t = asset.joint_poses.shape[0]
        stage.SetTimeCodesPerSecond(float(asset.fps))
        stage.SetFramesPerSecond(float(asset.fps))
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(float(t - 1))
        local = local_transforms(asset.joint_poses, asset.parents)  # [T, J, 4, 4]
        rot = local[..., :3, :3]
        err = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max()
        assert err < 1e-4, f"joint transforms are not rigid (|R^T R - I| = {err:.2e})"
        quats = matrix_to_quat(rot)  # [T, J, 4] (w, x, y, z)
        anim = UsdSkel.Animation.Define(stage, ANIMATION)
        anim.CreateJointsAttr(tokens)
        tr_attr, rot_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
        anim.CreateScalesAttr().Set(Vt.Vec3hArray.FromNumpy(np.ones((len(paths), 3), np.float16)))
        xyzw = np.ascontiguousarray(quat_wxyz_to_xyzw(quats), np.float32)
        for i in range(t):
            time = Usd.TimeCode(float(i))
            tr_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(local[i, :, :3, 3], np.float32)), time)
            rot_attr.Set(Vt.QuatfArray.FromNumpy(xyzw[i]), time)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    fmt = "usda" if path.suffix.lower() == ".usda" else "usdc"
    with output_group():  # the USD and its texture land together or not at all
        with atomic_path(tex_path) as tmp:
            Image.fromarray(asset.texture, "RGB").save(tmp, format="PNG", optimize=True)
        with atomic_path(path) as tmp:
            export_layer(stage.GetRootLayer(), tmp, path, fmt)
    return tex_path
