"""Reading the input photo, its mask and COCO keypoints JSON; the optional MediaPipe detector.

Oracles: arrays written with Pillow (and one 16-bit PNG written byte by byte here with zlib, an
encoder independent of Pillow), compared with what was written; the real RGBA photos.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dlacli.errors import DlaInputError
from dlacli.io.photo import MAX_SIDE, read_coco_keypoints, read_coco_keypoints_3d, read_photo

KP_DIR = Path(__file__).resolve().parents[1] / "data" / "keypoints"


def _rgba(h=80, w=96, seed=0):
    rng = np.random.default_rng(seed)
    arr = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
    arr[..., 3] = 0
    arr[20:60, 30:70, 3] = 255
    return arr


def _png16(path: Path, arr: np.ndarray) -> None:
    """Minimal PNG encoder: 16-bit grey (C=1), RGB (3) or RGBA (4), filter 0 on every row."""
    h, w, c = arr.shape
    colour_type = {1: 0, 3: 2, 4: 6}[c]
    raw = b"".join(b"\x00" + arr[y].astype(">u2").tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


def test_rgba_gives_rgb_and_alpha_mask(tmp_path):
    arr = _rgba()
    Image.fromarray(arr, "RGBA").save(tmp_path / "p.png")
    img, mask, kp = read_photo(tmp_path / "p.png")
    assert img.shape == (80, 96, 3) and img.dtype == np.float32 and kp is None
    np.testing.assert_allclose(img, arr[..., :3] / 255.0, atol=1e-6)  # colour as stored
    np.testing.assert_array_equal(mask, arr[..., 3] / 255.0)


def test_opaque_alpha_is_no_mask_and_rgb_jpeg_works(tmp_path):
    arr = _rgba()
    arr[..., 3] = 255
    Image.fromarray(arr, "RGBA").save(tmp_path / "p.png")
    assert read_photo(tmp_path / "p.png")[1] is None
    smooth = np.zeros((80, 96, 3), np.uint8)
    smooth[..., 0] = np.arange(96, dtype=np.uint8)[None] * 2
    smooth[..., 1] = 128
    smooth[..., 2] = np.arange(80, dtype=np.uint8)[:, None] * 3
    Image.fromarray(smooth).save(tmp_path / "p.jpg", quality=95)
    img, mask, _ = read_photo(tmp_path / "p.jpg")
    assert mask is None and np.abs(img - smooth / 255.0).max() < 0.03  # lossy, but close


def test_all_transparent_is_an_empty_mask_error(tmp_path):
    arr = _rgba()
    arr[..., 3] = 0
    Image.fromarray(arr, "RGBA").save(tmp_path / "p.png")
    with pytest.raises(DlaInputError, match=r"p\.png: empty mask"):
        read_photo(tmp_path / "p.png")


def test_grey_palette_and_grey_alpha(tmp_path):
    grey = np.tile(np.arange(96, dtype=np.uint8)[None] * 2, (80, 1))
    Image.fromarray(grey, "L").save(tmp_path / "g.png")
    img, mask, _ = read_photo(tmp_path / "g.png")
    assert mask is None
    for c in range(3):
        np.testing.assert_allclose(img[..., c], grey / 255.0, atol=1e-6)
    pal = Image.fromarray(grey, "L").convert("P")
    pal.save(tmp_path / "pal.png")
    img, _, _ = read_photo(tmp_path / "pal.png")
    np.testing.assert_allclose(img[..., 0], grey / 255.0, atol=1e-6)
    la = np.stack([grey, _rgba()[..., 3]], -1)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    img, mask, _ = read_photo(tmp_path / "la.png")
    np.testing.assert_array_equal(mask, la[..., 1] / 255.0)


def test_palette_with_transparency_gives_a_mask(tmp_path):
    idx = np.zeros((80, 96), np.uint8)
    idx[10:50, 10:50] = 1
    im = Image.fromarray(idx, "P")
    im.putpalette([0, 0, 0, 200, 100, 50] + [0] * 762)
    im.save(tmp_path / "p.png", transparency=0)
    img, mask, _ = read_photo(tmp_path / "p.png")
    np.testing.assert_array_equal(mask, (idx == 1).astype(np.float32))
    np.testing.assert_allclose(img[20, 20], np.array([200, 100, 50]) / 255.0, atol=1e-6)


def test_16_bit_pngs(tmp_path):
    grey16 = np.tile(np.linspace(0, 65535, 96).astype(np.uint16)[None], (80, 1))
    Image.fromarray(grey16.astype(np.uint16)).save(tmp_path / "g16.png")  # Pillow mode I;16
    img, mask, _ = read_photo(tmp_path / "g16.png")
    assert mask is None
    np.testing.assert_allclose(img[..., 1], grey16 / 65535.0, atol=1e-6)  # full 16-bit precision
    rgba16 = np.zeros((80, 96, 4), np.uint16)
    rgba16[..., 0] = grey16
    rgba16[..., 2] = 65535 - grey16
    rgba16[20:60, 30:70, 3] = 65535
    _png16(tmp_path / "c16.png", rgba16)
    img, mask, _ = read_photo(tmp_path / "c16.png")
    # Pillow reads 16-bit colour at 8 bits per channel: equal within 1/255
    np.testing.assert_allclose(img[..., 0], grey16 / 65535.0, atol=1.0 / 255 + 1e-6)
    np.testing.assert_allclose(img[..., 2], 1 - grey16 / 65535.0, atol=1.0 / 255 + 1e-6)
    np.testing.assert_array_equal(mask, (rgba16[..., 3] > 0).astype(np.float32))


def test_exif_orientation_is_applied(tmp_path):
    arr = np.zeros((70, 100, 3), np.uint8)
    arr[:10, :20] = 255  # a white block in the top-left corner
    im = Image.fromarray(arr)
    exif = im.getexif()
    exif[0x0112] = 6  # "rotate 90 CW to display"
    im.save(tmp_path / "r.jpg", exif=exif, quality=100)
    img, _, _ = read_photo(tmp_path / "r.jpg")
    assert img.shape == (100, 70, 3)  # displayed upright: width and height swap
    assert img[:20, -10:].mean() > 0.8 and img[:20, :10].mean() < 0.2  # block now top-right


def test_tiny_missing_and_corrupt_files(tmp_path):
    Image.fromarray(np.zeros((40, 300, 3), np.uint8)).save(tmp_path / "tiny.png")
    with pytest.raises(DlaInputError, match=r"tiny\.png: image is 300x40 px: need at least 64"):
        read_photo(tmp_path / "tiny.png")
    with pytest.raises(DlaInputError, match=r"nope\.png: no such file"):
        read_photo(tmp_path / "nope.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(DlaInputError, match=r"bad\.png: not a readable image"):
        read_photo(tmp_path / "bad.png")
    good = tmp_path / "good.png"
    Image.fromarray(_rgba(), "RGBA").save(good)
    trunc = tmp_path / "trunc.png"
    trunc.write_bytes(good.read_bytes()[:200])
    with pytest.raises(DlaInputError, match=r"trunc\.png: not a readable image"):
        read_photo(trunc)


def test_huge_image_is_downscaled_with_keypoints_and_a_note(tmp_path):
    w, h = MAX_SIDE + 808, 96  # 9000 x 96
    arr = np.zeros((h, w, 4), np.uint8)
    arr[..., :3] = 128
    arr[20:80, 1000:5000, 3] = 255
    Image.fromarray(arr, "RGBA").save(tmp_path / "big.png")
    kp = np.zeros((17, 3))
    kp[:, 0] = np.linspace(1000, 4999, 17)
    kp[:, 1] = 50
    kp[:, 2] = 2
    (tmp_path / "k.json").write_text(json.dumps({"keypoints": kp.reshape(-1).tolist()}))
    notes: list[str] = []
    img, mask, k = read_photo(tmp_path / "big.png", keypoints_path=tmp_path / "k.json", notes=notes)
    s = MAX_SIDE / w
    assert img.shape == (round(h * s), MAX_SIDE, 3)
    assert len(notes) == 1 and "downscaled to 8192x87" in notes[0] and "big.png" in notes[0]
    np.testing.assert_allclose(k[:, 0], kp[:, 0] * s, rtol=1e-6)
    np.testing.assert_allclose(k[:, 1], 50 * round(h * s) / h, rtol=1e-6)
    # the mask keeps its area (box filter) and position
    assert abs(mask.sum() - 60 * 4000 * s * (round(h * s) / h)) / (60 * 4000 * s * s) < 0.02
    assert mask[50, int(3000 * s)] == pytest.approx(1.0)


def test_separate_mask_file(tmp_path):
    Image.fromarray(_rgba()[..., :3]).save(tmp_path / "p.png")
    m = np.zeros((80, 96), np.uint8)
    m[10:30, 10:30] = 255
    Image.fromarray(m).save(tmp_path / "m.png")
    _, mask, _ = read_photo(tmp_path / "p.png", mask_path=tmp_path / "m.png")
    np.testing.assert_array_equal(mask, m / 255.0)
    Image.fromarray(m[:50]).save(tmp_path / "m2.png")
    with pytest.raises(DlaInputError, match=r"m2\.png: mask is 96x50 px, the photo 96x80"):
        read_photo(tmp_path / "p.png", mask_path=tmp_path / "m2.png")
    Image.fromarray(np.zeros_like(m)).save(tmp_path / "m3.png")
    with pytest.raises(DlaInputError, match=r"m3\.png: empty mask"):
        read_photo(tmp_path / "p.png", mask_path=tmp_path / "m3.png")


# ---------------------------------------------------------------------------------------------
# keypoints JSON


def test_coco_keypoints_json_single_and_list(tmp_path):
    vals = np.arange(51, dtype=float).reshape(17, 3)
    vals[:, 2] = [0, 1, 2] * 5 + [2, 2]
    (tmp_path / "a.json").write_text(json.dumps({"keypoints": vals.reshape(-1).tolist(), "x": 1}))
    kp = read_coco_keypoints(tmp_path / "a.json")
    np.testing.assert_array_equal(kp[:, :2], vals[:, :2])
    np.testing.assert_array_equal(kp[:, 2], (vals[:, 2] > 0).astype(np.float32))
    fewer = vals.copy()
    fewer[:10, 2] = 0
    anns = [{"keypoints": fewer.reshape(-1).tolist()}, {"keypoints": vals.reshape(-1).tolist()}]
    (tmp_path / "b.json").write_text(json.dumps(anns))
    np.testing.assert_array_equal(read_coco_keypoints(tmp_path / "b.json"), kp)  # most visible


@pytest.mark.parametrize(
    "content,problem",
    [
        ('{"keypoints": [1, 2, 2]}', "'keypoints' must be a list of 51 numbers .* got 3"),
        ('{"keypoints": [' + ", ".join(["1"] * 50) + ", NaN]}", "'keypoints' contains NaN or infinite"),
        ('{"points": []}', "expected an object with a 'keypoints' list"),
        ("[]", "empty list"),
        ('{"keypoints": [' + ", ".join(["1"] * 50) + ', "a"]}', "'keypoints' must contain numbers only"),
        ('{"keypoints": [' + ", ".join(["1"] * 50) + ", 3]}", "visibility values must be 0, 1 or 2"),
        ("{not json", "not valid JSON"),
    ],
)
def test_bad_keypoints_json(tmp_path, content, problem):
    (tmp_path / "k.json").write_text(content)
    with pytest.raises(DlaInputError, match=r"k\.json: (annotation 0: )?" + problem):
        read_coco_keypoints(tmp_path / "k.json")


def test_keypoints_3d_read_from_the_chosen_annotation(tmp_path):
    vals = np.tile([10.0, 20.0, 2.0], (17, 1))
    vals[4, 2] = 0  # not labelled: its 3D point gets confidence 0 too
    xyz = np.arange(51, dtype=np.float64).reshape(17, 3) / 100.0 - 0.2
    anns = [
        {"keypoints": [0.0] * 51},
        {"keypoints": vals.reshape(-1).tolist(), "keypoints_3d": xyz.reshape(-1).tolist()},
    ]
    (tmp_path / "k.json").write_text(json.dumps(anns))
    lm = read_coco_keypoints_3d(tmp_path / "k.json")
    assert lm.shape == (17, 4) and lm.dtype == np.float32
    np.testing.assert_allclose(lm[:, :3], xyz, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(lm[:, 3], (np.arange(17) != 4).astype(np.float32))
    (tmp_path / "old.json").write_text(json.dumps({"keypoints": vals.reshape(-1).tolist()}))
    assert read_coco_keypoints_3d(tmp_path / "old.json") is None  # old files: no 3D prior


@pytest.mark.parametrize(
    "xyz,problem",
    [
        ("[1, 2, 3]", "'keypoints_3d' must be a list of 51 numbers .* got 3"),
        ('"abc"', "'keypoints_3d' must be a list of 51 numbers .* got str"),
        ("[" + ", ".join(["0.1"] * 50) + ", NaN]", "'keypoints_3d' contains NaN or infinite"),
        ("[" + ", ".join(["0.1"] * 50) + ", Infinity]", "'keypoints_3d' contains NaN or infinite"),
        ("[" + ", ".join(["0.1"] * 50) + ', "a"]', "'keypoints_3d' must contain numbers only"),
        ("[" + ", ".join(["0.1"] * 50) + ", true]", "'keypoints_3d' must contain numbers only"),
        ("[" + ", ".join(["0.1"] * 50) + ", 12.5]", r"'keypoints_3d' holds a coordinate beyond \+-10 m"),
        ("[" + ", ".join(["0.1"] * 50) + ", " + "9" * 400 + "]", "'keypoints_3d' holds a number too large"),
    ],
)
def test_bad_keypoints_3d(tmp_path, xyz, problem):
    kp = ", ".join(["1"] * 51)
    (tmp_path / "k.json").write_text('{"keypoints": [' + kp + '], "keypoints_3d": ' + xyz + "}")
    with pytest.raises(DlaInputError, match=r"k\.json: " + problem):
        read_coco_keypoints_3d(tmp_path / "k.json")


def test_shipped_keypoints_carry_3d_landmarks():
    """The stored test keypoints have MediaPipe's world landmarks (tests/data/README.md): metres,
    hip-centred, y down, and the person's left on +x for these front-facing people."""
    for path in sorted(KP_DIR.glob("*.json")):
        lm = read_coco_keypoints_3d(path)
        assert lm is not None, path
        np.testing.assert_allclose(lm[11:13, :3].mean(0), 0.0, atol=0.01)  # origin between the hips
        assert lm[[15, 16], 1].min() > lm[[5, 6], 1].max() + 0.3  # ankles below the shoulders (y down)
        assert lm[5, 0] > lm[6, 0]  # left shoulder on the camera's right


