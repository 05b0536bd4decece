"""AMASS npz reader: synthetic files in the SMPL-H (156), SMPL-X (165) and SMPL (72) layouts."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.io.amass import SMPL_JOINTS, SMPL_REST_JOINTS, axis_angle_matrices, read_amass, summarize_amass
from dlacli.io.inspect import summarize
from dlacli.kinematics import forward_kinematics


def write_amass(path, width=156, frames=5, rate_key="mocap_framerate", fps=60.0, seed=0, **override):
    rng = np.random.default_rng(seed)
    arrays = {
        "poses": rng.normal(scale=0.3, size=(frames, width)),
        "trans": rng.normal(size=(frames, 3)),
        "betas": np.zeros(16),
        "gender": np.array("neutral"),
        rate_key: np.array(fps),
    }
    arrays.update(override)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(path, **arrays)
    return arrays


@pytest.mark.parametrize(
    "width, rate_key", [(156, "mocap_framerate"), (165, "mocap_frame_rate"), (72, "mocap_framerate")]
)
def test_layouts_and_framerate_keys(tmp_path, width, rate_key):
    arrays = write_amass(tmp_path / "a.npz", width, rate_key=rate_key)
    skel = read_amass(tmp_path / "a.npz")
    assert skel.names == list(SMPL_JOINTS) and skel.num_frames == 5 and skel.fps == 60.0
    assert skel.up == "z" and skel.dialect == "smpl"
    body = arrays["poses"][:, :66].reshape(5, 22, 3)
    expected = Rotation.from_rotvec(body.reshape(-1, 3)).as_matrix().reshape(5, 22, 3, 3)
    np.testing.assert_allclose(skel.rotations, expected, atol=1e-12)
    np.testing.assert_allclose(skel.root_positions, arrays["trans"] + SMPL_REST_JOINTS[0])
    # the rest skeleton reproduces the rest joint locations (pelvis at trans + rest pelvis)
    zero = skel.rotations.copy()
    zero[:] = np.eye(3)
    skel.rotations = zero
    _, pos = forward_kinematics(skel, [0])
    np.testing.assert_allclose(pos[0] - pos[0, 0], SMPL_REST_JOINTS - SMPL_REST_JOINTS[0], atol=1e-12)


def test_rodrigues_matches_scipy():
    aa = np.random.default_rng(1).normal(size=(50, 3)) * 1.5
    aa[0] = 0.0
    np.testing.assert_allclose(axis_angle_matrices(aa), Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)


@pytest.mark.parametrize(
    "override, problem",
    [
        ({"poses": np.zeros((5, 100))}, "100 values per frame"),
        ({"poses": np.zeros((0, 156)), "trans": np.zeros((0, 3))}, "no frames"),
        ({"poses": np.full((5, 156), np.nan)}, "non-finite"),
        ({"trans": np.zeros((4, 3))}, "trans has shape"),
        ({"trans": None}, "no 'trans'"),
        ({"mocap_framerate": None}, "no frame rate"),
        ({"mocap_framerate": np.array(0.0)}, "must be > 0"),
        ({"poses": None}, "no 'poses'"),
    ],
)
def test_bad_files(tmp_path, override, problem):
    path = tmp_path / "bad.npz"
    write_amass(path, **override)
    with pytest.raises(DlaInputError, match=problem) as err:
        read_amass(path)
    assert str(err.value).startswith(str(path))


def test_not_an_npz(tmp_path):
    path = tmp_path / "x.npz"
    path.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(DlaInputError, match="not a readable"):
        read_amass(path)


def test_summary_and_info(tmp_path):
    write_amass(tmp_path / "a.npz", 165, frames=31, fps=30.0)
    s = summarize_amass(tmp_path / "a.npz")
    assert s["kind"] == "amass" and "smplx" in s["format"] and s["frames"] == 31 and s["duration_s"] == 1.0
    assert summarize(tmp_path / "a.npz")["kind"] == "amass"
