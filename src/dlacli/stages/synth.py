"""Synthetic subjects with ground truth: the anny body dressed in MakeHuman garments (docs/synth.md).

`synth(seed, out)` writes a view folder of a seeded subject (4 input views), its true body.json,
and optionally ground-truth novel views and novel poses. Everything random comes from
`numpy.random.default_rng` generators seeded by `seed`, so a seed gives the same bytes on every run.
Dataset mode (many subjects, a manifest, parallel and resumable) is stages/synth_dataset.py.

Rendering: the body (anny "anny-full", faces under the garments and the helper geometry removed,
eyes kept) plus the garments are one triangle mesh, rasterised with dlacli.render.raster at
`SUPERSAMPLE` x the resolution; every covered sub-pixel gets a procedural colour evaluated at the
surface point's *rest* position (or the garment's .obj UV), so the texture sticks to the cloth in
every pose, then a shading term; sub-pixels are box-filtered down. Alpha is the covered fraction;
rgb is the straight (not premultiplied) colour, 0 where alpha is 0. Overlapping garment layers are
ordered with a small per-layer z-buffer bias (see `_render`).

Appearance "albedo" (the default) shades with a two-sided headlight Lambert term, so a surface
point's colour depends on neither the world's lights nor the pose. "lit" shades with lights fixed
in the world: albedo x (ambient x AO + sum of max(0, n.l) colour) + Blinn-Phong specular, with
normals of the posed mesh and ambient occlusion computed per pose (`ambient_occlusion`), so the
colour changes with the pose and, through the specular term, with the camera.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError
from dlacli.types import BodyParams, Cameras, Motion, ViewSet

SUPERSAMPLE = 2
DISTANCE = 3.0  # metres from the target
TARGET = (0.0, 0.0, -0.1)  # look-at point: mid-body (pelvis at z = 0 in anny's zero pose)
FOV_DEG = 45.0  # vertical = horizontal field of view (square images)
INPUT_AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
INPUT_ELEVATION = 8.0  # degrees: the eye at ~0.32 m above the pelvis, chest height
NOVEL_ELEVATIONS = (0.0, 20.0, -5.0, 35.0)
POSE_AZIMUTHS = (0.0, 120.0, 240.0)  # cameras of the novel-pose folder
POSE_KINDS = ("arms_raised", "step", "turn", "reach")
AMBIENT = 0.35
LAYER_BIAS = 0.006  # metres of z-buffer bias per garment layer (skin 0, shoes 1, suit and hair 2)
MATERIALS = ("skin", "eyes", "hair", "suit", "shoes")
APPEARANCES = ("albedo", "lit")
WARDROBES = ("default", "full", "train", "heldout")
# "full" wardrobe: every shipped garment of its kind (dlacli.body.garments.GARMENT_KIND)
SUITS_FEMALE = ("female_casualsuit01", "female_casualsuit02", "female_elegantsuit01")
SUITS_MALE = ("male_casualsuit01", "male_casualsuit02", "male_casualsuit03", "male_casualsuit04",
              "male_casualsuit05", "male_casualsuit06", "male_elegantsuit01")  # fmt: skip
SHOES = ("shoes01", "shoes02")
HAIRS = ("short02", "short01", "short03", "short04", "afro01", "bob01", "braid01", "long01", "ponytail01")
PATTERNS_FULL = ("stripes", "checks", "noise", "dots", "plain")
# "train" / "heldout": the full wardrobe split so that benchmark subjects can wear garments no
# training subject wore: "train" never draws these, "heldout" draws its suit and hair only from them
HELD_OUT = ("female_elegantsuit01", "male_casualsuit06", "braid01", "short04")
# "lit": Blinn-Phong specular strength and exponent per material; ambient occlusion sampling
SPECULAR = {"skin": (0.12, 24.0), "eyes": (0.6, 150.0), "hair": (0.22, 36.0), "suit": (0.04, 10.0),
            "shoes": (0.35, 60.0)}  # fmt: skip
AO_DIRECTIONS = 32  # directions on the sphere (about half of them in each normal's hemisphere)
AO_RES = 192  # depth-map pixels per side (about 1.2 cm per pixel on an adult)
# dataset mode: random input yaw, slight elevation jitter (degrees); the heights (m) between which
# a clip frame's body is kept (the cameras see ~+-1.24 m about TARGET at its distance)
ELEVATION_JITTER = 4.0
FRAME_Z = (-1.2, 0.98)

Progress = Callable[[str], None]


# ------------------------------------------------------------------------------- the subject


@dataclass
class SubjectSpec:
    """Everything random about a subject (drawn from the seed by `sample_subject`)."""

    seed: int
    phenotype: dict[str, float]
    rotations: np.ndarray  # [J, 3] axis-angle, local-ref: the input pose
    outfit: tuple[str, ...]  # shipped garment names: suit, shoes, hair
    palette: dict[str, dict] = field(default_factory=dict)  # material -> colours and pattern


class _Pose:
    """Per-bone rotations composed as R = Rz Ry Rx about the zero pose's world axes (radians)."""

    def __init__(self, labels: list[str], base: np.ndarray | None = None):
        self.labels = labels
        self.rot = np.zeros((len(labels), 3)) if base is None else np.array(base, np.float64)

    def rotate(self, bone: str, x=0.0, y=0.0, z=0.0) -> None:
        j = self.labels.index(bone)
        r = Rotation.from_euler("ZYX", [z, y, x]) * Rotation.from_rotvec(self.rot[j])
        self.rot[j] = r.as_rotvec()


def _deg(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.radians(rng.uniform(lo, hi)))


