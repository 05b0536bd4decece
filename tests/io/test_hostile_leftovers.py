"""Issue 20's hostile-input leftovers, one test each: what an attacker's file did before (an internal
error, an accepted file a consumer chokes on, a message quoting megabytes) is now one short
DlaInputError naming the file, from the reader every command shares."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import re
import shutil
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dlacli.errors import DlaInputError, excerpt, excerpts, one_line
from dlacli.io.validate import LOG_SCALE_RANGE, MAX_JSON_DEPTH, parse_json
from dlacli.types import Avatar

EXAMPLES = Path(__file__).resolve().parents[2] / "formats" / "examples"
MOTION_DATA = Path(__file__).resolve().parents[1] / "data" / "third_party" / "motion"
MAX_MESSAGE = 400  # characters: every message below stays one short line


def _refused(read, path, *needles, args=()) -> str:
    with pytest.raises(DlaInputError) as info:
        read(path, *args)
    msg = str(info.value)
    assert "\n" not in msg and len(msg) <= MAX_MESSAGE + len(str(path)), msg
    assert msg.startswith(str(path)), msg
    for needle in needles:
        assert needle in msg, msg
    return msg


def _dla_info(path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", "from dlacli.cli.app import main; main()", "info", str(path)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def _one_line_exit_2(result: subprocess.CompletedProcess, path, needle: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}") and needle in lines[0], result.stderr


# ------------------------------------------------------------------------------------- excerpts


def test_excerpt_is_short_escaped_and_says_how_long():
    assert excerpt("Hips") == "'Hips'"
    long = excerpt("x" * 1_000_000)
    assert len(long) < 90 and long.endswith("... (1,000,000 characters)")
    raw = excerpt(b"PK\x01\x02" + bytes(8700))
    assert len(raw) < 90 and "\\x00" in raw and raw.endswith("(8,704 bytes)")
    tricky = excerpt("a\nb\x1b[31m\u202e" * 40)
    assert "\n" not in tricky and "\x1b" not in tricky and "\u202e" not in tricky and "\\u202e" in tricky
    assert len(excerpt([list(range(10**5))] * 3)) <= 60  # a parsed value: its repr is never built whole
    assert excerpts(["a", "b", "c", "d", "e", "f", "g"]) == "'a', 'b', 'c', 'd', 'e' and 2 more"
    assert one_line(ValueError("x\n" * 10_000)).endswith("...") and len(one_line(ValueError("x" * 10_000))) == 120


def test_body_model_of_a_megabyte_is_quoted_as_an_excerpt(tmp_path):
    body = json.loads((EXAMPLES / "body.json").read_text())
    body["model"] = "m" * 2**20
    path = tmp_path / "body.json"
    path.write_text(json.dumps(body))
    from dlacli.io.body import summarize_body

    msg = _refused(summarize_body, path, "model 'mmm", "(1,048,576 characters) is not supported")
    assert len(msg) < 200 + len(str(path))


def test_zip_directory_bytes_are_not_echoed(tmp_path):
    """A member whose central-directory name (8 KB of raw bytes) differs from its local header's:
    zipfile's message quotes both names whole; dla's quotes an excerpt."""
    src = tmp_path / "src.npz"
    name = "a" * 8192 + ".npy"
    with zipfile.ZipFile(src, "w") as zf:
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.zeros(3))
        zf.writestr(name, buf.getvalue())
    data = bytearray(src.read_bytes())
    at = data.index(b"PK\x03\x04") + 30  # the local header's copy of the name
    data[at : at + 8192] = b"\xff" * 8192
    path = tmp_path / "motion.npz"
    path.write_bytes(bytes(data))
    from dlacli.io.motion import read_motion

    _refused(read_motion, path, "not a readable .npz file")


# -------------------------------------------------------------------------------- log-scales


def _ply_with_scale(tmp_path, value: float, name="g.ply") -> Path:
    import plyfile

    v = plyfile.PlyData.read(str(EXAMPLES / "gaussians_sh0.ply"))["vertex"].data.copy()
    v["scale_0"][1] = value
    path = tmp_path / name
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))
    return path


def test_log_scale_range_keeps_float32_scales_and_covariances_finite_and_nonzero():
    low, high = LOG_SCALE_RANGE
    for log_s in (low, high):
        s = np.float32(math.exp(log_s))
        assert np.isfinite(s * s) and s * s > np.finfo(np.float32).tiny and np.isfinite(1 / (s * s))
    with np.errstate(over="ignore"):
        assert np.isinf(np.float32(math.exp(89.0)))  # what the bound guards against


@pytest.mark.parametrize("value", [100.0, 89.0, 11.6, -42.0, -1000.0])
def test_ply_log_scales_beyond_the_range_are_refused(tmp_path, value):
    from dlacli.io.ply import read_ply, summarize_ply

    path = _ply_with_scale(tmp_path, value)
    for read in (read_ply, summarize_ply):
        _refused(read, path, "scale_0..2 holds a log-scale of", "dla reads log-scales in [-41.4, 11.5]")


@pytest.mark.parametrize("value", [11.5, -41.4])
def test_ply_log_scales_at_the_range_ends_read_finite(tmp_path, value):
    from dlacli.io.ply import read_ply

    g = read_ply(_ply_with_scale(tmp_path, value))
    s = g.scales[1, 0]
    assert 0 < float(s) and bool((s * s).isfinite())


def test_info_refuses_an_overflowing_ply_with_one_line(tmp_path):
    path = _ply_with_scale(tmp_path, 100.0)
    _one_line_exit_2(_dla_info(path), path, "log-scale of 100")


def test_splat_scales_beyond_the_range_are_refused(tmp_path):
    from dlacli.io.splat import RECORD, read_splat, summarize_splat

    rec = np.zeros(2, RECORD)
    rec["scale"], rec["rot"] = 0.01, (255, 128, 128, 128)
    rec["scale"][1, 2] = 3e38  # finite in float32; its square is not
    path = tmp_path / "g.splat"
    path.write_bytes(rec.tobytes())
    for read in (read_splat, summarize_splat):
        _refused(read, path, "scale holds a log-scale of 88.6")


def _avatar(tmp_path, decoder="identity", z=None, canonical=None, name="a.npz") -> Path:
    from dlacli.io.avatar import avatar_to_arrays
    from dlacli.io.body import body_from_dict
    from dlacli.io.validate import save_npz
    from dlacli.types import Avatar

    body = body_from_dict(json.loads((EXAMPLES / "body.json").read_text()), "body")
    z = np.zeros((14, 4, 4), np.float32) if z is None else z
    av = Avatar(z=z, encoder="unproject", decoder=decoder, body=body, uv_layout="anny", canonical=canonical)
    path = tmp_path / name
    save_npz(avatar_to_arrays(av), path)  # the writer's own check skipped: a hostile file
    return path


def test_the_reader_checks_the_channels_the_renderer_exponentiates(tmp_path):
    """Channel by channel, by behaviour: 100 in a channel of F overflows the Gaussians' scales
    (gaussian_map.skinned_params, what every render, animate and export goes through) exactly
    where the avatar reader refuses it, for z and for the canonical map."""
    import torch

    from dlacli.avatar import gaussian_map as gm
    from dlacli.io.avatar import read_avatar

    samples = gm.Samples(np.zeros(1, np.int64), np.full((1, 3), 1 / 3, np.float32), np.full((1, 2), 0.5, np.float32))
    frames = (torch.zeros(1, 1, 3), torch.eye(3)[None, None], torch.ones(1, 1), torch.tensor([[[1.0, 0, 0, 0]]]))
    overflowing, refused = [], {"z": [], "canonical": []}
    for c in range(gm.CHANNELS):
        fmap = np.zeros((gm.CHANNELS, 4, 4), np.float32)
        fmap[c] = 100.0
        params = gm.skinned_params(torch.from_numpy(fmap), samples, frames)
        if not all(torch.isfinite(p).all() for p in params):
            overflowing.append(c)
        for name, kw in (("z", {"z": fmap}), ("canonical", {"canonical": fmap})):
            try:
                read_avatar(_avatar(tmp_path, **kw, name=f"{name}{c}.npz"))
            except DlaInputError:
                refused[name].append(c)
    assert overflowing and refused == {"z": overflowing, "canonical": overflowing}


def test_avatar_log_scales_beyond_the_range_are_refused(tmp_path):
    from dlacli.io.avatar import read_avatar, summarize_avatar

    z = np.zeros((14, 4, 4), np.float32)
    z[12, 1, 2] = 100.0  # the map of an identity avatar: exp(100) overflows float32
    for decoder in ("identity", "view-cosine"):
        zz = z if decoder == "identity" else np.concatenate([z, np.zeros((1, 4, 4), np.float32)])
        path = _avatar(tmp_path, decoder, zz, name=f"{decoder}.npz")
        for read in (read_avatar, summarize_avatar):
            _refused(read, path, "z (channels 11-13, log scale) holds a log-scale of 100")
    canonical = np.zeros((14, 4, 4), np.float32)
    canonical[11] = -100.0
    path = _avatar(tmp_path, "identity", canonical=canonical, name="c.npz")
    _refused(read_avatar, path, "canonical (channels 11-13, log scale) holds a log-scale of -100")
    # a learned decoder's z is a latent code, not the map: its channel 12 may hold anything finite
    learned = _avatar(tmp_path, "gpd", z, name="learned.npz")
    assert read_avatar(learned).z[12, 1, 2] == 100.0
    _one_line_exit_2(_dla_info(tmp_path / "identity.npz"), tmp_path / "identity.npz", "log-scale of 100")


# -------------------------------------------------------------------------------- non-square z


def test_non_square_uv_maps_are_refused_by_read_write_and_info(tmp_path):
    from dlacli.io.avatar import read_avatar, summarize_avatar, write_avatar

    path = _avatar(tmp_path, z=np.zeros((14, 4, 6), np.float32))
    for read in (read_avatar, summarize_avatar):
        _refused(read, path, "z has shape (14, 4, 6); a UV map is square (C, R, R)")
    path = _avatar(tmp_path, canonical=np.zeros((14, 2, 3), np.float32), name="c.npz")
    _refused(read_avatar, path, "canonical has shape (14, 2, 3); a UV map is square")
    body = read_avatar(_avatar(tmp_path, name="ok.npz")).body
    z = np.zeros((14, 4, 6), np.float32)
    wide = Avatar(z=z, encoder="unproject", decoder="identity", body=body, uv_layout="anny")
    with pytest.raises(DlaInputError, match="a UV map is square"):
        write_avatar(wide, tmp_path / "w.npz")
    assert not (tmp_path / "w.npz").exists()


# ---------------------------------------------------------------------- views: info = the reader


def _views_with_int32_images(tmp_path, scale: int) -> Path:
    from PIL import Image

    folder = tmp_path / "views"
    shutil.copytree(EXAMPLES / "views", folder)
    meta = json.loads((folder / "transforms.json").read_text())
    for i, frame in enumerate(meta["frames"]):
        rgba = np.asarray(Image.open(folder / frame["file_path"]))
        Image.fromarray(rgba[..., :3].mean(-1).astype(np.int32) * scale, "I").save(folder / f"images/g{i}.tif")
        Image.fromarray(rgba[..., 3]).save(folder / f"images/m{i}.png")
        frame["file_path"], frame["mask_path"] = f"images/g{i}.tif", f"images/m{i}.png"
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_32_bit_integer_views_beyond_16_bits_are_refused_by_info_and_the_reader(tmp_path):
    """Before: info and lift both accepted them, reading colours of up to 389 (value / 65535)."""
    from dlacli.io.inspect import summarize
    from dlacli.io.views import read_views

    folder = _views_with_int32_images(tmp_path, 100_000)
    needle = "32-bit integer image with values 2100000 to 19100000, outside the 16-bit range 0-65535"
    for read in (read_views, summarize):
        with pytest.raises(DlaInputError, match=needle) as info:
            read(folder)
        assert info.value.where == str(folder / "images" / "g0.tif")
    ok = _views_with_int32_images(tmp_path / "ok", 257)  # within 16 bits: read as 16-bit gray
    views = read_views(ok)
    assert 0 <= views.images.min() and views.images.max() <= 1
    assert summarize(ok)["views"] == len(views)


# ------------------------------------------------------------------------------ JSON, guarded


def test_the_guarded_parser_refuses_depth_digits_constants_and_bad_bytes():
    deep = MAX_JSON_DEPTH + 1
    cases = [
        ("[" * 1500 + "]" * 1500, "nested too deeply"),
        ("[" * deep + "]" * deep, f"nested {deep} levels"),
        ('{"a": ' + "7" * 5000 + "}", "not valid JSON (Exceeds the limit"),
        (b'{"a": "\xff"}', "not UTF-8 text"),
    ]
    for text, problem in cases:
        with pytest.raises(DlaInputError, match=re.escape(problem)):
            parse_json(text, "f.json")
    assert parse_json("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH, "f.json") is not None
    assert math.isnan(parse_json('{"a": NaN}', "f.json")["a"])
    with pytest.raises(DlaInputError, match="NaN is not a JSON number"):
        parse_json('{"a": NaN}', "f.json", constants=False)


@dataclasses.dataclass
class _TinyConfig:
    width: int = 2


def _checkpoint(tmp_path) -> Path:
    import torch

    from dlacli.avatar.checkpoint import save_checkpoint

    net = torch.nn.Linear(2, 2)
    net.config = _TinyConfig()
    save_checkpoint(tmp_path / "ck", net, net.config)
    return tmp_path / "ck"


def _safetensors(header: bytes, body: bytes = b"") -> bytes:
    return struct.pack("<Q", len(header)) + header + body


@pytest.mark.parametrize(
    "which, content, problem",
    [
        ("config.json", "[" * 1500 + "]" * 1500, "nested too deeply"),
        ("config.json", '{"format": ' + "9" * 5000 + "}", "not valid JSON"),
        ("config.json", '{"format": "dla.checkpoint/1", "step": NaN}', "NaN is not a JSON number"),
        ("model.safetensors", _safetensors(b"[" * 1500 + b"]" * 1500), "its header is JSON nested too deeply"),
        ("model.safetensors", _safetensors(b'{"a": ' + b"9" * 5000 + b"}"), "its header is not valid JSON"),
        ("model.safetensors", _safetensors(b'{"a": {"data_offsets": [0, Infinity]}}'), "Infinity is not a JSON number"),
        ("model.safetensors", _safetensors(b"[1, 2]"), "its header is not a JSON object"),
    ],
)
def test_checkpoint_json_goes_through_the_guarded_parser(tmp_path, which, content, problem):
    """Before: RecursionError / ValueError from json.loads, an internal error."""
    from dlacli.avatar.checkpoint import checkpoint_info

    folder = _checkpoint(tmp_path)
    path = folder / which
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(DlaInputError) as info:
        checkpoint_info(folder)
    assert info.value.where == str(path) and problem in info.value.problem and len(str(info.value)) < 300


def test_a_rehashed_config_that_builds_a_huge_network_is_refused_unbuilt(tmp_path):
    """The content hash is no signature: a config.json whose widths were raised to millions and
    whose hash was recomputed would have made torch allocate 64 TB. The network is sized on the
    meta device first."""
    from dlacli.avatar import checkpoint as ck
    from dlacli.nn.discriminator import DiscriminatorConfig, PatchDiscriminator

    net = PatchDiscriminator(DiscriminatorConfig(base_channels=2, layers=1, max_channels=4))
    folder = tmp_path / "ck"
    ck.save_checkpoint(folder, net, net.config)
    assert ck.load_checkpoint(folder).config == net.config
    rec = json.loads((folder / "config.json").read_text())
    rec["config"].update(base_channels=10**6, max_channels=10**6)
    weights = (folder / "model.safetensors").read_bytes()
    rec["hash"] = ck.content_hash(rec["class"], rec["config_class"], rec["config"], weights)
    (folder / "config.json").write_text(json.dumps(rec))
    _refused(
        ck.load_checkpoint, folder / "config.json", "config builds a PatchDiscriminator of 64,000,268,000,004 bytes"
    )


def test_a_config_integer_too_large_for_a_float_field(tmp_path):
    from dlacli.avatar.checkpoint import config_from_dict

    @dataclasses.dataclass
    class C:
        gain: float = 1.0

    with pytest.raises(DlaInputError, match="config field gain is 1000"):
        config_from_dict(C, {"gain": 10**400}, "config.json")


@pytest.mark.parametrize(
    "change, problem",
    [
        (lambda r: "[" * 1500 + "]" * 1500, "nested too deeply"),
        (lambda r: json.dumps(r)[:-1] + ', "x": ' + "9" * 5000 + "}", "not valid JSON"),
        (lambda r: json.dumps({**r, "checkpoint": "../../elsewhere"}), "'checkpoint' must be null or a checkpoint"),
        (lambda r: json.dumps({**r, "settings": []}), "'settings' must be an object"),
        (lambda r: json.dumps({**r, "step": "3"}), "'step' must be a whole number"),
        (lambda r: json.dumps({**r, "history": [{"step": 1, "l1": [1]}]}), "'history' must be a list of objects"),
    ],
)
def test_train_json_for_resume_is_read_guarded(tmp_path, change, problem):
    """Before: RecursionError / ValueError; and a train.json naming "../../elsewhere" as its
    checkpoint would have had that folder deleted when the run saved its next checkpoint."""
    from dlacli.train.loop import FORMAT, _read_record

    history = [{"step": 1, "stage": "low", "l1": 0.5}]
    good = {
        "format": FORMAT,
        "settings": {},
        "step": 2,
        "history": history,
        "validation": [],
        "checkpoint": "ckpt-000002",
        "seconds": 1.5,
    }
    path = tmp_path / "train.json"
    path.write_text(json.dumps(good))
    assert _read_record(path) == good
    path.write_text(change(good))
    _refused(_read_record, path, problem)


# -------------------------------------------------------------------------- zip version > 6.3


def _zip_version_70(src: Path, dst: Path) -> Path:
    data = bytearray(src.read_bytes())
    for magic, at in ((b"PK\x03\x04", 4), (b"PK\x01\x02", 6)):
        i = data.find(magic)
        while i >= 0:
            data[i + at] = 70  # "version needed to extract": 7.0
            i = data.find(magic, i + 4)
    dst.write_bytes(bytes(data))
    return dst


def test_zip_version_above_63_is_refused_by_every_npz_reader(tmp_path):
    """Before: NotImplementedError from zipfile, an internal error in every npz reader."""
    from dlacli.io.amass import read_amass
    from dlacli.io.avatar import read_avatar
    from dlacli.io.inspect import summarize
    from dlacli.io.motion import read_motion
    from dlacli.io.validate import load_npz, npz_format

    motion = _zip_version_70(EXAMPLES / "motion.npz", tmp_path / "motion.npz")
    avatar = _zip_version_70(EXAMPLES / "avatar.npz", tmp_path / "avatar.npz")
    needle = "unsupported zip feature (zip file version 7.0)"
    readers = [
        (read_motion, motion),
        (read_avatar, avatar),
        (read_amass, motion),
        (load_npz, motion),
        (npz_format, avatar),
        (summarize, avatar),
    ]
    for read, path in readers:
        _refused(read, path, needle)
    _one_line_exit_2(_dla_info(motion), motion, needle)


# ---------------------------------------------------------------------------- keypoints 10^309


def test_keypoints_integer_beyond_float_range(tmp_path):
    """Before: OverflowError in dream."""
    from dlacli.io.photo import read_coco_keypoints

    path = tmp_path / "k.json"
    path.write_text('{"keypoints": [' + ", ".join(["1"] * 50 + ["1" + "0" * 309]) + "]}")
    _refused(read_coco_keypoints, path, "'keypoints' holds a number too large for a pixel coordinate")


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_keypoints_beyond_float32_are_refused_without_a_warning(tmp_path):
    """Before: a coordinate of 1e39 is finite in float64 but not in the float32 the fit takes: numpy
    printed an overflow warning and dream went on with an infinite keypoint."""
    from dlacli.io.photo import MAX_KEYPOINT_PX, read_coco_keypoints

    path = tmp_path / "k.json"
    path.write_text('{"keypoints": [' + ", ".join(["1e39"] + ["1"] * 50) + "]}")
    _refused(read_coco_keypoints, path, "'keypoints' holds a coordinate beyond")
    path.write_text('{"keypoints": [' + ", ".join([str(MAX_KEYPOINT_PX)] + ["1"] * 50) + "]}")
    assert read_coco_keypoints(path)[0, 0] == MAX_KEYPOINT_PX  # the bound itself is read


def test_json_arrays_with_integers_beyond_64_bits(tmp_path):
    from dlacli.io.validate import as_array

    with pytest.raises(DlaInputError, match="root_translation holds an integer beyond 64 bits"):
        as_array([0, 10**309, 0], (3,), "body.json", "root_translation")


# ----------------------------------------------------------------------- BVH / ASF-AMC bounds


def _bvh_with(tmp_path, column: int, value: str) -> Path:
    text = (MOTION_DATA / "131_01.bvh").read_text()
    head, motion = text.split("MOTION", 1)
    lines = motion.strip("\n").split("\n")
    last = lines[-1].split()
    last[column] = value
    path = tmp_path / "m.bvh"
    path.write_text(head + "MOTION\n" + "\n".join(lines[:-1] + [" ".join(last)]) + "\n")
    return path


def test_bvh_root_moving_1e20_units_is_refused_everywhere(tmp_path):
    """Before: `dla info` and `dla animate` read it (points spread over +-5e11 m), `dla motion
    convert` refused it: only the motion.npz writer bounded distances."""
    from dlacli.io.bvh import read_bvh, summarize_bvh

    path = _bvh_with(tmp_path, 0, "1e20")
    for read in (read_bvh, summarize_bvh):
        _refused(read, path, "the root position reaches", "at most 100000 is supported")
    angle = _bvh_with(tmp_path, 4, "1e9")
    _refused(read_bvh, angle, "rotation of joint 'Hips' reaches 1e+09 degrees")
    assert read_bvh(_bvh_with(tmp_path, 4, "7200")).num_frames > 1  # 20 turns is a motion
    huge_offset = tmp_path / "o.bvh"
    text = (MOTION_DATA / "131_01.bvh").read_text()
    huge_offset.write_text(text.replace("OFFSET 0.00000 0.00000 0.00000", "OFFSET 0 1e300 0", 1))
    _refused(read_bvh, huge_offset, "a joint offset reaches 5.64e+298 m")  # its unit guessed as mm


def test_amc_root_and_asf_units_beyond_the_bounds(tmp_path):
    from dlacli.io.asf_amc import read_amc

    asf = tmp_path / "s.asf"
    shutil.copy(MOTION_DATA / "cmu_01.asf", asf)
    lines = (MOTION_DATA / "cmu_01_01.amc").read_text().splitlines()
    root = next(i for i, line in enumerate(lines) if line.startswith("root "))
    far = lines.copy()
    far[root] = "root 1e20 0 0 0 0 0"
    (tmp_path / "far.amc").write_text("\n".join(far) + "\n")
    _refused(read_amc, tmp_path / "far.amc", "the root position reaches", args=(asf,))
    spun = lines.copy()
    spun[root] = "root 0 0 0 1e12 0 0"
    (tmp_path / "spun.amc").write_text("\n".join(spun) + "\n")
    _refused(read_amc, tmp_path / "spun.amc", "rotation of bone 'root' reaches", args=(asf,))
    tiny = tmp_path / "tiny.asf"
    tiny.write_text(asf.read_text().replace("length 0.45", "length 1e-300"))
    _refused(read_amc, MOTION_DATA / "cmu_01_01.amc", "reaches", args=(tiny,))


def test_a_float64_map_beyond_float32_is_refused_not_read_as_inf(tmp_path):
    from dlacli.io.avatar import read_avatar
    from dlacli.io.validate import load_npz, save_npz

    arrays = load_npz(_avatar(tmp_path, "gpd"))
    arrays["z"] = np.zeros((14, 2, 2))
    arrays["z"][1, 0, 0] = 1e300  # a colour stored as float64: finite there, inf once read as float32
    save_npz(arrays, tmp_path / "f64.npz")
    _refused(read_avatar, tmp_path / "f64.npz", "z has 1 non-finite value")
