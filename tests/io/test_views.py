"""View folders: analytic camera checks, independent parsing of written folders, image variants
and every bad-input case (formats/views.md)."""

from __future__ import annotations

import json
import shutil
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from dlacli.errors import DlaInputError
from dlacli.io.body import body_from_dict, body_to_dict
from dlacli.io.views import read_views, summarize_views, write_views
from dlacli.types import Cameras, ViewSet

BODY = {
    "format": "dla.body/1",
    "model": "anny",
    "phenotype": {"gender": 0.5, "age": 0.5, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5},
}
W, H, F = 8, 6, 10.0


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] camera-to-world, OpenGL axes (+X right, +Y up, looking down -Z)."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, -fwd, eye
    return m


def write_png(path, arr: np.ndarray, bit_depth: int) -> None:
    """A minimal PNG encoder (independent of Pillow): gray, gray+alpha, RGB or RGBA; 8 or 16 bit."""
    arr = arr if arr.ndim == 3 else arr[..., None]
    h, w, c = arr.shape
    color_type = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    dtype = ">u2" if bit_depth == 16 else "u1"
    raw = b"".join(b"\x00" + arr[y].astype(dtype).tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


def make_folder(tmp_path, frames=None, top=None, body=True, images=True, name="views"):
    """A hand-written view folder: two cameras on a circle of radius 3 looking at the origin."""
    folder = tmp_path / name
    (folder / "images").mkdir(parents=True)
    if frames is None:
        frames = [
            {"file_path": "images/a.png", "transform_matrix": look_at((0, -3, 0)).tolist()},
            {"file_path": "images/b.png", "transform_matrix": look_at((3, 0, 0)).tolist(), "time": 4},
        ]
    meta = {"camera_model": "OPENCV", "w": W, "h": H, "fl_x": F, "fl_y": F, "cx": W / 2, "cy": H / 2, "frames": frames}
    meta.update(top or {})
    (folder / "transforms.json").write_text(json.dumps(meta))
    if images:
        rgba = np.zeros((H, W, 4), np.uint8)
        rgba[..., 0] = 200
        rgba[2:5, 3:6, 3] = 255
        for f in frames:
            if isinstance(f, dict) and isinstance(f.get("file_path"), str) and "mask_path" not in f:
                Image.fromarray(rgba, "RGBA").save(folder / f["file_path"])
    if body:
        (folder / "body.json").write_text(json.dumps(BODY))
    return folder


def project(cams: Cameras, point) -> np.ndarray:
    """[C, 2] pixel coordinates of a world point, computed from viewmats and Ks."""
    p = np.append(np.asarray(point, float), 1.0)
    cam = cams.viewmats.double().numpy() @ p  # [C, 4]
    uvw = np.einsum("cij,cj->ci", cams.Ks.double().numpy(), cam[:, :3])
    return uvw[:, :2] / uvw[:, 2:3]


def _error(fn, *args, **kw) -> str:
    with pytest.raises(DlaInputError) as info:
        fn(*args, **kw)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def test_cameras_project_known_points(tmp_path):
    vs = read_views(make_folder(tmp_path))
    cams = vs.cameras
    assert (cams.width, cams.height) == (W, H)
    np.testing.assert_allclose(project(cams, (0, 0, 0)), [[W / 2, H / 2]] * 2, atol=1e-5)
    # (0, 0, 1) is 1 m above the origin at depth 3: F/3 pixels above the centre in both views
    np.testing.assert_allclose(project(cams, (0, 0, 1)), [[W / 2, H / 2 - F / 3]] * 2, atol=1e-5)
    # camera 0 at -Y looks along +Y: world +X is image right; camera 1 at +X: world +Y is image right
    np.testing.assert_allclose(project(cams, (1, 0, 0))[0], [W / 2 + F / 3, H / 2], atol=1e-5)
    np.testing.assert_allclose(project(cams, (0, 1, 0))[1], [W / 2 + F / 3, H / 2], atol=1e-5)
    assert vs.times == [None, 4] and vs.file_paths == ["images/a.png", "images/b.png"]
    assert body_to_dict(vs.body)["phenotype"] == BODY["phenotype"]


def _viewset(per_frame_k=False):
    rng = np.random.default_rng(0)
    c2w = np.stack([look_at((3 * np.cos(a), 3 * np.sin(a), 0.3)) for a in (0.0, 1.0, 2.5)])
    fx = [F, F * 1.1, F * 0.9] if per_frame_k else F
    cams = Cameras.from_c2w_opengl(c2w, fx, F, W / 2 + 0.25, H / 2, W, H)
    images = rng.uniform(size=(3, H, W, 3)).astype(np.float32)
    masks = (rng.uniform(size=(3, H, W)) > 0.5).astype(np.float32)
    return c2w, ViewSet(images, masks, cams, body_from_dict(BODY, "t"), ["x"] * 3, [0, None, 7], {"note": "hi"})


@pytest.mark.parametrize("per_frame_k", [False, True])
def test_written_folder_parses_independently(tmp_path, per_frame_k):
    c2w, vs = _viewset(per_frame_k)
    write_views(vs, tmp_path / "out")
    meta = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and (meta["w"], meta["h"]) == (W, H)
    assert meta["dla"] == {"format": "dla.views/1", "note": "hi"}
    for i, frame in enumerate(meta["frames"]):
        k = frame if per_frame_k else meta
        assert ("fl_x" in frame) == per_frame_k and ("fl_x" in meta) != per_frame_k
        assert k["fl_x"] == pytest.approx([F, F * 1.1, F * 0.9][i] if per_frame_k else F, rel=1e-6)
        assert (k["fl_y"], k["cx"], k["cy"]) == pytest.approx((F, W / 2 + 0.25, H / 2), rel=1e-6)
        # viewmats are float32: the written c2w inverts the rounded w2c, so its translation is off
        # by <= eps32 |t| = 3.6e-7 at 3 m (rotation entries by <= eps32 / 2)
        np.testing.assert_allclose(frame["transform_matrix"], c2w[i], atol=1e-6)
        assert frame.get("time") == vs.times[i]
        assert not frame["file_path"].startswith("/")
        img = np.asarray(Image.open(tmp_path / "out" / frame["file_path"]))
        assert img.dtype == np.uint8 and img.shape == (H, W, 4)
        np.testing.assert_array_equal(img[..., :3], np.round(vs.images[i] * 255))
        np.testing.assert_array_equal(img[..., 3], np.round(vs.masks[i] * 255))
    assert json.loads((tmp_path / "out" / "body.json").read_text()) == body_to_dict(vs.body)


def test_round_trip(tmp_path):
    _, vs = _viewset(per_frame_k=True)
    write_views(vs, tmp_path / "out")
    back = read_views(tmp_path / "out")
    np.testing.assert_allclose(back.images, vs.images, atol=0.5 / 255 + 1e-6)  # 8-bit PNG: rounding
    np.testing.assert_array_equal(back.masks, vs.masks)
    np.testing.assert_allclose(back.cameras.viewmats, vs.cameras.viewmats, atol=1e-5)
    np.testing.assert_allclose(back.cameras.Ks, vs.cameras.Ks, rtol=1e-6)
    assert back.times == vs.times and back.extra == vs.extra
    assert body_to_dict(back.body) == body_to_dict(vs.body)


def test_write_replaces_a_folder_atomically(tmp_path):
    _, vs = _viewset()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "stale.txt").write_text("old")
    write_views(vs, tmp_path / "out")
    assert not (tmp_path / "out" / "stale.txt").exists()
    vs.extra = {"bad": object()}
    with pytest.raises(DlaInputError, match="extra"):
        write_views(vs, tmp_path / "other")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_real_photo_alpha_is_the_mask(tmp_path, third_party_data):
    photo = third_party_data / "images" / "pexels-marta-wave-6437749.png"
    folder = tmp_path / "real"
    (folder / "images").mkdir(parents=True)
    shutil.copy(photo, folder / "images" / "p.png")
    w, h = Image.open(photo).size
    frame = {"file_path": "images/p", "transform_matrix": look_at((0, -3, 0)).tolist()}  # instant-ngp: no suffix
    (folder / "transforms.json").write_text(
        json.dumps({"w": w, "h": h, "fl_x": 500, "fl_y": 500, "cx": w / 2, "cy": h / 2, "frames": [frame]})
    )
    vs = read_views(folder, require_body=False)
    ref = np.asarray(Image.open(photo).convert("RGBA"), dtype=np.float64) / 255
    np.testing.assert_allclose(vs.masks[0], ref[..., 3], atol=1e-6)
    np.testing.assert_allclose(vs.images[0], ref[..., :3], atol=1e-6)
    assert vs.body is None and 0.05 < vs.masks[0].mean() < 0.95
    s = summarize_views(folder)
    assert s["body"].startswith("missing") and s["format"].startswith("nerfstudio")