def relaxed_pose(rng: np.random.Generator, labels: list[str], lower: float) -> np.ndarray:
    """[J, 3] a standing pose: arms `lower` degrees down from anny's A-pose, slight elbow and
    knee bend, small random variation of spine, neck and wrists."""
    p = _Pose(labels)
    for side, s in (("L", 1.0), ("R", -1.0)):
        p.rotate(f"upperarm01.{side}", y=s * np.radians(lower), x=_deg(rng, -6, 6))
        p.rotate(f"lowerarm01.{side}", x=_deg(rng, 15, 28))
        p.rotate(f"wrist.{side}", x=_deg(rng, -8, 8), y=_deg(rng, -6, 6))
        knee = _deg(rng, 0, 6)
        p.rotate(f"upperleg01.{side}", x=-knee / 2, y=s * _deg(rng, -2, 2))
        p.rotate(f"lowerleg01.{side}", x=knee)
    p.rotate("spine03", z=_deg(rng, -3, 3), x=_deg(rng, -2, 2))
    p.rotate("neck01", z=_deg(rng, -8, 8), x=_deg(rng, -4, 4))
    return p.rot.astype(np.float32)


def _palette(rng: np.random.Generator) -> dict[str, dict]:
    skins = np.array([[0.96, 0.80, 0.69], [0.87, 0.67, 0.53], [0.76, 0.57, 0.42],
                      [0.60, 0.43, 0.31], [0.43, 0.29, 0.20]])  # fmt: skip
    hairs = np.array([[0.08, 0.06, 0.05], [0.25, 0.15, 0.08], [0.45, 0.30, 0.16],
                      [0.80, 0.65, 0.40], [0.55, 0.22, 0.10], [0.60, 0.60, 0.60]])  # fmt: skip
    irises = np.array([[0.30, 0.18, 0.08], [0.25, 0.45, 0.65], [0.30, 0.45, 0.25]])
    t = rng.uniform(0, len(skins) - 1)
    k = int(t)
    skin = skins[k] * (1 - (t - k)) + skins[min(k + 1, len(skins) - 1)] * (t - k)

    def cloth() -> dict:
        base = rng.uniform(0.1, 0.9, 3)
        while np.linalg.norm(base - skin) < 0.3:  # keep the clothes distinguishable from the skin
            base = rng.uniform(0.1, 0.9, 3)
        second = np.clip(base * rng.uniform(0.3, 0.7) + rng.uniform(0.0, 0.5, 3), 0, 1)
        return {
            "base": base, "second": second,
            "pattern": str(rng.choice(["stripes", "checks", "noise"])),
            "freq": float(rng.uniform(12.0, 30.0)), "angle": float(rng.uniform(0, np.pi)),
        }  # fmt: skip

    return {
        "skin": {"base": skin},
        "eyes": {"iris": irises[rng.integers(len(irises))]},
        "hair": {"base": hairs[rng.integers(len(hairs))]},
        "suit": cloth(),
        "shoes": {"base": rng.uniform(0.05, 0.45, 3)},
    }


def _full_wardrobe(spec: SubjectSpec, wardrobe: str = "full") -> None:
    """Redraw the outfit from every shipped garment and widen the colours and patterns, from a
    stream of its own (`default_rng([seed, 2])`), so the phenotype and pose stay the default's.
    wardrobe "train" leaves out the HELD_OUT garments, "heldout" takes suit and hair from them."""
    def pool(names):
        if wardrobe == "train":
            return tuple(n for n in names if n not in HELD_OUT)
        if wardrobe == "heldout":
            return tuple(n for n in names if n in HELD_OUT)
        return names

    rng = np.random.default_rng([spec.seed, 2])
    own, other = (SUITS_FEMALE, SUITS_MALE) if spec.phenotype["gender"] >= 0.5 else (SUITS_MALE, SUITS_FEMALE)
    suits = pool(own if rng.uniform() < 0.85 else other)
    hairs = pool(HAIRS)
    spec.outfit = (str(suits[rng.integers(len(suits))]), str(SHOES[rng.integers(len(SHOES))]),
                   str(hairs[rng.integers(len(hairs))]))  # fmt: skip
    pal = spec.palette
    pal["suit"]["pattern"] = str(PATTERNS_FULL[rng.integers(len(PATTERNS_FULL))])
    pal["suit"]["freq"] = float(rng.uniform(8.0, 40.0))
    pal["shoes"]["base"] = rng.uniform(0.05, 0.9, 3)


def sample_subject(seed: int, wardrobe: str = "default") -> SubjectSpec:
    """A seeded adult: phenotype, relaxed pose (hands kept off the body), outfit and colours.
    wardrobe "default": a casual suit by gender, shoes01, hair short02; "full": see `_full_wardrobe`."""
    from dlacli.body.model import get_body_model

    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise DlaInputError("--seed", f"must be a non-negative integer, got {seed!r}")
    if wardrobe not in WARDROBES:
        raise DlaInputError("--wardrobe", f"must be one of {', '.join(WARDROBES)}, got {wardrobe!r}")
    rng = np.random.default_rng(int(seed))
    pheno = {
        "gender": float(rng.uniform(0.0, 1.0)),  # anny: 0 male, 1 female
        "age": float(rng.uniform(0.6, 0.9)),  # adults (0.5 is a teenager)
        "muscle": float(rng.uniform(0.3, 0.7)),
        "weight": float(rng.uniform(0.3, 0.7)),
        "height": float(rng.uniform(0.25, 0.55)),  # ~1.63-1.96 m (male), 1.50-1.82 m (female)
        "proportions": float(rng.uniform(0.35, 0.65)),
    }
    labels = get_body_model().bone_labels
    lower = float(rng.uniform(20.0, 28.0))
    pose_seed = int(rng.integers(2**63))
    suit = "female_casualsuit01" if pheno["gender"] >= 0.5 else "male_casualsuit01"
    spec = SubjectSpec(int(seed), pheno, relaxed_pose(np.random.default_rng(pose_seed), labels, lower),
                       (suit, "shoes01", "short02"), _palette(rng))  # fmt: skip
    while lower > 4.0 and hand_clearance(spec) < 0.06:  # keep the hands off the body
        lower -= 4.0
        spec.rotations = relaxed_pose(np.random.default_rng(pose_seed), labels, lower)
    if wardrobe != "default":
        _full_wardrobe(spec, wardrobe)
    return spec