def test_keypoints_far_outside_the_photo(tmp_path):
    Image.fromarray(_rgba(), "RGBA").save(tmp_path / "p.png")
    vals = np.full((17, 3), 2.0)
    vals[:, :2] = 5000.0
    (tmp_path / "k.json").write_text(json.dumps({"keypoints": vals.reshape(-1).tolist()}))
    with pytest.raises(DlaInputError, match=r"k\.json: keypoints lie far outside"):
        read_photo(tmp_path / "p.png", keypoints_path=tmp_path / "k.json")


def test_real_photos_and_shipped_keypoints(third_party_data):
    for path in sorted((third_party_data / "images").glob("*.png")):
        img, mask, kp = read_photo(path, keypoints_path=KP_DIR / f"{path.stem}.json")
        assert img.shape[:2] == mask.shape and kp.shape == (17, 3)
        assert 0.1 < (mask > 0.5).mean() < 0.5
        inside = mask[
            np.clip(kp[:, 1].astype(int), 0, mask.shape[0] - 1), np.clip(kp[:, 0].astype(int), 0, mask.shape[1] - 1)
        ]
        assert (inside > 0.5).mean() >= 0.8  # the detector's keypoints lie on the person


# ---------------------------------------------------------------------------------------------
# detector


def test_detect_without_mediapipe_says_what_to_do(monkeypatch):
    from dlacli.io.detect import detect_person

    monkeypatch.setitem(sys.modules, "mediapipe", None)  # makes `import mediapipe` fail
    with pytest.raises(DlaInputError, match=r"--mask/--keypoints: .*pip install 'dla\[detect\]'"):
        detect_person(np.zeros((64, 64, 3), np.float32))