def test_rgb_with_16_bit_gray_mask_and_16_bit_colour(tmp_path):
    rng = np.random.default_rng(3)
    frames = [
        {"file_path": "images/a.png", "mask_path": "masks/a.png", "transform_matrix": look_at((0, -3, 0)).tolist()},
        {"file_path": "images/b.png", "mask_path": "masks/b.png", "transform_matrix": look_at((3, 0, 0)).tolist()},
        {"file_path": "images/c.png", "transform_matrix": look_at((0, 3, 0)).tolist()},
    ]
    folder = make_folder(tmp_path, frames, images=False)
    (folder / "masks").mkdir()
    rgb16 = rng.integers(0, 65536, size=(H, W, 3))
    mask16 = rng.integers(0, 65536, size=(H, W))
    write_png(folder / "images" / "a.png", rgb16, 16)
    write_png(folder / "masks" / "a.png", mask16, 16)
    rgb8 = rng.integers(0, 256, size=(H, W, 3))
    la8 = rng.integers(1, 256, size=(H, W, 2))  # gray+alpha mask: alpha is the mask
    write_png(folder / "images" / "b.png", rgb8, 8)
    write_png(folder / "masks" / "b.png", la8, 8)
    rgba16 = rng.integers(0, 65536, size=(H, W, 4))
    write_png(folder / "images" / "c.png", rgba16, 16)
    vs = read_views(folder)
    np.testing.assert_allclose(vs.masks[0], mask16 / 65535, atol=1e-6)  # 16-bit gray: full precision
    np.testing.assert_allclose(vs.images[0], rgb16 / 65535, atol=1 / 255)  # 16-bit colour: 8-bit precision
    np.testing.assert_allclose(vs.images[1], rgb8 / 255, atol=1e-6)
    np.testing.assert_allclose(vs.masks[1], la8[..., 1] / 255, atol=1e-6)
    np.testing.assert_allclose(vs.images[2], rgba16[..., :3] / 65535, atol=1 / 255)
    np.testing.assert_allclose(vs.masks[2], rgba16[..., 3] / 65535, atol=1 / 255)
    assert vs.images.dtype == np.float32 and vs.images.shape == (3, H, W, 3)


