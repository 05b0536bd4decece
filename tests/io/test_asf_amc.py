"""ASF/AMC parser, checked against the CMU converter's BVH of the same clip, and bad files."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.io.asf_amc import find_asf, read_amc, read_asf, summarize_amc, summarize_asf
from dlacli.io.bvh import read_bvh
from dlacli.io.inspect import summarize
from dlacli.kinematics import forward_kinematics

# ASF bone -> joint name in the MotionBuilder-style BVH that CMU's converter made of the same clip
ASF_TO_BVH = {
    "root": "Hips",
    "lhipjoint": "LHipJoint",
    "lfemur": "LeftUpLeg",
    "ltibia": "LeftLeg",
    "lfoot": "LeftFoot",
    "ltoes": "LeftToeBase",
    "rhipjoint": "RHipJoint",
    "rfemur": "RightUpLeg",
    "rtibia": "RightLeg",
    "rfoot": "RightFoot",
    "rtoes": "RightToeBase",
    "lowerback": "LowerBack",
    "upperback": "Spine",
    "thorax": "Spine1",
    "lowerneck": "Neck",
    "upperneck": "Neck1",
    "head": "Head",
    "lclavicle": "LeftShoulder",
    "lhumerus": "LeftArm",
    "lradius": "LeftForeArm",
    "lwrist": "LeftHand",
    "lhand": "LeftFingerBase",
    "lfingers": "LFingers",
    "lthumb": "LThumb",
    "rclavicle": "RightShoulder",
    "rhumerus": "RightArm",
    "rradius": "RightForeArm",
    "rwrist": "RightHand",
    "rhand": "RightFingerBase",
    "rfingers": "RFingers",
    "rthumb": "RThumb",
}
LOWER_BODY = [
    "root",
    "lhipjoint",
    "lfemur",
    "ltibia",
    "lfoot",
    "ltoes",
    "rfemur",
    "rtibia",
    "rfoot",
    "lowerback",
    "upperback",
    "thorax",
]


@pytest.fixture(scope="module")
def clip(third_party_data):
    d = third_party_data / "motion"
    return read_amc(d / "cmu_01_01.amc", d / "cmu_01.asf"), read_bvh(d / "cmu_01_01.bvh")


def test_asf_units_and_bones(third_party_data):
    asf = read_asf(third_party_data / "motion" / "cmu_01.asf")
    assert asf.length_unit == 0.45 and asf.angle_unit == "deg"
    assert asf.metres_per_unit == pytest.approx(0.0254 / 0.45)
    assert len(asf.bones) == 30
    femur = asf.bones["lfemur"]
    assert femur.length * asf.metres_per_unit == pytest.approx(0.404, abs=0.001)  # a thigh, in metres
    assert femur.dofs == ["rx", "ry", "rz"] and femur.axis_order == "xyz"
    assert asf.children["root"] == ["lhipjoint", "rhipjoint", "lowerback"]


def test_world_rotations_match_the_cmu_converters_bvh(clip, third_party_data, frames_in):
    """BVH frame 0 is the converter's added T-pose, so AMC frame k is BVH frame k + 1."""
    amc, bvh = clip
    n = frames_in(third_party_data / "motion" / "cmu_01_01.amc")
    assert amc.num_frames == n and bvh.num_frames == n + 1 and amc.fps == 120.0
    frames = np.arange(0, amc.num_frames, 25)
    g_amc, p_amc = forward_kinematics(amc, frames)
    g_bvh, p_bvh = forward_kinematics(bvh, frames + 1)
    for bone, joint in ASF_TO_BVH.items():
        i, j = amc.names.index(bone), bvh.names.index(joint)
        # the files' rounding, float64 adds nothing: <= 30 angles along the longest chain
        # (10 joints x 3), each rounded in both files by 5e-5 deg = 8.7e-7 rad (4 decimals;
        # AMC angles >= 100 deg have 6 significant digits: 8.7e-6 rad) -> 5e-5 .. 2.9e-4
        np.testing.assert_allclose(g_amc[:, i], g_bvh[:, j], atol=2e-4, err_msg=bone)
    # positions in metres: equal below the thorax (the converter drops the thorax length above it)
    for bone in LOWER_BODY:
        i, j = amc.names.index(bone), bvh.names.index(ASF_TO_BVH[bone])
        # <= 6 joints from the root: 18 angles x 1.7e-6 rad x <= 1 m, plus the roots' rounding
        # (2 x 5e-5 units = 5.6e-6 m) and the offsets' (6 significant digits)
        np.testing.assert_allclose(p_amc[:, i], p_bvh[:, j] * bvh.metres_per_unit, atol=1e-4, err_msg=bone)


