"""Retargeting onto anny: posed anny bones follow the mocap; formats agree; AMASS; policies;
frame-rate resampling; built-in motions.

Tolerances (measured values in brackets, on the vendored clips: their first 300 frames, see
tests/data/third_party/LICENSES.md):
- limb directions (upper arm, forearm, thigh, shin, clavicle): the retargeting makes each mapped
  anny segment point exactly where the source segment points, so the only errors are float32
  storage and anny's float32 FK: median < 0.5 deg, 95th percentile < 1 deg [0.01 / 0.02 deg].
- pelvis left-right axis: < 3 deg [0.33 deg for 131_*, 1.03 deg for 01_01: a constant offset
  from aligning whole pelvis frames, up and left, with one rotation].
- the lowest vertex over the clip rests on anny's ground: median within [-3, +6] cm, 5th
  percentile above -5 cm [+1.8 / +1.9 cm, +0.7 / +1.5 cm]; soles are not ankles, CMU's
  ankle height is not anny's.
- ASF/AMC vs BVH of clip 01_01: rotations within 1 deg [0.59 deg: the converter drops the
  thorax length, which tilts the torso frame], root path (relative to frame 0) within 1 mm
  [0.02 mm].
- AMASS arm direction: 0.5 deg from the rotated SMPL rest arm [0.01 deg]; 6 deg from the
  ideal (cos a, 0, sin a) [4.9 deg: the rest arm of SMPL points a little back and down].
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from dlacli.body.builtin_motions import BUILTINS, builtin_motion
from dlacli.body.model import get_body_model
from dlacli.body.retarget import Y_UP_TO_ANNY, anny_rig, match_joints, resample_motion, retarget
from dlacli.errors import DlaInputError
from dlacli.io.amass import SMPL_REST_JOINTS
from dlacli.io.asf_amc import read_amc
from dlacli.io.bvh import read_bvh
from dlacli.stages.motion.source import load_motion
from dlacli.types import Motion

SEGMENTS = [  # (anny bone, anny bone at the segment's end)
    ("upperarm01.L", "lowerarm01.L"),
    ("lowerarm01.L", "wrist.L"),
    ("upperarm01.R", "lowerarm01.R"),
    ("lowerarm01.R", "wrist.R"),
    ("upperleg01.L", "lowerleg01.L"),
    ("lowerleg01.L", "foot.L"),
    ("upperleg01.R", "lowerleg01.R"),
    ("lowerleg01.R", "foot.R"),
    ("clavicle.L", "upperarm01.L"),
    ("clavicle.R", "upperarm01.R"),
]


def fk_positions(skel, frames):
    """Joint world positions [T, J, 3] by a recursive walk with scipy rotations (an FK written
    independently of dlacli.kinematics.forward_kinematics, which the retargeting uses)."""
    children = {k: [c for c in range(skel.num_joints) if skel.parents[c] == k] for k in range(skel.num_joints)}
    out = np.zeros((len(frames), skel.num_joints, 3))
    for n, f in enumerate(frames):

        def walk(k, rot, pos, n=n, f=f):
            out[n, k] = pos
            rot = rot * Rotation.from_matrix(skel.rotations[f, k])
            for c in children[k]:
                walk(c, rot, pos + rot.apply(skel.offsets[c]))

        walk(0, Rotation.identity(), skel.root_positions[f])
    return out


def _angles(a, b):
    cos = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@pytest.fixture(scope="module")
def rig():
    return anny_rig()


@pytest.fixture(scope="module")
def clips(third_party_data):
    d = third_party_data / "motion"
    return {
        "131_01.bvh": read_bvh(d / "131_01.bvh"),
        "131_02.bvh": read_bvh(d / "131_02.bvh"),
        "cmu_01_01.bvh": read_bvh(d / "cmu_01_01.bvh"),
        "cmu_01_01.amc": read_amc(d / "cmu_01_01.amc", d / "cmu_01.asf"),
    }


@pytest.fixture(scope="module")
def motions(clips, rig):
    return {name: retarget(skel, rig) for name, skel in clips.items()}


@pytest.mark.parametrize("name", ["131_01.bvh", "131_02.bvh", "cmu_01_01.amc"])
def test_posed_anny_follows_the_mocap(name, clips, motions, rig):
    skel, motion = clips[name], motions[name]
    _, mapped = match_joints(skel.names)
    src_of = {label: s for s, label in mapped.items()}
    frames = np.arange(0, skel.num_frames, 20)
    src = fk_positions(skel, frames) @ Y_UP_TO_ANNY.T  # source world in anny's axes
    heads = get_body_model().forward_motion({}, motion, frames=frames).bone_heads.numpy()
    idx = rig.bone_labels.index
    for a, b in SEGMENTS:
        ang = _angles(heads[:, idx(b)] - heads[:, idx(a)], src[:, src_of[b]] - src[:, src_of[a]])
        assert np.median(ang) < 0.5 and np.percentile(ang, 95) < 1.0, (a, b, np.median(ang), ang.max())
    left = _angles(
        heads[:, idx("upperleg01.L")] - heads[:, idx("upperleg01.R")],
        src[:, src_of["upperleg01.L"]] - src[:, src_of["upperleg01.R"]],
    )
    assert left.max() < 3.0


@pytest.mark.parametrize("name", ["131_01.bvh", "cmu_01_01.amc"])
def test_feet_stay_on_the_ground(name, motions, rig):
    motion = motions[name]
    verts = get_body_model().forward_motion({}, motion, frames=np.arange(0, motion.num_frames, 15)).vertices
    lowest = verts[..., 2].min(dim=1).values.numpy() - rig.ground_z  # [T] metres above the ground
    assert -0.03 < np.median(lowest) < 0.06 and np.percentile(lowest, 5) > -0.05


def test_asf_amc_and_bvh_give_the_same_motion(motions):
    amc, bvh = motions["cmu_01_01.amc"], motions["cmu_01_01.bvh"]
    assert bvh.num_frames == amc.num_frames + 1  # the BVH starts with the converter's T-pose
    r_amc = Rotation.from_rotvec(amc.rotations.reshape(-1, 3))
    r_bvh = Rotation.from_rotvec(bvh.rotations[1:].reshape(-1, 3))
    assert np.degrees((r_amc.inv() * r_bvh).magnitude()).max() < 1.0
    root = Rotation.from_rotvec(amc.root_rotation).inv() * Rotation.from_rotvec(bvh.root_rotation[1:])
    assert np.degrees(root.magnitude()).max() < 1.0
    path_amc = amc.root_translation - amc.root_translation[0]
    path_bvh = bvh.root_translation[1:] - bvh.root_translation[1]
    np.testing.assert_allclose(path_amc, path_bvh, atol=1e-3)


def _amass(path, width, rate_key, poses):
    np.savez(
        path,
        poses=poses,
        trans=np.zeros((poses.shape[0], 3)) + [0, 0, 0.95],
        betas=np.zeros(10),
        **{rate_key: np.array(30.0)},
    )


@pytest.mark.parametrize("width, rate_key", [(156, "mocap_framerate"), (165, "mocap_frame_rate")])
def test_amass_shoulder_rotation_arrives_on_anny(tmp_path, width, rate_key, rig):
    """SMPL's left shoulder turned by a known angle a about its canonical Z, the body stood up with
    root_orient = +90 deg about X (facing -Y like anny) -> anny's left upper arm points where the
    SMPL upper arm points: Rx(90) Rz(a) applied to the rest shoulder->elbow vector, which is
    close to +X: (cos a, 0, sin a), horizontal at 0 and straight down at -90 deg."""
    alphas = np.radians([0.0, -90.0, 45.0, -30.0])
    poses = np.zeros((4, width))
    poses[:, 0] = np.pi / 2  # root_orient
    poses[:, 3 * 16 + 2] = alphas  # left_shoulder is SMPL joint 16
    _amass(tmp_path / "m.npz", width, rate_key, poses)
    motion = load_motion(tmp_path / "m.npz")
    assert motion.fps == 30.0 and motion.num_frames == 4
    heads = get_body_model().forward_motion({}, motion).bone_heads.numpy()
    idx = rig.bone_labels.index
    arm = heads[:, idx("lowerarm01.L")] - heads[:, idx("upperarm01.L")]
    rest = SMPL_REST_JOINTS[18] - SMPL_REST_JOINTS[16]
    expected = (Rotation.from_rotvec([np.pi / 2, 0, 0]) * Rotation.from_rotvec(np.outer(alphas, [0, 0, 1]))).apply(rest)
    assert _angles(arm, expected).max() < 0.5
    assert _angles(arm, np.stack([np.cos(alphas), np.zeros(4), np.sin(alphas)], 1)).max() < 6.0
    # the body stands up facing -Y: left hip on +X, head above the pelvis
    hips = heads[:, idx("upperleg01.L")] - heads[:, idx("upperleg01.R")]
    assert _angles(hips, np.array([[1.0, 0.0, 0.0]])).max() < 3.0
    assert np.all(heads[:, idx("head"), 2] > heads[:, 0, 2] + 0.4)
    # the anny root rotation of a standing SMPL body is the identity up to the rest-frame alignment
    assert np.degrees(np.linalg.norm(motion.root_rotation, axis=1)).max() < 8.0


BVH_TWO = """HIERARCHY
ROOT {root}
{{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT {child}
  {{
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {{
      OFFSET 0 -10 0
    }}
  }}
}}
MOTION
Frames: 2
Frame Time: 0.0333333
0 20 0 0 0 0 0 0 0
0 20 0 0 0 0 30 0 0
"""


def test_joint_name_policy(tmp_path, rig):
    """No joint matches -> error; a few unknown joints -> ignored with a warning on stderr."""
    path = tmp_path / "alien.bvh"
    path.write_text(BVH_TWO.format(root="Body", child="Tentacle"))
    with pytest.raises(DlaInputError, match="none of its 2 joints match") as err:
        retarget(read_bvh(path), rig)
    assert str(err.value).startswith(str(path))
    path.write_text(BVH_TWO.format(root="Hips", child="Tentacle"))
    with pytest.raises(DlaInputError, match="too few joints"):
        retarget(read_bvh(path), rig)


def test_unknown_extra_joint_is_ignored_with_a_warning(tmp_path, third_party_data, frames_in, rig, capsys):
    text = (third_party_data / "motion" / "131_01.bvh").read_text().replace("JOINT lhand", "JOINT Antenna", 1)
    path = tmp_path / "extra.bvh"
    path.write_text(text)
    motion = retarget(read_bvh(path), rig)
    err = capsys.readouterr().err
    assert "warning:" in err and "Antenna" in err and str(path) in err
    assert motion.num_frames == frames_in(path)


def test_resampling_120_to_30_keeps_every_4th_frame(motions):
    src = motions["131_01.bvh"]
    out = resample_motion(src, 30.0)
    assert out.fps == 30.0 and out.num_frames == (src.num_frames - 1) // 4 + 1
    same = lambda a, b: Rotation.from_rotvec(a.reshape(-1, 3)).inv() * Rotation.from_rotvec(b.reshape(-1, 3))  # noqa: E731
    assert same(out.rotations, src.rotations[::4]).magnitude().max() < 1e-5
    assert same(out.root_rotation, src.root_rotation[::4]).magnitude().max() < 1e-5
    np.testing.assert_allclose(out.root_translation, src.root_translation[::4], atol=1e-6)


def test_resampling_between_frames_is_slerp_and_lerp():
    rng = np.random.default_rng(3)
    rot = Rotation.random(5 * 2, random_state=4).as_rotvec().reshape(5, 2, 3).astype(np.float32)
    root = Rotation.random(5, random_state=5).as_rotvec().astype(np.float32)
    trans = rng.normal(size=(5, 3)).astype(np.float32)
    src = Motion(["a", "b"], rot, root, trans, 10.0)
    out = resample_motion(src, 25.0)  # new frame n at source frame 0.4 n
    assert out.num_frames == 11
    pos = np.arange(11) * 0.4
    for j in range(2):  # scipy's Slerp is the oracle
        ref = Slerp(np.arange(5), Rotation.from_rotvec(rot[:, j]))(pos)
        assert (ref.inv() * Rotation.from_rotvec(out.rotations[:, j])).magnitude().max() < 1e-5
    lerp = np.stack([np.interp(pos, np.arange(5), trans[:, i]) for i in range(3)], 1)
    np.testing.assert_allclose(out.root_translation, lerp, atol=1e-5)
    with pytest.raises(DlaInputError, match="must be > 0"):
        resample_motion(src, 0.0)


# ---------------------------------------------------------------------------------------------
# built-in motions


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_builtins_load_with_sensible_length(name):
    motion = load_motion(name)
    assert motion.fps == 30.0 and 2.0 <= (motion.num_frames - 1) / motion.fps <= 6.0
    assert set(motion.bone_labels) <= set(get_body_model().bone_labels)
    assert np.all(np.isfinite(motion.rotations)) and np.ptp(motion.rotations, axis=0).max() > 0.05
    assert load_motion(name, fps=15).num_frames == (motion.num_frames - 1) // 2 + 1
    with pytest.raises(DlaInputError, match="not a built-in motion"):
        builtin_motion("moonwalk")


def test_turnaround_accumulates_360_degrees_of_yaw(tol):
    motion = builtin_motion("turnaround")
    forward = Rotation.from_rotvec(motion.root_rotation).apply([0.0, -1.0, 0.0])  # body's facing
    yaw = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    # two float32 rotation vectors of length <= pi, each rounded by <= eps32 / 2 per component
    # (was abs=0.01 deg, ~1e3 times that)
    assert np.degrees(yaw[-1] - yaw[0]) == pytest.approx(360.0, abs=np.degrees(tol(np.float32, np.pi, 4)))
    assert np.all(np.diff(yaw) >= -1e-9)  # one way round
    np.testing.assert_allclose(forward[:, 2], 0.0, atol=1e-9)  # yaw only


def test_builtins_do_what_they_say(rig):
    model = get_body_model()
    idx = rig.bone_labels.index
    walk = builtin_motion("walk")
    assert walk.root_translation[-1, 1] - walk.root_translation[0, 1] < -2.5  # forward is -Y
    wave = builtin_motion("wave")
    heads = model.forward_motion({}, wave, frames=[0, wave.num_frames // 2]).bone_heads.numpy()
    assert heads[0, idx("wrist.R"), 2] < heads[0, idx("upperarm01.R"), 2] - 0.25  # hand down at the start
    assert heads[1, idx("wrist.R"), 2] > heads[1, idx("head"), 2]  # above the head mid-wave
    idle = builtin_motion("idle")
    assert np.abs(idle.root_translation).max() < 0.05
    verts = model.forward_motion({}, idle, frames=[0, 30, 60]).vertices.numpy()
    assert np.abs(verts[..., 2].min(axis=1) - rig.ground_z).max() < 0.02  # standing on the ground


def test_units_do_not_matter(third_party_data, motions, rig):
    """scaled_131_01.bvh is 131_01.bvh in metres (made by a third party): same native motion."""
    metric = retarget(read_bvh(third_party_data / "motion" / "scaled_131_01.bvh"), rig)
    cmu = motions["131_01.bvh"]
    n = cmu.num_frames
    rel = Rotation.from_rotvec(cmu.rotations.reshape(-1, 3)).inv() * Rotation.from_rotvec(
        metric.rotations[:n].reshape(-1, 3)
    )
    assert np.degrees(rel.magnitude()).max() < 0.01
    np.testing.assert_allclose(metric.root_translation[:n], cmu.root_translation, atol=1e-4)


# MotionBuilder-style CMU names -> Reallusion Character Creator / iClone names
_CC_NAMES = {
    "Hips": "CC_Base_Hip",
    "LowerBack": "CC_Base_Waist",
    "Spine": "CC_Base_Spine01",
    "Spine1": "CC_Base_Spine02",
    "Neck": "CC_Base_NeckTwist01",
    "Neck1": "CC_Base_NeckTwist02",
    "Head": "CC_Base_Head",
    **{
        f"{side}{mb}": f"CC_Base_{side[0]}_{cc}"
        for side in ("Left", "Right")
        for mb, cc in (
            ("Shoulder", "Clavicle"),
            ("Arm", "Upperarm"),
            ("ForeArm", "Forearm"),
            ("Hand", "Hand"),
            ("UpLeg", "Thigh"),
            ("Leg", "Calf"),
            ("Foot", "Foot"),
        )
    },
}


def test_character_creator_names_give_the_same_motion(clips, motions, rig):
    """An iClone / Character Creator export ("CC_Base_" names) maps onto the same anny bones as
    the MotionBuilder-style names: the clip renamed retargets to the same motion, bit for bit."""
    skel = clips["cmu_01_01.bvh"]
    renamed = type(skel)(**{**vars(skel), "names": [_CC_NAMES.get(n, n) for n in skel.names]})
    assert match_joints(renamed.names)[0] == "character-creator"
    assert sum(n.startswith("CC_Base_") for n in renamed.names) == len(_CC_NAMES)
    got, want = retarget(renamed, rig), motions["cmu_01_01.bvh"]
    np.testing.assert_array_equal(got.rotations, want.rotations)
    np.testing.assert_array_equal(got.root_rotation, want.root_rotation)
    np.testing.assert_array_equal(got.root_translation, want.root_translation)


# MotionBuilder-style CMU names -> the Bandai Namco Research Motion dataset's: its trunk has two
# joints (Spine, Chest) where CMU has three, so LowerBack and Neck1 get names no table knows
_BANDAI_NAMES = {
    "LowerBack": "LowerBack_unmapped",
    "Spine1": "Chest",
    "Neck1": "Neck1_unmapped",
    **{
        f"{side}{mb}": f"{bn}_{side[0]}"
        for side in ("Left", "Right")
        for mb, bn in (
            ("Shoulder", "Shoulder"),
            ("Arm", "UpperArm"),
            ("ForeArm", "LowerArm"),
            ("Hand", "Hand"),
            ("UpLeg", "UpperLeg"),
            ("Leg", "LowerLeg"),
            ("Foot", "Foot"),
        )
    },
}

_LIMB_BONES = ("clavicle", "upperarm01", "lowerarm01", "wrist", "upperleg01", "lowerleg01")
_LIMBS = [f"{b}.{s}" for s in "LR" for b in _LIMB_BONES]


def _world_rotations(motion, rig):
    """[T, J] world rotations of anny's bones: local-ref rotations composed root first."""
    local = Rotation.from_rotvec(motion.rotations.reshape(-1, 3)).as_matrix().reshape(*motion.rotations.shape, 3)
    world = np.empty_like(local)
    root = Rotation.from_rotvec(motion.root_rotation).as_matrix()
    for j, p in enumerate(rig.bone_parents):
        world[:, j] = (root if p < 0 else world[:, p]) @ local[:, j]
    return world


