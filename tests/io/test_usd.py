"""USD writer/reader checked by reopening files with pxr directly, scipy rotations as the
quaternion oracle, UsdGeom's own extent computation, and pxr.UsdValidation."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch
from pxr import Gf, Sdf, Usd, UsdGeom, Vt
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.io.usd import write_usd
from dlacli.io.usd_read import read_usd, summarize_usd, validate_usd

SH_C0 = 0.28209479177387814
# Rotation tolerances (radians) of stored quaternions. Rounding a unit quaternion's components to
# a float type moves it by <= eps / 2 (relative, per component), so the rotation, twice the angle
# between the 4-vectors, by <= eps; float32 normalisations on write and read add <= eps32 each.
QUATH_RAD = 2 * float(np.finfo(np.float16).eps)  # quath: 2e-3 rad (0.11 deg)
QUATF_RAD = 4 * float(np.finfo(np.float32).eps)  # quatf: 5e-7 rad


def make_anim(t=4, n=6, seed=0, varying_scales=False):
    rng = np.random.default_rng(seed)
    positions = rng.normal(size=(t, n, 3)).astype(np.float32)
    quats = Rotation.random(t * n, random_state=seed).as_quat()  # (x, y, z, w)
    quats = quats[:, [3, 0, 1, 2]].reshape(t, n, 4).astype(np.float32)  # -> (w, x, y, z)
    scales = rng.uniform(0.01, 0.1, size=(t, n, 3) if varying_scales else (n, 3)).astype(np.float32)
    rgb = rng.uniform(size=(n, 3)).astype(np.float32)
    opacities = rng.uniform(size=n).astype(np.float32)
    return positions, quats, scales, rgb, opacities


def open_stage(path):
    stage = Usd.Stage.Open(str(path))
    assert stage is not None
    return stage


def rotation_angle(q_wxyz_a: np.ndarray, q_wxyz_b: np.ndarray) -> np.ndarray:
    """Angle (radians) of the rotation taking b to a, for quaternions [..., 4]; q and -q are the
    same rotation. 4 atan2(|a - b|, |a + b|) after aligning signs: well conditioned near 0, unlike
    acos(|<a, b>|), whose deviation from 1 is only second order in the angle."""
    a = q_wxyz_a / np.linalg.norm(q_wxyz_a, axis=-1, keepdims=True)
    b = q_wxyz_b / np.linalg.norm(q_wxyz_b, axis=-1, keepdims=True)
    b = b * np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return 4 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def same_rotation(q_wxyz_a: np.ndarray, q_wxyz_b: np.ndarray, atol: float) -> bool:
    """Every rotation of a within atol radians of b's."""
    return bool(np.all(rotation_angle(q_wxyz_a, q_wxyz_b) <= atol))


# --- the instancer, reopened with pxr ---------------------------------------------------------


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usd"])
def test_instancer_reopened_with_pxr(tmp_path, suffix):
    positions, quats, scales, rgb, opacities = make_anim()
    path = tmp_path / f"anim{suffix}"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=24.0)
    head = path.read_bytes()[:8]
    assert head.startswith(b"#usda") if suffix == ".usda" else head == b"PXR-USDC"

    stage = open_stage(path)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetFramesPerSecond() == 24.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 3.0)
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Avatar")
    assert stage.GetDefaultPrim().GetTypeName() == "Xform"
    assert dict(stage.GetRootLayer().customLayerData) == {"dla:format": "dla.usd/1"}

    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Avatar/Gaussians"))
    assert inst
    targets = inst.GetPrototypesRel().GetTargets()
    assert len(targets) == 1
    sphere = UsdGeom.Sphere(stage.GetPrimAtPath(targets[0]))
    assert sphere and sphere.GetRadiusAttr().Get() == 1.0
    assert str(targets[0]).startswith("/Avatar/Gaussians/")
    assert list(inst.GetProtoIndicesAttr().Get()) == [0] * 6

    pos_attr, rot_attr = inst.GetPositionsAttr(), inst.GetOrientationsAttr()
    assert pos_attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    assert rot_attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    assert rot_attr.GetTypeName() == Sdf.ValueTypeNames.QuathArray
    assert inst.GetScalesAttr().GetNumTimeSamples() == 0
    np.testing.assert_allclose(np.asarray(inst.GetScalesAttr().Get()), scales)
    for t in range(4):
        np.testing.assert_array_equal(np.asarray(pos_attr.Get(t)), positions[t])
        got = [(q.GetReal(), *q.GetImaginary()) for q in rot_attr.Get(t)]  # Gf.Quath: w, then x y z
        assert same_rotation(np.asarray(got, dtype=np.float64), quats[t].astype(np.float64), atol=QUATH_RAD)

    color = UsdGeom.Primvar(inst.GetPrim().GetAttribute("primvars:displayColor"))
    alpha = UsdGeom.Primvar(inst.GetPrim().GetAttribute("primvars:displayOpacity"))
    assert color.GetInterpolation() == UsdGeom.Tokens.vertex
    assert alpha.GetInterpolation() == UsdGeom.Tokens.vertex
    assert color.GetTypeName() == Sdf.ValueTypeNames.Color3fArray
    np.testing.assert_array_equal(np.asarray(color.Get()), rgb)
    np.testing.assert_array_equal(np.asarray(alpha.Get()), opacities)
    assert not stage.GetPrimAtPath("/Avatar/Splats")


