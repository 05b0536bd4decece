"""avatar.npz: the float16 rule, golden file, round trips and every bad-input case (formats/avatar.md)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from dlacli.errors import DlaInputError
from dlacli.io.avatar import FLOAT16_RTOL, half_if_lossless, read_avatar, summarize_avatar, write_avatar
from dlacli.io.body import body_from_dict, body_to_dict
from dlacli.types import Avatar

BODY = {
    "format": "dla.body/1",
    "model": "anny",
    "phenotype": {"gender": 0.2, "age": 0.6, "muscle": 0.5, "weight": 0.5, "height": 0.4, "proportions": 0.5},
    "pose": {"head": [0.0, 0.1, 0.0]},
}


def _smooth(c=4, h=8, w=8, scale=1.0):
    y, x = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    return np.stack([scale * np.sin(3 * x + c_) * np.cos(2 * y) for c_ in range(c)]).astype(np.float32)


def _avatar(z=None, **kw):
    args = dict(
        z=_smooth() if z is None else z,
        encoder="unproject",
        decoder="identity",
        body=body_from_dict(BODY, "test"),
        uv_layout="anny",
    )
    args.update(kw)
    return Avatar(**args)


def _raw(path):
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def _error(path) -> str:
    with pytest.raises(DlaInputError) as info:
        read_avatar(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_smooth_small_z_is_stored_float16_within_the_stated_tolerance(tmp_path):
    z = _smooth(scale=0.8)
    write_avatar(_avatar(z), tmp_path / "a.npz")
    assert _raw(tmp_path / "a.npz")["z"].dtype == np.float16
    back = read_avatar(tmp_path / "a.npz").z
    assert back.dtype == np.float32 and back.shape == z.shape
    err = np.abs(back.astype(np.float64) - z.astype(np.float64)).max()
    assert 0 < err <= FLOAT16_RTOL * np.abs(z).max()
    # float16 keeps 11 significant bits: every value is within half an ulp, 2^-11 relative
    assert np.all(np.abs(back.astype(np.float64) - z) <= 2.0**-11 * np.abs(z) + 1e-12)


@pytest.mark.parametrize("scale", [1e5, 1e-6])
def test_large_or_tiny_z_stays_float32_and_round_trips_exactly(tmp_path, scale):
    z = _smooth(scale=1.0)
    z[0, 0, 0] = scale  # 1e5 overflows float16; at 1e-6 scale the subnormal steps are too coarse
    if scale < 1:
        z = z * scale
    write_avatar(_avatar(z), tmp_path / "a.npz")
    assert _raw(tmp_path / "a.npz")["z"].dtype == np.float32
    np.testing.assert_array_equal(read_avatar(tmp_path / "a.npz").z, z)


def test_float16_rule_against_a_direct_evaluation():
    rng = np.random.default_rng(1)
    for scale in [1e-7, 1e-5, 1e-3, 1.0, 1e3, 6e4, 7e4]:
        a = (rng.normal(size=(3, 5, 5)) * scale).astype(np.float32)
        with np.errstate(over="ignore"):
            as16 = a.astype(np.float16).astype(np.float64)
        expect16 = bool(np.all(np.isfinite(as16))) and (
            np.abs(as16 - a.astype(np.float64)).max() <= FLOAT16_RTOL * np.abs(a.astype(np.float64)).max()
        )
        assert (half_if_lossless(a).dtype == np.float16) == expect16, scale
    assert half_if_lossless(np.zeros((1, 2, 2))).dtype == np.float16
    assert half_if_lossless(np.full((1, 2, 2), 70000.0)).dtype == np.float32


def test_full_round_trip(tmp_path):
    weights = b"pretend checkpoint bytes"
    digest = hashlib.sha256(weights).hexdigest()
    canonical = np.linspace(-1, 1, 14 * 6 * 6, dtype=np.float32).reshape(14, 6, 6)  # UV maps are square
    extra = {"source": "photo.png", "views": 4, "nested": {"a": [1, 2]}}
    av = _avatar(encoder="learned", decoder="gpd", checkpoint=digest, canonical=canonical, extra=extra)
    write_avatar(av, tmp_path / "a.npz")
    raw = _raw(tmp_path / "a.npz")
    assert str(raw["format"]) == "dla.avatar/1" and str(raw["checkpoint"]) == digest
    assert json.loads(str(raw["body"])) == body_to_dict(av.body)
    assert json.loads(str(raw["extra"])) == extra
    back = read_avatar(tmp_path / "a.npz")
    assert (back.encoder, back.decoder, back.uv_layout, back.checkpoint) == ("learned", "gpd", "anny", digest)
    assert back.extra == extra and body_to_dict(back.body) == body_to_dict(av.body)
    np.testing.assert_allclose(back.canonical, canonical, rtol=0, atol=FLOAT16_RTOL)
    assert back.canonical.dtype == np.float32


def test_optional_entries_may_be_absent(tmp_path):
    write_avatar(_avatar(), tmp_path / "a.npz")
    raw = _raw(tmp_path / "a.npz")
    assert "canonical" not in raw and "extra" not in raw and str(raw["checkpoint"]) == ""
    back = read_avatar(tmp_path / "a.npz")
    assert back.canonical is None and back.extra == {} and back.checkpoint == ""


def test_golden_file(formats_dir):
    path = formats_dir / "examples" / "avatar.npz"
    raw = _raw(path)
    a = read_avatar(path)
    assert str(raw["format"]) == "dla.avatar/1"
    np.testing.assert_array_equal(a.z, raw["z"].astype(np.float32))
    assert a.z.ndim == 3 and a.encoder == str(raw["encoder"]) and a.uv_layout == str(raw["uv_layout"])
    assert body_to_dict(a.body) == json.loads(str(raw["body"]))
    assert path.stat().st_size < 8192


def _save(tmp_path, **changes):
    write_avatar(_avatar(canonical=np.zeros((14, 2, 2), np.float32), extra={"k": 1}), tmp_path / "ok.npz")
    arrays = _raw(tmp_path / "ok.npz")
    for k, v in changes.items():
        if v is None:
            del arrays[k]
        else:
            arrays[k] = v
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "changes, needle",
    [
        (dict(format=None), "missing 'format'"),
        (dict(format=np.array("dla.avatar/2")), "'dla.avatar/2' is not supported by this version"),
        (dict(format=np.array("dla.motion/1")), "format is 'dla.motion/1', expected 'dla.avatar/1'"),
        (dict(z=None), "missing array 'z'"),
        (dict(body=None, uv_layout=None), "missing arrays 'body', 'uv_layout'"),
        (dict(z=np.zeros((8, 8), np.float32)), "z has shape (8, 8), expected (*, *, *)"),
        (dict(z=np.zeros((4, 0, 8), np.float32)), "z has an empty shape"),
        (dict(z=np.zeros((4, 8, 8), np.int32)), "z must be float16 or float32"),
        (dict(z=np.full((2, 2, 2), np.nan, np.float16)), "z has 8 non-finite values"),
        (dict(canonical=np.zeros((13, 4, 4), np.float16)), "canonical has shape (13, 4, 4), expected (14, *, *)"),
        (dict(canonical=np.full((14, 1, 1), np.inf, np.float32)), "canonical has 14 non-finite values"),
        (dict(checkpoint=np.array("abc123")), "neither '' nor a lower-case sha256"),
        (dict(encoder=np.array("")), "encoder is an empty string"),
        (dict(body=np.array("{not json")), "body is not valid JSON"),
        (
            dict(body=np.array(json.dumps({**BODY, "phenotype": {**BODY["phenotype"], "age": 3}}))),
            "bad.npz:body: phenotype.age = 3.0 is outside [0, 1]",
        ),
        (dict(extra=np.array("[1, 2]")), "extra must be a JSON object"),
        (dict(mystery=np.zeros(3)), "unknown array 'mystery'"),
    ],
)
def test_bad_arrays_are_one_line_errors(tmp_path, changes, needle):
    assert needle in _error(_save(tmp_path, **changes))


def test_truncated_and_missing_files(tmp_path, formats_dir):
    data = (formats_dir / "examples" / "avatar.npz").read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    assert "not a readable .npz file" in _error(cut)
    assert "no such file" in _error(tmp_path / "nope.npz")


def test_writer_rejects_bad_avatars_and_leaves_no_file(tmp_path):
    z = _smooth()
    z[0, 0, 0] = np.inf
    with pytest.raises(DlaInputError, match="z has 1 non-finite value"):
        write_avatar(_avatar(z), tmp_path / "a.npz")
    with pytest.raises(DlaInputError, match="canonical has shape"):
        write_avatar(_avatar(canonical=np.zeros((3, 2, 2))), tmp_path / "a.npz")
    with pytest.raises(DlaInputError, match="extra"):
        write_avatar(_avatar(extra={"x": object()}), tmp_path / "a.npz")
    assert list(tmp_path.iterdir()) == []


def test_summary(formats_dir):
    path = formats_dir / "examples" / "avatar.npz"
    s = summarize_avatar(path)
    raw = _raw(path)
    z = raw["z"].astype(np.float64)
    assert s["kind"] == "avatar" and s["format"] == "dla.avatar/1"
    assert s["z_shape"] == list(z.shape) and s["z_stored_dtype"] == str(raw["z"].dtype)
    assert s["z_min"] == pytest.approx(z.min()) and s["z_max"] == pytest.approx(z.max())
    assert s["z_std"] == pytest.approx(z.std(), rel=1e-4)
    json.dumps(s)