def test_per_frame_intrinsics_override_the_top_level(tmp_path):
    frames = [
        {"file_path": "images/a.png", "transform_matrix": look_at((0, -3, 0)).tolist(), "fl_x": 20.0, "cx": 3.0},
        {"file_path": "images/b.png", "transform_matrix": look_at((3, 0, 0)).tolist()},
    ]
    vs = read_views(make_folder(tmp_path, frames))
    ks = vs.cameras.Ks.numpy()
    assert (ks[0, 0, 0], ks[0, 0, 2], ks[0, 1, 1]) == (20.0, 3.0, F)
    assert (ks[1, 0, 0], ks[1, 0, 2]) == (F, W / 2)
    np.testing.assert_allclose(project(vs.cameras, (1, 0, 0))[0], [3.0 + 20.0 / 3, H / 2], atol=1e-5)


def test_absent_camera_model_and_zero_distortion_are_accepted(tmp_path):
    folder = make_folder(tmp_path, top={"k1": 0.0, "p2": 0})
    meta = json.loads((folder / "transforms.json").read_text())
    del meta["camera_model"]
    (folder / "transforms.json").write_text(json.dumps(meta))
    assert len(read_views(folder)) == 2


def _frame(**kw):
    f = {"file_path": "images/a.png", "transform_matrix": look_at((0, -3, 0)).tolist()}
    f.update(kw)
    return f


