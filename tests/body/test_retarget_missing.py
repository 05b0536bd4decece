"""A joint the retargeting needs but the file lacks is an error (exit 2) unless
--allow-missing-joints; extra joints are ignored with a warning. Every file is written here."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from dlacli.body.retarget import DIALECTS, NEEDED, anny_rig, match_joints, retarget
from dlacli.cli.app import main
from dlacli.errors import DlaInputError
from dlacli.io.asf_amc import read_amc
from dlacli.io.bvh import read_bvh
from dlacli.stages.motion.source import load_motion

# CMU MotionBuilder-style names (as in cmu_01_01.bvh), metres, Y up, facing +Z, left on +X
MB = [  # (name, parent, offset)
    ("Hips", None, (0.0, 0.95, 0.0)),
    ("LHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "LHipJoint", (0.09, -0.05, 0.0)),
    ("LeftLeg", "LeftUpLeg", (0.0, -0.42, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -0.42, 0.0)),
    ("LeftToeBase", "LeftFoot", (0.0, -0.04, 0.12)),
    ("RHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("RightUpLeg", "RHipJoint", (-0.09, -0.05, 0.0)),
    ("RightLeg", "RightUpLeg", (0.0, -0.42, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -0.42, 0.0)),
    ("RightToeBase", "RightFoot", (0.0, -0.04, 0.12)),
    ("LowerBack", "Hips", (0.0, 0.08, 0.0)),
    ("Spine", "LowerBack", (0.0, 0.12, 0.0)),
    ("Spine1", "Spine", (0.0, 0.12, 0.0)),
    ("Neck", "Spine1", (0.0, 0.14, 0.0)),
    ("Neck1", "Neck", (0.0, 0.05, 0.0)),
    ("Head", "Neck1", (0.0, 0.07, 0.0)),
    ("LeftShoulder", "Spine1", (0.03, 0.11, 0.0)),
    ("LeftArm", "LeftShoulder", (0.15, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (0.28, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (0.25, 0.0, 0.0)),
    ("RightShoulder", "Spine1", (-0.03, 0.11, 0.0)),
    ("RightArm", "RightShoulder", (-0.15, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-0.28, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-0.25, 0.0, 0.0)),
]
# the same skeleton with CMU's 3dsMax-style names (as in 131_01.bvh)
TO_3DSMAX = {
    "LeftUpLeg": "LeftHip",
    "LeftLeg": "LeftKnee",
    "LeftFoot": "LeftAnkle",
    "LeftToeBase": "LeftToe",
    "RightUpLeg": "RightHip",
    "RightLeg": "RightKnee",
    "RightFoot": "RightAnkle",
    "RightToeBase": "RightToe",
    "LowerBack": "lowerback",
    "Spine": "Chest",
    "Spine1": "Chest2",
    "Neck": "lowerneck",
    "Neck1": "Neck",
    "LeftShoulder": "LeftCollar",
    "LeftArm": "LeftShoulder",
    "LeftForeArm": "LeftElbow",
    "LeftHand": "LeftWrist",
    "RightShoulder": "RightCollar",
    "RightArm": "RightShoulder",
    "RightForeArm": "RightElbow",
    "RightHand": "RightWrist",
}
FRAMES = 4


def bvh_text(joints=MB, rename: dict[str, str] | None = None, seed: int = 0) -> str:
    """A BVH of `joints` with small random rotations (root: 6 channels, others 3)."""
    rename = rename or {}
    kids: dict[str | None, list[int]] = {}
    for i, (_, parent, _) in enumerate(joints):
        kids.setdefault(parent, []).append(i)
    out = ["HIERARCHY"]

    def emit(i: int, depth: int) -> None:
        name, _, off = joints[i]
        pad = "  " * depth
        out.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {rename.get(name, name)}")
        out.append(pad + "{")
        out.append(f"{pad}  OFFSET {off[0]} {off[1]} {off[2]}")
        chans = "6 Xposition Yposition Zposition" if depth == 0 else "3"
        out.append(f"{pad}  CHANNELS {chans} Zrotation Yrotation Xrotation")
        for k in kids.get(name, []):
            emit(k, depth + 1)
        if name not in kids:
            out.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET 0 -0.05 0", pad + "  }"])
        out.append(pad + "}")

    emit(0, 0)
    rng = np.random.default_rng(seed)
    out += ["MOTION", f"Frames: {FRAMES}", "Frame Time: 0.0333333"]
    for f in range(FRAMES):
        values = [0.01 * f, 0.95, 0.02 * f] + list(rng.uniform(-20, 20, 3 * len(joints)))
        out.append(" ".join(f"{v:.4f}" for v in values))
    return "\n".join(out) + "\n"


def threedsmax() -> list:
    return [(TO_3DSMAX.get(n, n), TO_3DSMAX.get(p, p) if p else None, o) for n, p, o in MB]


@pytest.fixture(scope="module")
def rig():
    return anny_rig()


def _main(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["dla", *args])
    with pytest.raises(SystemExit) as info:
        main()
    return info.value.code, capsys.readouterr().err


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_needed_bones_are_the_body_not_fingers():
    for dialect, needed in NEEDED.items():
        assert set(needed) == set(DIALECTS[dialect].values())
        assert not any(b.startswith(("finger", "toe", "metacarpal", "eye")) for b in needed), dialect
        assert {"root", "upperleg01.L", "lowerarm01.R", "head"} <= set(needed), dialect


@pytest.mark.parametrize("joints, dialect", [(MB, "cmu-motionbuilder"), (threedsmax(), "cmu-3dsmax")])
def test_complete_files_need_no_flag(tmp_path, rig, capsys, joints, dialect):
    """No finger joints in these files: fingers are never needed; nothing is reported."""
    skel = read_bvh(_write(tmp_path, "full.bvh", bvh_text(joints)))
    assert match_joints(skel.names)[0] == dialect
    motion = retarget(skel, rig)
    assert motion.num_frames == FRAMES and capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "joints, renamed, tried",
    [(MB, "LeftUpLeg", "LeftUpLeg"), (threedsmax(), "LeftHip", "LeftHip")],
)
def test_renamed_thigh_is_exit_2_with_bones_and_names_tried(tmp_path, monkeypatch, capsys, joints, renamed, tried):
    path = _write(tmp_path, "renamed.bvh", bvh_text(joints, {renamed: "LeftThigh"}))
    out = tmp_path / "out.npz"
    code, err = _main(monkeypatch, capsys, "motion", "convert", str(path), "-o", str(out))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"error: {path}: no source joint for anny bone(s) upperleg01.L (tried {tried}")
    assert "LeftThigh" in lines[0] and "--allow-missing-joints" in lines[0]
    assert not out.exists()


def test_flag_lets_it_through_and_the_note_names_the_left_leg_bones(tmp_path, monkeypatch, capsys, rig):
    leg = {"LeftUpLeg": "LThigh", "LeftLeg": "LShin", "LeftFoot": "LPaw"}
    path = _write(tmp_path, "noleg.bvh", bvh_text(MB, leg))
    out = tmp_path / "out.npz"
    code, err = _main(monkeypatch, capsys, "motion", "convert", str(path), "-o", str(out), "--allow-missing-joints")
    assert code == 0, err
    notes = [line for line in err.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and str(path) in notes[0]
    assert "upperleg01.L, lowerleg01.L, foot.L" in notes[0] and "rest" in notes[0]
    assert "error" not in err
    # those bones are at rest (relative to their parents) in every frame; the right leg moves
    motion = load_motion(out)
    idx = motion.bone_labels.index
    for bone in ("upperleg01.L", "lowerleg01.L", "foot.L"):
        np.testing.assert_array_equal(motion.rotations[:, idx(bone)], 0.0)
    assert np.abs(motion.rotations[:, idx("upperleg01.R")]).max() > 0.01
    # without the flag, the library call refuses it too
    with pytest.raises(
        DlaInputError, match=r"upperleg01\.L, lowerleg01\.L, foot\.L \(tried LeftUpLeg, LeftLeg, LeftFoot"
    ):
        retarget(read_bvh(path), rig)


def test_unknown_extra_joint_is_a_warning_and_exit_0(tmp_path, monkeypatch, capsys):
    joints = MB + [("Antenna", "Head", (0.0, 0.1, 0.0))]
    path = _write(tmp_path, "extra.bvh", bvh_text(joints))
    code, err = _main(monkeypatch, capsys, "motion", "convert", str(path), "-o", str(tmp_path / "out.npz"))
    assert code == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: ") and "Antenna" in lines[0] and str(path) in lines[0]


def test_mixamo_without_spine2_is_read_as_mixamo_missing_one_bone(tmp_path, rig):
    """Ties between name tables go to the one with fewer gaps (Mixamo here, not MotionBuilder)."""
    names = {"LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Spine1X", "Neck1": "Neck1X"}
    joints = [(names.get(n, n), names.get(p, p) if p else None, o) for n, p, o in MB]
    joints = [(f"mixamorig:{n}", f"mixamorig:{p}" if p else None, o) for n, p, o in joints]
    skel = read_bvh(_write(tmp_path, "mixamo.bvh", bvh_text(joints)))
    assert match_joints(skel.names)[0] == "mixamo"
    with pytest.raises(DlaInputError, match=r"bone\(s\) spine01 \(tried Spine2: mixamo names\)"):
        retarget(skel, rig)


# ---------------------------------------------------------------------------------------------
# ASF/AMC

ASF_BONES = [  # (name, parent, direction, length in units of 1/0.45 inch, has dofs)
    ("lhipjoint", "root", (0.6, -0.8, 0.0), 2.0, False),
    ("lfemur", "lhipjoint", (0.34, -0.94, 0.0), 7.0, True),
    ("ltibia", "lfemur", (0.0, -1.0, 0.0), 7.5, True),
    ("lfoot", "ltibia", (0.0, -0.2, 0.98), 2.2, True),
    ("rhipjoint", "root", (-0.6, -0.8, 0.0), 2.0, False),
    ("rfemur", "rhipjoint", (-0.34, -0.94, 0.0), 7.0, True),
    ("rtibia", "rfemur", (0.0, -1.0, 0.0), 7.5, True),
    ("rfoot", "rtibia", (0.0, -0.2, 0.98), 2.2, True),
    ("lowerback", "root", (0.0, 1.0, 0.0), 2.0, True),
    ("upperback", "lowerback", (0.0, 1.0, 0.0), 2.0, True),
    ("thorax", "upperback", (0.0, 1.0, 0.0), 2.0, True),
    ("lowerneck", "thorax", (0.0, 1.0, 0.0), 1.5, True),
    ("upperneck", "lowerneck", (0.0, 1.0, 0.0), 1.5, True),
    ("head", "upperneck", (0.0, 1.0, 0.0), 1.5, True),
    ("lclavicle", "thorax", (0.9, 0.4, 0.0), 3.0, True),
    ("lhumerus", "lclavicle", (1.0, 0.0, 0.0), 5.0, True),
    ("lradius", "lhumerus", (1.0, 0.0, 0.0), 3.5, True),
    ("lwrist", "lradius", (1.0, 0.0, 0.0), 1.7, True),
    ("rclavicle", "thorax", (-0.9, 0.4, 0.0), 3.0, True),
    ("rhumerus", "rclavicle", (-1.0, 0.0, 0.0), 5.0, True),
    ("rradius", "rhumerus", (-1.0, 0.0, 0.0), 3.5, True),
    ("rwrist", "rradius", (-1.0, 0.0, 0.0), 1.7, True),
]


def asf_amc_texts(bones=ASF_BONES, frames: int = 3) -> tuple[str, str]:
    asf = [
        ":version 1.10",
        ":name test",
        ":units",
        "  mass 1.0",
        "  length 0.45",
        "  angle deg",
        ":documentation",
        ":root",
        "   order TX TY TZ RX RY RZ",
        "   axis XYZ",
        "   position 0 0 0",
        "   orientation 0 0 0",
        ":bonedata",
    ]
    for i, (name, _, d, length, dofs) in enumerate(bones, 1):
        asf += (
            [
                "  begin",
                f"     id {i}",
                f"     name {name}",
                f"     direction {d[0]} {d[1]} {d[2]}",
                f"     length {length}",
                "     axis 0 0 0  XYZ",
            ]
            + (["    dof rx ry rz"] if dofs else [])
            + ["  end"]
        )
    asf += [":hierarchy", "  begin"]
    kids: dict[str, list[str]] = {}
    for name, parent, *_ in bones:
        kids.setdefault(parent, []).append(name)
    asf += [f"    {p} {' '.join(k)}" for p, k in kids.items()] + ["  end"]
    rng = np.random.default_rng(1)
    amc = [":FULLY-SPECIFIED", ":DEGREES"]
    for f in range(1, frames + 1):
        amc += [str(f), f"root {0.1 * f} 17.0 0.0 " + " ".join(f"{v:.3f}" for v in rng.uniform(-10, 10, 3))]
        amc += [f"{name} " + " ".join(f"{v:.3f}" for v in rng.uniform(-15, 15, 3)) for name, *_, dofs in bones if dofs]
    return "\n".join(asf) + "\n", "\n".join(amc) + "\n"


def test_asf_amc_renamed_bone(tmp_path, monkeypatch, capsys, rig):
    asf, amc = asf_amc_texts()
    full = read_amc(_write(tmp_path, "full.amc", amc), _write(tmp_path, "full.asf", asf))
    assert retarget(full, rig).num_frames == 3 and capsys.readouterr().err == ""
    _write(tmp_path, "s.asf", asf.replace("lfemur", "lthigh"))
    amc_path = _write(tmp_path, "s.amc", amc.replace("lfemur", "lthigh"))
    code, err = _main(monkeypatch, capsys, "motion", "convert", str(amc_path), "-o", str(tmp_path / "o.npz"))
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith(
        f"error: {amc_path}: no source joint for anny bone(s) upperleg01.L (tried lfemur: cmu-asf"
    )
    code, err = _main(
        monkeypatch, capsys, "motion", "convert", str(amc_path), "-o", str(tmp_path / "o.npz"), "--allow-missing-joints"
    )
    assert code == 0, err
    notes = [line for line in err.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "upperleg01.L" in notes[0] and str(amc_path) in notes[0]


# ---------------------------------------------------------------------------------------------
# AMASS: fewer joints than the body has


def test_amass_with_too_few_joints(tmp_path, rig, capsys):
    path = tmp_path / "cut.npz"
    poses = np.random.default_rng(2).normal(scale=0.2, size=(3, 15 * 3))  # pelvis .. right_collar
    np.savez(path, poses=poses, trans=np.zeros((3, 3)), mocap_framerate=np.array(30.0))
    with pytest.raises(DlaInputError) as err:
        load_motion(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: no source joint for anny bone(s) head, upperarm01.L")
    assert "tried head, left_shoulder" in msg and "smpl names" in msg
    motion = load_motion(path, allow_missing_joints=True)
    assert motion.num_frames == 3
    note = capsys.readouterr().err
    assert note.startswith("note: ") and "wrist.R" in note and note.count("\n") == 1
