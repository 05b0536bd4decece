"""The seeded synthetic subject: phenotype, relaxed pose, outfit and colours (docs/synth.md).

`sample_subject(seed, wardrobe)` draws a `SubjectSpec` from `default_rng(seed)` (the outfit of the
wider wardrobes from a stream of its own, `default_rng([seed, 2])`), so the phenotype and pose of
a seed are the same in every wardrobe.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from dlacli.errors import DlaInputError

WARDROBES = ("default", "full", "train", "heldout")
# "full" wardrobe: every shipped garment of its kind (dlacli.body.garments.GARMENT_KIND)
SUITS_FEMALE = ("female_casualsuit01", "female_casualsuit02", "female_elegantsuit01")
SUITS_MALE = (
    "male_casualsuit01",
    "male_casualsuit02",
    "male_casualsuit03",
    "male_casualsuit04",
    "male_casualsuit05",
    "male_casualsuit06",
    "male_elegantsuit01",
)
SHOES = ("shoes01", "shoes02")
HAIRS = ("short02", "short01", "short03", "short04", "afro01", "bob01", "braid01", "long01", "ponytail01")
PATTERNS_FULL = ("stripes", "checks", "noise", "dots", "plain")
# "train" / "heldout": the full wardrobe split so that benchmark subjects can wear garments no
# training subject wore: "train" never draws these, "heldout" draws its suit and hair only from them
HELD_OUT = ("female_elegantsuit01", "male_casualsuit06", "braid01", "short04")


@dataclass
class SubjectSpec:
    """Everything random about a subject (drawn from the seed by `sample_subject`)."""

    seed: int
    phenotype: dict[str, float]
    rotations: np.ndarray  # [J, 3] axis-angle, local-ref: the input pose
    outfit: tuple[str, ...]  # shipped garment names: suit, shoes, hair
    palette: dict[str, dict] = field(default_factory=dict)  # material -> colours and pattern


class BonePose:
    """Per-bone rotations composed as R = Rz Ry Rx about the zero pose's world axes (radians)."""

    def __init__(self, labels: list[str], base: np.ndarray | None = None):
        self.labels = labels
        self.rot = np.zeros((len(labels), 3)) if base is None else np.array(base, np.float64)

    def rotate(self, bone: str, x=0.0, y=0.0, z=0.0) -> None:
        j = self.labels.index(bone)
        r = Rotation.from_euler("ZYX", [z, y, x]) * Rotation.from_rotvec(self.rot[j])
        self.rot[j] = r.as_rotvec()


def radians_between(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.radians(rng.uniform(lo, hi)))


def relaxed_pose(rng: np.random.Generator, labels: list[str], lower: float) -> np.ndarray:
    """[J, 3] a standing pose: arms `lower` degrees down from anny's A-pose, slight elbow and
    knee bend, small random variation of spine, neck and wrists."""
    p = BonePose(labels)
    for side, s in (("L", 1.0), ("R", -1.0)):
        p.rotate(f"upperarm01.{side}", y=s * np.radians(lower), x=radians_between(rng, -6, 6))
        p.rotate(f"lowerarm01.{side}", x=radians_between(rng, 15, 28))
        p.rotate(f"wrist.{side}", x=radians_between(rng, -8, 8), y=radians_between(rng, -6, 6))
        knee = radians_between(rng, 0, 6)
        p.rotate(f"upperleg01.{side}", x=-knee / 2, y=s * radians_between(rng, -2, 2))
        p.rotate(f"lowerleg01.{side}", x=knee)
    p.rotate("spine03", z=radians_between(rng, -3, 3), x=radians_between(rng, -2, 2))
    p.rotate("neck01", z=radians_between(rng, -8, 8), x=radians_between(rng, -4, 4))
    return p.rot.astype(np.float32)


def _palette(rng: np.random.Generator) -> dict[str, dict]:
    skins = np.array(
        [[0.96, 0.80, 0.69], [0.87, 0.67, 0.53], [0.76, 0.57, 0.42], [0.60, 0.43, 0.31], [0.43, 0.29, 0.20]]
    )
    hairs = np.array(
        [
            [0.08, 0.06, 0.05],
            [0.25, 0.15, 0.08],
            [0.45, 0.30, 0.16],
            [0.80, 0.65, 0.40],
            [0.55, 0.22, 0.10],
            [0.60, 0.60, 0.60],
        ]
    )
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
            "base": base,
            "second": second,
            "pattern": str(rng.choice(["stripes", "checks", "noise"])),
            "freq": float(rng.uniform(12.0, 30.0)),
            "angle": float(rng.uniform(0, np.pi)),
        }

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
    spec.outfit = (
        str(suits[rng.integers(len(suits))]),
        str(SHOES[rng.integers(len(SHOES))]),
        str(hairs[rng.integers(len(hairs))]),
    )
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
    spec = SubjectSpec(
        int(seed),
        pheno,
        relaxed_pose(np.random.default_rng(pose_seed), labels, lower),
        (suit, "shoes01", "short02"),
        _palette(rng),
    )
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
    verts, _ = full.forward(
        spec.phenotype, torch.from_numpy(spec.rotations[None]), torch.zeros(1, 3), torch.zeros(1, 3)
    )
    v = verts[0].numpy()
    names = full.bone_labels
    bone = full.dominant_bone
    hand = np.isin(bone, [i for i, n in enumerate(names) if n.startswith(("wrist", "finger", "metacarpal"))])
    trunk_bones = ("root", "pelvis", "spine", "upperleg")
    trunk = np.isin(bone, [i for i, n in enumerate(names) if n.startswith(trunk_bones)])
    body = np.arange(v.shape[0]) < 13380  # hm08 body group (not the helpers)
    return float(cKDTree(v[trunk & body]).query(v[hand & body])[0].min())