def hand_clearance(spec: SubjectSpec) -> float:
    """Smallest distance (metres) from a hand vertex to the torso, hips or thighs, posed."""
    from scipy.spatial import cKDTree

    from dlacli.body.garments import get_full_body

    full = get_full_body()
    verts, _ = full.forward(spec.phenotype, torch.from_numpy(spec.rotations[None]),
                            torch.zeros(1, 3), torch.zeros(1, 3))  # fmt: skip
    v = verts[0].numpy()
    names = full.bone_labels
    bone = full.dominant_bone
    hand = np.isin(bone, [i for i, n in enumerate(names) if n.startswith(("wrist", "finger", "metacarpal"))])
    trunk_bones = ("root", "pelvis", "spine", "upperleg")
    trunk = np.isin(bone, [i for i, n in enumerate(names) if n.startswith(trunk_bones)])
    body = np.arange(v.shape[0]) < 13380  # hm08 body group (not the helpers)
    return float(cKDTree(v[trunk & body]).query(v[hand & body])[0].min())


def novel_motion(seed: int, spec: SubjectSpec, n: int) -> Motion:
    """n seeded poses on anny's rig, cycling through POSE_KINDS on top of the input pose."""
    from dlacli.body.model import get_body_model

    labels = get_body_model().bone_labels
    rng = np.random.default_rng([int(seed), 1])
    rots = np.zeros((n, len(labels), 3), np.float32)
    root = np.zeros((n, 3), np.float32)
    for t in range(n):
        kind = POSE_KINDS[t % len(POSE_KINDS)]
        p = _Pose(labels, spec.rotations)
        side, s = (("L", 1.0), ("R", -1.0))[int(rng.integers(2))]
        if kind == "arms_raised":
            for sd, sg in (("L", 1.0), ("R", -1.0)):
                p.rotate(f"upperarm01.{sd}", y=-sg * _deg(rng, 45, 85))
        elif kind == "step":
            p.rotate(f"upperleg01.{side}", x=-_deg(rng, 15, 30))
            p.rotate(f"lowerleg01.{side}", x=_deg(rng, 10, 35))
            other = "R" if side == "L" else "L"
            p.rotate(f"upperleg01.{other}", x=_deg(rng, 5, 15))
        elif kind == "turn":
            root[t] = [0.0, 0.0, s * _deg(rng, 30, 75)]
            p.rotate("spine03", z=s * _deg(rng, 5, 15))
            p.rotate("neck01", z=s * _deg(rng, 5, 20))
        else:  # reach: one arm forward
            p.rotate(f"upperarm01.{side}", x=-_deg(rng, 40, 80), y=-s * _deg(rng, 10, 25))
            p.rotate(f"lowerarm01.{side}", x=-_deg(rng, 0, 20))
        rots[t] = p.rot
    return Motion(list(labels), rots, root, np.zeros((n, 3), np.float32), 30.0)


# ------------------------------------------------------------------------------- the mesh


class DressedBody:
    """One subject's body + garments as a single mesh, posable with anny rotations."""

    def __init__(self, spec: SubjectSpec):
        from dlacli.body import garments as gm

        self.full = gm.get_full_body()
        self.spec = spec
        zero = torch.zeros(1, 3)
        _, rest = self.full.forward(spec.phenotype, torch.zeros(1, len(self.full.bone_labels), 3), zero, zero)
        self.bound = [gm.bind_garment(gm.shipped_garment(n), rest) for n in spec.outfit]
        hidden = np.zeros(gm.HM08_VERTICES, bool)
        for b in self.bound:
            hidden[b.garment.binding.delete_verts] = True
        ids = np.arange(gm.HM08_VERTICES)
        shown = ((ids >= gm.HM08_BODY[0]) & (ids < gm.HM08_BODY[1])) | (
            (ids >= gm.HM08_EYES[0]) & (ids < gm.HM08_EYES[1]))  # fmt: skip
        hidden &= ids < gm.HM08_BODY[1]  # delete_verts only hide skin (the files also list eyes)
        body_faces = self.full.faces[np.all(shown[self.full.faces] & ~hidden[self.full.faces], axis=1)]
        eye = np.all((body_faces >= gm.HM08_EYES[0]) & (body_faces < gm.HM08_EYES[1]), axis=1)
        faces, mats, uvs = [body_faces], [np.where(eye, 1, 0)], [np.zeros((len(body_faces), 3, 2))]
        bias = [np.zeros(gm.HM08_VERTICES)]
        offset = gm.HM08_VERTICES
        for name, b in zip(spec.outfit, self.bound):
            mesh = b.garment.mesh
            faces.append(mesh.faces + offset)
            mats.append(np.full(len(mesh.faces), MATERIALS.index(gm.GARMENT_KIND[name])))
            uvs.append(mesh.uv[mesh.face_uv])  # [F, 3, 2] corner UVs
            bias.append(np.full(b.garment.num_vertices, LAYER_BIAS * (1 + (b.garment.binding.z_depth > 10))))
            offset += b.garment.num_vertices
        self.depth_bias = np.concatenate(bias)  # [V] metres, see _render
        self.faces = np.concatenate(faces).astype(np.int64)  # [F, 3]
        self.face_material = np.concatenate(mats).astype(np.int64)  # [F]
        self.face_uv = np.concatenate(uvs).astype(np.float64)  # [F, 3, 2]
        rest_np = rest.double().numpy()
        self.rest = np.concatenate([rest_np] + [b.rest.double().numpy() for b in self.bound])  # [V, 3]
        self.eye_centres = np.stack([rest_np[gm.HM08_EYES[0]:gm.HM08_EYES[0] + 72].mean(0),
                                     rest_np[gm.HM08_EYES[0] + 72:gm.HM08_EYES[1]].mean(0)])  # fmt: skip

    def vertices(self, rotations, root_rotation, root_translation) -> np.ndarray:
        """rotations [T, J, 3], root_rotation [T, 3], root_translation [T, 3] -> [T, V, 3]."""
        body, _ = self.full.forward(self.spec.phenotype, torch.as_tensor(rotations, dtype=torch.float32),
                                    root_rotation, root_translation)  # fmt: skip
        parts = [body] + [b.pose(body) for b in self.bound]
        return torch.cat(parts, dim=1).double().numpy()