def test_bandai_namco_names_move_the_limbs_as_the_cmu_names_do(clips, motions, rig):
    """The Bandai Namco skeleton's names ("UpperArm_L", "Chest") map onto anny: the CMU clip
    renamed to them moves every limb bone to the same world rotation as the CMU names do (a limb
    follows its source bone's world rotation, whatever the trunk's joints), on the same path."""
    skel = clips["cmu_01_01.bvh"]
    renamed = type(skel)(**{**vars(skel), "names": [_BANDAI_NAMES.get(n, n) for n in skel.names]})
    assert match_joints(renamed.names)[0] == "bandai-namco"
    got, want = retarget(renamed, rig), motions["cmu_01_01.bvh"]
    wg, ww = _world_rotations(got, rig), _world_rotations(want, rig)
    idx = [rig.index(b) for b in _LIMBS]
    # float64 products of <= 12 rotations, stored as float32 axis-angles: ~1e-6
    np.testing.assert_allclose(wg[:, idx], ww[:, idx], atol=1e-5)
    np.testing.assert_allclose(got.root_translation, want.root_translation, atol=1e-6)


def _twist_trunk(skel, joint: str, angle: float):
    """The same motion with `angle` of twist baked into `joint`'s rotation channels: its rest
    subtree turned by -angle about the rest axis from the joint to the skeleton's top, its rotation
    R T and every rotation below it T^-1 R T, so that the posed skeleton is unchanged."""
    from dlacli.kinematics import rest_positions

    j = skel.names.index(joint)
    rest = rest_positions(skel)
    below = set()
    for k in range(skel.num_joints):
        p = int(skel.parents[k])
        if p == j or p in below:
            below.add(k)
    top = max(below, key=lambda k: rest[k, 1])  # the head end of the chain (Y up)
    axis = (rest[top] - rest[j]) / np.linalg.norm(rest[top] - rest[j])
    t = Rotation.from_rotvec(angle * axis).as_matrix()
    rot, off = skel.rotations.copy(), skel.offsets.copy()
    rot[:, j] = rot[:, j] @ t
    idx = sorted(below)
    rot[:, idx] = t.T @ rot[:, idx] @ t
    off[idx] = off[idx] @ t  # T^-1 applied to each row
    ends = {k: (v @ t if k in below else v) for k, v in skel.end_sites.items()}
    return type(skel)(**{**vars(skel), "rotations": rot, "offsets": off, "end_sites": ends}), axis


