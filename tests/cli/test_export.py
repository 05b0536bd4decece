"""`dla export`: the avatar's own Gaussians, in the poses and axes the help text states.

Oracles: the render path's own Gaussians (body model -> tangent frames -> gaussian map, as
stages/render.render_avatar draws them), rigid-motion identities of the body model (the input
pose is the canonical one moved by the root rotation and translation), the stated --up rotation,
gsply (PyPI) as the .ply reader, and pygltflib for .glb."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlacli.avatar import gaussian_map as gm
from dlacli.cli.app import main
from dlacli.io.avatar import write_avatar
from dlacli.types import PHENOTYPE_KEYS, Avatar, BodyParams

N = 1024
RES = 32


def _avatar() -> Avatar:
    rng = np.random.default_rng(7)
    z = np.zeros((gm.CHANNELS, RES, RES), np.float32)
    z[gm.OPACITY] = rng.normal(1.0, 1.0, (1, RES, RES))
    z[gm.RGB] = rng.uniform(0.1, 0.9, (3, RES, RES))
    z[gm.OFFSET] = rng.normal(0, 0.004, (3, RES, RES))
    z[gm.ROTATION] = rng.normal(0, 1, (4, RES, RES))
    z[gm.LOG_SCALE] = rng.normal(np.log(2.0), 0.3, (3, RES, RES))
    body = BodyParams(
        phenotype={**{k: 0.5 for k in PHENOTYPE_KEYS}, "gender": 0.3, "height": 0.6},
        root_rotation=np.array([0.2, -0.3, 0.5]),
        root_translation=np.array([0.1, -0.2, 0.05]),
        pose={"upperarm01.L": np.array([0.0, 0.6, 0.3]), "lowerleg01.R": np.array([0.7, 0.0, 0.0])},
    )
    return Avatar(
        z=z,
        encoder="unproject",
        decoder="identity",
        body=body,
        uv_layout="anny",
        extra={"samples": {"count": N, "seed": 4}},
    )


@pytest.fixture(scope="module")
def avatar_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("export") / "av.npz"
    write_avatar(_avatar(), path)
    return path


@pytest.fixture(scope="module")
def avatar(avatar_path):
    """The avatar as dla reads it back (its maps may be stored as float16)."""
    from dlacli.io.avatar import read_avatar

    return read_avatar(avatar_path)


def _run(capsys, *argv) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    return info.value.code, capsys.readouterr().err


def _export(capsys, *argv):
    code, err = _run(capsys, "export", *argv)
    assert code == 0, err


def _read(path):
    """(means, quats, scales, opacities, rgb) of a .ply through gsply (third-party reader)."""
    gsply = pytest.importorskip("gsply", reason="gsply (PyPI) is the third-party .ply/.spz reader")

    d = gsply.plyread(str(path))
    q = d.quats.astype(np.float64)
    return (
        d.means.astype(np.float64),
        q / np.linalg.norm(q, axis=1, keepdims=True),
        np.exp(d.scales.astype(np.float64)),
        1 / (1 + np.exp(-d.opacities.astype(np.float64))),
        0.5 + 0.28209479177387814 * d.sh0.astype(np.float64),
    )


def _same_rotation(a, b, atol):
    """Quaternions [N, 4] equal up to sign (q and -q are one rotation)."""
    return np.abs(np.abs(np.sum(a * b, axis=1)) - 1).max() <= atol


def _reference(avatar: Avatar, vertices: torch.Tensor):
    """The render path's Gaussians for posed vertices [1, V, 3] (stages/render.render_avatar)."""
    from dlacli.avatar.codec import Decoded

    samples = gm.make_samples(N, 4)
    (g,) = gm.gaussians_at_frames(Decoded(avatar).at(), samples, gm.sample_frames(vertices, samples))
    return g