def test_quaternion_order_with_a_non_symmetric_rotation(tmp_path):
    """(w, x, y, z) in memory vs (x, y, z, w) for FromNumpy: a swap would rotate a vector elsewhere."""
    rot = Rotation.from_rotvec(np.radians(130.0) * np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0))
    x, y, z, w = rot.as_quat()
    quats = np.array([[[w, x, y, z]]], np.float32)
    path = tmp_path / "q.usdc"
    write_usd(path, np.zeros((1, 1, 3)), quats, np.ones((1, 3)), np.ones((1, 3)), np.ones(1), fps=30)
    stage = open_stage(path)
    q = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Avatar/Gaussians")).GetOrientationsAttr().Get(0)[0]
    gf_rot = Gf.Rotation(Gf.Quatd(q.GetReal(), Gf.Vec3d(q.GetImaginary())))
    for v in np.eye(3):  # quath: a unit vector turned by <= QUATH_RAD moves by <= QUATH_RAD
        np.testing.assert_allclose(np.asarray(gf_rot.TransformDir(Gf.Vec3d(*v))), rot.apply(v), atol=QUATH_RAD)
    # and UsdGeom's own instance transforms agree (row-vector convention: p' = p M)
    xform = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Avatar/Gaussians")).ComputeInstanceTransformsAtTime(0, 0)[0]
    np.testing.assert_allclose(np.asarray(xform)[:3, :3].T, rot.as_matrix(), atol=QUATH_RAD)


@pytest.mark.parametrize("schema", ["instancer", "points", "particlefield"])
@pytest.mark.parametrize("tolerance", [0.0, 0.05])
def test_extent_matches_usdgeom(tmp_path, schema, tolerance):
    """Every geometry prim's authored extent is what UsdGeom's own extent plug-ins compute at
    each frame (in the prim's own space; parts included), except the particle field, whose 3-sigma
    ellipsoid box has no plug-in: there, the box must hold every splat centre."""
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=20, seed=4, varying_scales=True)
    path = tmp_path / "ext.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=schema, tolerance=tolerance)
    stage = open_stage(path)  # keep the stage alive while its prims are used
    prims = [
        p for p in stage.Traverse() if p.GetTypeName() in ("PointInstancer", "Points", "ParticleField3DGaussianSplat")
    ]
    assert prims
    for prim in prims:
        for t in range(3):
            ours = np.asarray(UsdGeom.Boundable(prim).GetExtentAttr().Get(t))
            if schema == "particlefield":
                centres = np.asarray(prim.GetAttribute("positions").Get(t))
                assert np.all(ours[0] <= centres.min(0)) and np.all(centres.max(0) <= ours[1])
                continue
            theirs = np.asarray(UsdGeom.Boundable.ComputeExtentFromPlugins(UsdGeom.Boundable(prim), t))
            np.testing.assert_allclose(ours, theirs, atol=1e-5)


def test_scales_time_sampled_only_when_varying(tmp_path):
    positions, quats, scales_tn, rgb, opacities = make_anim(t=3, n=5, varying_scales=True)
    const = np.broadcast_to(scales_tn[0], scales_tn.shape)
    cases = {"const_n.usda": scales_tn[0], "const_tn.usda": const, "varying.usda": scales_tn}
    for (name, scales), (schema, prim) in itertools.product(
        cases.items(), [("instancer", "/Avatar/Gaussians"), ("particlefield", "/Avatar/Splats")]
    ):
        out = tmp_path / f"{schema}_{name}"  # a new name: pxr keeps an open layer cached
        write_usd(out, positions, quats, scales, rgb, opacities, fps=30, schema=schema)
        stage = open_stage(out)
        attr = stage.GetPrimAtPath(prim).GetAttribute("scales")
        if name == "varying.usda":
            assert attr.GetTimeSamples() == [0.0, 1.0, 2.0]
            for t in range(3):
                np.testing.assert_array_equal(np.asarray(attr.Get(t)), scales_tn[t])
        else:
            assert attr.GetNumTimeSamples() == 0
            np.testing.assert_array_equal(np.asarray(attr.Get()), scales_tn[0])


