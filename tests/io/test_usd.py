"""USD writer/reader checked by reopening files with pxr directly, scipy rotations as the
quaternion oracle, UsdGeom's own extent computation, and pxr.UsdValidation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from pxr import Gf, Sdf, Usd, UsdGeom, Vt
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.io.usd import read_usd, summarize_usd, validate_usd, write_usd

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


@pytest.mark.parametrize("schema", ["instancer", "both"])
def test_extent_matches_usdgeom(tmp_path, schema):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=20, seed=4, varying_scales=True)
    path = tmp_path / "ext.usdc"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=schema)
    stage = open_stage(path)  # keep the stage alive while its prims are used
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Avatar/Gaussians"))
    for t in range(3):
        ours = np.asarray(inst.GetExtentAttr().Get(t))
        theirs = np.asarray(inst.ComputeExtentAtTime(t, t))
        np.testing.assert_allclose(ours, theirs, atol=1e-5)


def test_scales_time_sampled_only_when_varying(tmp_path):
    positions, quats, scales_tn, rgb, opacities = make_anim(t=3, n=5, varying_scales=True)
    const = np.broadcast_to(scales_tn[0], scales_tn.shape)
    cases = {"const_n.usda": scales_tn[0], "const_tn.usda": const, "varying.usda": scales_tn}
    for name, scales in cases.items():
        write_usd(tmp_path / name, positions, quats, scales, rgb, opacities, fps=30, schema="both")
        stage = open_stage(tmp_path / name)
        for prim in ("/Avatar/Gaussians", "/Avatar/Splats"):
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


@pytest.mark.parametrize("schema", ["instancer", "particlefield", "both"])
@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_validators_find_no_errors(tmp_path, schema, suffix):
    positions, quats, scales, rgb, opacities = make_anim(t=3, n=8, varying_scales=True)
    path = tmp_path / f"v{suffix}"
    write_usd(path, positions, quats, scales, rgb, opacities, fps=30, schema=schema)
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
    assert "/Avatar/Gaussians (PointInstancer)" in summary["prims"]
    assert "/Avatar/Splats (ParticleField3DGaussianSplat)" in summary["prims"]
    assert "/Avatar/Gaussians.positions" in summary["time_sampled"]
    assert "/Avatar/Gaussians.scales" not in summary["time_sampled"]


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