# ------------------------------------------------------------------------------- texturing


def _hash01(ix, iy, iz, seed: int) -> np.ndarray:
    h = (ix.astype(np.uint64) * np.uint64(73856093)) ^ (iy.astype(np.uint64) * np.uint64(19349663))
    h ^= iz.astype(np.uint64) * np.uint64(83492791) + np.uint64(seed * 2654435761 % 2**32)
    h ^= h >> np.uint64(13)
    h *= np.uint64(0x5BD1E995)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0xFFFFFF)


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth lattice noise in [0, 1]: p [N, 3] (lattice units) -> [N]."""
    base = np.floor(p)
    f = p - base
    f = f * f * (3.0 - 2.0 * f)
    b = base.astype(np.int64) + (1 << 20)  # keep the lattice coordinates positive
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = ((f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1])
                     * (f[:, 2] if dz else 1 - f[:, 2]))  # fmt: skip
                out += w * _hash01(b[:, 0] + dx, b[:, 1] + dy, b[:, 2] + dz, seed)
    return out


def shade_colors(body: DressedBody, material, rest_pos, uv, seed: int) -> np.ndarray:
    """Procedural albedo: material [N] ids, rest_pos [N, 3], uv [N, 2] -> rgb [N, 3]."""
    pal = body.spec.palette
    out = np.zeros((material.shape[0], 3))
    for m, name in enumerate(MATERIALS):
        sel = material == m
        if not np.any(sel):
            continue
        p, t = rest_pos[sel], uv[sel]
        fine = value_noise(p * 150.0, seed + 7 * m)[:, None]  # ~7 mm grain
        if name == "skin":
            col = pal["skin"]["base"] * (0.92 + 0.12 * value_noise(p * 25.0, seed)[:, None] + 0.03 * fine)
        elif name == "eyes":
            which = np.argmin(np.linalg.norm(p[:, None] - body.eye_centres[None], axis=-1), axis=1)
            c = body.eye_centres[which]
            d = p - c
            front = -d[:, 1] / np.maximum(np.linalg.norm(d, axis=1), 1e-9)  # cos angle to -Y
            col = np.where(front[:, None] > 0.93, pal["eyes"]["iris"], np.array([0.92, 0.90, 0.86]))
            col = np.where(front[:, None] > 0.985, np.array([0.03, 0.03, 0.03]), col)
        elif name == "hair":
            streak = value_noise(p * np.array([400.0, 400.0, 40.0]), seed + 3)[:, None]
            col = pal["hair"]["base"] * (0.7 + 0.6 * streak)
        elif name == "shoes":
            col = pal["shoes"]["base"] * (0.85 + 0.3 * fine)
        else:
            c = pal["suit"]
            ca, sa = np.cos(c["angle"]), np.sin(c["angle"])
            u = t[:, 0] * ca + t[:, 1] * sa
            v = -t[:, 0] * sa + t[:, 1] * ca
            if c["pattern"] == "stripes":
                mix = (np.sin(2 * np.pi * c["freq"] * u) > 0.3).astype(np.float64)
            elif c["pattern"] == "checks":
                mix = ((np.floor(u * c["freq"]) + np.floor(v * c["freq"])) % 2).astype(np.float64)
            elif c["pattern"] == "dots":
                fu, fv = u * c["freq"] % 1.0 - 0.5, v * c["freq"] % 1.0 - 0.5
                mix = (fu * fu + fv * fv < 0.09).astype(np.float64)
            elif c["pattern"] == "plain":
                mix = np.zeros(u.shape[0])
            else:
                mix = np.clip((value_noise(p * c["freq"], seed + 11) - 0.35) * 3.0, 0.0, 1.0)
            col = c["base"] * (1 - mix[:, None]) + c["second"] * mix[:, None]
            col = col * (0.9 + 0.2 * fine)
        out[sel] = col
    return np.clip(out, 0.0, 1.0)


# ------------------------------------------------------------------------------- lighting ("lit")


@dataclass
class Lighting:
    """Lights fixed in the world for the "lit" appearance (anny's frame: +Z up, the body faces -Y)."""

    ambient: float  # ambient intensity, scaled by the ambient occlusion
    directions: np.ndarray  # [L, 3] unit vectors from the surface toward each (directional) light
    colours: np.ndarray  # [L, 3] rgb intensity of each light

    def as_dict(self) -> dict:
        return {"ambient": round(float(self.ambient), 6),
                "lights": [{"direction": [round(float(x), 6) for x in d], "colour": [round(float(x), 6) for x in c]}
                           for d, c in zip(self.directions, self.colours)]}  # fmt: skip


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector toward (azimuth, elevation) in degrees, the camera convention (azimuth 0 on -Y)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    return np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])


