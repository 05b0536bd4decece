"""The codec seam (avatar/codec.py): resolution of an avatar's decoder, and render / animate
decoding per camera and per frame when a decoder asks for it.

The conditioned decoders here are toys written in the test: a view-conditioned one shifts
colour by the ray direction, a pose-conditioned one by how far the body moved from rest."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlacli.avatar import codec
from dlacli.avatar import gaussian_map as gm
from dlacli.errors import DlaInputError
from dlacli.types import Avatar, BodyParams, Motion

RES = 32  # UV resolution of the test avatars
N = 4096  # Gaussians


def _avatar(decoder: str = "identity", checkpoint: str = "") -> Avatar:
    z = np.zeros((gm.CHANNELS, RES, RES), np.float32)
    z[gm.OPACITY] = 3.0
    z[gm.RGB] = 0.5
    z[gm.ROTATION.start] = 1.0
    z[gm.LOG_SCALE] = np.log(4.0)
    return Avatar(
        z=z,
        encoder="unproject",
        decoder=decoder,
        body=BodyParams(),
        uv_layout="anny",
        checkpoint=checkpoint,
        extra={"samples": {"count": N, "seed": 3}},
    )


class ViewToy(codec.Decoder):
    """F_delta: rgb += 0.4 * (x component of the ray direction); records every call."""

    name = "toy-view"
    view_conditioned = True
    resolution = RES

    def __init__(self, checkpoint: str = "", where: str = "avatar"):
        self.calls: list[torch.Tensor] = []

    def canonical(self, z):
        return z

    def delta(self, z, pose, rays):
        assert pose is None and rays.shape == (6, RES, RES)
        self.calls.append(rays)
        d = torch.zeros_like(z)
        d[gm.RGB] = 0.4 * rays[0]
        return d


class PoseToy(codec.Decoder):
    """F_delta: rgb += 0.4 tanh(mean |posed - rest|) (a scalar per pose), so colour follows the pose."""

    name = "toy-pose"
    pose_conditioned = True
    resolution = RES

    def __init__(self, checkpoint: str = "", where: str = "avatar"):
        pass

    def canonical(self, z):
        return z

    def delta(self, z, pose, rays):
        assert rays is None and pose.relative_positions.shape == (3, RES, RES)
        d = torch.zeros_like(z)
        d[gm.RGB] = 0.4 * torch.tanh(pose.relative_positions.norm(dim=0).mean())
        return d


@pytest.fixture
def toys():
    made = {}

    def view_factory(checkpoint, where):
        made["view"] = ViewToy(checkpoint, where)
        return made["view"]

    codec.register_decoder("toy-view", view_factory)
    codec.register_decoder("toy-pose", PoseToy)
    yield made
    codec._DECODERS.pop("toy-view")
    codec._DECODERS.pop("toy-pose")


def test_identity_is_resolved_and_unknown_names_fail_in_one_line():
    dec = codec.resolve_decoder(_avatar())
    assert isinstance(dec, codec.IdentityDecoder) and dec.linear and not dec.conditioned
    with pytest.raises(DlaInputError, match="decoder 'gpd' is not available.*known: identity") as err:
        codec.resolve_decoder(_avatar("gpd"), "a.npz")
    assert err.value.where == "a.npz" and "\n" not in str(err.value)
    with pytest.raises(DlaInputError, match="takes no checkpoint"):
        codec.resolve_decoder(_avatar("identity", "ab" * 32))


def test_missing_checkpoint_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv("DLA_CACHE_DIR", str(tmp_path / "cache"))
    with pytest.raises(DlaInputError) as err:
        codec.resolve_decoder(_avatar("gpd", "c0ffee" * 10 + "abcd"), "a.npz")
    message = str(err.value)
    assert "c0ffee" in message and str(tmp_path / "cache") in message and "--checkpoint" in message
    assert "\n" not in message


def test_identity_decoding_is_the_code_itself():
    av = _avatar()
    decoded = codec.Decoded(av)
    assert torch.equal(decoded.at(), torch.from_numpy(av.z))
    assert decoded.pose(torch.zeros(3, 3)) is None and decoded.rays(torch.zeros(3, 3), torch.zeros(3)) is None


def _cameras(azimuths, size=24):
    from dlacli.geometry import look_at_orbit_cameras

    return look_at_orbit_cameras(np.array([0.0, 0.0, -0.2]), 3.2, np.asarray(azimuths, float), 0.0, 40.0, size)


def test_view_conditioned_decoder_is_decoded_per_camera(toys):
    from dlacli.stages.render import render_avatar

    cams = _cameras([90.0, 270.0])  # on the +X and the -X side of the body
    plain = [s.rgba for s in render_avatar(_avatar(), cams, [None, None])]
    viewed = [s.rgba for s in render_avatar(_avatar("toy-view"), cams, [None, None])]
    assert len(toys["view"].calls) == 2  # one decode per camera, one canonical map
    assert not torch.equal(toys["view"].calls[0], toys["view"].calls[1])
    shift = []
    for p, v in zip(plain, viewed):
        inside = (p[..., 3] > 0.5) & (v[..., 3] > 0.5)
        assert inside.sum() > 20
        np.testing.assert_array_equal(p[..., 3], v[..., 3])  # only colour is conditioned
        shift.append(float((v[..., :3] - p[..., :3])[inside].mean()))
    # the camera on +X sees rays heading to -X (darker), the one on -X rays heading to +X
    assert shift[0] < -0.05 and shift[1] > 0.05


def _three_poses() -> Motion:
    from dlacli.body.builtin_motions import builtin_motion

    walk = builtin_motion("walk")
    pick = np.array([0, walk.num_frames // 4, walk.num_frames // 2])
    return Motion(
        walk.bone_labels, walk.rotations[pick], walk.root_rotation[pick], walk.root_translation[pick], walk.fps
    )


def test_pose_conditioned_decoder_is_decoded_per_frame(toys, tmp_path):
    from dlacli.stages.animate import pose_avatar, write_animation

    motion = _three_poses()
    plain = pose_avatar(_avatar(), motion)
    posed = pose_avatar(_avatar("toy-pose"), motion)
    assert plain.rgb.shape == (N, 3) and posed.rgb.shape == (3, N, 3)
    np.testing.assert_array_equal(plain.positions, posed.positions)  # geometry is not conditioned
    means = posed.rgb.reshape(3, -1).mean(axis=1)
    assert len(set(np.round(means, 4))) == 3  # a different colour for each pose
    # a USD file keeps the per-frame colours as time samples
    from pxr import Usd, UsdGeom

    write_animation(posed, tmp_path / "a.usda")
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    color = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Avatar/Gaussians")).GetPrimvar("displayColor")
    times = color.GetAttr().GetTimeSamples()
    assert len(times) == 3
    for t, want in zip(times, posed.rgb):
        np.testing.assert_allclose(np.asarray(color.Get(t)), want, rtol=0, atol=0)
    from dlacli.io.usd_read import read_usd

    back = read_usd(tmp_path / "a.usda")
    np.testing.assert_array_equal(back.rgb, posed.rgb)  # float32 colours round-trip exactly
    # opacities did not change with the pose, so the file holds them once
    assert back.opacities.shape == (N,)
    np.testing.assert_array_equal(np.broadcast_to(back.opacities, posed.opacities.shape), posed.opacities)


def test_render_and_animate_default_to_the_recorded_samples():
    from dlacli.avatar.posed import sample_settings

    assert sample_settings(_avatar()) == (N, 3)
    assert sample_settings(_avatar(), 100, 7) == (100, 7)
    bare = _avatar()
    bare.extra = {}
    assert sample_settings(bare) == (gm.DEFAULT_GAUSSIANS, 0)
    bad = _avatar()
    bad.extra = {"samples": {"count": 10**12, "seed": 0}}
    with pytest.raises(DlaInputError, match="extra.samples.count"):
        sample_settings(bad)


def test_edits_drop_a_canonical_cache_of_a_nonlinear_decoder(toys):
    from dlacli.stages.edit import interpolate, swap_region

    a, b = _avatar("toy-pose"), _avatar("toy-pose")
    b.z = b.z + 0.25
    for av in (a, b):
        av.canonical = av.z.copy()
    assert swap_region(a, b, "face").canonical is None
    assert interpolate(a, b, 0.5).canonical is None
    assert interpolate(a, b, 0.0).canonical is a.canonical  # t = 0 is a itself
    lin_a, lin_b = _avatar(), _avatar()
    lin_a.canonical, lin_b.canonical = lin_a.z.copy(), lin_b.z + 1.0
    np.testing.assert_allclose(interpolate(lin_a, lin_b, 0.5).canonical, lin_a.z + 0.5, atol=1e-6)
