"""Dream's `body` backend: the photo baked onto the fitted body's UV map, completed where the photo
does not see the body, and rendered from the orbit cameras (docs/dream.md "Backend body").

1. Clothing and hair (`clothing_offsets`): where the person mask reaches beyond the fitted body's
   silhouette, each silhouette vertex measures how far (metres at its depth) the mask goes along
   its projected normal; the offsets are spread over the vertices of the same body part, smoothed
   over the mesh and clamped (`offset_bounds`), and the body is displaced along its normals.
2. Bake (`bake`): every texel of the UV map (`dlacli.body.uv`) is a point on the displaced body;
   it takes the photo's colour where the crop camera sees it (depth test against the body's
   z-buffer, inside the person mask, not at a border between body parts) with weight
   cos(normal, direction to the camera)^POWER.
3. Complete (`complete`): the left/right mirror texel (`mirror_texels`), then the front/back
   mirror within the same part (`back_texels`), then the nearest well-seen texel of the same part
   in 3D, blurred (`FALLBACK` when a part is not seen at all: hands from the arm's end, feet from
   the leg's, the hair never from the face).
4. Beyond the body (`dlacli.stages.dream.beyond`): person pixels the displaced body does not cover
   (a bun, a hat's tip, a skirt's hem) become a thin shell layer coloured from the photo.
5. Render (`body_views`): the textured, displaced body and that layer in one z-buffer through
   `dlacli.render.raster.render_textured`.

Texels are handled as flat arrays over `dlacli.body.uv.valid_texels(R)` (row-major order).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree

from dlacli.types import Cameras

POWER = 2.0  # viewing-angle weight cos^POWER: 45 degrees -> 0.5, 60 -> 0.25
SEEN = 0.5  # weight at which a texel's own photo colour is fully trusted (about 45 degrees)
UV_MIN, UV_MAX = 256, 1024  # the UV map resolution's range
DEPTH_TOL = 0.01  # metres: a texel within this of the z-buffer is visible
BORDER_DIV = 170  # photo pixels within max(1, res // BORDER_DIV) of a part border are not baked
FACE_BORDER_DIV = 40  # nor torso (neck) texels within res / FACE_BORDER_DIV of the face
GRAZING = 0.35  # |cos(normal, view ray)| below this: a silhouette vertex candidate
SPREAD = 0.06  # metres: Gaussian radius spreading silhouette offsets over a part
OFFSET_FRACTION = 0.25  # an offset is at most this fraction of its part's length (rest pose)
OFFSET_MAX = 0.2  # metres: and never more than this
SKIN_PARTS = ("face",)  # parts never displaced
SMALL_PARTS = {"left_hand": 0.02, "right_hand": 0.02, "left_foot": 0.03, "right_foot": 0.03}  # metres
FALLBACK = {  # where a part no texel of which is seen takes its colours from (in order)
    "face": ("hair", "torso"),
    "hair": ("torso",),
    "torso": ("left_arm", "right_arm", "left_leg", "right_leg"),
    "left_arm": ("right_arm", "torso"),
    "right_arm": ("left_arm", "torso"),
    "left_hand": ("right_hand", "left_arm"),
    "right_hand": ("left_hand", "right_arm"),
    "left_leg": ("right_leg", "torso"),
    "right_leg": ("left_leg", "torso"),
    "left_foot": ("right_foot", "left_leg"),
    "right_foot": ("left_foot", "right_leg"),
}


def uv_resolution(res: int) -> int:
    """The UV map's resolution for a res x res crop: res rounded to a power of two, in [256, 1024].
    The person fills ~85 % of the crop's height; at R = res the texels the photo sees within 45
    degrees are about as many as the person's pixels (measured on the synthetic photo at 512:
    31,093 texels for 31,484 person pixels; 42,526 texels seen at any angle), so the bake keeps
    the photo's resolution without many texels per pixel."""
    return int(min(UV_MAX, max(UV_MIN, 2 ** round(math.log2(max(int(res), 1))))))


# ------------------------------------------------------------------------------- texel geometry