def sample_lighting(seed: int) -> Lighting:
    """A seeded three-light rig (`default_rng([seed, 4])`): a key light 25-60 degrees up from a
    random side, a dimmer fill light roughly opposite it and a rim light from the side or back."""
    rng = np.random.default_rng([int(seed), 4])
    key = float(rng.uniform(0.0, 360.0))
    rigs = ((key, rng.uniform(25.0, 60.0), rng.uniform(0.55, 0.75)),
            (key + 180.0 + rng.uniform(-45.0, 45.0), rng.uniform(5.0, 30.0), rng.uniform(0.2, 0.35)),
            (key + rng.choice([-1.0, 1.0]) * rng.uniform(90.0, 150.0), rng.uniform(20.0, 60.0), rng.uniform(0.15, 0.3)))
    dirs, cols = [], []
    for az, el, power in rigs:
        tint = rng.uniform(0.9, 1.1, 3)
        dirs.append(_direction(az, el))
        cols.append(power * tint / tint.mean())
    return Lighting(float(rng.uniform(0.25, 0.35)), np.array(dirs), np.array(cols))


def lit_terms(material, normal, to_eye, ao, lighting: Lighting, light_dirs=None) -> tuple[np.ndarray, np.ndarray]:
    """The "lit" shading of N surface points: material [N] ids, normal [N, 3] and to_eye [N, 3]
    unit vectors (any frame; light_dirs [L, 3] in the same frame, default the world's), ao [N] ->
    (diffuse [N, 3]: the factor the albedo is multiplied by, specular [N, 3]: added). Two-sided:
    a normal facing away from the eye is flipped."""
    dirs = lighting.directions if light_dirs is None else np.asarray(light_dirs, np.float64)
    n = np.where(np.sum(normal * to_eye, axis=1, keepdims=True) < 0.0, -normal, normal)
    ndl = n @ dirs.T  # [N, L]
    lit = ndl > 0.0
    diffuse = lighting.ambient * ao[:, None] + np.maximum(ndl, 0.0) @ lighting.colours
    half = dirs[None] + to_eye[:, None]  # [N, L, 3] Blinn-Phong half vectors
    half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    ndh = np.maximum(np.sum(n[:, None] * half, axis=-1), 0.0)  # [N, L]
    table = np.array([SPECULAR[m] for m in MATERIALS])  # [M, 2]
    strength, power = table[material, 0], table[material, 1]
    spec = np.where(lit, strength[:, None] * ndh ** power[:, None], 0.0) @ lighting.colours
    return diffuse, spec