def test_input_pose_is_what_render_draws(avatar, avatar_path, tmp_path, capsys):
    from dlacli.body.model import get_body_model
    from dlacli.stages.render import _pose_vertices

    _export(capsys, avatar_path, "-o", tmp_path / "in.ply", "--up", "z")
    means, quats, scales, opac, rgb = _read(tmp_path / "in.ply")
    ref = _reference(avatar, _pose_vertices(avatar, None, np.array([0])))
    assert means.shape == (N, 3)
    # the torch path of the skinning (the reference) and the numba one export takes agree to float32
    # rounding: positions of ~1 m, a few ulps (6e-8 each) apart
    assert np.abs(means - ref.means.double().numpy()).max() < 1e-6
    assert _same_rotation(quats, ref.quats.double().numpy(), 1e-6)
    assert np.abs(scales / ref.scales.double().numpy() - 1).max() < 1e-6  # log, exp in float32
    assert np.abs(opac - ref.opacities.double().numpy()).max() < 1e-6
    assert np.abs(rgb - ref.rgb.double().numpy()).max() < 1e-6
    # rest: the zero pose
    _export(capsys, avatar_path, "-o", tmp_path / "rest.ply", "--up", "z", "--pose", "rest")
    rest = _read(tmp_path / "rest.ply")[0]
    zero = _reference(avatar, get_body_model().zero_pose(avatar.body.phenotype).vertices)
    assert np.abs(rest - zero.means.double().numpy()).max() < 1e-6
    assert np.median(np.linalg.norm(rest - means, axis=1)) > 0.05  # rotated and posed: far apart


def test_input_is_canonical_moved_by_the_root(avatar, avatar_path, tmp_path, capsys):
    """x_input = R_root x_canonical + t_root and q_input = q_root q_canonical (the root bone's
    world pose is [R | t], docs/body.md); rest differs from canonical by the joint rotations."""
    from dlacli.geometry import axis_angle_to_matrix, matrix_to_quat, quat_multiply

    for pose in ("input", "canonical", "rest"):
        _export(capsys, avatar_path, "-o", tmp_path / f"{pose}.ply", "--up", "z", "--pose", pose)
    inp, can, rest = (_read(tmp_path / f"{p}.ply") for p in ("input", "canonical", "rest"))
    body = avatar.body
    r = axis_angle_to_matrix(np.asarray(body.root_rotation, dtype=np.float64))
    moved = can[0] @ r.T + body.root_translation
    assert np.abs(moved - inp[0]).max() < 1e-5  # float32 skinning of coordinates ~1 m: ~10 ulps
    q = quat_multiply(np.broadcast_to(matrix_to_quat(r), can[1].shape).copy(), can[1])
    assert _same_rotation(q, inp[1], 1e-5)
    # rigid motion keeps the sigmas, up to float32 triangle areas: edges of ~5 mm at ~1 m from the
    # origin carry a relative error of ~2 eps (1 m / 5 mm) = 5e-5 in area, half that in sqrt(area)
    assert np.abs(can[2] / inp[2] - 1).max() < 1e-4
    bent = np.linalg.norm(rest[0] - can[0], axis=1)
    assert np.percentile(bent, 99) > 0.05 and np.median(bent) < 0.02  # an arm and a leg move, the torso stays


def test_up_y_is_the_stated_rotation(avatar_path, tmp_path, capsys):
    from dlacli.geometry import matrix_to_quat, quat_multiply
    from dlacli.stages.export import R_3DGS

    _export(capsys, avatar_path, "-o", tmp_path / "z.ply", "--up", "z", "--pose", "canonical")
    _export(capsys, avatar_path, "-o", tmp_path / "y.ply", "--pose", "canonical")  # default --up y
    z, y = _read(tmp_path / "z.ply"), _read(tmp_path / "y.ply")
    assert np.array_equal(y[0], z[0] @ R_3DGS.T)  # signed permutation: exact
    # the stated map: +Z up -> -Y, the body's front (-Y) -> +Z, its left (+X) -> -X
    assert np.array_equal(R_3DGS @ [0, 0, 1], [0, -1, 0]) and np.array_equal(R_3DGS @ [0, -1, 0], [0, 0, 1])
    q = quat_multiply(np.broadcast_to(matrix_to_quat(R_3DGS), z[1].shape).copy(), z[1])
    assert _same_rotation(q, y[1], 1e-6)
    for a, b in zip(y[2:], z[2:]):
        assert np.abs(a - b).max() < 1e-6
    # upright at the origin: the head (~0.7 m above the pelvis) is at -Y in the file, the feet
    # (~0.95 m below) at +Y, so a viewer that turns the data 180 degrees about Z shows it standing
    assert -1.0 < y[0][:, 1].min() < -0.5 and 0.7 < y[0][:, 1].max() < 1.2


