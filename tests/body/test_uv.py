"""UV space: rasters, maps, tangent frames and sampling, checked against geometry from trimesh."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from dlacli.body import uv as U
from dlacli.body.model import get_body_model

RES = 256


@pytest.fixture(scope="module")
def body():
    return get_body_model()


@pytest.fixture(scope="module")
def posed(body):
    """Two frames: the zero pose and a random pose with a root transform."""
    rng = np.random.default_rng(11)
    rot = torch.from_numpy((rng.normal(size=(2, 104, 3)) * 0.25).astype(np.float32))
    rot[0] = 0
    rot[:, 0] = 0
    rr = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.3, 1.1]])
    rt = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.5, -0.1]])
    return body.forward({}, rot, rr, rt).vertices.double()  # [2, V, 3]


def test_raster_texels_map_to_their_uv_centres(body):
    ras = U.uv_raster(RES)
    assert ras.face_id.shape == (RES, RES) and ras.mask.mean() > 0.5
    rows, cols, fid = U.valid_texels(RES)
    uv = U.sample_uv_points(fid, ras.bary[rows, cols])
    # texel (i, j) has its centre at u = (j + 0.5) / R, v = 1 - (i + 0.5) / R (row 0 is v = 1)
    np.testing.assert_allclose(uv[:, 0], (cols + 0.5) / RES, atol=1e-5)
    np.testing.assert_allclose(uv[:, 1], 1.0 - (rows + 0.5) / RES, atol=1e-5)
    assert ras.bary[rows, cols].min() >= -1e-6


def test_raster_disk_cache_round_trip():
    first = U.uv_raster(64)
    U.uv_raster.cache_clear()
    again = U.uv_raster(64)  # from the npz cache
    np.testing.assert_array_equal(first.face_id, again.face_id)
    np.testing.assert_array_equal(first.bary, again.bary)


def test_position_map_lies_on_posed_mesh(body, posed):
    pmap = U.position_map(posed, RES).numpy()  # [2, R, R, 3]
    ras = U.uv_raster(RES)
    rows, cols, fid = U.valid_texels(RES)
    assert np.all(pmap[:, ~ras.mask] == 0)
    for t in range(2):
        pts = pmap[t, rows, cols]
        tri = posed[t].numpy()[body.faces[fid]]  # [N, 3, 3]
        # direct: solve p - a = s e1 + t e2 + d n (n unit normal): inside when s, t >= 0, s + t <= 1,
        # and then the distance to the triangle is |d|
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        n = np.cross(e1, e2)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        coef = np.linalg.solve(np.stack([e1, e2, n], axis=-1), (pts - tri[:, 0])[..., None])[..., 0]
        assert coef[:, :2].min() > -1e-4 and coef[:, :2].sum(1).max() < 1 + 1e-4
        assert np.abs(coef[:, 2]).max() < 1e-5
        # whole mesh (trimesh, brute force: no rtree here), on a sample of texels whose triangles
        # are not sub-millimetre slivers (trimesh's closest-point tolerances are ~1e-4 m on those)
        mesh = trimesh.Trimesh(posed[t].numpy(), body.faces, process=False)
        big = np.flatnonzero(np.linalg.norm(np.cross(e1, e2), axis=1) > 1e-5)
        sample = np.random.default_rng(t).choice(big, 40, replace=False)
        _, dist, _ = trimesh.proximity.closest_point_naive(mesh, pts[sample])
        assert dist.max() < 1e-5


def test_tangent_frames_orthonormal_right_handed_and_aligned(body, posed):
    fid, bary = U.sample_surface(4000, seed=3)
    pos, rot, scale = U.tangent_frames(posed, fid, bary)
    assert pos.shape == (2, 4000, 3) and rot.shape == (2, 4000, 3, 3) and scale.shape == (2, 4000)
    eye = torch.eye(3, dtype=rot.dtype)
    assert (rot.transpose(-1, -2) @ rot - eye).abs().max() < 1e-9
    assert (torch.linalg.det(rot) - 1).abs().max() < 1e-9
    # normals agree with the (independently computed) face normals
    for t in range(2):
        mesh = trimesh.Trimesh(posed[t].numpy(), body.faces, process=False)
        fn = mesh.face_normals[fid]
        dots = (rot[t, :, :, 2].numpy() * fn).sum(1)
        # smooth normals differ from face normals only at a few creases (finger tips, lips)
        assert np.median(dots) > 0.98 and np.mean(dots > 0.7) > 0.98 and np.mean(dots > 0) > 0.999
    # the tangent points along +u: a small step in u within the triangle moves along it
    _, uv, face_uv = U._layout()
    pts_uv = U.sample_uv_points(fid, bary)
    inner = bary.min(1) > 0.05
    step = pts_uv[inner] + np.array([1e-4, 0.0])
    b2 = U.uv_barycentrics(step, fid[inner])
    p1 = U.surface_points(posed, fid[inner], b2).numpy()
    d = p1 - pos[:, inner].numpy()
    n = rot[:, inner, :, 2].numpy()
    d -= (d * n).sum(-1, keepdims=True) * n
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    cos = (d * rot[:, inner, :, 0].numpy()).sum(-1)
    assert np.median(cos) > 0.999 and np.mean(cos > 0.95) > 0.99


def test_texel_scale_integrates_to_surface_area(body, posed):
    """S is metres per texel: the covered texels' S^2 sum to the mesh area (charts barely overlap)."""
    _, _, smap = U.texel_frames(posed[0], RES)
    area = trimesh.Trimesh(posed[0].numpy(), body.faces, process=False).area
    total = float((smap.double() ** 2).sum())
    assert abs(total / area - 1) < 0.03, (total, area)
    # S at another reference resolution scales with 1 / R
    fid, bary = U.sample_surface(100, seed=0)
    _, _, s256 = U.tangent_frames(posed[0], fid, bary, resolution=256)
    _, _, s512 = U.tangent_frames(posed[0], fid, bary, resolution=512)
    np.testing.assert_allclose(s256.numpy(), 2 * s512.numpy(), rtol=1e-9)