def sphere_directions(n: int) -> np.ndarray:
    """[n, 3] unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def ambient_occlusion(verts: np.ndarray, faces: np.ndarray, directions: int = AO_DIRECTIONS,
                      res: int = AO_RES) -> np.ndarray:  # fmt: skip
    """Per-vertex ambient occlusion of a posed mesh: verts [V, 3] or [T, V, 3], faces [F, 3] ->
    [V] or [T, V] in [0, 1], the cosine-weighted fraction of `directions` (`sphere_directions`)
    in each vertex normal's hemisphere along which no part of the mesh lies in front of it.
    Visibility along a direction is read from a depth map of the mesh rendered from far away
    along it (near-orthographic, res x res) with a slope-scaled bias of 1-5 depth-map pixels.
    The hemisphere is the one the area-weighted vertex normal (the mesh's winding) points into."""
    from dlacli.render.raster import rasterize_camera_space, vertex_normals

    v_all = np.asarray(verts, np.float64)
    if v_all.ndim == 2:
        return ambient_occlusion(v_all[None], faces, directions, res)[0]
    dirs = sphere_directions(directions)  # [K, 3]
    # camera k looks along -dirs[k]: rows right, down, forward (OpenCV axes)
    fwd = -dirs
    helper = np.where(np.abs(fwd[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    right = np.cross(fwd, helper)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(fwd, right)
    rot = np.stack([right, down, fwd], axis=1)  # [K, 3, 3] world -> camera
    used = np.unique(faces)
    out = np.ones(v_all.shape[:2])
    for t, v in enumerate(v_all):
        centre = 0.5 * (v[used].min(0) + v[used].max(0))
        radius = float(np.linalg.norm(v[used] - centre, axis=1).max()) * 1.02
        dist = 50.0 * radius
        f = 0.5 * res * (dist - radius) / radius
        ks = np.tile(np.array([[f, 0.0, res / 2.0], [0.0, f, res / 2.0], [0.0, 0.0, 1.0]]), (directions, 1, 1))
        cam = (v - centre) @ rot.transpose(0, 2, 1)  # [K, V, 3]
        cam[..., 2] += dist
        ras = rasterize_camera_space(cam, faces, ks, res, res)
        px = np.floor(f * cam[..., :2] / cam[..., 2:3] + res / 2.0).astype(np.int64)  # [K, V, 2]
        ix, iy = np.clip(px[..., 0], 0, res - 1), np.clip(px[..., 1], 0, res - 1)
        surface = ras.depth[np.arange(directions)[:, None], iy, ix].astype(np.float64)  # [K, V]
        n = vertex_normals(v, faces)  # [V, 3]
        cos = dirs @ n.T  # [K, V]
        texel = 2.0 * radius / res
        tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / np.maximum(np.abs(cos), 1e-3)
        visible = cam[..., 2] <= surface + texel * (1.0 + np.minimum(tan, 4.0))
        weight = np.maximum(cos, 0.0)
        out[t] = (weight * visible).sum(0) / np.maximum(weight.sum(0), 1e-12)
    return out


def render(body: DressedBody, verts: np.ndarray, cameras: Cameras, seed: int, chunk: int = 4, *,
           lighting: Lighting | None = None, ao: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """verts [V, 3] or [C, V, 3] -> RGBA [C, H, W, 4] float32 (straight alpha, see module doc),
    `chunk` cameras at a time (bounds the memory of the supersampled z-buffers). Appearance
    "albedo" when `lighting` is None, else "lit" with the per-vertex ao [V] or [C, V]."""
    if lighting is not None and ao is None:
        raise ValueError("the lit appearance needs the ambient occlusion of the posed vertices")
    parts = []
    for s in range(0, len(cameras), chunk):
        cams = Cameras(cameras.viewmats[s:s + chunk], cameras.Ks[s:s + chunk], cameras.width, cameras.height)
        sub_ao = None if ao is None else (ao if ao.ndim == 1 else ao[s:s + chunk])
        parts.append(_render(body, verts if verts.ndim == 2 else verts[s:s + chunk], cams, seed, lighting, sub_ao))
    return np.concatenate(parts)


def _render(body: DressedBody, verts: np.ndarray, cameras: Cameras, seed: int,
            lighting: Lighting | None = None, ao: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    from dlacli.render.raster import rasterize_camera_space, vertex_normals, world_to_camera

    ss = SUPERSAMPLE
    ks = cameras.Ks.clone()
    ks[:, :2, :] *= ss
    hi = Cameras(cameras.viewmats, ks, cameras.width * ss, cameras.height * ss)
    c, h, w = len(cameras), hi.height, hi.width
    vcam = world_to_camera(verts, cameras.viewmats.double().numpy())  # [C, V, 3]
    normals = vertex_normals(vcam, body.faces)  # [C, V, 3]
    # Garment layers overlap by millimetres (a shoe's collar inside the trousers, the tights
    # under a suit): outer layers win the z-buffer within their bias. Sliding a vertex along
    # its camera ray changes its depth but not where it projects, so silhouettes are exact.
    dist = np.linalg.norm(vcam, axis=-1, keepdims=True)  # [C, V, 1]
    biased = vcam * (1.0 - body.depth_bias[None, :, None] / np.maximum(dist, 1e-9))
    ras = rasterize_camera_space(biased, body.faces, hi.Ks, hi.width, hi.height)
    out = np.zeros((c, cameras.height, cameras.width, 4), np.float32)
    for k in range(c):
        fid = ras.face_id[k].reshape(-1)
        cov = fid >= 0
        f, bary = fid[cov], ras.bary[k].reshape(-1, 3)[cov].astype(np.float64)
        corners = body.faces[f]  # [N, 3]
        rest = np.einsum("nk,nkd->nd", bary, body.rest[corners])
        uv = np.einsum("nk,nkd->nd", bary, body.face_uv[f])
        albedo = shade_colors(body, body.face_material[f], rest, uv, seed)
        n = np.einsum("nk,nkd->nd", bary, normals[k][corners])
        pt = np.einsum("nk,nkd->nd", bary, vcam[k][corners])
        norms = np.linalg.norm(n, axis=1) * np.linalg.norm(pt, axis=1)
        rgb = np.zeros((h * w, 3))
        if lighting is None:  # "albedo": a two-sided headlight
            lam = np.abs((n * pt).sum(1)) / np.maximum(norms, 1e-12)  # |cos| normal vs view ray
            rgb[cov] = albedo * (AMBIENT + (1.0 - AMBIENT) * lam)[:, None]
        else:  # "lit": camera-space normals, eye at the origin, the world's lights turned into the camera
            unit = lambda a: a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)  # noqa: E731
            occlusion = np.einsum("nk,nk->n", bary, (ao if ao.ndim == 1 else ao[k])[corners])
            turn = cameras.viewmats[k, :3, :3].double().numpy()
            diffuse, spec = lit_terms(body.face_material[f], unit(n), unit(-pt), occlusion, lighting,
                                      lighting.directions @ turn.T)  # fmt: skip
            rgb[cov] = np.clip(albedo * diffuse + spec, 0.0, 1.0)
        cover = cov.astype(np.float64).reshape(h, w)
        rgb = rgb.reshape(h, w, 3)
        pool = lambda a: a.reshape(cameras.height, ss, cameras.width, ss, -1).mean(axis=(1, 3))  # noqa: E731
        alpha = pool(cover[..., None])[..., 0]
        col = pool(rgb) / np.maximum(alpha, 1e-12)[..., None]
        out[k, ..., :3] = np.where(alpha[..., None] > 0, col, 0.0)
        out[k, ..., 3] = alpha
    return out


# ------------------------------------------------------------------------------- cameras


def synth_orbit_cameras(azimuths, elevations, res: int) -> Cameras:
    """The synth rig: cameras DISTANCE from TARGET at azimuths / elevations (degrees, [C] each),
    looking at it; res x res images with a FOV_DEG field of view (docs/conventions.md for the angles)."""
    from dlacli.geometry import look_at_orbit_cameras

    return look_at_orbit_cameras(TARGET, DISTANCE, azimuths, elevations, FOV_DEG, res)


def novel_view_angles(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n (azimuth, elevation) pairs in degrees spread around the subject, none on an input view."""
    az = (17.0 + 360.0 * np.arange(n) / max(n, 1)) % 360.0
    clash = np.min(np.abs(((az[:, None] - np.array(INPUT_AZIMUTHS)[None]) + 180.0) % 360.0 - 180.0), axis=1)
    az = np.where(clash < 5.0, az + 7.0, az)
    el = np.array([NOVEL_ELEVATIONS[i % len(NOVEL_ELEVATIONS)] for i in range(n)], np.float64)
    return az, el


# ------------------------------------------------------------------------------- the stage


def _body_params(spec: SubjectSpec, rotations: np.ndarray | None) -> BodyParams:
    from dlacli.body.model import rotations_to_pose

    pose = {} if rotations is None else rotations_to_pose(rotations)
    pose = {k: np.asarray(v, np.float64) for k, v in pose.items()}
    return BodyParams(phenotype=dict(spec.phenotype), pose=pose)


def _view_set(rgba: np.ndarray, cams: Cameras, body: BodyParams, times, extra: dict) -> ViewSet:
    return ViewSet(images=rgba[..., :3], masks=rgba[..., 3], cameras=cams, body=body,
                   file_paths=[], times=list(times), extra=extra)  # fmt: skip


# what synth writes (paths relative to the subject folder; dla.io.atomic.check_outputs)
SUBJECT_LAYOUT = ("transforms.json", "body.json", "images", "images/view_*.png",
                  *(f"{sub}{rest}" for sub in ("novel_views", "novel_poses")
                    for rest in ("", "/transforms.json", "/body.json", "/images", "/images/view_*.png")),
                  "novel_poses/motion.npz")  # fmt: skip


def _check_options(res, novel_views, novel_poses, appearance: str, wardrobe: str) -> None:
    checks = (("--res", res, 16), ("--novel-views", novel_views, 0), ("--novel-poses", novel_poses, 0))
    for name, value, lo in checks:
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lo:
            raise DlaInputError(name, f"must be an integer >= {lo}, got {value!r}")
    if res > 4096:
        raise DlaInputError("--res", f"must be <= 4096, got {res}")
    if appearance not in APPEARANCES:
        raise DlaInputError("--appearance", f"must be one of {', '.join(APPEARANCES)}, got {appearance!r}")
    if wardrobe not in WARDROBES:
        raise DlaInputError("--wardrobe", f"must be one of {', '.join(WARDROBES)}, got {wardrobe!r}")


def input_rig(seed: int, random_yaw: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(azimuths [4], elevations [4], start yaw) of the input cameras, degrees: the fixed rig
    (INPUT_AZIMUTHS at INPUT_ELEVATION), or with `random_yaw` (dataset mode) 4 cameras 90 degrees
    apart from a random start yaw, each raised by up to +-ELEVATION_JITTER (`default_rng([seed, 3])`)."""
    if not random_yaw:
        return np.array(INPUT_AZIMUTHS), np.full(4, INPUT_ELEVATION), 0.0
    rng = np.random.default_rng([int(seed), 3])
    yaw = float(rng.uniform(0.0, 360.0))
    return (yaw + np.array(INPUT_AZIMUTHS)) % 360.0, INPUT_ELEVATION + rng.uniform(-1, 1, 4) * ELEVATION_JITTER, yaw


def target_motion(seed: int, spec: SubjectSpec, n: int, clips: Sequence[str] = ()) -> tuple[Motion, list[str]]:
    """n target poses and their kinds: `novel_motion`'s; with `clips` (built-in motion names or
    motion files, loaded and retargeted for the subject's phenotype as `dla animate` does), poses
    0, 2, 4, ... are random frames of random clips (`default_rng([seed, 5])`) and poses 1, 3, ...
    `novel_motion`'s kinds in their cycle. A clip frame keeps its root rotation and height, but
    the root is put above the origin and moved down or up as far as needed to keep the (naked)
    body between FRAME_Z[0] and FRAME_Z[1] metres, so the cameras see all of it."""
    from dlacli.body.model import get_body_model
    from dlacli.stages.motion_source import load_motion

    if not clips or n == 0:
        return novel_motion(seed, spec, n), [POSE_KINDS[t % len(POSE_KINDS)] for t in range(n)]
    model = get_body_model()
    labels = list(model.bone_labels)
    rots = np.zeros((n, len(labels), 3), np.float32)
    root_rot, root_pos = np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32)
    kinds = [""] * n
    novel = novel_motion(seed, spec, n // 2)
    for j, t in enumerate(range(1, n, 2)):
        rots[t], root_rot[t], root_pos[t] = novel.rotations[j], novel.root_rotation[j], novel.root_translation[j]
        kinds[t] = POSE_KINDS[j % len(POSE_KINDS)]
    rng = np.random.default_rng([int(seed), 5])
    loaded: dict[int, tuple[Motion, np.ndarray]] = {}
    for t in range(0, n, 2):
        c = int(rng.integers(len(clips)))
        if c not in loaded:
            clip = load_motion(clips[c], phenotype=spec.phenotype)
            loaded[c] = (clip, model.motion_rotations(clip))
        clip, clip_rots = loaded[c]
        i = int(rng.integers(clip.num_frames))
        rots[t], root_rot[t] = clip_rots[i], clip.root_rotation[i]
        root_pos[t] = [0.0, 0.0, float(clip.root_translation[i, 2])]
        kinds[t] = f"{Path(clips[c]).name}@{i}"
    # keep every clip frame's body between the FRAME_Z heights (a raised hand, a crouch)
    sel = np.arange(0, n, 2)
    z = model.forward(spec.phenotype, torch.from_numpy(rots[sel]), torch.from_numpy(root_rot[sel]),
                      torch.from_numpy(root_pos[sel])).vertices[..., 2].numpy()  # fmt: skip
    low, high = z.min(axis=1), z.max(axis=1)
    shift = np.minimum(FRAME_Z[1] - high, 0.0)
    shift = np.where(low + shift < FRAME_Z[0], np.minimum(FRAME_Z[0] - low, FRAME_Z[1] - high), shift)
    root_pos[sel, 2] += shift.astype(np.float32)
    return Motion(labels, rots, root_rot, root_pos, novel.fps), kinds


def synth(seed: int, out: str | os.PathLike, *, res: int = 512, novel_views: int = 12, novel_poses: int = 8,
          appearance: str = "albedo", wardrobe: str = "default", random_yaw: bool = False,
          motions: Sequence[str] = (), progress: Progress | None = None) -> Path:  # fmt: skip
    """Write the synthetic subject `seed` as the view folder `out` (atomic as a whole):
    4 input views + body.json, novel_views/ (n ground-truth views of the same pose) and
    novel_poses/ (frames with `time` into novel_poses/motion.npz) when n > 0.
    appearance "albedo" | "lit", wardrobe "default" | "full" (module doc, `sample_subject`);
    random_yaw: the dataset's input rig (`input_rig`); motions: clips for the target poses
    (`target_motion`). The defaults write today's subject, byte for byte."""
    from dlacli.io.atomic import atomic_dir
    from dlacli.io.motion import write_motion
    from dlacli.io.views import write_views

    _check_options(res, novel_views, novel_poses, appearance, wardrobe)
    say = progress or (lambda msg: None)
    out = Path(out)
    say("sampling the subject")
    spec = sample_subject(seed, wardrobe)
    say("dressing the body")
    body = DressedBody(spec)
    info = {"seed": int(seed), "outfit": list(spec.outfit),
            "suit_pattern": spec.palette["suit"]["pattern"], "generator": "dla synth"}  # fmt: skip
    lighting = sample_lighting(seed) if appearance == "lit" else None
    if wardrobe != "default":
        info["wardrobe"] = wardrobe
    if lighting is not None:
        info.update(appearance=appearance, lighting=lighting.as_dict())
    zero = torch.zeros(1, 3)
    verts = body.vertices(spec.rotations[None], zero, zero)[0]  # [V, 3] the input pose
    ao = None if lighting is None else ambient_occlusion(verts, body.faces)
    truth = _body_params(spec, spec.rotations)
    az0, el0, yaw = input_rig(seed, random_yaw)
    with atomic_dir(out) as tmp:
        say("rendering the 4 input views")
        cams = synth_orbit_cameras(az0, el0, res)
        rgba = render(body, verts, cams, seed, lighting=lighting, ao=ao)
        rig = {"azimuths": list(INPUT_AZIMUTHS), "elevation": INPUT_ELEVATION}
        if random_yaw:
            rig = {"azimuths": az0.tolist(), "elevations": el0.tolist(), "start_yaw": yaw}
        write_views(_view_set(rgba, cams, truth, [None] * 4, {"synth": {**info, **rig}}), tmp)
        if novel_views:
            say(f"rendering {novel_views} novel views")
            az, el = novel_view_angles(novel_views)
            az = (az + yaw) % 360.0 if random_yaw else az
            cams = synth_orbit_cameras(az, el, res)
            rgba = render(body, verts, cams, seed, lighting=lighting, ao=ao)
            extra = {"synth": {**info, "azimuths": az.tolist(), "elevations": el.tolist()}}
            write_views(_view_set(rgba, cams, truth, [None] * novel_views, extra), tmp / "novel_views")
        if novel_poses:
            motion, kinds = target_motion(seed, spec, novel_poses, motions)
            say(f"rendering {novel_poses} novel poses x {len(POSE_AZIMUTHS)} cameras")
            posed = body.vertices(motion.rotations, torch.from_numpy(motion.root_rotation),
                                  torch.from_numpy(motion.root_translation))  # [T, V, 3]
            pose_az = (np.array(POSE_AZIMUTHS) + yaw) % 360.0 if random_yaw else list(POSE_AZIMUTHS)
            cams1 = synth_orbit_cameras(pose_az, INPUT_ELEVATION, res)
            k = len(POSE_AZIMUTHS)
            cams = Cameras(cams1.viewmats.repeat(novel_poses, 1, 1),
                           cams1.Ks.repeat(novel_poses, 1, 1), res, res)  # fmt: skip
            pose_ao = None if lighting is None else np.repeat(ambient_occlusion(posed, body.faces), k, axis=0)
            rgba = render(body, np.repeat(posed, k, axis=0), cams, seed, lighting=lighting, ao=pose_ao)
            times = [t for t in range(novel_poses) for _ in range(k)]
            extra = {"synth": {**info, "azimuths": np.asarray(pose_az).tolist(), "elevation": INPUT_ELEVATION},
                     "motion": "motion.npz", "pose_kinds": kinds}  # fmt: skip
            write_views(_view_set(rgba, cams, _body_params(spec, None), times, extra), tmp / "novel_poses")
            write_motion(motion, tmp / "novel_poses" / "motion.npz")
    return out