def test_start_frame_and_torch_inputs(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=2, n=3)
    path = tmp_path / "s.usda"
    write_usd(
        path, *(torch.from_numpy(a) for a in (positions, quats, scales, rgb, opacities)), fps=12.5, start_frame=10
    )
    stage = open_stage(path)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (10.0, 11.0)
    assert stage.GetTimeCodesPerSecond() == 12.5
    pos = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Avatar/Gaussians")).GetPositionsAttr()
    assert pos.GetTimeSamples() == [10.0, 11.0]
    np.testing.assert_array_equal(np.asarray(pos.Get(11)), positions[1])


# --- the particle field -----------------------------------------------------------------------


def test_particle_field_values(tmp_path):
    from pxr import UsdVol

    positions, quats, scales, rgb, opacities = make_anim(t=2, n=4, seed=2)
    sh = np.random.default_rng(3).normal(size=(4, 16, 3)).astype(np.float32)
    path = tmp_path / "pf.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, sh=sh, schema="particlefield")
    stage = open_stage(path)
    assert not stage.GetPrimAtPath("/Avatar/Gaussians")
    splats = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/Avatar/Splats"))
    assert splats
    assert splats.GetPositionsAttr().GetTimeSamples() == [0.0, 1.0]
    for t in range(2):
        np.testing.assert_array_equal(np.asarray(splats.GetPositionsAttr().Get(t)), positions[t])
        got = np.asarray([(q.GetReal(), *q.GetImaginary()) for q in splats.GetOrientationsAttr().Get(t)])
        assert same_rotation(got, quats[t].astype(np.float64), atol=QUATF_RAD)
    np.testing.assert_array_equal(np.asarray(splats.GetScalesAttr().Get()), scales)
    np.testing.assert_array_equal(np.asarray(splats.GetOpacitiesAttr().Get()), opacities)
    assert splats.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 3
    coeffs = np.asarray(splats.GetRadianceSphericalHarmonicsCoefficientsAttr().Get())
    assert coeffs.shape == (4 * 16, 3)
    for i in range(4):  # particle-major: particle i's 16 coefficients are contiguous
        np.testing.assert_array_equal(coeffs[16 * i : 16 * (i + 1)], sh[i])


def test_particle_field_dc_from_rgb(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=1, n=5)
    path = tmp_path / "dc.usda"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="particlefield")
    stage = open_stage(path)
    prim = stage.GetPrimAtPath("/Avatar/Splats")
    assert prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get() == 0
    coeffs = np.asarray(prim.GetAttribute("radiance:sphericalHarmonicsCoefficients").Get())
    np.testing.assert_allclose(0.5 + SH_C0 * coeffs, rgb, atol=1e-6)


# --- validation -------------------------------------------------------------------------------


@pytest.mark.parametrize("schema", ["points", "instancer", "particlefield", "both"])
@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
@pytest.mark.parametrize("tolerance", [0.0, 0.01])
def test_validators_find_no_errors(tmp_path, schema, suffix, tolerance):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=8, varying_scales=True)
    path = tmp_path / f"v{suffix}"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=schema, tolerance=tolerance)
    assert validate_usd(path) == []


def test_validators_do_report_errors(tmp_path):
    path = tmp_path / "bare.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Xform.Define(stage, "/Thing")
    stage.Save()
    errors = validate_usd(path)
    assert any("upAxis" in e for e in errors) and any("defaultPrim" in e for e in errors)


# --- read_usd ---------------------------------------------------------------------------------


@pytest.mark.parametrize("schema", ["instancer", "particlefield", "both"])
def test_read_round_trip(tmp_path, schema):
    """Exact files (tolerance 0) give back what was written; `both` reads its geometry from the
    particle field and its colours from the points."""
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=7, seed=9, varying_scales=True)
    path = tmp_path / "rt.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=25, schema=schema, start_frame=5)
    anim = read_usd(path)
    assert anim.schema == schema and anim.fps == 25.0
    assert (anim.start_time_code, anim.end_time_code) == (5.0, 7.0)
    np.testing.assert_array_equal(anim.time_codes, [5.0, 6.0, 7.0])
    assert anim.num_frames == 3
    np.testing.assert_array_equal(anim.positions, positions)
    np.testing.assert_array_equal(anim.scales, scales)
    np.testing.assert_array_equal(anim.opacities, opacities)
    atol = QUATH_RAD if schema == "instancer" else QUATF_RAD
    assert same_rotation(anim.quats.astype(np.float64), quats.astype(np.float64), atol=atol)
    if schema == "particlefield":  # colour comes back from the DC coefficient
        np.testing.assert_allclose(anim.rgb, rgb, atol=1e-6)
    else:
        np.testing.assert_array_equal(anim.rgb, rgb)