@pytest.mark.parametrize(
    "frames, top, needle",
    [
        (None, {"camera_model": "OPENCV_FISHEYE"}, "camera_model 'OPENCV_FISHEYE' is not supported"),
        (None, {"k1": 0.1}, "lens distortion k1 = 0.1 is not supported"),
        ([_frame(p1=-0.01)], None, "frames[0]: lens distortion p1"),
        (
            [_frame(transform_matrix=np.diag([1.0, 1, 0, 1]).tolist())],
            None,
            "frames[0].transform_matrix is not invertible",
        ),
        (
            [_frame(transform_matrix=np.diag([1.0, 1, -1, 1]).tolist())],
            None,
            "not a rigid camera pose (rotation part: determinant -1",
        ),
        ([_frame(transform_matrix=np.diag([2.0, 2, 2, 1]).tolist())], None, "not a rigid camera pose"),
        ([_frame(transform_matrix=np.eye(3).tolist())], None, "transform_matrix has shape (3, 3), expected (4, 4)"),
        (
            [_frame(transform_matrix=(np.eye(4) + np.diag([0, 0, 0, 1.0])).tolist())],
            None,
            "last row is [0.0, 0.0, 0.0, 2.0]",
        ),
        ([_frame(time=1.5)], None, "frames[0].time = 1.5 must be a non-negative integer"),
        ([_frame(time=-1)], None, "must be a non-negative integer"),
        ([_frame(w=10)], None, "different image sizes 8x6, 10x6"),
        ([_frame(fl_x=-5)], None, "frames[0].fl_x = -5.0 must be > 0"),
        ([{"transform_matrix": np.eye(4).tolist()}], None, "frames[0]: missing 'file_path'"),
        ([{"file_path": "images/a.png"}], None, "frames[0]: missing 'transform_matrix'"),
        ([], None, "'frames' must be a non-empty list"),
        (None, {"dla": {"format": "dla.views/2"}}, "'dla.views/2' is not supported by this version"),
        (None, {"dla": {"format": "other/1"}}, "expected 'dla.views/1'"),
    ],
)
def test_bad_transforms_are_one_line_errors(tmp_path, frames, top, needle):
    if frames is not None and len(frames) == 1 and frames[0].get("w") == 10:
        frames = frames + [_frame(file_path="images/b.png")]
    folder = make_folder(tmp_path, frames, top)
    msg = _error(read_views, folder)
    assert needle in msg and "transforms.json" in msg