@functools.lru_cache(maxsize=4)
def texel_samples(resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face_id [N], bary [N, 3] summing to 1, part [N] index into PARTS) of the valid texels."""
    from dlacli.body.regions import face_parts
    from dlacli.body.uv import uv_raster, valid_texels

    rows, cols, fid = valid_texels(resolution)
    bary = uv_raster(resolution).bary[rows, cols].astype(np.float64)
    return fid, bary / bary.sum(axis=1, keepdims=True), face_parts()[fid]


def texel_points(vertices: np.ndarray, resolution: int) -> np.ndarray:
    """[V, 3] -> [N, 3] the texels' surface points."""
    from dlacli.body.model import get_body_model

    fid, bary, _ = texel_samples(resolution)
    corners = np.asarray(vertices, np.float64)[get_body_model().faces[fid]]  # [N, 3, 3]
    return (corners * bary[..., None]).sum(axis=1)


def _normals(vertices: np.ndarray) -> np.ndarray:
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import vertex_normals

    return vertex_normals(vertices, get_body_model().faces)


@functools.lru_cache(maxsize=1)
def _rest() -> np.ndarray:
    from dlacli.body.model import get_body_model

    return get_body_model().rest_vertices().astype(np.float64)


@functools.lru_cache(maxsize=4)
def rest_texel_points(resolution: int) -> np.ndarray:
    """[N, 3] the texels' points on the rest body (default phenotype, zero pose)."""
    return texel_points(_rest(), resolution)


def _cached(name: str, resolution: int, build) -> np.ndarray:
    """An int64 texel map, cached on disk beside the UV rasters (cache_dir("uv"))."""
    from dlacli.body.uv import UV_LAYOUT, layout_hash
    from dlacli.io.atomic import atomic_path
    from dlacli.paths import cache_dir

    path = cache_dir("uv") / f"{UV_LAYOUT}_{layout_hash()}_{resolution}_{name}.npy"
    n = texel_samples(resolution)[0].size
    if path.exists():
        try:
            out = np.load(path)
            if out.shape == (n,) and out.dtype == np.int64 and out.min() >= 0 and out.max() < n:
                return out
        except (OSError, ValueError):
            pass  # a damaged cache file is rebuilt
    out = np.asarray(build(), np.int64)
    with atomic_path(path, cache=True) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, out)
    return out


@functools.lru_cache(maxsize=4)
def mirror_texels(resolution: int) -> np.ndarray:
    """[N] for each texel the texel nearest its left/right mirror image (x -> -x) on the rest body
    (anny's rest body is symmetric to 0.4 mm)."""

    def build():
        p = rest_texel_points(resolution)
        return cKDTree(p).query(p * [-1.0, 1.0, 1.0])[1]

    return _cached("mirror", resolution, build)


@functools.lru_cache(maxsize=4)
def back_texels(resolution: int) -> np.ndarray:
    """[N] for each texel the texel of the same part nearest its mirror image through the part's
    coronal plane (y = the part's mean y in the rest pose): front <-> back."""

    def build():
        p = rest_texel_points(resolution)
        part = texel_samples(resolution)[2]
        out = np.arange(p.shape[0])
        for k in np.unique(part):
            idx = np.nonzero(part == k)[0]
            q = p[idx].copy()
            q[:, 1] = 2.0 * q[:, 1].mean() - q[:, 1]
            out[idx] = idx[cKDTree(p[idx]).query(q)[1]]
        return out

    return _cached("back", resolution, build)


# ------------------------------------------------------------------------------- clothing thickness


@functools.lru_cache(maxsize=1)
def _vertex_parts_and_adjacency():
    """(part [V] of each vertex (its first face's), row-normalised vertex adjacency [V, V])."""
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import face_parts

    faces = get_body_model().faces
    nv = int(faces.max()) + 1
    part = np.zeros(nv, np.int64)
    part[faces[::-1].reshape(-1)] = np.repeat(face_parts()[::-1], 3)
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    adj = sparse.coo_matrix((np.ones(i.size), (i, j)), shape=(nv, nv)).tocsr()
    adj.data[:] = 1.0
    deg = np.asarray(adj.sum(axis=1)).ravel()
    return part, sparse.diags(1.0 / np.maximum(deg, 1.0)) @ adj