# MediaPipe's documented BlazePose landmark names, in index order
BLAZEPOSE_NAMES = (
    "nose left_eye_inner left_eye left_eye_outer right_eye_inner right_eye right_eye_outer "
    "left_ear right_ear mouth_left mouth_right left_shoulder right_shoulder left_elbow "
    "right_elbow left_wrist right_wrist left_pinky right_pinky left_index right_index left_thumb "
    "right_thumb left_hip right_hip left_knee right_knee left_ankle right_ankle left_heel "
    "right_heel left_foot_index right_foot_index"
).split()


def test_detect_maps_blazepose_to_coco_by_name(monkeypatch):
    """A stand-in mediapipe returns landmark i at (i / 40, i / 80) with visibility i / 33."""
    import types

    from dlacli.body.keypoints import COCO_NAMES
    from dlacli.io.detect import detect_person

    class _Pose:
        def __init__(self, **kwargs):
            assert kwargs["static_image_mode"] is True

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def process(self, img):
            assert img.dtype == np.uint8 and img.shape == (100, 120, 3)
            lms = [types.SimpleNamespace(x=i / 40, y=i / 80, visibility=i / 33) for i in range(33)]
            world = [types.SimpleNamespace(x=i / 100, y=-i / 50, z=i / 25, visibility=i / 33) for i in range(33)]
            seg = np.zeros(img.shape[:2], np.float32)
            seg[10:20] = 1.0
            return types.SimpleNamespace(
                pose_landmarks=types.SimpleNamespace(landmark=lms),
                pose_world_landmarks=types.SimpleNamespace(landmark=world),
                segmentation_mask=seg,
            )

    fake = types.SimpleNamespace(solutions=types.SimpleNamespace(pose=types.SimpleNamespace(Pose=_Pose)))
    monkeypatch.setitem(sys.modules, "mediapipe", fake)
    det = detect_person(np.zeros((100, 120, 3), np.float32))
    mask, kp = det.mask, det.keypoints
    assert mask.shape == (100, 120) and mask[15].min() == 1.0 and mask[50].max() == 0.0
    assert det.world.shape == (17, 4)
    for k, name in enumerate(COCO_NAMES):
        i = BLAZEPOSE_NAMES.index(name)
        np.testing.assert_allclose(kp[k], [i / 40 * 120, i / 80 * 100, i / 33], rtol=1e-5)
        np.testing.assert_allclose(det.world[k], [i / 100, -i / 50, i / 25, i / 33], rtol=1e-5)