def test_read_bad_inputs(tmp_path):
    with pytest.raises(DlaInputError, match="no such file"):
        read_usd(tmp_path / "missing.usdc")
    garbage = tmp_path / "garbage.usdc"
    garbage.write_bytes(b"PXR-USDC" + bytes(range(256)) * 4)
    with pytest.raises(DlaInputError) as err:
        read_usd(garbage)
    assert str(garbage) in str(err.value) and "\n" not in str(err.value)
    text = tmp_path / "text.usda"
    text.write_text("this is not usd at all {")
    with pytest.raises(DlaInputError) as err:
        read_usd(text)
    assert str(text) in str(err.value) and "\n" not in str(err.value)

    other = tmp_path / "other.usda"
    stage = Usd.Stage.CreateNew(str(other))
    UsdGeom.Xform.Define(stage, "/Avatar")
    stage.GetRootLayer().customLayerData = {"dla:format": "dla.usd/1"}
    stage.Save()
    with pytest.raises(DlaInputError, match="/Avatar/Gaussians"):
        read_usd(other)
    stage.GetRootLayer().customLayerData = {"dla:format": "dla.usd/9"}
    stage.Save()
    with pytest.raises(DlaInputError, match="dla.usd/9"):
        read_usd(other)


def test_write_bad_arguments(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=2, n=3)
    with pytest.raises(DlaInputError, match="--schema"):
        write_usd(tmp_path / "a.usdc", positions, quats, scales, rgb, opacities, 30, schema="voxels")
    with pytest.raises(DlaInputError, match=r"quats.*\[2, 3, 4\].*\[2, 3, 3\]"):
        write_usd(tmp_path / "a.usdc", positions, quats[..., :3], scales, rgb, opacities, 30)
    with pytest.raises(DlaInputError, match="rgb"):
        write_usd(tmp_path / "a.usdc", positions, quats, scales, rgb[:2], opacities, 30)
    with pytest.raises(DlaInputError, match="fps"):
        write_usd(tmp_path / "a.usdc", positions, quats, scales, rgb, opacities, 0)
    with pytest.raises(DlaInputError, match="suffix"):
        write_usd(tmp_path / "a.abc", positions, quats, scales, rgb, opacities, 30)
    bad = positions.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(DlaInputError, match="positions"):
        write_usd(tmp_path / "a.usdc", bad, quats, scales, rgb, opacities, 30)
    assert list(tmp_path.iterdir()) == []


# --- the golden file (values documented in formats/usd.md) ------------------------------------


def test_golden_animation(formats_dir):
    path = formats_dir / "examples" / "animation.usda"
    anim = read_usd(path)
    assert anim.schema == "both" and anim.fps == 30.0 and anim.num_frames == 3
    stage = open_stage(path)
    widths = np.asarray(UsdGeom.Points(stage.GetPrimAtPath("/Avatar/Points")).GetWidthsAttr().Get())
    np.testing.assert_allclose(widths, 2 * np.cbrt(0.01 * 0.02 * 0.03), rtol=1e-6)  # float32 cube root
    for t in range(3):
        np.testing.assert_allclose(anim.positions[t], [[0.1 * i, 0, 0.05 * t] for i in range(3)], atol=1e-7)
        half = math.radians(45.0 * t) / 2
        expected = np.tile([math.cos(half), 0, 0, math.sin(half)], (3, 1))
        assert same_rotation(anim.quats[t].astype(np.float64), expected, atol=QUATF_RAD)
    np.testing.assert_allclose(anim.scales, np.tile([0.01, 0.02, 0.03], (3, 3, 1)))
    np.testing.assert_array_equal(anim.rgb, np.eye(3))
    np.testing.assert_array_equal(anim.opacities, [0.25, 0.5, 1.0])
    assert validate_usd(path) == []


def test_summarize_golden(formats_dir):
    from dlacli.io.inspect import summarize

    summary = summarize(formats_dir / "examples" / "animation.usda")
    json.dumps(summary)
    assert summary["kind"] == "usd" and summary["format"] == "dla.usd/1"
    assert summary["encoding"] == "usda" and summary["up_axis"] == "Z"
    assert summary["meters_per_unit"] == 1.0 and summary["fps"] == 30.0
    assert summary["frames"] == 3 and summary["instances"] == 3 and summary["schema"] == "both"
    assert "/Avatar/Points (Points)" in summary["prims"]
    assert "/Avatar/Splats (ParticleField3DGaussianSplat)" in summary["prims"]
    assert "/Avatar/Points.points" in summary["time_sampled"]
    assert "/Avatar/Points.widths" not in summary["time_sampled"]
    assert "/Avatar/Splats.scales" not in summary["time_sampled"]