def test_glb_is_gltf_axes_of_the_same_gaussians(avatar_path, tmp_path, capsys):
    pygltflib = pytest.importorskip("pygltflib", reason="pygltflib (PyPI) is the third-party glTF parser")

    from dlacli.stages.export import R_GLTF

    _export(capsys, avatar_path, "-o", tmp_path / "z.ply", "--up", "z")
    _export(capsys, avatar_path, "-o", tmp_path / "a.glb")
    z = _read(tmp_path / "z.ply")
    gltf = pygltflib.GLTF2().load(str(tmp_path / "a.glb"))
    acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    view = gltf.bufferViews[acc.bufferView]
    pos = np.frombuffer(gltf.binary_blob(), "<f4", acc.count * 3, view.byteOffset).reshape(-1, 3)
    assert np.array_equal(pos, z[0] @ R_GLTF.T)
    assert pos[:, 1].max() - pos[:, 1].min() > 1.0  # +Y up: the body's height is along y


def test_motion_frame_and_sequence(avatar, avatar_path, tmp_path, capsys):
    from dlacli.body.builtin_motions import builtin_motion
    from dlacli.body.model import get_body_model
    from dlacli.stages.motion.source import _resample

    motion = _resample(builtin_motion("wave"), 2.0)  # what --fps 2 loads
    t = motion.num_frames
    assert 3 <= t < 10
    _export(capsys, avatar_path, "--motion", "wave", "--fps", "2", "--sequence", tmp_path / "seq", "--up", "z")
    names = sorted(p.name for p in (tmp_path / "seq").iterdir())
    assert names == [f"frame_{k:04d}.ply" for k in range(t)]
    _export(capsys, avatar_path, "--motion", "wave", "--fps", "2", "--frame", 2, "-o", tmp_path / "f2.ply", "--up", "z")
    one = _read(tmp_path / "f2.ply")[0]
    assert np.array_equal(one, _read(tmp_path / "seq" / "frame_0002.ply")[0])
    verts = get_body_model().forward_motion(avatar.body.phenotype, motion, frames=[2]).vertices
    assert np.abs(one - _reference(avatar, verts).means.double().numpy()).max() < 1e-6
    assert not np.array_equal(one, _read(tmp_path / "seq" / "frame_0000.ply")[0])
    # a sequence in another format replaces the folder dla wrote
    _export(capsys, avatar_path, "--motion", "wave", "--fps", "2", "--sequence", tmp_path / "seq", "--format", "spz")
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == [f"frame_{k:04d}.spz" for k in range(t)]


def test_rotate_sh_keeps_the_colour_seen_along_rotated_directions():
    from dlacli.geometry import axis_angle_to_matrix
    from dlacli.render.sh import sh_basis
    from dlacli.stages.export import R_3DGS, rotate_sh

    rng = np.random.default_rng(1)
    sh = torch.from_numpy(rng.normal(size=(20, 16, 3)))
    d = torch.nn.functional.normalize(torch.randn(200, 3, dtype=torch.float64), dim=-1)
    for rot in (R_3DGS, axis_angle_to_matrix(rng.normal(size=3))):
        new = rotate_sh(sh, rot)
        before = torch.einsum("mk,nkc->nmc", sh_basis(3, d), sh)
        after = torch.einsum("mk,nkc->nmc", sh_basis(3, d @ torch.from_numpy(rot).T), new)  # at R d
        assert torch.allclose(before, after, atol=1e-10)
        assert torch.equal(new[:, 0], sh[:, 0])


