"""BVH parser: real CMU files, a third-party metric conversion, Euler semantics, bad files."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.io.bvh import read_bvh, summarize_bvh
from dlacli.io.inspect import summarize
from dlacli.kinematics import forward_kinematics, rest_positions

CMU_UNIT = 0.0254 / 0.45  # metres per CMU length unit


def test_cmu_files_parse(third_party_data, frames_in):
    for name, first in (("131_01.bvh", "LeftHip"), ("cmu_01_01.bvh", "LeftUpLeg")):
        skel = read_bvh(third_party_data / "motion" / name)
        assert skel.num_frames == frames_in(third_party_data / "motion" / name) and skel.num_joints == 31
        assert skel.fps == 120.0
        assert skel.names[0] == "Hips" and first in skel.names
        assert skel.parents[0] == -1 and all(skel.parents[k] < k for k in range(1, 31))
        assert skel.metres_per_unit == pytest.approx(CMU_UNIT)
        rot = skel.rotations
        np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    # the first data line of 131_01: root position and its Z Y X rotation channels
    skel = read_bvh(third_party_data / "motion" / "131_01.bvh")
    np.testing.assert_allclose(skel.root_positions[0], [5.2300, 16.9002, -33.8986])
    expected = Rotation.from_euler("ZYX", [-5.4029, 9.8098, 10.4956], degrees=True).as_matrix()
    np.testing.assert_allclose(skel.rotations[0, 0], expected, atol=1e-12)


def test_metric_copy_by_a_third_party_matches_after_unit_conversion(third_party_data):
    """scaled_131_01.bvh (made by bvh11's authors) is 131_01.bvh in metres: FK positions agree."""
    cmu = read_bvh(third_party_data / "motion" / "131_01.bvh")
    metric = read_bvh(third_party_data / "motion" / "scaled_131_01.bvh")
    assert metric.units == "m" and metric.metres_per_unit == 1.0
    # The files' own precision bounds the match, float64 adds nothing: the metric file's offsets
    # are the CMU ones times ~0.056444 (its offset ratios agree with 0.0254 / 0.45 to ~8e-6
    # relative), written to 6 decimals; 131_01 has 5-decimal offsets, 4-decimal angles and root.
    # Rest positions (<= 1 m from the root, <= 10 offsets): 8e-6 * 1 m + 10 * (2.8e-7 + 5e-7) m.
    np.testing.assert_allclose(rest_positions(cmu) * CMU_UNIT, rest_positions(metric), atol=2e-5)
    frames = np.arange(0, cmu.num_frames, 37)
    _, p_cmu = forward_kinematics(cmu, frames)
    _, p_metric = forward_kinematics(metric, frames)
    # posed (<= 2 m from the origin): the scale mismatch 8e-6 * 2 m, the root's rounding
    # 5e-5 units = 2.8e-6 m, <= 30 angles on a chain (10 joints x 3) each rounded by
    # 5e-5 deg = 8.7e-7 rad at <= 1 m lever, the offsets as above: 1.6e-5 + 2.8e-6 + 2.6e-5
    # + 7.8e-6 ~ 5.3e-5, about half of atol
    np.testing.assert_allclose(p_cmu * CMU_UNIT, p_metric, atol=1e-4)


BVH_ONE_BONE = """HIERARCHY
ROOT Hips
{{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition {order}
  JOINT Arm
  {{
    OFFSET 1 2 3
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {{
      OFFSET 0 -1 0
    }}
  }}
}}
MOTION
Frames: {frames}
Frame Time: 0.04
{data}"""


def _write(tmp_path, text, name="clip.bvh"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "order", ["Xrotation Yrotation Zrotation", "Yrotation Zrotation Xrotation", "Zrotation Yrotation Xrotation"]
)
def test_euler_channel_order_semantics(tmp_path, order):
    """The first listed rotation is the outermost (intrinsic order), checked with scipy."""
    rng = np.random.default_rng(0)
    angles = np.round(rng.uniform(-170, 170, size=(3, 6)), 6)
    data = "\n".join(" ".join(f"{v:.6f}" for v in [0.5, 1.0, -2.0, *row]) for row in angles)
    skel = read_bvh(_write(tmp_path, BVH_ONE_BONE.format(order=order, frames=3, data=data)))
    assert skel.fps == 25.0
    letters = "".join(c[0] for c in order.split())
    glob, pos = forward_kinematics(skel)
    for f in range(3):
        r_root = Rotation.from_euler(letters, angles[f, :3], degrees=True)
        r_arm = Rotation.from_euler("ZXY", angles[f, 3:], degrees=True)
        np.testing.assert_allclose(pos[f, 1], [0.5, 1.0, -2.0] + r_root.apply([1, 2, 3]), atol=1e-9)
        np.testing.assert_allclose(glob[f, 1], (r_root * r_arm).as_matrix(), atol=1e-9)
    assert skel.end_sites[1].tolist() == [0, -1, 0]


@pytest.mark.parametrize(
    "order, frames, data, problem",
    [
        ("Xrotation Yrotation Zrotation", 2, "0 0 0 1 2 3 4 5 6\n0 0 0 1 2 3", "truncated"),
        ("Xrotation Yrotation Zrotation", 1, "0 0 nan 1 2 3 4 5 6", "non-finite"),
        ("Xrotation Yrotation Zrotation", 0, "", "0 frames"),
        ("Xrotation Xrotation Zrotation", 1, "0 0 0 1 2 3 4 5 6", "unsupported rotation order"),
        ("Xrotation Wrotation Zrotation", 1, "0 0 0 1 2 3 4 5 6", "unsupported channel"),
        ("Xrotation Yrotation Zrotation", 1, "0 0 0 1 2 x 4 5 6", "non-numeric"),
    ],
)
def test_bad_files_name_the_file_and_problem(tmp_path, order, frames, data, problem):
    path = _write(tmp_path, BVH_ONE_BONE.format(order=order, frames=frames, data=data), "bad.bvh")
    with pytest.raises(DlaInputError, match=problem) as err:
        read_bvh(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_cut_files(tmp_path, third_party_data):
    text = (third_party_data / "motion" / "131_01.bvh").read_text()
    for cut, problem in (
        (len(text) // 2, "truncated"),
        (text.index("MOTION"), "no MOTION"),
        (text.index("JOINT LeftKnee"), "unexpected end"),
    ):
        path = _write(tmp_path, text[:cut], "cut.bvh")
        with pytest.raises(DlaInputError, match=problem):
            read_bvh(path)
    with pytest.raises(DlaInputError, match="not a BVH"):
        read_bvh(_write(tmp_path, "hello", "x.bvh"))
    with pytest.raises(DlaInputError, match="cannot read"):
        read_bvh(tmp_path / "missing.bvh")


def test_summary_and_info(third_party_data, frames_in):
    path = third_party_data / "motion" / "cmu_01_01.bvh"
    s, n = summarize_bvh(path), frames_in(path)
    assert s["kind"] == "bvh" and s["frames"] == n and s["fps"] == 120.0 and s["joints"] == 31
    assert s["duration_s"] == pytest.approx((n - 1) / 120)
    assert 1.2 < s["height_m"] < 2.0  # a grown-up's joints, toes to head top
    assert summarize(path)["kind"] == "bvh"


BVH_CARRIED_ROOT = """HIERARCHY
ROOT joint_Root
{{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Hips
  {{
    OFFSET 1 90 -4
    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
    JOINT Spine
    {{
      OFFSET 15 0 0
      CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
      End Site
      {{
        OFFSET 0 10 0
      }}
    }}
  }}
}}
MOTION
Frames: {frames}
Frame Time: 0.0333333
{data}"""


def test_a_fixed_root_whose_only_child_carries_the_path_moves_the_body(tmp_path):
    """An exporter that puts a still joint above the hips (joint_Root -> Hips, all joints with 6
    channels, as the Bandai Namco Research Motion dataset writes): the hips' per-frame positions
    are the body's path. Every joint sits where composing the file's channels by hand (scipy)
    puts it; the Spine's own position channels are its offset (constant, as such files hold)."""
    rng = np.random.default_rng(3)
    n = 4
    root_rot = np.round(rng.uniform(-40, 40, (n, 3)), 4)
    hips_pos = np.round(np.stack([np.linspace(0, 30, n), 90 + rng.uniform(-2, 2, n), np.linspace(-4, -200, n)], 1), 4)
    hips_rot = np.round(rng.uniform(-90, 90, (n, 3)), 4)
    spine_rot = np.round(rng.uniform(-90, 90, (n, 3)), 4)
    rows = [[0, 0, 0, *root_rot[f], *hips_pos[f], *hips_rot[f], 15, 0, 0, *spine_rot[f]] for f in range(n)]
    data = "\n".join(" ".join(f"{v:.4f}" for v in row) for row in rows)
    skel = read_bvh(_write(tmp_path, BVH_CARRIED_ROOT.format(frames=n, data=data)))
    glob, pos = forward_kinematics(skel)
    for f in range(n):
        r0 = Rotation.from_euler("ZXY", root_rot[f], degrees=True)
        r1 = r0 * Rotation.from_euler("ZXY", hips_rot[f], degrees=True)
        r2 = r1 * Rotation.from_euler("ZXY", spine_rot[f], degrees=True)
        hips = r0.apply(hips_pos[f])
        np.testing.assert_allclose(pos[f, 1], hips, atol=1e-9)
        np.testing.assert_allclose(pos[f, 2], hips + r1.apply([15, 0, 0]), atol=1e-9)
        np.testing.assert_allclose(glob[f, 2], r2.as_matrix(), atol=1e-9)