def test_summarize_binary(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=5, n=2)
    path = tmp_path / "b.usd"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=60)
    summary = summarize_usd(path)
    assert summary["encoding"] == "usdc" and summary["frames"] == 5 and summary["instances"] == 2
    assert summary["schema"] == "instancer"


def test_read_returns_sh_from_the_particle_field(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=2, n=5, seed=6)
    sh = np.random.default_rng(7).normal(size=(5, 9, 3)).astype(np.float32)
    path = tmp_path / "sh.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, sh=sh, schema="both")
    anim = read_usd(path)
    np.testing.assert_array_equal(anim.sh, sh)
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="instancer")
    assert read_usd(path).sh is None


def test_particle_field_needs_the_schema(tmp_path, monkeypatch):
    from pxr import UsdVol

    monkeypatch.delattr(UsdVol, "ParticleField3DGaussianSplat")
    positions, quats, scales, rgb, opacities = make_anim(t=1, n=2)
    with pytest.raises(DlaInputError, match="--schema.*usd-core >= 26"):
        write_usd(tmp_path / "x.usdc", positions, quats, scales, rgb, opacities, 30, schema="both")
    write_usd(tmp_path / "ok.usdc", positions, quats, scales, rgb, opacities, 30)  # instancer still works
    assert [p.name for p in tmp_path.iterdir()] == ["ok.usdc"]


# --- the points schema ------------------------------------------------------------------------


def test_points_reopened_with_pxr(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=7, seed=11, varying_scales=True)
    path = tmp_path / "p.usda"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=24, schema="points")
    stage = open_stage(path)
    assert not stage.GetPrimAtPath("/Avatar/Gaussians") and not stage.GetPrimAtPath("/Avatar/Splats")
    points = UsdGeom.Points(stage.GetPrimAtPath("/Avatar/Points"))
    assert points and points.GetPurposeAttr().Get() == UsdGeom.Tokens.default_
    assert points.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    assert points.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
    for t in range(3):
        np.testing.assert_array_equal(np.asarray(points.GetPointsAttr().Get(t)), positions[t])
        # diameter 2 (s0 s1 s2)^(1/3); float32 log/exp/mean against a float64 cube root
        want = 2 * np.cbrt(np.prod(scales[t].astype(np.float64), axis=-1))
        np.testing.assert_allclose(np.asarray(points.GetWidthsAttr().Get(t)), want, rtol=1e-6)
    color = UsdGeom.PrimvarsAPI(points).GetPrimvar("displayColor")
    alpha = UsdGeom.PrimvarsAPI(points).GetPrimvar("displayOpacity")
    assert color.GetInterpolation() == alpha.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_array_equal(np.asarray(color.Get()), rgb)
    np.testing.assert_array_equal(np.asarray(alpha.Get()), opacities)
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(points.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == Sdf.Path("/Avatar/Looks/GaussianColor")
    shader = material.ComputeSurfaceSource()[0]
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    source = shader.GetInput("diffuseColor").GetConnectedSources()[0][0].source
    assert UsdShade.Shader(source.GetPrim()).GetInput("varname").Get() == "displayColor"


def test_read_points_schema(tmp_path):
    """Points have no orientations: identity rotations and isotropic scales width / 2."""
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=9, seed=12, varying_scales=True)
    path = tmp_path / "p.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="points", start_frame=2)
    anim = read_usd(path)
    assert anim.schema == "points" and anim.num_frames == 3
    np.testing.assert_array_equal(anim.time_codes, [2.0, 3.0, 4.0])
    np.testing.assert_array_equal(anim.positions, positions)
    np.testing.assert_array_equal(anim.quats, np.broadcast_to([1, 0, 0, 0], (3, 9, 4)))
    radius = np.cbrt(np.prod(scales.astype(np.float64), axis=-1))  # [T, N]
    np.testing.assert_allclose(anim.scales, np.repeat(radius[..., None], 3, -1), rtol=1e-6)
    np.testing.assert_array_equal(anim.rgb, rgb)
    np.testing.assert_array_equal(anim.opacities, opacities)


def test_both_is_points_and_splats_with_no_purpose(tmp_path):
    """`both` must show something in a default Blender import (which skips "proxy" prims)."""
    positions, quats, scales, rgb, opacities = make_anim(t=2, n=4)
    path = tmp_path / "b.usda"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="both")
    stage = open_stage(path)
    assert stage.GetPrimAtPath("/Avatar/Points").GetTypeName() == "Points"
    assert stage.GetPrimAtPath("/Avatar/Splats").GetTypeName() == "ParticleField3DGaussianSplat"
    assert not stage.GetPrimAtPath("/Avatar/Gaussians")
    for prim in stage.Traverse():
        assert not prim.GetAttribute("purpose").HasAuthoredValue(), prim.GetPath()


