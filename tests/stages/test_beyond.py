"""The layer beyond the body (dlacli.stages.dream.beyond) against a synthetic oracle: the body-backend
scene of test_texture (a posed body with a known texture photographed by a known camera, the
true body as the fit) with a uniformly coloured bun added above the head, a one-pixel fringe
around the whole mask and a detached blob. Oracles: the bun's known pixels, colour and place in
3D projected into the orbit views; the body's own render where the layer covers nothing."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from tests.stages.test_texture import RES, _camera, _map, _render, _straight, _true_texels

from dlacli.types import BodyParams, Cameras

BUN = np.array([0.85, 0.1, 0.6])  # a colour the body's texture never has


@pytest.fixture(scope="module")
def bun_photo():
    from dlacli.body.model import get_body_model, rotations_to_pose
    from dlacli.data.subject import relaxed_pose
    from dlacli.render.raster import rasterize
    from dlacli.stages.dream.views import frame_crop

    m = get_body_model()
    rot = relaxed_pose(np.random.default_rng(3), m.bone_labels, 20.0)
    verts = m.forward_body(BodyParams(pose=rotations_to_pose(rot, m))).vertices[0].numpy().astype(np.float64)
    photo = _render(verts, _map(_true_texels("pattern")), _camera())[0]
    rgb, alpha, cam = frame_crop(_straight(photo), photo[..., 3], _camera(), RES)
    body = rasterize(verts, m.faces, cam).face_id[0] >= 0
    ys, xs = np.nonzero(body)
    top = ys.min()
    cx = int(np.median(xs[ys < top + 4]))
    r = RES // 20
    yy, xx = np.mgrid[:RES, :RES]
    bun = (yy - (top - 0.5 * r)) ** 2 + (xx - cx) ** 2 <= r * r  # half of it over the head
    blob = (abs(yy - RES // 2) < 5) & (abs(xx - 8) < 5)  # 81 px, touching nothing
    person = ndimage.binary_dilation((alpha > 0.5) | bun, iterations=1) | blob  # + a 1 px fringe
    rgb = np.where((ndimage.binary_dilation(bun, iterations=1) & ~body)[..., None], BUN, rgb).astype(np.float32)
    return {
        "rgb": rgb,
        "alpha": person.astype(np.float32),
        "cam": cam,
        "verts": verts,
        "bun": bun & ~body,
        "body": body,
    }


def test_only_the_bun_lies_beyond_the_body(bun_photo):
    from dlacli.stages.dream.beyond import beyond_pixels

    s = bun_photo
    kept = beyond_pixels(s["alpha"] > 0.5, s["body"])
    near_bun = ndimage.binary_dilation(s["bun"], iterations=1)
    assert not (kept & ~near_bun).any()  # neither the fringe nor the blob
    assert (kept & s["bun"]).sum() > 0.8 * s["bun"].sum()


def test_a_mask_that_took_the_background_makes_no_layer(bun_photo):
    """A rectangle of background beside the body (larger than a quarter of the body's
    silhouette) is the segmentation's error, not clothing: no layer, the bun stays."""
    from dlacli.stages.dream.beyond import MAX_SHARE, beyond_pixels

    s = bun_photo
    ys, xs = np.nonzero(s["body"])
    wall = np.zeros_like(s["body"])
    wall[ys.min() : ys.max(), xs.max() - 2 :] = True  # from the body's right edge to the border
    assert (wall & ~s["body"]).sum() > MAX_SHARE * s["body"].sum()
    kept = beyond_pixels((s["alpha"] > 0.5) | wall, s["body"])
    assert not (kept & wall & ~ndimage.binary_dilation(s["bun"], iterations=1)).any()
    assert (kept & s["bun"]).sum() > 0.8 * s["bun"].sum()


