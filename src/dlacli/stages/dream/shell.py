"""The "shell" backend of dla dream (docs/dream.md "Shell"): a 2.5D shell built from the photo's
silhouette and the fitted body's depth (`shell_mesh`), coloured from the photo in front and from
the mirrored front behind (`back_colours`), rendered from the orbit cameras (`template_views`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from dlacli.errors import DlaInputError
from dlacli.types import Cameras

CUT_DEPTH = 0.04  # metres: a shell triangle over two body parts spanning a larger jump is left out
CUT_FAR = 0.3  # metres: any shell triangle spanning a larger depth jump is left out
INFLATE = 0.8  # thickness of the shell outside the body (hair, loose cloth), x a round profile


def body_depth_layers(vertices: np.ndarray, faces: np.ndarray, camera: Cameras):
    """Nearest and farthest body surface per pixel of one camera.

    vertices [V, 3] world, faces [F, 3], camera: 1 camera (H x W).

    -> (front face id [H, W], front depth [H, W], back face id [H, W], back depth [H, W]); ids -1
    and depths +inf where the body is not seen. The farthest layer is the nearest layer of the
    mesh with camera depths mirrored (z -> z_min + z_max - z) and x, y moved along their rays,
    which keeps every vertex on its pixel and reverses the depth order.
    """
    from dlacli.render.raster import interpolate, rasterize_camera_space, world_to_camera

    vc = world_to_camera(vertices, camera.viewmats.double().numpy())[0]  # [V, 3]
    front = rasterize_camera_space(vc, faces, camera.Ks[0], camera.width, camera.height)
    z = vc[:, 2]
    zm = z.min() + z.max() - z
    flipped = np.concatenate([vc[:, :2] * (zm / z)[:, None], zm[:, None]], axis=1)
    back = rasterize_camera_space(flipped, faces, camera.Ks[0], camera.width, camera.height)
    bd = interpolate(z[:, None], faces, back.face_id[0], back.bary[0])[..., 0]  # [H, W]
    bd = np.where(back.face_id[0] >= 0, bd, np.inf)
    return front.face_id[0], front.depth[0].astype(np.float64), back.face_id[0], bd


def shell_depths(person: np.ndarray, front_id, front_depth, back_depth, focal: float):
    """Front and back depth maps [H, W] of the person's 2.5D shell (inf outside the person).

    person [H, W] bool, front_id [H, W] int (-1: no body), front_depth / back_depth [H, W] camera
    z of the body's nearest / farthest surface (inf: none), focal: fx in pixels.
    Inside the body's silhouette the shell is the body (nearest to farthest surface); outside it
    (hair, loose clothing) its mid-depth is that of the nearest body pixel and its half thickness
    a round profile from the silhouette: sqrt(d (2 r - d)) x INFLATE, d the distance to the
    person's outline and r the local maximum of d (about the local half width).
    """
    body = person & (front_id >= 0) & np.isfinite(back_depth)
    if not body.any():
        raise DlaInputError("photo", "the fitted body does not overlap the person mask (check --keypoints / --mask)")
    mid, half = np.zeros(person.shape), np.zeros(person.shape)
    mid[body] = (front_depth[body] + back_depth[body]) / 2.0
    half[body] = (back_depth[body] - front_depth[body]) / 2.0
    _, (iy, ix) = ndimage.distance_transform_edt(~body, return_indices=True)
    mid = mid[iy, ix]  # nearest body pixel's mid-depth everywhere
    inflate = round_profile(person, person, mid, focal)  # metres
    half = np.maximum(half, inflate)
    w = ndimage.gaussian_filter(person.astype(np.float64), 1.0)
    mid = ndimage.gaussian_filter(mid * person, 1.0) / np.maximum(w, 1e-9)
    half = ndimage.gaussian_filter(half * person, 1.0) / np.maximum(w, 1e-9)
    front = np.where(person, mid - half, np.inf)
    back = np.where(person, mid + half, np.inf)
    return front, back


def round_profile(person: np.ndarray, where: np.ndarray, mid: np.ndarray, focal: float) -> np.ndarray:
    """[H, W] half thickness in metres of a shell beyond the body: sqrt(d (2 r - d)) x INFLATE
    pixels at depth `mid` [H, W] (fx `focal`), d the distance to the person's outline (person
    [H, W] bool) and r the largest d on `where` [H, W] bool within 0.12 of the person's height
    (about the local half width there)."""
    d = ndimage.distance_transform_edt(np.pad(person, 1))[1:-1, 1:-1]  # px to the outline
    height = np.ptp(np.nonzero(person)[0]) + 1
    r = ndimage.maximum_filter(np.where(where, d, 0.0), size=max(3, int(height * 0.12)) | 1)
    return np.sqrt(np.clip(d * (2.0 * r - d), 0.0, None)) * mid / focal * INFLATE


def _unproject(depth: np.ndarray, ys: np.ndarray, xs: np.ndarray, camera: Cameras) -> np.ndarray:
    """Pixel centres (ys, xs) [N] at camera depths -> [N, 3] world points."""
    k = camera.Ks[0].double().numpy()
    z = depth[ys, xs]
    pc = np.stack([(xs + 0.5 - k[0, 2]) / k[0, 0] * z, (ys + 0.5 - k[1, 2]) / k[1, 1] * z, z, np.ones_like(z)], 1)
    c2w = np.linalg.inv(camera.viewmats[0].double().numpy())  # OpenCV camera -> world
    return (pc @ c2w.T)[:, :3]


def shell_mesh(
    person: np.ndarray,
    front: np.ndarray,
    back: np.ndarray,
    camera: Cameras,
    front_label: np.ndarray | None = None,
    back_label: np.ndarray | None = None,
):
    """A closed mesh of the shell: one vertex per person pixel on each layer, two triangles per
    2x2 block of person pixels on each layer, walls along the person's outline.

    -> (vertices [2N, 3] world (front layer first), faces [M, 3], pixel rows [N], pixel cols [N]).
    Triangles across a depth jump would be rubber sheets (e.g. between an arm and the torso behind
    it) and are left out: those whose corners lie on different body parts (labels [H, W] int,
    per layer) and differ in depth by more than CUT_DEPTH, and any spanning more than CUT_FAR.
    A surface seen at a grazing angle within one part (a thigh pointing at the camera) is kept.
    """
    h, w = person.shape  # person [H, W] bool, front / back [H, W] camera depths
    ys, xs = np.nonzero(person)
    n = ys.size
    index = np.full((h, w), -1, np.int64)
    index[ys, xs] = np.arange(n)
    verts = np.concatenate([_unproject(front, ys, xs, camera), _unproject(back, ys, xs, camera)])
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    quad = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    a, b, c, d = a[quad], b[quad], c[quad], d[quad]
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])  # [T, 3] grid triangles
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    uniq, counts = np.unique(key[:, 0] * n + key[:, 1], return_counts=True)
    outline = np.isin(key[:, 0] * n + key[:, 1], uniq[counts == 1])
    e = edges[outline]  # [E, 2] outline edges, oriented as in their triangle
    walls = np.concatenate(
        [np.stack([e[:, 1], e[:, 0], e[:, 0] + n], 1), np.stack([e[:, 1], e[:, 0] + n, e[:, 1] + n], 1)]
    )
    keep = []
    for depth, label in ((front, front_label), (back, back_label)):
        jump = np.ptp(depth[ys, xs][tris], axis=1)  # [T]
        lab = np.zeros(n, np.int64) if label is None else label[ys, xs]
        mixed = np.ptp(lab[tris], axis=1) > 0
        keep.append((jump <= CUT_FAR) & ~(mixed & (jump > CUT_DEPTH)))
    keep_f, keep_b = keep
    faces = np.concatenate([tris[keep_f], tris[keep_b][:, [0, 2, 1]] + n, walls])
    return verts, faces, ys, xs


def back_colours(rgb: np.ndarray, person: np.ndarray, front_part: np.ndarray, back_part: np.ndarray) -> np.ndarray:
    """Colours [H, W, 3] for the back layer, seen through the front pixel by pixel.

    rgb [H, W, 3] photo colours; front_part / back_part [H, W] body part (index into
    dlacli.body.regions.PARTS, -1 off the body) of the nearest / farthest body surface. Where both
    layers are the same part (or one is off the body) the back takes the front's colour: the
    mirrored front appearance, so skin stays skin and clothes stay clothes. Where they differ (the
    face in front of the back of the head, an arm in front of the torso), the photo does not show
    the back: it is filled from the nearest pixel whose back layer is the same part and is known,
    then smoothed (sigma 2 px).
    """
    from dlacli.body.regions import PARTS

    face = PARTS.index("face")
    known = person & ((front_part == back_part) | (front_part < 0) | (back_part < 0)) & (front_part != face)
    out = np.where(known[..., None], rgb, 0.0)
    unknown = person & ~known
    if not unknown.any():
        return out
    if not known.any():
        return np.broadcast_to(np.median(rgb[person], axis=0), rgb.shape).copy()
    for part in np.unique(back_part[unknown]):
        todo = unknown & (back_part == part)
        src = known & (back_part == part)
        if not src.any():
            src = known
        _, (iy, ix) = ndimage.distance_transform_edt(~src, return_indices=True)
        out[todo] = rgb[iy[todo], ix[todo]]
    w = ndimage.gaussian_filter(unknown.astype(np.float64), 2.0)
    blur = np.stack([ndimage.gaussian_filter(out[..., k] * unknown, 2.0) for k in range(3)], -1)
    out[unknown] = (blur / np.maximum(w, 1e-9)[..., None])[unknown]
    return out


def _nearest_fill(label: np.ndarray) -> np.ndarray:
    """[H, W] int labels with -1 replaced by the nearest labelled pixel's (all -1 stays)."""
    if not (label >= 0).any():
        return label
    _, (iy, ix) = ndimage.distance_transform_edt(label < 0, return_indices=True)
    return label[iy, ix]