def _legacy_both(tmp_path, positions, quats, scales, rgb, opacities):
    """A file as dla wrote `--schema both` before the points schema: the instancer (purpose
    proxy) and the splats (purpose render, proxyPrim -> the instancer) in one layer."""
    write_usd(tmp_path / "inst.usda", positions, quats, scales, rgb, opacities, fps=30, schema="instancer")
    write_usd(tmp_path / "pf.usda", positions, quats, scales, rgb, opacities, fps=30, schema="particlefield")
    layer, splats = Sdf.Layer.FindOrOpen(str(tmp_path / "inst.usda")), Sdf.Layer.FindOrOpen(str(tmp_path / "pf.usda"))
    assert Sdf.CopySpec(splats, "/Avatar/Splats", layer, "/Avatar/Splats")
    stage = Usd.Stage.Open(layer)
    UsdGeom.Imageable(stage.GetPrimAtPath("/Avatar/Gaussians")).CreatePurposeAttr(UsdGeom.Tokens.proxy)
    UsdGeom.Imageable(stage.GetPrimAtPath("/Avatar/Splats")).CreatePurposeAttr(UsdGeom.Tokens.render)
    stage.GetPrimAtPath("/Avatar/Splats").CreateRelationship("proxyPrim").SetTargets([Sdf.Path("/Avatar/Gaussians")])
    out = tmp_path / "legacy.usdc"
    layer.Export(str(out))
    return out


def test_files_of_the_previous_version_are_read(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=5, seed=13)
    anim = read_usd(_legacy_both(tmp_path, positions, quats, scales, rgb, opacities))
    assert anim.schema == "instancer+particlefield" and anim.num_frames == 3
    np.testing.assert_array_equal(anim.positions, positions)
    assert same_rotation(anim.quats.astype(np.float64), quats.astype(np.float64), atol=QUATF_RAD)
    np.testing.assert_array_equal(anim.scales, np.broadcast_to(scales, (3, 5, 3)))
    np.testing.assert_array_equal(anim.rgb, rgb)
    np.testing.assert_array_equal(anim.opacities, opacities)


# --- compact time samples ---------------------------------------------------------------------


def test_keep_frames_keeps_every_corner_of_a_piecewise_linear_path():
    """Linear interpolation reproduces a piecewise-linear path exactly between its corners and
    nowhere across one, so the kept frames are the corners (and both ends), and nothing else."""
    from dlacli.io.usd_compact import keep_frames, lerp_check

    corners = [0, 5, 6, 19, 33, 34, 47]
    rng = np.random.default_rng(3)
    values = rng.normal(size=(len(corners), 4, 3))
    path = np.stack(
        [
            np.array([np.interp(t, corners, values[:, i, d]) for i in range(4) for d in range(3)]).reshape(4, 3)
            for t in range(48)
        ]
    ).astype(np.float32)
    kept = keep_frames(lerp_check(path, path, 1e-5), 48)  # 1e-5 m: far above float32 rounding of O(1) values
    assert kept.tolist() == corners


def analytic_motion(t=40, per_group=2048, jump=23):
    """Three groups of Gaussians [T, 3 * per_group]: (a) a ring spinning about +Z at a smoothly
    varying rate (rigid), its Gaussians turning with it; (b) a sheet swaying on sine waves of
    per-Gaussian phase, its scales growing smoothly, that stretches by 1.3 at frame `jump`
    (abrupt and not rigid: interpolation across it would be 2 cm or more off); (c) still."""
    rng = np.random.default_rng(8)
    tt = np.arange(t, dtype=np.float64)
    angle = 0.6 * np.sin(tt / 12)  # [T]
    ring0 = np.stack(
        [np.cos(a := rng.uniform(0, 2 * np.pi, per_group)), np.sin(a), rng.uniform(-0.1, 0.1, per_group)], -1
    )
    ring = np.stack([Rotation.from_rotvec([0, 0, x]).apply(ring0) for x in angle]) + [2, 0, 0]
    sheet0 = np.stack([rng.uniform(-0.5, 0.5, per_group), np.zeros(per_group), rng.uniform(0, 1, per_group)], -1)
    phase = rng.uniform(0, 2 * np.pi, per_group)
    sway = 0.05 * np.sin(tt[:, None] / 5 + phase)  # [T, n]
    sheet = sheet0 + np.stack([np.zeros_like(sway), sway, np.zeros_like(sway)], -1)
    sheet = np.where(tt[:, None, None] >= jump, sheet * 1.3, sheet) + [-2, 0, 0]
    still = np.broadcast_to(rng.normal(size=(per_group, 3)) + [0, 3, 0], (t, per_group, 3))
    positions = np.concatenate([ring, sheet, still], axis=1).astype(np.float32)
    n = 3 * per_group
    base = Rotation.random(n, random_state=9)
    quats = np.empty((t, n, 4), np.float32)
    for k in range(t):
        spin = Rotation.from_rotvec(
            np.concatenate([np.tile([0, 0, angle[k]], (per_group, 1)), np.tile([0.01 * k, 0, 0], (2 * per_group, 1))])
        )
        quats[k] = (spin * base).as_quat()[:, [3, 0, 1, 2]]
    scales = np.broadcast_to(rng.uniform(0.002, 0.01, size=(n, 3)), (t, n, 3)).copy()
    scales[:, per_group : 2 * per_group] *= (1 + 0.3 * np.sin(tt / 20))[:, None, None]
    return positions, quats, scales.astype(np.float32), jump


