"""avatar/posed.py, the one path from a decoded avatar to posed Gaussians: what it computes once
and what per body and camera, against the pieces it is made of (gaussian_map's skinning of a map,
the codec's F = F_c + F_delta), and gradients through it to the code."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlacli.avatar import codec
from dlacli.avatar import gaussian_map as gm
from dlacli.avatar.posed import PosedAvatar
from dlacli.types import Avatar, BodyParams

R = 16
N = 600


def _z(channels: int = gm.CHANNELS) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    z = torch.zeros(channels, R, R)
    z[gm.OPACITY] = 2.0 + torch.rand(1, R, R, generator=g)
    z[gm.RGB] = 0.2 + 0.6 * torch.rand(3, R, R, generator=g)
    z[gm.OFFSET] = 0.005 * torch.randn(3, R, R, generator=g)
    z[gm.ROTATION.start] = 1.0
    z[gm.LOG_SCALE] = np.log(3.0)
    return z


@pytest.fixture(scope="module")
def bodies():
    """Two posed bodies [2, V, 3] (rest and an arm raised) and the zero pose [V, 3]."""
    from dlacli.body.model import get_body_model

    m = get_body_model()
    bent = BodyParams(pose={"upperarm01.L": np.array([0.0, 0.0, 0.8])})
    verts = torch.cat([m.forward_body(BodyParams()).vertices, m.forward_body(bent).vertices])
    return verts, m.rest_vertices(BodyParams().phenotype)


def _eyes(p: int, c: int) -> torch.Tensor:
    a = torch.linspace(0.0, 2.0 * np.pi, c + 1)[:c]
    ring = torch.stack([3.0 * torch.sin(a), -3.0 * torch.cos(a), torch.full_like(a, 0.2)], dim=-1)  # [C, 3]
    return ring[None].expand(p, -1, -1) + 0.1 * torch.arange(p, dtype=torch.float32)[:, None, None]


class Counting(codec.Decoder):
    """F_c = z; F_delta shifts colour by the pose (mean relative position) and the ray's x; counts
    every call and records what each delta saw."""

    name = "counting"
    pose_conditioned = view_conditioned = True
    resolution = R

    def __init__(self):
        self.calls = {"prepare": 0, "canonical": 0, "delta": []}

    def prepare(self, z):
        self.calls["prepare"] += 1
        return "trunk"

    def canonical(self, z, prepared=None):
        assert prepared == "trunk"
        self.calls["canonical"] += 1
        return z

    def delta(self, z, pose, rays, prepared=None):
        assert prepared == "trunk"
        self.calls["delta"].append((pose, rays))
        d = torch.zeros_like(z)
        d[gm.RGB] = 0.3 * torch.tanh(pose.relative_positions.mean()) + 0.2 * rays[0]
        return d


def test_an_unconditioned_avatar_is_its_map_skinned_onto_every_body(bodies):
    verts, _ = bodies
    samples = gm.make_samples(N, 1)
    z = _z()
    av = Avatar(z=z.numpy(), encoder="unproject", decoder="identity", body=BodyParams(), uv_layout="anny")
    posed = PosedAvatar(codec.Decoded(av), samples, verts, eyes=_eyes(2, 3))
    assert not posed.per_camera and posed.cameras == 3 and len(posed) == 2
    placed = posed.all()
    want = gm.skinned_params_on_body(z, samples, verts)  # one batch, shared colours
    for got, ref in zip((placed.means, placed.quats, placed.scales, placed.opacities, placed.rgb), want):
        assert torch.equal(got, ref)
    for p in range(2):  # body by body: what render and export drew before, bit for bit
        alone = gm.skinned_params_on_body(z, samples, verts[p : p + 1])
        got = posed.gaussians(p, 2)
        for a, b in zip((got.means, got.quats, got.scales), alone[:3]):
            assert torch.equal(a, b[0])


def test_conditioning_is_computed_once_per_body_and_per_camera(bodies, monkeypatch):
    verts, rest = bodies
    samples = gm.make_samples(N, 1)
    made = []
    real = codec.PoseConditioning.of_body
    monkeypatch.setattr(codec.PoseConditioning, "of_body", lambda *a: made.append(a) or real(*a))
    dec = Counting()
    decoded = codec.Decoded.of(dec, _z(), rest)
    eyes = _eyes(2, 3)
    posed = PosedAvatar(decoded, samples, verts, eyes=eyes)
    assert posed.per_camera
    sets = {(p, c): posed.placed(p, c) for p in range(2) for c in range(3)}
    assert dec.calls["prepare"] == 1 and dec.calls["canonical"] == 1  # F_c once, the shared part once
    assert len(made) == 2 and len(dec.calls["delta"]) == 6  # pose maps once per body, F_delta per pair
    for k, (p, c) in enumerate(sets):
        pose, rays = dec.calls["delta"][k]
        assert torch.equal(pose.relative_positions, codec.pose_conditioning(verts[p], rest, R).relative_positions)
        assert torch.equal(rays, codec.uv_rays(verts[p], eyes[p, c], R))
        # the set is F = F_c + F_delta of that body and camera, skinned onto that body
        fmap = decoded.f_c + Counting.delta(dec, decoded.z, pose, rays, "trunk")
        means, _, _, _, rgb = gm.skinned_params_on_body(fmap, samples, verts[p : p + 1])
        assert torch.equal(sets[p, c].means, means) and torch.equal(sets[p, c].rgb[0], rgb)
        assert sets[p, c].delta.shape == (1, gm.CHANNELS, R, R)
    assert not torch.equal(sets[0, 0].rgb, sets[0, 1].rgb) and not torch.equal(sets[0, 0].rgb, sets[1, 0].rgb)
    stacked = posed.all(c=1)  # every body from its camera 1
    assert torch.equal(stacked.rgb, torch.cat([sets[0, 1].rgb, sets[1, 1].rgb]))
    assert stacked.delta.shape == (2, gm.CHANNELS, R, R)


def test_a_colour_only_delta_reuses_the_geometry_and_changes_nothing(bodies):
    """A decoder whose F_delta touches colour only (view-cosine) is skinned once per body and
    looked up per camera for its colours: the same numbers, bit for bit, as skinning F_c + F_delta
    whole for every camera, and the rays share the body's texel positions."""
    from dlacli.body.uv import position_map

    verts, rest = bodies
    samples = gm.make_samples(N, 1)
    z = torch.cat([_z(), torch.full((1, R, R), 0.6)])  # falloff k = 0.6
    dec = codec.ViewCosineDecoder()
    assert not dec.delta_geometry
    decoded = codec.Decoded.of(dec, z, rest)
    eyes = _eyes(2, 3)
    posed = PosedAvatar(decoded, samples, verts, eyes=eyes)
    for p in range(2):
        pose = decoded.pose(verts[p])
        assert torch.equal(pose.positions, position_map(verts[p], R))
        for c in range(3):
            rays = codec.uv_rays(verts[p], eyes[p, c], R)
            assert torch.equal(decoded.rays(verts[p], eyes[p, c], pose), rays)
            fmap = decoded.f_c + dec.delta(z, pose, rays)
            want = gm.skinned_params_on_body(fmap, samples, verts[p : p + 1])
            got = posed.placed(p, c)
            for a, b in zip((got.means, got.quats, got.scales, got.opacities[0], got.rgb[0]), want):
                assert torch.equal(a, b[0] if a.ndim == b.ndim - 1 and b.shape[0] == 1 else b)
    assert not torch.equal(posed.placed(0, 0).rgb, posed.placed(0, 1).rgb)  # the colours do follow the camera
    assert posed.placed(1, 0).means is posed.placed(1, 2).means  # one skinning per body


