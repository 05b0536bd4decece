"""The learned method as one network (stages/lift/learned.py): checkpoints, the codec's decoder "gpd",
`dla lift --method learned`, and the stages that decode a learned avatar (animate, edit swap)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch


def conditioning(vertices, rest_vertices, eye, resolution: int) -> torch.Tensor:
    """[12, R, R] what the GPD's pose/view branch sees of one target, built here from the codec's
    own maps (relative positions, normals, Plücker rays in UV space) as the oracle's input."""
    from dlacli.avatar.codec import pose_conditioning, uv_rays

    v = torch.as_tensor(vertices, dtype=torch.float32)
    pose = pose_conditioning(v, np.asarray(rest_vertices), resolution)
    rays = uv_rays(v, torch.as_tensor(eye, dtype=torch.float32), resolution)
    return torch.cat([pose.relative_positions, pose.normals, rays], dim=0)


def decode(net, z: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
    """The GPD's batched form, the oracle of the codec's per-frame path: z [B], cond [B, 12] -> F [B]."""
    trunk = net.gpd.trunk(z)
    return net.gpd.canonical(z, trunk=trunk) + net.gpd.delta(z, cond, trunk=trunk)


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """A randomly initialised tiny network whose pose/view branch is switched on (non-zero)."""
    from dlacli.avatar.checkpoint import save_checkpoint
    from dlacli.nn.learned import LearnedAvatarNet, learned_config

    torch.manual_seed(0)
    cfg = learned_config("tiny")
    net = LearnedAvatarNet(cfg)
    with torch.no_grad():  # a fresh branch outputs exactly 0; give it weights so delta matters
        net.gpd.delta_out.weight.normal_(0.0, 0.01)
    path = tmp_path_factory.mktemp("ckpt") / "generator"
    digest = save_checkpoint(path, net, cfg, step=0)
    return path, digest, net.eval()


def _posed(subject_dir):
    from dlacli.body.model import get_body_model
    from dlacli.io.views import read_views

    views = read_views(subject_dir)
    m = get_body_model()
    return views, m.forward_body(views.body).vertices[0].float(), m.rest_vertices(views.body.phenotype)


def test_presets_agree_and_variants_switch_the_ablations():
    from dlacli.nn.learned import LearnedAvatarNet, learned_config

    for preset in ("tiny", "small", "paper"):
        cfg = learned_config(preset)
        assert cfg.unet.feature_channels == cfg.encoder.feature_channels
        assert cfg.encoder.latent_channels == cfg.gpd.latent_channels
    a = learned_config("tiny", "learned-query")
    b = learned_config("tiny", "no-conditioning")
    assert a.encoder.query == "learned" and a.gpd.pose_conditioned
    assert not b.gpd.pose_conditioned and not b.gpd.view_conditioned
    assert not LearnedAvatarNet(b).conditioned and LearnedAvatarNet(a).conditioned


def test_checkpoint_round_trip_gives_the_same_avatar_maps(tiny_checkpoint, subject):
    from dlacli.avatar.checkpoint import load_checkpoint
    from dlacli.geometry import camera_centers

    path, digest, net = tiny_checkpoint
    loaded = load_checkpoint(path)
    assert loaded.hash == digest
    views, verts, rest = _posed(subject)
    z = torch.randn(16, 16, 16, generator=torch.Generator().manual_seed(1))
    cond = conditioning(verts, rest, camera_centers(views.cameras.viewmats)[0], net.resolution)[None]
    with torch.no_grad():
        a = decode(net, z[None], cond)
        b = decode(loaded.module, z[None], cond)
    assert torch.equal(a, b)


def test_codec_decodes_a_learned_avatar_as_the_batched_path_does(tiny_checkpoint, subject):
    """Decoded.at (the codec's per-frame path used by animate/render) equals the network's batched
    decode with the same conditioning maps, and the delta depends on pose and on camera."""
    from dlacli.avatar.codec import Decoded
    from dlacli.body.uv import UV_LAYOUT
    from dlacli.geometry import camera_centers
    from dlacli.types import Avatar

    path, digest, net = tiny_checkpoint
    views, verts, rest = _posed(subject)
    z = torch.randn(16, 16, 16, generator=torch.Generator().manual_seed(2)).numpy()
    av = Avatar(z=z, encoder="learned", decoder="gpd", body=views.body, uv_layout=UV_LAYOUT, checkpoint=digest)
    dec = Decoded(av, checkpoint=str(path))
    assert dec.conditioned and dec.resolution == net.resolution
    eyes = camera_centers(views.cameras.viewmats)
    with torch.no_grad():
        got = dec.at(dec.pose(verts), dec.rays(verts, eyes[0]))
        want = decode(net, torch.from_numpy(z)[None], conditioning(verts, rest, eyes[0], net.resolution)[None])
        other_cam = dec.at(dec.pose(verts), dec.rays(verts, eyes[1]))
        rest_pose = dec.at(dec.pose(torch.from_numpy(rest).float()), dec.rays(verts, eyes[0]))
    np.testing.assert_allclose(got.numpy(), want[0].numpy(), rtol=1e-5, atol=1e-5)
    assert float((other_cam - got).abs().max()) > 1e-4  # view-conditioned
    assert float((rest_pose - got).abs().max()) > 1e-4  # pose-conditioned
    # a wrong checkpoint for the avatar's hash is refused in one line
    from dlacli.errors import DlaInputError

    bad = Avatar(z=z, encoder="learned", decoder="gpd", body=views.body, uv_layout=UV_LAYOUT, checkpoint="0" * 64)
    with pytest.raises(DlaInputError, match="made with"):
        Decoded(bad, checkpoint=str(path))


def test_lift_learned_refines_z_against_the_input_views(tiny_checkpoint, subject):
    from dlacli.io.views import read_views
    from dlacli.stages.lift.learned import lift_learned

    path, digest, _ = tiny_checkpoint
    views = read_views(subject)
    zero = lift_learned(views, str(path), steps=0)
    refined = lift_learned(views, str(path), steps=6, render_size=64)
    av = zero.avatar
    assert (av.encoder, av.decoder, av.checkpoint) == ("learned", "gpd", digest)
    assert av.z.shape == (16, 16, 16) and np.isfinite(av.z).all()
    assert av.canonical is not None and av.canonical.shape == (14, 64, 64)
    assert len(zero.unstructured.means) == 4 * 32 * 32  # the U-Net's pixel-aligned Gaussians
    hist = [refined.avatar.extra["lift"]["final_loss"]]
    assert hist[0] is not None
    # the renders of the refined Z are closer to the inputs than those of the encoder's Z
    from dlacli.stages.lift.learned import load_learned, render_targets

    net, _ = load_learned(str(path))
    rgb, mask, cams = views.targets(64)
    _, verts, rest = _posed(subject)

    def err(z):
        with torch.no_grad():
            pred, alpha = render_targets(net, torch.from_numpy(z), verts, rest, cams)
        return float((pred - rgb).abs().mean() + (alpha - mask).abs().mean())

    assert err(refined.avatar.z) < err(zero.avatar.z)


def _dla(*args, env=None):
    return subprocess.run(
        [sys.executable, "-m", "dlacli.cli.app", *map(str, args)], capture_output=True, text=True, env=env
    )


def test_cli_lift_learned_then_animate_and_swap(tiny_checkpoint, subject, tmp_path, monkeypatch):
    import os

    from dlacli.paths import cache_dir

    path, digest, _ = tiny_checkpoint
    # a fresh checkpoints cache (anny's model cache stays where it is)
    env = {**os.environ, "DLA_CACHE_DIR": str(tmp_path / "cache"), "ANNY_CACHE_DIR": str(cache_dir("anny"))}
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    r = _dla("lift", subject, "--method", "learned", "--checkpoint", path, "-o", a, env=env)
    assert r.returncode == 0, r.stderr
    r = _dla("lift", subject, "--method", "learned", "--checkpoint", path, "--steps", "1", "-o", b, env=env)
    assert r.returncode == 0, r.stderr
    # the checkpoint was installed in the cache under its hash: animate needs no --checkpoint
    r = _dla("animate", a, "wave", "--gaussians", "2048", "-o", tmp_path / "wave.usdc", env=env)
    assert r.returncode == 0, r.stderr
    from dlacli.io.avatar import read_avatar

    r = _dla("edit", "swap", a, b, "--region", "face", "-o", tmp_path / "ab.npz", env=env)
    assert r.returncode == 0, r.stderr
    za, zb, zab = (read_avatar(p).z for p in (a, b, tmp_path / "ab.npz"))
    from dlacli.body.regions import region_mask

    face = region_mask("face", za.shape[1])
    assert face.any() and (~face).any()
    np.testing.assert_array_equal(zab[:, face], zb[:, face])
    np.testing.assert_array_equal(zab[:, ~face], za[:, ~face])
    assert read_avatar(tmp_path / "ab.npz").canonical is None  # re-decoded from the swapped Z
    r = _dla("render", tmp_path / "ab.npz", "-o", tmp_path / "frames", "--turntable", "2", "--size", "64", env=env)
    assert r.returncode == 0, r.stderr


def test_cli_lift_method_and_checkpoint_must_agree(subject, tmp_path, tiny_checkpoint):
    path = tiny_checkpoint[0]
    r = _dla("lift", subject, "--method", "learned", "-o", tmp_path / "x.npz")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [r.stderr.strip()]
    assert "--checkpoint" in r.stderr
    r = _dla("lift", subject, "--checkpoint", path, "-o", tmp_path / "x.npz")
    assert r.returncode == 2 and "takes no checkpoint" in r.stderr
    r = _dla("lift", subject, "--method", "learned", "--checkpoint", tmp_path, "-o", tmp_path / "x.npz")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert not (tmp_path / "x.npz").exists()