def composed(stage, kind: str, n: int, time) -> dict[str, np.ndarray]:
    """World values of every Gaussian at `time`, straight from pxr: each part's values (pxr
    interpolates), times its prim's local-to-world matrix, put back by `dla:indices`."""
    path = {"instancer": "/Avatar/Gaussians", "points": "/Avatar/Points", "particlefield": "/Avatar/Splats"}[kind]
    group = stage.GetPrimAtPath(path)
    parts = list(group.GetChildren()) if group.GetTypeName() == "Xform" else [group]
    parts = [p for p in parts if p.GetTypeName() != "Scope"]
    out = {
        "positions": np.zeros((n, 3)),
        "quats": np.zeros((n, 4)),
        "sizes": np.zeros((n, 3 if kind != "points" else 1)),
    }
    for prim in parts:
        idx = np.asarray(prim.GetAttribute("dla:indices").Get()) if prim.GetAttribute("dla:indices") else np.arange(n)
        m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time))  # row vectors: p M
        local = np.asarray(prim.GetAttribute("points" if kind == "points" else "positions").Get(time), np.float64)
        out["positions"][idx] = local @ m[:3, :3] + m[3, :3]
        if kind == "points":
            out["sizes"][idx] = np.asarray(prim.GetAttribute("widths").Get(time))[:, None]
            continue
        q = np.asarray(prim.GetAttribute("orientations").Get(time), np.float64)  # (x, y, z, w)
        world = Rotation.from_matrix(m[:3, :3].T) * Rotation.from_quat(q)
        out["quats"][idx] = world.as_quat()[:, [3, 0, 1, 2]]
        out["sizes"][idx] = np.asarray(prim.GetAttribute("scales").Get(time))
    return out


@pytest.mark.parametrize("kind", ["instancer", "points", "particlefield"])
def test_compact_samples_stay_within_the_tolerance(tmp_path, kind):
    """At every time code, what pxr returns from the compact file (interpolated where samples
    were left out) is within the tolerance of the analytic motion; the abrupt stretch is kept;
    and the smooth and still groups really are stored with fewer samples than frames."""
    from dlacli.io.usd_compact import SIZE_REL

    positions, quats, scales, jump = analytic_motion()
    t, n = positions.shape[:2]
    rgb, opacities = np.full((n, 3), 0.5, np.float32), np.ones(n, np.float32)
    tol = 0.002
    path = tmp_path / "c.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=kind, tolerance=tol)
    stage = open_stage(path)
    assert stage.GetInterpolationType() == Usd.InterpolationTypeLinear  # what the compaction assumes
    widths = 2 * np.cbrt(np.prod(scales.astype(np.float64), axis=-1))[..., None]  # [T, N, 1]
    sigma_max = scales.max(axis=(0, 2)).astype(np.float64)  # [N]
    for k in range(t):
        got = composed(stage, kind, n, Usd.TimeCode(k))
        # positions: tol, plus float32 rounding of coordinates <= 4 m through ~8 operations
        assert np.linalg.norm(got["positions"] - positions[k], axis=-1).max() <= tol + 8 * 4 * 1.2e-7, k
        want = widths[k] if kind == "points" else scales[k]
        # sizes: SIZE_REL relative, plus float32 rounding
        assert np.all(np.abs(got["sizes"] - want) <= (SIZE_REL + 1e-6) * want), k
        if kind != "points":
            # the 1-sigma ellipsoid's surface moves <= tol; plus half-precision rounding of the
            # stored samples and of pxr's slerp result (instancer), float32 (particle field)
            slack = 2 * QUATH_RAD if kind == "instancer" else 1e-5
            angle = rotation_angle(got["quats"], quats[k].astype(np.float64))
            assert np.all(angle <= tol / sigma_max + slack), k
    group = stage.GetPrimAtPath(
        {"instancer": "/Avatar/Gaussians", "points": "/Avatar/Points", "particlefield": "/Avatar/Splats"}[kind]
    )
    parts = list(group.GetChildren()) if group.GetTypeName() == "Xform" else [group]
    samples = [p.GetAttribute("points" if kind == "points" else "positions").GetTimeSamples() for p in parts]
    for prim, times in zip(parts, samples):
        idx = np.asarray(prim.GetAttribute("dla:indices").Get()) if prim.GetAttribute("dla:indices") else np.arange(n)
        if np.any((idx >= 2048) & (idx < 4096)):  # holds sheet Gaussians: the stretch is kept
            assert {jump - 1.0, jump}.issubset(times), (prim.GetPath(), times)
    if kind != "particlefield":  # parts: the still and the rigid ring need no per-frame samples
        assert len(parts) >= 3
        assert sum(len(s) for s in samples) < 0.6 * t * len(parts), samples
    else:  # one world-space prim: the sway and the spin need (nearly) every frame
        assert len(parts) == 1