def test_rig_passes_its_arguments_to_the_rig_writer(avatar_path, tmp_path, capsys, monkeypatch):
    """--rig hands the avatar, path, motion, count, seed and checkpoint to
    dlacli.stages.rig.write_rigged_usd (a stand-in here, so this runs without pxr)."""
    import dlacli.stages.rig as rig

    calls = []
    monkeypatch.setattr(rig, "write_rigged_usd", lambda avatar, path, **kw: calls.append((avatar, path, kw)))
    _export(
        capsys, avatar_path, "--rig", "-o", tmp_path / "rig.usdc", "--motion", "wave", "--gaussians", 64, "--seed", 9
    )
    ((av, path, kw),) = calls
    assert path == tmp_path / "rig.usdc" and kw["n_gaussians"] == 64 and kw["seed"] == 9
    assert kw["motion"].num_frames == 91 and kw["checkpoint"] is None and av.decoder == "identity"


def test_rig_writes_a_usd(avatar_path, tmp_path, capsys):
    """The real --rig path: a UsdSkel file and its colour texture (tests/io/test_usd_rig.py and
    tests/blender/ check what is in them)."""
    _export(capsys, avatar_path, "--rig", "-o", tmp_path / "rig.usda")
    assert (tmp_path / "rig.usda").stat().st_size > 0 and (tmp_path / "rig.albedo.png").is_file()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["-o", "{w}/a.obj"], ["a.obj", "splat format"]),
        (["-o", "{w}/a.usdc"], ["--rig"]),
        (["--rig", "-o", "{w}/a.ply"], [".usdc"]),
        (["--rig", "-o", "{w}/a.usdc", "--motion", "wave", "--sequence", "{w}/s"], ["--sequence", "--rig"]),
        (["--motion", "wave", "-o", "{w}/a.ply"], ["--motion", "--frame"]),
        (["--sequence", "{w}/s"], ["--sequence", "--motion"]),
        (["--frame", "2", "-o", "{w}/a.ply"], ["--frame", "--motion"]),
        (["--motion", "wave", "--frame", "91", "-o", "{w}/a.ply"], ["--frame", "90"]),
        (["--motion", "wave", "--frame", "1", "--pose", "rest", "-o", "{w}/a.ply"], ["--pose"]),
        (["--pose", "tpose", "-o", "{w}/a.ply"], ["--pose", "tpose"]),
        (["--up", "x", "-o", "{w}/a.ply"], ["--up"]),
        (["--up", "z", "-o", "{w}/a.glb"], ["--up", "glTF"]),
        (["-o", "{w}/a.ply", "--sequence", "{w}/s", "--motion", "wave"], ["-o", "--sequence"]),
        (["--motion", "wave", "--sequence", "{w}/s", "--format", "obj"], ["--format"]),
        (["-o", "{av}"], ["splat format"]),
    ],
)
def test_usage_errors_are_one_line_and_write_nothing(avatar_path, tmp_path, capsys, argv, words):
    argv = [a.format(w=tmp_path, av=avatar_path) for a in argv]
    code, err = _run(capsys, "export", avatar_path, *argv)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    for word in words:
        assert word in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_outputs_never_replace_inputs(avatar_path, tmp_path, capsys):
    import shutil

    shutil.copy(avatar_path, tmp_path / "av.ply")  # an avatar under a splat name is still the input
    before = (tmp_path / "av.ply").read_bytes()
    code, err = _run(capsys, "export", tmp_path / "av.ply", "-o", tmp_path / "av.ply")
    assert code == 2 and "input" in err
    (tmp_path / "seq").mkdir()
    shutil.copy(avatar_path, tmp_path / "seq" / "frame_0000.ply")
    code, err = _run(
        capsys, "export", tmp_path / "seq" / "frame_0000.ply", "--motion", "wave", "--sequence", tmp_path / "seq"
    )
    assert code == 2 and "input" in err
    (tmp_path / "seq" / "notes.txt").write_text("mine")
    code, err = _run(capsys, "export", avatar_path, "--motion", "wave", "--sequence", tmp_path / "seq")
    assert code == 2 and "notes.txt" in err
    assert (tmp_path / "av.ply").read_bytes() == before and (tmp_path / "seq" / "notes.txt").exists()