def template_views(rgb: np.ndarray, alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, azimuths=None):
    """The shell backend (legacy name "template") on a framed photo.

    rgb [R, R, 3], alpha [R, R] (the cropped photo), camera (its camera), vertices [V, 3] the
    fitted posed body -> (images [A, R, R, 3], masks [A, R, R], cameras) at `azimuths` (default
    dream's AZIMUTHS). View 0 is the photo.
    """
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import face_parts
    from dlacli.render.raster import render_mesh
    from dlacli.stages.dream.orbit import AZIMUTHS, body_pivot, orbit_cameras

    faces = get_body_model().faces
    parts = face_parts()
    person = alpha > 0.5
    fid, fdepth, bid, bdepth = body_depth_layers(vertices, faces, camera)
    front, back = shell_depths(person, fid, fdepth, bdepth, float(camera.Ks[0, 0, 0]))
    assert np.all(np.isfinite(front[person])) and np.all(np.isfinite(back[person]))
    fpart = np.where(fid >= 0, parts[np.maximum(fid, 0)], -1)
    bpart = np.where(bid >= 0, parts[np.maximum(bid, 0)], -1)
    verts, tris, ys, xs = shell_mesh(person, front, back, camera, _nearest_fill(fpart), _nearest_fill(bpart))
    colour = np.concatenate([rgb[ys, xs], back_colours(rgb, person, fpart, bpart)[ys, xs]])
    cams = orbit_cameras(camera, body_pivot(vertices), AZIMUTHS if azimuths is None else azimuths)
    novel = Cameras(cams.viewmats[1:], cams.Ks[1:], cams.width, cams.height)
    rgba = render_mesh(verts, tris, colour, novel, antialias=2, shading=False)  # [A-1, R, R, 4]
    a = rgba[..., 3]
    straight = np.where(a[..., None] > 1e-6, rgba[..., :3] / np.maximum(a[..., None], 1e-6), 0.0)
    images = np.concatenate([rgb[None], np.clip(straight, 0, 1)]).astype(np.float32)
    masks = np.concatenate([alpha[None], a]).astype(np.float32)
    return images, masks, cams