@functools.lru_cache(maxsize=1)
def offset_bounds() -> np.ndarray:
    """[len(PARTS)] metres: the largest offset of each part, OFFSET_FRACTION x its length (the
    longest side of its rest-pose bounding box), at most OFFSET_MAX; 0 for the face, a few cm for
    hands and feet (SMALL_PARTS)."""
    from dlacli.body.regions import PARTS

    part, _ = _vertex_parts_and_adjacency()
    rest = _rest()
    out = np.zeros(len(PARTS))
    for k, name in enumerate(PARTS):
        pts = rest[part == k]
        out[k] = min(OFFSET_FRACTION * float(np.ptp(pts, axis=0).max()), OFFSET_MAX) if pts.size else 0.0
        if name in SKIN_PARTS:
            out[k] = 0.0
        elif name in SMALL_PARTS:
            out[k] = min(out[k], SMALL_PARTS[name])
    return out


@functools.lru_cache(maxsize=1)
def local_radius() -> np.ndarray:
    """[V] metres: each rest-pose vertex's distance to the nearest axis segment (bone head to a
    child bone's head; a leaf bone: its head) of the bones that move it (skinning weight > 0.05):
    about the local half thickness of the limb, neck or trunk there."""
    from dlacli.body.model import get_body_model

    m = get_body_model()
    heads = m.rest_bone_heads().astype(np.float64)  # [J, 3]
    parents = np.asarray(m.bone_parents)
    kids = [np.nonzero(parents == j)[0] for j in range(heads.shape[0])]
    cmax = max(1, max(len(c) for c in kids))
    tails = np.repeat(heads[:, None], cmax, axis=1)  # [J, Cmax, 3], padded with the head itself
    for j, c in enumerate(kids):
        tails[j, : len(c)] = heads[c]
    idx, wts = m.vertex_bone_weights
    rest = _rest()
    out = np.full(rest.shape[0], np.inf)
    for k in range(idx.shape[1]):
        a, b = heads[idx[:, k]][:, None], tails[idx[:, k]]  # [V, 1, 3], [V, Cmax, 3]
        ab = b - a
        t = np.clip(((rest[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(rest[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)
        out = np.where(wts[:, k] > 0.05, np.minimum(out, d), out)
    return np.where(np.isfinite(out), out, 0.0)


def vertex_bounds() -> np.ndarray:
    """[V] metres: the largest offset of each vertex: its part's bound (`offset_bounds`) and at
    most its `local_radius` (a limb's surface at most doubles its thickness there)."""
    part, _ = _vertex_parts_and_adjacency()
    return np.minimum(offset_bounds()[part], local_radius())


def silhouette_offsets(alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, normals: np.ndarray):
    """Per silhouette vertex: how far the person mask reaches beyond the body along its normal.

    alpha [H, W] person mask, camera (1), vertices / normals [V, 3] world ->
    (vertex ids [S], offsets [S] metres). A silhouette vertex is visible (not behind the body's
    z-buffer), seen at a grazing angle (|cos| < GRAZING) and leaves the body's silhouette within
    2 px along its projected normal; its offset is the run of mask pixels outside the body that
    follows, converted to metres at its depth, up to its part's bound.
    """
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import rasterize, world_to_camera

    h, w = alpha.shape
    ras = rasterize(vertices, get_body_model().faces, camera)
    body, depth = ras.face_id[0] >= 0, ras.depth[0]
    person = alpha > 0.5
    vm = camera.viewmats[0].double().numpy()
    k = camera.Ks[0].double().numpy()
    pc = world_to_camera(vertices, vm[None])[0]
    nc = np.asarray(normals, np.float64) @ vm[:3, :3].T
    z = pc[:, 2]
    x, y = k[0, 0] * pc[:, 0] / z + k[0, 2], k[1, 1] * pc[:, 1] / z + k[1, 2]
    inside = (z > 0.01) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    xi, yi = np.clip(x.astype(np.int64), 0, w - 1), np.clip(y.astype(np.int64), 0, h - 1)
    visible = inside & (z <= depth[yi, xi] + DEPTH_TOL)
    cosv = np.abs((nc * pc).sum(1)) / np.linalg.norm(pc, axis=1)
    tx = k[0, 0] * (nc[:, 0] - pc[:, 0] / z * nc[:, 2])
    ty = k[1, 1] * (nc[:, 1] - pc[:, 1] / z * nc[:, 2])
    tn = np.hypot(tx, ty)
    cand = np.nonzero(visible & (cosv < GRAZING) & (tn > 1e-9))[0]
    part, _ = _vertex_parts_and_adjacency()
    bound = vertex_bounds()[cand]
    bound_px = bound * k[0, 0] / z[cand]  # [S]
    steps = int(math.ceil(bound_px.max())) + 4 if cand.size else 1
    s = np.arange(steps, dtype=np.float64)
    px = x[cand, None] + (tx / tn)[cand, None] * s
    py = y[cand, None] + (ty / tn)[cand, None] * s
    ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    pxi, pyi = np.clip(px.astype(np.int64), 0, w - 1), np.clip(py.astype(np.int64), 0, h - 1)
    in_body = body[pyi, pxi] & ok
    in_person = person[pyi, pxi] & ok
    exit_ = np.argmin(in_body, axis=1)  # first step outside the body
    on_edge = (exit_ <= 2) & ~in_body.all(axis=1)
    after = s[None] >= exit_[:, None]
    beyond = in_person & ~in_body & after  # mask outside the body, after the exit
    run_end = np.argmin(beyond | ~after, axis=1)  # first step after the exit that is not beyond
    run_end = np.where((beyond | ~after).all(axis=1), steps, run_end)
    run = np.clip(run_end - exit_, 0, None).astype(np.float64)
    metres = np.minimum(run, bound_px) * z[cand] / np.maximum(tn[cand], 0.5 * k[0, 0])  # px / (px per metre)
    metres = np.minimum(metres, bound)
    return cand[on_edge], metres[on_edge]


def clothing_offsets(alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, normals: np.ndarray | None = None):
    """[V] metres to move each vertex along its normal so the body's silhouette covers the clothes
    and hair the photo shows (module docstring, step 1). Each part's vertices take a Gaussian
    (SPREAD) average of its silhouette vertices' offsets, mixed with the part's median where none
    is near; then 8 steps of mesh smoothing join the parts; the result is clamped to
    `vertex_bounds`."""
    normals = _normals(vertices) if normals is None else normals
    ids, off = silhouette_offsets(alpha, camera, vertices, normals)
    part, adj = _vertex_parts_and_adjacency()
    v = np.asarray(vertices, np.float64)
    out = np.zeros(v.shape[0])
    bounds = offset_bounds()
    for k in np.unique(part):
        if bounds[k] <= 0:
            continue
        sel = part[ids] == k
        if not sel.any():
            continue
        src, val = v[ids[sel]], off[sel]
        dst = np.nonzero(part == k)[0]
        prior, w0 = float(np.median(val)), 0.3
        num, den = np.full(dst.size, prior * w0), np.full(dst.size, w0)
        for a in range(0, dst.size, 4096):
            d2 = ((v[dst[a : a + 4096], None] - src[None]) ** 2).sum(-1)
            wgt = np.exp(-d2 / (2.0 * SPREAD**2))
            num[a : a + 4096] += wgt @ val
            den[a : a + 4096] += wgt.sum(1)
        out[dst] = num / den
    cap = vertex_bounds()
    out = np.clip(out, 0.0, cap)
    for _ in range(8):
        out = np.minimum(0.5 * out + 0.5 * (adj @ out), cap)
    return out


# ------------------------------------------------------------------------------- bake + complete


def bake(rgb: np.ndarray, alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, resolution: int):
    """The photo on the body's UV map: rgb [H, W, 3] straight colours, alpha [H, W] person mask,
    camera (1), vertices [V, 3] the (displaced) posed body -> (colour [N, 3], weight [N]) per valid
    texel: the bilinear photo colour at the texel's projection, weight cos^POWER of the angle
    between its normal and the direction to the camera x the mask there, 0 where the body's
    z-buffer hides it or it faces away."""
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import PARTS
    from dlacli.render.raster import sample_texture, world_to_camera
    from dlacli.stages.dream.occluders import covered_pixels

    h, w = alpha.shape
    fid, bary, part = texel_samples(resolution)
    faces = get_body_model().faces
    pts = texel_points(vertices, resolution)
    nrm = (_normals(vertices)[faces[fid]] * bary[..., None]).sum(1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    vm = camera.viewmats[0].double().numpy()
    k = camera.Ks[0].double().numpy()
    pc = world_to_camera(pts, vm[None])[0]
    z = pc[:, 2]
    x, y = k[0, 0] * pc[:, 0] / z + k[0, 2], k[1, 1] * pc[:, 1] / z + k[1, 2]
    inside = (z > 0.01) & (x >= 0) & (x < w) & (y >= 0) & (y < h)
    pimg, pure, depth = _photo_parts(vertices, camera)
    xi, yi = np.clip(x.astype(np.int64), 0, w - 1), np.clip(y.astype(np.int64), 0, h - 1)
    visible = inside & (z <= depth[yi, xi] + DEPTH_TOL)
    visible &= pure[yi, xi] & (pimg[yi, xi] == part)
    # a wider border between the face and the torso (the neck): the chin or a beard seen over the
    # fitted neck would be mirrored to the back of the neck (the hair keeps the narrow border: a
    # short haircut is only a thin band above the forehead)
    face_px = pimg == PARTS.index("face")
    if face_px.any():
        near_face = ndimage.distance_transform_edt(~face_px) < max(1.0, w / FACE_BORDER_DIV)
        visible &= ~near_face[yi, xi] | (part != PARTS.index("torso"))
    eye = np.linalg.inv(vm)[:3, 3]
    to_cam = eye - pts
    cos = (nrm * to_cam).sum(1) / np.linalg.norm(to_cam, axis=1)
    # image coordinates -> the photo as a "texture" whose texel (y, x) centres are pixel centres
    uv = np.stack([x / w, 1.0 - y / h], axis=1)
    colour = sample_texture(rgb, uv)
    mask = sample_texture(alpha[..., None], uv)[:, 0]
    visible &= ~covered_pixels(rgb, pimg, pure, alpha > 0.5, depth)[yi, xi]
    weight = np.where(visible & (cos > 0), np.clip(cos, 0, 1) ** POWER * np.clip(mask, 0, 1), 0.0)
    weight = np.where(mask > 0.5, weight, 0.0)
    return colour.astype(np.float32), weight.astype(np.float32)


def _photo_parts(vertices: np.ndarray, camera: Cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the camera (1) sees of the body (vertices [V, 3]) at each pixel: (the body part [H, W],
    -1 off the body; pure [H, W] bool, no other part within max(1, W // BORDER_DIV) px: at part
    borders as the camera sees them (face / hair, an arm over the torso) the photo's pixels mix
    both parts and the fit's error moves the border; the z-buffer depth [H, W])."""
    from dlacli.body.model import get_body_model
    from dlacli.body.regions import face_parts
    from dlacli.render.raster import rasterize

    ras = rasterize(vertices, get_body_model().faces, camera)
    pimg = np.where(ras.face_id[0] >= 0, face_parts()[np.maximum(ras.face_id[0], 0)], -1)
    size = 2 * max(1, camera.width // BORDER_DIV) + 1
    pure = ndimage.maximum_filter(pimg, size) == ndimage.minimum_filter(pimg, size)
    return pimg, pure, ras.depth[0]


def photo_trust(rgb: np.ndarray, alpha: np.ndarray, camera: Cameras, vertices: np.ndarray) -> np.ndarray:
    """[H, W] float32: 1 where the photo (rgb [H, W, 3], person mask alpha [H, W], its camera)
    shows the surface the fitted body (vertices [V, 3]) puts at the pixel, 0 where it shows a limb
    in front of it that the fit placed elsewhere (`occluders.covered_pixels`: a hand on a thigh, a
    raised knee over the belly). The view folder records it as view 0's colour trust
    (formats/views.md), so that the lift does not give the covered surface the limb's colour."""
    from dlacli.stages.dream.occluders import covered_pixels

    pimg, pure, depth = _photo_parts(np.asarray(vertices, np.float64), camera)
    return (~covered_pixels(rgb, pimg, pure, alpha > 0.5, depth)).astype(np.float32)


def _over(colour, conf, other, other_conf):
    """Composite: (premultiplied colour, coverage) over a second candidate."""
    return colour + (1.0 - conf)[:, None] * other * other_conf[:, None], conf + (1.0 - conf) * other_conf


def complete(colour: np.ndarray, weight: np.ndarray, resolution: int) -> np.ndarray:
    """Baked texels (colour [N, 3], weight [N]) -> completed colours [N, 3] (module docstring,
    step 3). Confidences a = min(weight / SEEN, 1) composite front to back: own colour, the
    left/right mirror texel's (only from the mirrored part: left arm <-> right arm, face <-> face),
    the front/back mirror's, and last the part's fill
    (nearest texel with confidence > 0.5 in the rest body, blurred over the part in UV space)."""
    from dlacli.body.regions import PARTS

    _, _, part = texel_samples(resolution)
    swap = {"left": "right", "right": "left"}
    mirrored_part = np.array(
        [PARTS.index(swap.get(n.split("_")[0], n.split("_")[0]) + n[len(n.split("_")[0]) :]) for n in PARTS]
    )
    a0 = np.clip(weight / SEEN, 0.0, 1.0)
    mirror, back = mirror_texels(resolution), back_texels(resolution)
    a1 = np.where(part[mirror] == mirrored_part[part], a0[mirror], 0.0)  # the mirrored part only
    acc, cov = _over(colour * a0[:, None], a0, colour[mirror], a1)
    a2 = cov[back]  # the front/back mirror texel, already completed by symmetry
    col2 = acc[back] / np.maximum(cov[back], 1e-6)[:, None]
    acc, cov = _over(acc, cov, col2, a2)
    known = cov > 0.5
    known_col = acc / np.maximum(cov, 1e-6)[:, None]
    fill = _fill(known_col, known, part, resolution, need=cov < 1.0)
    out = acc + (1.0 - cov)[:, None] * fill
    if not known.any():  # nothing of the body seen: keep the photo's mean colour
        out[:] = colour[weight > 0].mean(0) if (weight > 0).any() else 0.5
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _fill(colour, known, part, resolution, need=None):
    """[N, 3]: per part, the colour of the nearest known texel of the same part (FALLBACK parts
    when it has none) in the rest body, then a Gaussian blur (sigma R / 96 texels) in UV space
    within the part. Only parts with a texel in `need` [N] bool (default all) are filled."""
    from dlacli.body.regions import PARTS
    from dlacli.body.uv import valid_texels

    rest = rest_texel_points(resolution)
    rows, cols, _ = valid_texels(resolution)
    out = np.zeros_like(colour)
    sigma = resolution / 96.0
    for k in np.unique(part if need is None else part[need]):
        idx = np.nonzero(part == k)[0]
        src = idx[known[idx]]
        for name in FALLBACK[PARTS[k]]:
            if src.size:
                break
            j = np.nonzero(part == PARTS.index(name))[0]
            src = j[known[j]]
        if not src.size:
            src = np.nonzero(known & (part != PARTS.index("face")))[0]
        if not src.size:
            continue
        val = colour[idx].copy()  # a known texel is its own nearest known texel
        todo = ~known[idx]
        val[todo] = colour[src[cKDTree(rest[src]).query(rest[idx[todo]])[1]]]
        r0, r1, c0, c1 = rows[idx].min(), rows[idx].max() + 1, cols[idx].min(), cols[idx].max() + 1
        pad = int(3 * sigma) + 1
        r0, c0 = max(r0 - pad, 0), max(c0 - pad, 0)
        r1, c1 = min(r1 + pad, resolution), min(c1 + pad, resolution)
        m = np.zeros((r1 - r0, c1 - c0))
        m[rows[idx] - r0, cols[idx] - c0] = 1.0
        den = ndimage.gaussian_filter(m, sigma)
        for ch in range(3):
            img = np.zeros_like(m)
            img[rows[idx] - r0, cols[idx] - c0] = val[:, ch]
            out[idx, ch] = (ndimage.gaussian_filter(img, sigma) / np.maximum(den, 1e-9))[rows[idx] - r0, cols[idx] - c0]
    return out


def texture_map(colour: np.ndarray, resolution: int) -> np.ndarray:
    """Texel colours [N, 3] -> [R, R, 3] UV map, empty texels padded with the nearest valid texel's
    colour (so bilinear lookups at chart borders do not mix in black)."""
    from dlacli.body.uv import uv_raster, valid_texels

    rows, cols, _ = valid_texels(resolution)
    tex = np.zeros((resolution, resolution, 3), np.float32)
    tex[rows, cols] = colour
    _, (iy, ix) = ndimage.distance_transform_edt(~uv_raster(resolution).mask, return_indices=True)
    return tex[iy, ix]


# ------------------------------------------------------------------------------- the backend


def displaced_body(alpha: np.ndarray, camera: Cameras, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: (the body [V, 3] moved along its normals by `clothing_offsets`, the offsets [V])."""
    v = np.asarray(vertices, np.float64)
    normals = _normals(v)
    offsets = clothing_offsets(alpha, camera, v, normals)
    return v + offsets[:, None] * normals, offsets


def textured_body(
    rgb: np.ndarray, alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, resolution=None, prior=None
):
    """Steps 1-3 on a framed photo (rgb [R, R, 3], alpha [R, R], its camera, the fitted body
    [V, 3]) -> dict(vertices = the displaced body [V, 3], offsets [V], texture [Ru, Ru, 3],
    weight [N] the bake's weights, resolution Ru). `prior`: a completion prior
    (stages/dream/completion.CompletionPrior) whose `fill` corrects step 3 where the photo does not
    see the body."""
    res = uv_resolution(rgb.shape[0]) if resolution is None else int(resolution)
    displaced, offsets = displaced_body(alpha, camera, vertices)
    colour, weight = bake(rgb, alpha, camera, displaced, res)
    completed = complete(colour, weight, res)
    if prior is not None:
        completed = prior.fill(rgb, alpha, camera, displaced, completed, weight, res)
    texture = texture_map(completed, res)
    return {"vertices": displaced, "offsets": offsets, "texture": texture, "weight": weight, "resolution": res}


def render_body(body: dict, cameras: Cameras, antialias: int = 2) -> np.ndarray:
    """RGBA [C, H, W, 4] (premultiplied: over black) of a `textured_body` from the cameras."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import render_textured

    m = get_body_model()
    return render_textured(body["vertices"], m.faces, m.uv, m.face_uv, body["texture"], cameras, antialias=antialias)


def mask_iou(alpha: np.ndarray, camera: Cameras, vertices: np.ndarray) -> float:
    """IoU of the person mask (alpha > 0.5) with the body's silhouette seen by the camera."""
    from dlacli.body.model import get_body_model
    from dlacli.render.raster import rasterize

    body = rasterize(vertices, get_body_model().faces, camera).face_id[0] >= 0
    person = alpha > 0.5
    return float((body & person).sum() / max((body | person).sum(), 1))


def body_views(rgb: np.ndarray, alpha: np.ndarray, camera: Cameras, vertices: np.ndarray, azimuths=None, prior=None):
    """The body backend on a framed photo: rgb [R, R, 3], alpha [R, R], camera (the crop's),
    vertices [V, 3] the fitted body -> (images [A, R, R, 3] straight colours, masks [A, R, R],
    cameras [A], settings dict). View 0 is the photo itself. `prior`: see `textured_body`."""
    from dlacli.stages.dream.beyond import layer_mesh, render_with_layer
    from dlacli.stages.dream.orbit import AZIMUTHS, body_pivot, orbit_cameras

    azimuths = AZIMUTHS if azimuths is None else azimuths
    body = textured_body(rgb, alpha, camera, vertices, prior=prior)
    layer = layer_mesh(alpha, camera, body["vertices"])
    cams = orbit_cameras(camera, body_pivot(vertices), azimuths)
    novel = Cameras(cams.viewmats[1:], cams.Ks[1:], cams.width, cams.height)
    rgba = render_body(body, novel) if layer is None else render_with_layer(body, layer, rgb, novel)
    a = rgba[..., 3]
    straight = np.where(a[..., None] > 1e-6, rgba[..., :3] / np.maximum(a[..., None], 1e-6), 0.0)
    images = np.concatenate([rgb[None], np.clip(straight, 0, 1)]).astype(np.float32)
    masks = np.concatenate([alpha[None], a]).astype(np.float32)
    settings = {
        "uv_resolution": body["resolution"],
        "mask_iou_body": round(mask_iou(alpha, camera, vertices), 4),
        "mask_iou_displaced": round(mask_iou(alpha, camera, body["vertices"]), 4),
        "max_offset_m": round(float(body["offsets"].max()), 4),
        "beyond_body_px": 0 if layer is None else int(layer.pixels.sum()),
    }
    if prior is not None:
        settings["prior"] = {"hash": prior.checkpoint_hash}
    return images, masks, cams, settings