def test_nan_and_missing_intrinsics(tmp_path):
    folder = make_folder(tmp_path)
    text = (folder / "transforms.json").read_text()
    meta = json.loads(text)
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    (folder / "transforms.json").write_text(json.dumps(meta))  # writes the NaN literal
    assert "frames[1].transform_matrix has 1 non-finite value" in _error(read_views, folder)
    del meta["fl_y"]
    meta["frames"][1]["transform_matrix"][0][3] = 0.0
    (folder / "transforms.json").write_text(json.dumps(meta))
    assert "frames[0]: missing 'fl_y'" in _error(read_views, folder)
    (folder / "transforms.json").write_text(text[: len(text) // 2])
    assert "transforms.json: not valid JSON" in _error(read_views, folder)


def test_image_problems_name_the_file(tmp_path):
    folder = make_folder(tmp_path)
    a = folder / "images" / "a.png"
    Image.fromarray(np.full((H, W + 1, 4), 255, np.uint8)).save(a)
    msg = _error(read_views, folder)
    assert str(a) in msg and "image is 9x6 but transforms.json declares 8x6" in msg

    Image.fromarray(np.zeros((H, W, 4), np.uint8)).save(a)
    msg = _error(read_views, folder)
    assert str(a) in msg and "person mask is empty" in msg

    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(a)
    assert "no alpha channel and its frame has no mask_path" in _error(read_views, folder)

    good = (folder / "images" / "b.png").read_bytes()
    a.write_bytes(good[: len(good) // 2])
    msg = _error(read_views, folder)
    assert str(a) in msg and "not a readable image" in msg

    a.unlink()
    msg = _error(read_views, folder)
    assert str(a) in msg and "image file not found" in msg


def test_mask_problems_name_the_mask(tmp_path):
    folder = make_folder(tmp_path, [_frame(mask_path="m.png")])
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(folder / "images" / "a.png")
    m = folder / "m.png"
    Image.fromarray(np.zeros((H, W), np.uint8)).save(m)
    assert f"{m}: the person mask is empty" in _error(read_views, folder)
    Image.fromarray(np.full((H - 1, W), 255, np.uint8)).save(m)
    assert f"{m}: image is 8x5" in _error(read_views, folder)
    Image.fromarray(np.full((H, W, 3), 255, np.uint8)).save(m)
    assert "must be grayscale or carry an alpha channel" in _error(read_views, folder)


def test_body_is_required_by_default(tmp_path):
    folder = make_folder(tmp_path, body=False)
    assert "body.json: missing" in _error(read_views, folder)
    vs = read_views(folder, require_body=False)
    assert vs.body is None and len(vs) == 2
    s = summarize_views(folder)
    assert s["body"].startswith("missing") and s["views"] == 2
    (folder / "body.json").write_text(json.dumps({**BODY, "format": "dla.body/9"}))
    assert "'dla.body/9' is not supported" in _error(read_views, folder, require_body=False)


def test_missing_folder_and_transforms(tmp_path):
    assert "no such view folder" in _error(read_views, tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    assert "transforms.json: no such file" in _error(read_views, tmp_path / "empty")


def test_golden_folder(formats_dir):
    folder = formats_dir / "examples" / "views"
    meta = json.loads((folder / "transforms.json").read_text())
    vs = read_views(folder)
    assert len(vs) == len(meta["frames"]) and meta["dla"]["format"] == "dla.views/1"
    for i, frame in enumerate(meta["frames"]):
        img = np.asarray(Image.open(folder / frame["file_path"]).convert("RGBA"), dtype=np.float64) / 255
        assert img.shape == (meta["h"], meta["w"], 4)
        np.testing.assert_allclose(vs.masks[i], img[..., 3], atol=1e-6)
        np.testing.assert_allclose(vs.cameras.c2w_opengl()[i], frame["transform_matrix"], atol=1e-6)
    # every golden camera looks at the origin: it projects to the principal point
    np.testing.assert_allclose(project(vs.cameras, (0, 0, 0)), [[meta["cx"], meta["cy"]]] * len(vs), atol=1e-5)
    s = summarize_views(folder)
    assert s["kind"] == "views" and s["format"] == "dla.views/1" and s["body"] == "present"
    json.dumps(s)


def test_palette_jpeg_and_one_bit_inputs(tmp_path):
    frames = [
        {"file_path": "images/a.png", "transform_matrix": look_at((0, -3, 0)).tolist()},
        {
            "file_path": "images/b.jpg",
            "mask_path": "images/b_mask.png",
            "transform_matrix": look_at((3, 0, 0)).tolist(),
        },
    ]
    folder = make_folder(tmp_path, frames, images=False)
    pal = Image.new("P", (W, H), 0)
    pal.putpalette([0, 0, 0, 255, 0, 0] + [0] * 762)
    pal.paste(1, (2, 1, 5, 4))
    pal.save(folder / "images" / "a.png", transparency=0)  # index 0 transparent, index 1 opaque red
    Image.fromarray(np.full((H, W, 3), 128, np.uint8)).save(folder / "images" / "b.jpg", quality=95)
    bits = np.zeros((H, W), bool)
    bits[:3] = True
    Image.fromarray(bits).save(folder / "images" / "b_mask.png")  # mode "1"
    vs = read_views(folder)
    expect = np.zeros((H, W))
    expect[1:4, 2:5] = 1.0
    np.testing.assert_array_equal(vs.masks[0], expect)
    np.testing.assert_array_equal(vs.images[0][expect > 0], np.tile([1.0, 0.0, 0.0], (9, 1)))
    np.testing.assert_array_equal(vs.masks[1], bits.astype(np.float32))
    np.testing.assert_allclose(vs.images[1], 128 / 255, atol=2 / 255)


def test_colour_trust_round_trips_and_is_written_only_where_it_is_not_one(tmp_path):
    """A view's colour trust goes to images/trust_NNN.png (8-bit gray) only when some pixel is below
    1; reading gives it back to 8-bit rounding, views without a file at 1, and `dla info`'s
    summary the trusted share of each view's person (mask-weighted mean)."""
    _, vs = _viewset()
    trust = np.ones(vs.masks.shape, np.float32)
    trust[1] = np.random.default_rng(1).uniform(size=trust[1].shape)
    vs.trust = trust
    write_views(vs, tmp_path / "out")
    frames = json.loads((tmp_path / "out" / "transforms.json").read_text())["frames"]
    assert [f.get("trust_path") for f in frames] == [None, "images/trust_001.png", None]
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == [
        "trust_001.png",
        "view_000.png",
        "view_001.png",
        "view_002.png",
    ]
    gray = Image.open(tmp_path / "out" / "images" / "trust_001.png")
    assert gray.mode == "L"
    np.testing.assert_array_equal(np.asarray(gray), np.round(trust[1] * 255))
    back = read_views(tmp_path / "out")
    np.testing.assert_array_equal(back.trust[[0, 2]], 1.0)
    np.testing.assert_allclose(back.trust[1], trust[1], atol=0.5 / 255 + 1e-6)
    share = summarize_views(tmp_path / "out")["colour_trust"]
    m = back.masks[1]
    assert share[0] == share[2] == 1.0
    assert share[1] == pytest.approx(float((m * back.trust[1]).sum() / m.sum()), abs=1e-4)

    vs.trust = None  # no trust: no files, and the reader gives None
    write_views(vs, tmp_path / "plain")
    assert not list((tmp_path / "plain" / "images").glob("trust_*"))
    assert read_views(tmp_path / "plain").trust is None
    assert summarize_views(tmp_path / "plain")["colour_trust"] == [1.0, 1.0, 1.0]


def test_colour_trust_problems_name_the_file(tmp_path):
    folder = make_folder(tmp_path, [_frame(trust_path="images/t.png")])
    t = folder / "images" / "t.png"
    assert f"{t}: image file not found" in _error(read_views, folder)
    Image.fromarray(np.full((H, W + 1), 255, np.uint8)).save(t)
    assert f"{t}: image is 9x6" in _error(read_views, folder)
    for bad in (np.full((H, W, 3), 255, np.uint8), np.full((H, W, 2), 255, np.uint8)):
        Image.fromarray(bad).save(t)
        assert f"{t}: a colour trust image must be grayscale without alpha" in _error(read_views, folder)
    folder = make_folder(tmp_path, [_frame(trust_path="../t.png")], name="outside")
    assert "trust_path" in _error(read_views, folder)
    _, vs = _viewset()
    vs.trust = np.ones((2, H, W), np.float32)
    assert "views.trust: has shape (2, 6, 8)" in _error(write_views, vs, tmp_path / "x")
    vs.trust = np.full((3, H, W), np.nan, np.float32)
    assert "views.trust: has non-finite values" in _error(write_views, vs, tmp_path / "x")
    assert not (tmp_path / "x").exists()