def test_compact_keeps_per_frame_colours(tmp_path):
    positions, quats, scales, _, opacities = make_anim(t=4, n=20, seed=14)
    rgb = np.random.default_rng(15).uniform(size=(4, 20, 3)).astype(np.float32)
    path = tmp_path / "c.usda"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="points", tolerance=0.001)
    anim = read_usd(path)
    np.testing.assert_array_equal(anim.rgb, rgb)
    np.testing.assert_array_equal(anim.opacities, opacities)
    # random positions cannot be interpolated within 1 mm: every frame is kept, values exact
    # up to float32 rounding of the part's rigid transform (coordinates ~ 3, a few operations)
    np.testing.assert_allclose(anim.positions, positions, atol=8 * 3 * 1.2e-7)


@pytest.mark.parametrize("tolerance", [-0.001, float("nan"), 2.0])
def test_bad_tolerance(tmp_path, tolerance):
    positions, quats, scales, rgb, opacities = make_anim(t=2, n=3)
    with pytest.raises(DlaInputError, match="tolerance"):
        write_usd(tmp_path / "a.usdc", positions, quats, scales, rgb, opacities, 30, tolerance=tolerance)
    assert list(tmp_path.iterdir()) == []


def test_rigid_reassignment_scores_like_the_brute_force_sum():
    """The expanded, matrix-product form of the rigid fit cost picks the same part as summing
    |R_f^T (p_f - c_f) - (p_0 - c_0)|^2 directly (float64 oracle), and split_parts separates
    limbs that swing alike in space but out of phase."""
    from dlacli.io.usd_compact import _best_rigid_part, _part_motions, split_parts

    rng = np.random.default_rng(1)
    frames = rng.normal(size=(5, 300, 3)).astype(np.float32)
    motions = _part_motions(frames, rng.integers(0, 4, 300), 4)
    costs = []
    for r, c, c0 in motions:
        local = np.matmul(frames.astype(np.float64) - c[:, None], r.astype(np.float64))
        costs.append(((local - (frames[0] - c0)) ** 2).sum(axis=(0, 2)))
    np.testing.assert_array_equal(_best_rigid_part(frames, motions), np.argmin(np.stack(costs, 1), 1))

    t, n = 24, 4096  # two overlapping blobs, each swinging rigidly about +X, a quarter turn apart
    limb = rng.integers(0, 2, n)
    base = rng.normal(0, 0.2, (n, 3))
    angle = 0.5 * np.sin(np.arange(t)[:, None] / 4 + np.pi / 2 * limb)  # [T, N]
    c, s = np.cos(angle), np.sin(angle)
    positions = np.stack(
        [np.broadcast_to(base[:, 0], c.shape), c * base[:, 1] - s * base[:, 2], s * base[:, 1] + c * base[:, 2]], -1
    )
    labels = split_parts(positions.astype(np.float32), 2)
    assert abs(np.corrcoef(labels, limb)[0, 1]) == pytest.approx(1.0)


def test_parts_with_bad_indices_are_one_line_errors(tmp_path):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=4200, seed=16)  # 2 parts
    path = tmp_path / "c.usda"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema="points", tolerance=0.001)
    stage = open_stage(path)
    parts = stage.GetPrimAtPath("/Avatar/Points").GetChildren()
    assert len(parts) == 2
    attr = parts[0].GetAttribute("dla:indices")
    bad = np.asarray(attr.Get()).copy()
    bad[0] = bad[1]
    attr.Set(Vt.IntArray.FromNumpy(bad))
    stage.GetRootLayer().Export(str(tmp_path / "dup.usda"))
    with pytest.raises(DlaInputError, match="permutation"):
        read_usd(tmp_path / "dup.usda")
    parts[0].RemoveProperty("dla:indices")
    stage.GetRootLayer().Export(str(tmp_path / "none.usda"))
    with pytest.raises(DlaInputError, match="dla:indices"):
        read_usd(tmp_path / "none.usda")
