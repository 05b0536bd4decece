"""Region swap and interpolation of avatars (stages/edit.py, `dla edit swap`, `dla interp`)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dlacli.body.regions import region_mask
from dlacli.errors import DlaInputError
from dlacli.io.avatar import read_avatar, write_avatar
from dlacli.stages.edit import feathered_weight, interpolate, swap_region
from dlacli.types import PHENOTYPE_KEYS, Avatar, BodyParams

RES = 64


def _avatar(seed: int, res: int = RES, encoder: str = "unproject") -> Avatar:
    rng = np.random.default_rng(seed)
    body = BodyParams(
        phenotype={k: float(rng.uniform(0.2, 0.8)) for k in PHENOTYPE_KEYS},
        root_rotation=rng.normal(0, 0.3, 3),
        root_translation=rng.normal(0, 0.1, 3),
        pose={"upperarm01.L": rng.normal(0, 0.5, 3)},
    )
    z = rng.normal(0, 1, (6, res, res)).astype(np.float16).astype(np.float32)
    return Avatar(z=z, encoder=encoder, decoder="identity", body=body, uv_layout="anny")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dlacli.cli.app", *args], capture_output=True, text=True)


def test_swap_changes_exactly_the_region():
    a, b = _avatar(0), _avatar(1)
    mask = region_mask("face", RES)
    assert 0 < mask.sum() < mask.size
    out = swap_region(a, b, "face")
    np.testing.assert_array_equal(out.z[:, mask], b.z[:, mask])
    np.testing.assert_array_equal(out.z[:, ~mask], a.z[:, ~mask])
    assert out.body is a.body


def test_feather_reaches_only_nearby_texels():
    a, b = _avatar(0), _avatar(1)
    mask = region_mask("left_hand", RES)
    feather = 3.0
    out = swap_region(a, b, "left_hand", feather=feather)
    changed = np.any(out.z != a.z, axis=0)
    # independent distance oracle: nearest region texel by a k-d tree over texel centres
    rows, cols = np.nonzero(mask)
    tree = cKDTree(np.stack([rows, cols], 1))
    all_rc = np.stack(np.meshgrid(np.arange(RES), np.arange(RES), indexing="ij"), -1).reshape(-1, 2)
    dist = tree.query(all_rc)[0].reshape(RES, RES)
    assert np.all(dist[changed] < feather + 1.0)
    assert changed[(dist > 0) & (dist <= feather)].mean() > 0.99  # the feather ring does change
    w = feathered_weight(mask, feather)
    np.testing.assert_allclose(w, np.clip(1.0 - dist / (feather + 1.0), 0, 1), atol=1e-6)


def test_interp_endpoints_exact_and_midpoint():
    a, b = _avatar(0), _avatar(1)
    np.testing.assert_array_equal(interpolate(a, b, 0.0).z, a.z)
    np.testing.assert_array_equal(interpolate(a, b, 1.0).z, b.z)
    mid = interpolate(a, b, 0.5)
    np.testing.assert_allclose(mid.z, (a.z + b.z) / 2, atol=1e-6)
    for t, ref in ((0.0, a), (1.0, b)):
        body = interpolate(a, b, t).body
        assert body.phenotype == ref.body.phenotype
        np.testing.assert_array_equal(body.root_rotation, ref.body.root_rotation)
        np.testing.assert_array_equal(body.pose["upperarm01.L"], ref.body.pose["upperarm01.L"])


def test_interp_rotation_follows_shortest_arc():
    a, b = _avatar(0), _avatar(1)
    a.body.root_rotation = np.array([0.0, 0.0, 0.2])
    b.body.root_rotation = np.array([0.0, 0.0, 1.0])
    mid = interpolate(a, b, 0.5).body.root_rotation
    np.testing.assert_allclose(mid, [0.0, 0.0, 0.6], atol=1e-9)


def test_incompatible_avatars_are_rejected():
    a = _avatar(0)
    with pytest.raises(DlaInputError, match="encoder"):
        swap_region(a, _avatar(1, encoder="learned"), "face")
    with pytest.raises(DlaInputError, match="shape"):
        interpolate(a, _avatar(1, res=32), 0.5)


def test_cli_swap_and_interp(tmp_path):
    pa, pb = tmp_path / "a.npz", tmp_path / "b.npz"
    write_avatar(_avatar(0), pa)
    write_avatar(_avatar(1), pb)
    r = _run("edit", "swap", str(pa), str(pb), "--region", "hair", "-o", str(tmp_path / "s.npz"))
    assert r.returncode == 0, r.stderr
    out, a, b = read_avatar(tmp_path / "s.npz"), read_avatar(pa), read_avatar(pb)
    mask = region_mask("hair", RES)
    np.testing.assert_array_equal(out.z[:, mask], b.z[:, mask])
    np.testing.assert_array_equal(out.z[:, ~mask], a.z[:, ~mask])

    r = _run("interp", str(pa), str(pb), "--steps", "3", "-o", str(tmp_path / "morph"))
    assert r.returncode == 0, r.stderr
    files = sorted((tmp_path / "morph").glob("*.npz"))
    assert [f.name for f in files] == ["interp_000.npz", "interp_001.npz", "interp_002.npz"]
    np.testing.assert_array_equal(read_avatar(files[0]).z, a.z)
    np.testing.assert_array_equal(read_avatar(files[2]).z, b.z)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["edit", "swap", "{a}", "{b}", "--region", "tail", "-o", "{o}"], "unknown region 'tail'"),
        (["edit", "swap", "{a}", "{c}", "--region", "face", "-o", "{o}"], "encoder"),
        (["edit", "swap", "{a}", "{missing}", "--region", "face", "-o", "{o}"], "missing.npz"),
        (["interp", "{a}", "{c}", "-o", "{o}"], "encoder"),
    ],
)
def test_cli_bad_input_one_line_exit_2(tmp_path, args, needle):
    paths = {k: tmp_path / f"{k}.npz" for k in ("a", "b", "c", "o", "missing")}
    write_avatar(_avatar(0), paths["a"])
    write_avatar(_avatar(1), paths["b"])
    write_avatar(_avatar(2, encoder="learned"), paths["c"])
    r = _run(*[x.format(**{k: str(v) for k, v in paths.items()}) for x in args])
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert not paths["o"].exists()


def test_cli_interp_video(subject, tmp_path):
    import imageio.v2 as imageio

    from dlacli.io.views import read_views
    from dlacli.stages.lift.methods.unproject import UnprojectConfig
    from dlacli.stages.lift.unproject import lift

    a = lift(read_views(subject), UnprojectConfig(steps=0, gaussians=2048)).avatar
    b = Avatar(z=a.z.copy(), encoder=a.encoder, decoder=a.decoder, body=a.body, uv_layout=a.uv_layout)
    b.z[1:4] = 1.0 - b.z[1:4]  # inverted colours
    write_avatar(a, tmp_path / "a.npz")
    write_avatar(b, tmp_path / "b.npz")
    r = _run(
        "interp",
        str(tmp_path / "a.npz"),
        str(tmp_path / "b.npz"),
        "--steps",
        "3",
        "-o",
        str(tmp_path / "m"),
        "--video",
        str(tmp_path / "m.mp4"),
        "--size",
        "48",
    )
    assert r.returncode == 0, r.stderr
    frames = [f.astype(float) for f in imageio.get_reader(tmp_path / "m.mp4")]
    assert len(frames) == 3 and frames[0].shape[:2] == (48, 48)
    assert np.abs(frames[0] - frames[2]).mean() > 5  # the colours changed across the blend