def test_normal_and_relative_maps(body, posed):
    nmap = U.normal_map(posed, RES)
    ras = U.uv_raster(RES)
    norms = nmap[:, torch.from_numpy(ras.mask)].norm(dim=-1)
    assert (norms - 1).abs().max() < 1e-6
    rest = posed[0]
    rel = U.relative_position_map(posed, rest, RES)
    assert rel[0].abs().max() == 0
    diff = U.position_map(posed[1], RES) - U.position_map(rest, RES)
    assert (rel[1] - diff).abs().max() < 1e-9
    # a pure translation shows up unchanged on every covered texel
    shift = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    rel_t = U.relative_position_map(rest + shift, rest, RES)
    assert (rel_t[torch.from_numpy(ras.mask)] - shift).abs().max() < 1e-9


def test_surface_sampling_is_area_weighted_and_seeded(body, posed):
    fid, bary = U.sample_surface(20000, seed=5)
    fid2, bary2 = U.sample_surface(20000, seed=5)
    np.testing.assert_array_equal(fid, fid2)
    np.testing.assert_array_equal(bary, bary2)
    assert not np.array_equal(fid, U.sample_surface(20000, seed=6)[0])
    assert bary.min() >= 0 and np.allclose(bary.sum(1), 1, atol=1e-6)
    mesh = trimesh.Trimesh(posed[0].numpy(), body.faces, process=False)
    upper = mesh.triangles_center[:, 2] > 0
    expect = mesh.area_faces[upper].sum() / mesh.area
    got = upper[fid].mean()
    assert abs(got - expect) < 4 * np.sqrt(expect * (1 - expect) / 20000)


def test_uv_sampling_uniform_over_covered_texels():
    n = 40000
    fid, bary = U.sample_uv(n, seed=1, resolution=RES)
    assert np.array_equal(fid, U.sample_uv(n, seed=1, resolution=RES)[0])
    assert bary.min() >= -1e-6 and np.allclose(bary.sum(1), 1, atol=1e-5)
    uv = U.sample_uv_points(fid, bary)
    ras = U.uv_raster(RES)
    col = np.clip((uv[:, 0] * RES).astype(int), 0, RES - 1)
    row = np.clip(((1 - uv[:, 1]) * RES).astype(int), 0, RES - 1)
    assert ras.mask[row, col].mean() > 0.99
    # uniform over covered texels: the covered left and right halves get their share
    left = ras.mask[:, : RES // 2].sum() / ras.mask.sum()
    got = np.mean(col < RES // 2)
    assert abs(got - left) < 4 * np.sqrt(left * (1 - left) / n)