def test_find_asf_rules(tmp_path, third_party_data):
    src = third_party_data / "motion"
    shutil.copy(src / "cmu_01_01.amc", tmp_path / "01_01.amc")
    with pytest.raises(DlaInputError, match="no ASF skeleton found") as err:
        find_asf(tmp_path / "01_01.amc")
    assert str(err.value).startswith(str(tmp_path / "01_01.amc"))
    shutil.copy(src / "cmu_01.asf", tmp_path / "other.asf")
    assert find_asf(tmp_path / "01_01.amc") == tmp_path / "other.asf"  # the lone ASF
    shutil.copy(src / "cmu_01.asf", tmp_path / "01.asf")
    assert find_asf(tmp_path / "01_01.amc") == tmp_path / "01.asf"  # stem with "_01" removed
    shutil.copy(src / "cmu_01.asf", tmp_path / "01_01.asf")
    assert find_asf(tmp_path / "01_01.amc") == tmp_path / "01_01.asf"  # same stem wins


AMC_HEAD = ":FULLY-SPECIFIED\n:DEGREES\n"


def _amc_frame(third_party_data, frame: int = 1) -> str:
    text = (third_party_data / "motion" / "cmu_01_01.amc").read_text().splitlines()
    start = text.index(str(frame))
    end = text.index(str(frame + 1))
    return "\n".join(text[start:end]) + "\n"


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda f: f.replace("lfemur", "lfemurX"), "bone 'lfemurX' is not in the skeleton"),
        (lambda f: f.replace("\nltibia ", "\nltibia 1 "), "bone 'ltibia' has 2 values"),
        (lambda f: f.replace("\nltibia ", "\nltibia 1\nltibia "), "bone 'ltibia' appears twice"),
        (lambda f: "\n".join(line for line in f.splitlines() if not line.startswith("rfoot")), "lacks bone 'rfoot'"),
        (lambda f: "", "no frames"),
    ],
)
def test_bad_amc(tmp_path, third_party_data, edit, problem):
    path = tmp_path / "bad.amc"
    path.write_text(AMC_HEAD + edit(_amc_frame(third_party_data)))
    with pytest.raises(DlaInputError, match=problem) as err:
        read_amc(path, third_party_data / "motion" / "cmu_01.asf")
    assert str(err.value).startswith(str(path))


def test_nan_in_amc(tmp_path, third_party_data):
    lines = _amc_frame(third_party_data).splitlines()
    lines = [("ltibia nan" if line.startswith("ltibia ") else line) for line in lines]
    path = tmp_path / "nan.amc"
    path.write_text(AMC_HEAD + "\n".join(lines))
    with pytest.raises(DlaInputError, match="non-finite"):
        read_amc(path, third_party_data / "motion" / "cmu_01.asf")


def test_bad_asf(tmp_path, third_party_data):
    text = (third_party_data / "motion" / "cmu_01.asf").read_text()
    cases = [
        (text[: text.index(":hierarchy")], "no :hierarchy"),
        (text.replace("lhumerus lradius", "lhumerus lradiusX"), "unknown bone 'lradiusX'"),
        (text.replace("axis 0 0 20  XYZ", "axis 0 0 20  XXZ", 1), "unsupported rotation order"),
        (text.replace("length 0.45", "length -1"), "must be > 0"),
    ]
    for content, problem in cases:
        path = tmp_path / "bad.asf"
        path.write_text(content)
        with pytest.raises(DlaInputError, match=problem):
            read_asf(path)


def test_summaries(third_party_data, frames_in):
    d = third_party_data / "motion"
    s = summarize_asf(d / "cmu_01.asf")
    assert s["kind"] == "asf" and s["bones"] == 30 and s["length_unit"] == 0.45
    s = summarize_amc(d / "cmu_01_01.amc")
    assert s["kind"] == "amc" and s["frames"] == frames_in(d / "cmu_01_01.amc") and s["asf"].endswith("cmu_01.asf")
    assert 1.3 < s["height_m"] < 2.0
    assert summarize(d / "cmu_01_01.amc")["kind"] == "amc" and summarize(d / "cmu_01.asf")["kind"] == "asf"