def test_the_bun_is_seen_from_every_side(bun_photo):
    """Views 90 / 180 / 270 show the bun where the centre of its part beyond the displaced head,
    unprojected at the head's mid depth, projects, in the bun's colour; the body alone (the
    offset bound) cuts it off. Seen from the
    side, its round profile makes it about as deep as it is high."""
    from dlacli.stages.dream.beyond import layer_mesh
    from dlacli.stages.dream.shell import _unproject, body_depth_layers
    from dlacli.stages.dream.texture import body_views, render_body, textured_body

    s = bun_photo
    images, masks, cams, settings = body_views(s["rgb"], s["alpha"], s["cam"], s["verts"])
    assert settings["beyond_body_px"] >= 0.8 * s["bun"].sum()
    body = textured_body(s["rgb"], s["alpha"], s["cam"], s["verts"])
    layer = layer_mesh(s["alpha"], s["cam"], body["vertices"])
    from dlacli.body.model import get_body_model

    fid, front, _, back = body_depth_layers(body["vertices"], get_body_model().faces, s["cam"])
    ys, xs = np.nonzero(layer.pixels & s["bun"])  # the bun's part beyond the displaced head
    cy, cx = int(round(ys.mean())), int(round(xs.mean()))
    touch = ndimage.binary_dilation(layer.pixels, iterations=2) & (fid >= 0)
    mid = np.full((RES, RES), np.median(((front + back) / 2)[touch]))
    centre = _unproject(mid, np.array([cy]), np.array([cx]), s["cam"])[0]
    alone = render_body(body, Cameras(cams.viewmats[1:], cams.Ks[1:], cams.width, cams.height))
    for k in (1, 2, 3):
        vc = cams.viewmats[k].double().numpy() @ np.append(centre, 1.0)
        uvw = cams.Ks[k].double().numpy() @ vc[:3]
        u, v = int(uvw[0] / uvw[2]), int(uvw[1] / uvw[2])
        win = np.s_[v - 3 : v + 4, u - 3 : u + 4]
        pink = np.all(np.abs(images[k][win] - BUN) < 0.1, axis=-1) & (masks[k][win] > 0.99)
        gained = (masks[k] > 0.5) & (alone[k - 1][..., 3] < 0.5)  # the silhouette the layer adds
        gy, gx = np.nonzero(gained & np.all(np.abs(images[k] - BUN) < 0.1, axis=-1))
        near = np.hypot(gy - v, gx - u) < 2 * RES // 20
        print(
            f"view {k}: bun-coloured around its centre {pink.mean():.2f}; added, bun-coloured, near it: {near.sum()} px"
            f" of {gained.sum()} added, {layer.pixels.sum()} beyond the body in the photo"
        )
        share = 0.6 if k == 2 else 0.25  # seen from behind as the photo sees it; from the side, its depth
        assert pink.mean() > 0.6 and near.sum() > share * layer.pixels.sum() and near.sum() > 0.8 * gained.sum(), k
    bun_px = np.all(np.abs(images[1] - BUN) < 0.05, axis=-1) & (masks[1] > 0.99)
    rows, cols = np.nonzero(bun_px)
    height, depth = np.ptp(rows) + 1, np.ptp(cols) + 1
    print("the bun seen from the side: height, depth (px):", height, depth)
    assert 0.4 * height < depth < 1.5 * height


def test_the_body_renders_the_same_bits_where_the_layer_is_not(bun_photo):
    """The layer's colours sit beside the body's UV map in one texture: every pixel the layer
    does not touch is the body's own render, bit for bit."""
    from dlacli.render.raster import render_textured
    from dlacli.stages.dream.beyond import layer_mesh, render_with_layer
    from dlacli.stages.dream.orbit import body_pivot, orbit_cameras
    from dlacli.stages.dream.texture import render_body, textured_body

    s = bun_photo
    body = textured_body(s["rgb"], s["alpha"], s["cam"], s["verts"])
    layer = layer_mesh(s["alpha"], s["cam"], body["vertices"])
    cams = orbit_cameras(s["cam"], body_pivot(s["verts"]), (45.0, 90.0, 180.0))
    both = render_with_layer(body, layer, s["rgb"], cams)
    alone = render_body(body, cams)
    only = render_textured(layer.vertices, layer.faces, layer.uv, layer.faces, s["rgb"], cams)
    free = only[..., 3] == 0
    assert free.mean() > 0.9 and (both[..., 3] > alone[..., 3] + 0.5).any()
    np.testing.assert_array_equal(both[free], alone[free])


def test_the_layer_takes_the_photos_colour_beyond_the_body_only(bun_photo):
    """Blurred over the pixels beyond the body alone: a uniform bun keeps its colour exactly, up
    to the join inside the head, whose skin does not bleed in."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import rasterize
    from dlacli.stages.dream.beyond import layer_colours, layer_mesh
    from dlacli.stages.dream.texture import displaced_body

    s = bun_photo
    displaced, _ = displaced_body(s["alpha"], s["cam"], s["verts"])
    layer = layer_mesh(s["alpha"], s["cam"], displaced)
    colours = layer_colours(s["rgb"].astype(np.float64), layer)
    on_bun = layer.cover & ndimage.binary_dilation(s["bun"], iterations=4)
    assert (on_bun & (rasterize(displaced, get_body_model().faces, s["cam"]).face_id[0] >= 0)).any()
    np.testing.assert_allclose(colours[on_bun], np.broadcast_to(BUN, colours[on_bun].shape), atol=1e-9)
    assert not colours[~layer.cover].any()


def test_each_piece_stands_at_one_depth():
    """A piece touching two body parts at different depths (2 m and 4 m) is not stretched
    between them (a sheet): it stands at one mid depth, the median of what it touches."""
    from dlacli.stages.dream.beyond import layer_depths

    h = w = 64
    fid = np.full((h, w), -1)
    front, back = np.full((h, w), np.inf), np.full((h, w), np.inf)
    fid[20:44, 10:30], front[20:44, 10:30], back[20:44, 10:30] = 0, 1.9, 2.1
    fid[20:44, 34:54], front[20:44, 34:54], back[20:44, 34:54] = 1, 3.9, 4.1
    pixels = np.zeros((h, w), bool)
    pixels[10:20, 20:44] = True  # above both blocks, touching both
    person = pixels | (fid >= 0)
    cover = pixels | (ndimage.binary_dilation(pixels, iterations=2) & person)
    f, b = layer_depths(person, pixels, cover, fid, front, back, focal=100.0)
    mid = ((f + b) / 2)[cover]
    np.testing.assert_allclose(mid, np.full_like(mid, np.median(mid)), rtol=1e-12)
    assert 2.0 <= mid[0] <= 4.0 and np.all(b[cover] >= f[cover]) and not np.isfinite(f[~cover]).any()