def test_pose_maps_are_made_when_read(bodies):
    from dlacli.body.uv import normal_map, position_map, relative_position_map, surface_maps

    verts, rest = bodies
    asked = []
    pose = codec.PoseConditioning.of_body(verts[1], lambda: asked.append(1) or rest, R)
    assert torch.equal(pose.normals, normal_map(verts[1], R).permute(2, 0, 1))
    assert not asked  # the normals alone never ask for the rest pose
    assert torch.equal(pose.relative_positions, relative_position_map(verts[1], rest, R).permute(2, 0, 1))
    assert asked == [1]
    pos, nrm = surface_maps(verts, R)  # one pass of the kernels for both maps
    assert torch.equal(pos, position_map(verts, R)) and torch.equal(nrm, normal_map(verts, R))
    v = verts.clone().requires_grad_(True)  # a gradient asked for: the torch path
    pos, nrm = surface_maps(v, R)
    assert pos.requires_grad and nrm.requires_grad
    assert torch.equal(pos, position_map(v, R)) and torch.equal(nrm, normal_map(v, R))


def test_canonical_only_places_f_c(bodies):
    verts, rest = bodies
    samples = gm.make_samples(N, 1)
    dec = Counting()
    posed = PosedAvatar(codec.Decoded.of(dec, _z(), rest), samples, verts[:1], canonical_only=True)
    placed = posed.all()
    assert dec.calls["delta"] == [] and placed.delta is None and placed.rgb.shape == (N, 3)
    assert torch.equal(placed.rgb, gm.skinned_params(_z(), samples, posed.frames)[4])


