"""motion.npz: golden file, round trips and every bad-input case (formats/motion.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.io.motion import read_motion, summarize_motion, write_motion
from dlacli.types import Motion


def _arrays(t=3, j=2):
    rng = np.random.default_rng(0)
    return {
        "format": np.array("dla.motion/1"),
        "model": np.array("anny"),
        "bone_labels": np.array([f"bone{i}" for i in range(j)]),
        "rotations": rng.normal(size=(t, j, 3)).astype(np.float32),
        "root_rotation": rng.normal(size=(t, 3)).astype(np.float32),
        "root_translation": rng.normal(size=(t, 3)).astype(np.float32),
        "fps": np.array(24.0),
    }


def _save(tmp_path, arrays, name="m.npz"):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _error(path) -> str:
    with pytest.raises(DlaInputError) as info:
        read_motion(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_golden_file_matches_a_raw_numpy_load(formats_dir):
    path = formats_dir / "examples" / "motion.npz"
    with np.load(path, allow_pickle=False) as raw:
        raw = {k: raw[k] for k in raw.files}
    m = read_motion(path)
    assert str(raw["format"]) == "dla.motion/1" and m.model == str(raw["model"])
    assert m.bone_labels == raw["bone_labels"].tolist()
    np.testing.assert_array_equal(m.rotations, raw["rotations"])
    np.testing.assert_array_equal(m.root_rotation, raw["root_rotation"])
    np.testing.assert_array_equal(m.root_translation, raw["root_translation"])
    assert m.fps == float(raw["fps"]) and m.num_frames == raw["rotations"].shape[0] >= 2


def test_round_trip_is_exact_and_pickle_free(tmp_path):
    a = _arrays(t=7, j=5)
    motion = Motion(a["bone_labels"].tolist(), a["rotations"], a["root_rotation"], a["root_translation"], 24.0)
    path = tmp_path / "clip.motion"  # any name: the writer must not append ".npz"
    write_motion(motion, path)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.motion"]
    with np.load(path, allow_pickle=False) as raw:  # a pickled array would raise here
        assert raw["bone_labels"].dtype.kind == "U"
        assert raw["rotations"].dtype == np.float32
        assert str(raw["format"]) == "dla.motion/1"
    back = read_motion(path)
    assert back.bone_labels == motion.bone_labels and back.fps == 24.0 and back.model == "anny"
    for name in ("rotations", "root_rotation", "root_translation"):
        got = getattr(back, name)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, getattr(motion, name))


def test_single_frame_and_zero_bones_are_valid(tmp_path):
    m = read_motion(_save(tmp_path, _arrays(t=1, j=0)))
    assert m.num_frames == 1 and m.bone_labels == [] and m.rotations.shape == (1, 0, 3)


def test_float64_and_integer_data_are_read_as_float32(tmp_path):
    a = _arrays()
    a["rotations"] = a["rotations"].astype(np.float64)
    a["root_translation"] = np.zeros((3, 3), np.int64)
    m = read_motion(_save(tmp_path, a))
    assert m.rotations.dtype == np.float32 and m.root_translation.dtype == np.float32


def _with(**changes):
    a = _arrays()
    for k, v in changes.items():
        if v is None:
            del a[k]
        else:
            a[k] = v
    return a


@pytest.mark.parametrize(
    "arrays, needle",
    [
        (_with(format=None), "missing 'format'"),
        (_with(format=np.array("dla.motion/2")), "'dla.motion/2' is not supported by this version"),
        (_with(format=np.array("dla.avatar/1")), "format is 'dla.avatar/1', expected 'dla.motion/1'"),
        (_with(fps=None), "missing array 'fps'"),
        (_with(rotations=None, root_rotation=None), "missing arrays 'rotations', 'root_rotation'"),
        (_with(model=np.array("smpl")), "model 'smpl' is not supported"),
        (_with(rotations=np.zeros((3, 4, 3), np.float32)), "rotations has shape (3, 4, 3), expected (*, 2, 3)"),
        (_with(rotations=np.zeros((3, 2, 4), np.float32)), "rotations has shape (3, 2, 4), expected (*, 2, 3)"),
        (_with(rotations=np.zeros((0, 2, 3), np.float32)), "no frames"),
        (_with(root_rotation=np.zeros((4, 3), np.float32)), "root_rotation has shape (4, 3), expected (3, 3)"),
        (_with(root_translation=np.zeros((3,), np.float32)), "root_translation has shape (3,), expected (3, 3)"),
        (_with(fps=np.array(0.0)), "fps = 0.0 must be > 0"),
        (_with(fps=np.array(-30.0)), "fps = -30.0 must be > 0"),
        (_with(fps=np.array([30.0, 30.0])), "fps has shape (2,), expected a scalar"),
        (_with(fps=np.array(np.inf)), "fps is not finite"),
        (_with(bone_labels=np.array([1, 2])), "bone_labels must be a unicode string array"),
        (_with(bone_labels=np.array(["a", "a"])), "bone_labels repeats 'a'"),
        (_with(bone_labels=np.array([["a", "b"]])), "bone_labels has shape (1, 2), expected (*,)"),
        (_with(rotations=np.full((3, 2, 3), "x")), "rotations must be a numeric array"),
    ],
)
def test_bad_arrays_are_one_line_errors(tmp_path, arrays, needle):
    assert needle in _error(_save(tmp_path, arrays))


@pytest.mark.parametrize("name", ["rotations", "root_rotation", "root_translation"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_values_are_rejected(tmp_path, name, bad):
    a = _arrays()
    a[name].reshape(-1)[1] = bad
    assert f"{name} has 1 non-finite value" in _error(_save(tmp_path, a))


def test_pickled_object_arrays_are_refused(tmp_path):
    a = _arrays()
    a["bone_labels"] = np.array(["a", "b"], dtype=object)
    assert "pickled" in _error(_save(tmp_path, a))


@pytest.mark.parametrize("keep", [0.5, 0.9])
def test_truncated_file(tmp_path, formats_dir, keep):
    data = (formats_dir / "examples" / "motion.npz").read_bytes()
    path = tmp_path / "cut.npz"
    path.write_bytes(data[: int(len(data) * keep)])
    assert "not a readable .npz file" in _error(path)


def test_missing_and_non_npz_files(tmp_path):
    assert "no such file" in _error(tmp_path / "none.npz")
    junk = tmp_path / "junk.npz"
    junk.write_text("hello")
    assert "not a readable .npz file" in _error(junk)


def test_writer_rejects_invalid_motion_and_leaves_no_file(tmp_path):
    a = _arrays()
    a["rotations"][0, 0, 0] = np.nan
    motion = Motion(a["bone_labels"].tolist(), a["rotations"], a["root_rotation"], a["root_translation"], 24.0)
    with pytest.raises(DlaInputError, match="non-finite"):
        write_motion(motion, tmp_path / "m.npz")
    assert list(tmp_path.iterdir()) == []


def test_summary(formats_dir):
    path = formats_dir / "examples" / "motion.npz"
    s = summarize_motion(path)
    with np.load(path) as raw:
        t, j = raw["rotations"].shape[:2]
        fps = float(raw["fps"])
        max_deg = np.degrees(np.linalg.norm(raw["rotations"].astype(np.float64), axis=-1).max())
        moving = int((np.ptp(raw["rotations"], axis=0).max(axis=-1) > 1e-6).sum())
    assert s["kind"] == "motion" and s["format"] == "dla.motion/1"
    assert s["frames"] == t and s["bones"] == j and s["fps"] == fps
    assert s["duration_s"] == pytest.approx((t - 1) / fps)
    assert s["max_rotation_deg"] == pytest.approx(max_deg, rel=1e-5)
    assert s["moving_bones"] == moving
    json.dumps(s)


def test_writer_is_byte_deterministic(tmp_path):
    import time

    motion = Motion(["root", "spine01"], np.ones((4, 2, 3), np.float32), np.zeros((4, 3)), np.zeros((4, 3)), 24.0)
    write_motion(motion, tmp_path / "a.npz")
    time.sleep(2.1)  # zip timestamps have 2 s resolution
    write_motion(motion, tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