def test_a_trunk_twist_baked_into_the_rotation_channels_does_not_turn_the_torso(clips, motions, rig):
    """Some exporters write a trunk joint's orientation into its channels (the Bandai Namco files
    twist "Spine" by 90 degrees: in their rest pose the shoulders cross the hips). The same CMU clip
    with such a twist baked into LowerBack moves every trunk bone (spine, neck, head) as the clip
    does, to within the clip's own rest misalignment of shoulders and hips (under a degree), and
    every limb joint to the same place; the root and its path are untouched."""
    from dlacli.kinematics import forward_kinematics, rest_positions

    skel = clips["cmu_01_01.bvh"]
    twisted, axis = _twist_trunk(skel, "LowerBack", np.pi / 2)
    frames = np.arange(0, skel.num_frames, 25)
    # the oracle's own check: the posed skeletons are the same
    np.testing.assert_allclose(forward_kinematics(twisted, frames)[1], forward_kinematics(skel, frames)[1], atol=1e-9)
    rest = rest_positions(skel)
    names = skel.names

    def flat(v):  # the component across the twist axis, normalised
        v = v - np.dot(v, axis) * axis
        return v / np.linalg.norm(v)

    hips = flat(rest[names.index("LeftUpLeg")] - rest[names.index("RightUpLeg")])
    arms = flat(rest[names.index("LeftArm")] - rest[names.index("RightArm")])
    misalignment = np.arccos(np.clip(hips @ arms, -1, 1))  # ~0.8 degrees in this clip
    got, want = retarget(twisted, rig), motions["cmu_01_01.bvh"]
    wg, ww = _world_rotations(got, rig), _world_rotations(want, rig)
    trunk = [rig.index(b) for b in ("spine05", "spine03", "spine01", "neck01", "neck02", "head")]
    angle = Rotation.from_matrix((np.swapaxes(wg[:, trunk], -1, -2) @ ww[:, trunk]).reshape(-1, 3, 3)).magnitude()
    assert angle.max() <= misalignment + 1e-5, (np.degrees(angle.max()), np.degrees(misalignment))
    np.testing.assert_allclose(wg[:, rig.index("root")], ww[:, rig.index("root")], atol=1e-6)
    np.testing.assert_allclose(got.root_translation, want.root_translation, atol=1e-6)
    model = get_body_model()
    heads_got = model.forward_motion({}, got, frames=frames).bone_heads.numpy()
    heads_want = model.forward_motion({}, want, frames=frames).bone_heads.numpy()
    limbs = [model.bone_index(f"{b}.{s}") for s in "LR" for b in ("lowerarm01", "wrist", "lowerleg01", "foot")]
    # a trunk turned by under a degree moves the arms' joints by under 2 cm (0.6 m levers)
    np.testing.assert_allclose(heads_got[:, limbs], heads_want[:, limbs], atol=np.sin(misalignment) * 0.6 + 1e-5)