def test_render_splats_each_set_with_its_cameras(bodies):
    from dlacli.geometry import camera_centers, look_at_orbit_cameras
    from dlacli.render.splat import render_gaussians
    from dlacli.types import rgb_to_sh0

    verts, rest = bodies
    samples = gm.make_samples(N, 1)
    cams = look_at_orbit_cameras(np.array([0.0, 0.0, -0.2]), 3.0, np.array([0.0, 90.0, 200.0]), 5.0, 40.0, 24)
    view = PosedAvatar(codec.Decoded.of(Counting(), _z(), rest), samples, verts, cams)
    assert torch.equal(view.eyes, camera_centers(cams.viewmats)[None].expand(2, -1, -1))
    groups = list(view.renders(body=1))
    assert [list(g) for g, _ in groups] == [[0], [1], [2]]  # F_delta moves the geometry: a set per camera
    for c, (_, out) in enumerate(groups):
        assert torch.equal(out.rgb, render_gaussians(view.gaussians(1, c), cams.select(c)).rgb)
    av = Avatar(z=_z().numpy(), encoder="unproject", decoder="identity", body=BodyParams(), uv_layout="anny")
    plain = PosedAvatar(codec.Decoded(av), samples, verts, cams)
    groups = list(plain.renders(per_call=2))
    assert [list(g) for g, _ in groups] == [[0, 1], [2]]  # one set, cameras in calls of 2
    assert torch.equal(groups[1][1].alpha, render_gaussians(plain.gaussians(0), cams.select(2)).alpha)
    # a colour-only F_delta (view-cosine): one geometry, each camera's colours, in one call; the
    # same bits as each camera's own set rendered alone
    z = torch.cat([_z(), torch.full((1, R, R), 0.6)])
    cosine = PosedAvatar(codec.Decoded.of(codec.ViewCosineDecoder(), z, rest), samples, verts, cams)
    assert cosine.per_camera
    with torch.no_grad():
        groups = list(cosine.renders(body=0))
        assert [list(g) for g, _ in groups] == [[0, 1, 2]]
        joined = cosine.render(0)
        for c in range(3):
            alone = render_gaussians(cosine.gaussians(0, c), cams.select(c))
            assert torch.equal(joined.rgb[c], alone.rgb[0]) and torch.equal(joined.alpha[c], alone.alpha[0])
        assert not torch.equal(joined.rgb[0], render_gaussians(cosine.gaussians(0, 1), cams.select(0)).rgb[0])
        placed = cosine.placed(0, 2)
        assert torch.equal(rgb_to_sh0(placed.rgb[0])[:, None], cosine.gaussians(0, 2).sh)
    # with a gradient asked for, each camera alone with its own set (the gradients as before)
    tracked = PosedAvatar(
        codec.Decoded.of(codec.ViewCosineDecoder(), z.clone().requires_grad_(True), rest), samples, verts, cams
    )
    groups = list(tracked.renders(body=0))
    assert [list(g) for g, _ in groups] == [[0], [1], [2]] and groups[0][1].rgb.requires_grad
    # the torch path (skinning and view-cosine with gradients) against the kernels': float32
    # rounding of colours <= 1 composited over a few Gaussians
    assert (groups[2][1].rgb.detach() - joined.rgb[2:3]).abs().max() < 1e-4
    # one Cameras per body: body p is drawn from its own
    own = PosedAvatar(codec.Decoded(av), samples, verts, [cams.select(1), cams.select(2)])
    assert torch.equal(own.render(1).rgb, render_gaussians(own.gaussians(1), cams.select(2)).rgb)


def test_gradients_reach_the_code(bodies):
    from dlacli.geometry import look_at_orbit_cameras

    verts, rest = bodies
    samples = gm.make_samples(N, 1)
    cams = look_at_orbit_cameras(np.array([0.0, 0.0, -0.2]), 3.0, np.array([90.0, 270.0]), 5.0, 40.0, 24)
    k = torch.full((1, R, R), 0.5)
    z = torch.cat([_z(), k]).requires_grad_(True)  # a view-cosine code being refined
    decoded = codec.Decoded.of(codec.ViewCosineDecoder(), z, rest)
    posed = PosedAvatar(decoded, samples, verts[:1], cams)
    out = posed.render()
    loss = out.rgb.sum() + out.alpha.sum()
    loss.backward()
    grad = z.grad
    assert torch.isfinite(grad).all()
    for channels in (gm.OPACITY, gm.RGB, gm.OFFSET, slice(14, 15)):  # geometry, colour and the falloff k
        assert float(grad[channels].abs().max()) > 0
