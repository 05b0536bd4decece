"""What colour a surface point of a synthetic subject has (docs/synth.md).

Texture: a procedural albedo evaluated at the surface point's *rest* position (or the garment's
.obj UV), so it sticks to the cloth in every pose (`shade_colors`).

Appearance "albedo" (the default) shades with a two-sided headlight Lambert term (dlacli.data.images),
so a surface point's colour depends on neither the world's lights nor the pose. "lit" shades with
lights fixed in the world (`sample_lighting`, `lit_terms`): albedo x (ambient x AO + sum of
max(0, n.l) colour) + Blinn-Phong specular, with normals of the posed mesh and ambient occlusion
computed per pose (`ambient_occlusion`), so the colour changes with the pose and, through the
specular term, with the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dlacli.data.garments import MATERIALS, DressedBody

APPEARANCES = ("albedo", "lit")
# "lit": Blinn-Phong specular strength and exponent per material; ambient occlusion sampling
SPECULAR = {
    "skin": (0.12, 24.0),
    "eyes": (0.6, 150.0),
    "hair": (0.22, 36.0),
    "suit": (0.04, 10.0),
    "shoes": (0.35, 60.0),
}
AO_DIRECTIONS = 32  # directions on the sphere (about half of them in each normal's hemisphere)
AO_RES = 192  # depth-map pixels per side (about 1.2 cm per pixel on an adult)


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
                w = (
                    (f[:, 0] if dx else 1 - f[:, 0])
                    * (f[:, 1] if dy else 1 - f[:, 1])
                    * (f[:, 2] if dz else 1 - f[:, 2])
                )
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
        return {
            "ambient": round(float(self.ambient), 6),
            "lights": [
                {"direction": [round(float(x), 6) for x in d], "colour": [round(float(x), 6) for x in c]}
                for d, c in zip(self.directions, self.colours)
            ],
        }


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector toward (azimuth, elevation) in degrees, the camera convention (azimuth 0 on -Y)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    return np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])


def sample_lighting(seed: int) -> Lighting:
    """A seeded three-light rig (`default_rng([seed, 4])`): a key light 25-60 degrees up from a
    random side, a dimmer fill light roughly opposite it and a rim light from the side or back."""
    rng = np.random.default_rng([int(seed), 4])
    key = float(rng.uniform(0.0, 360.0))
    rigs = (
        (key, rng.uniform(25.0, 60.0), rng.uniform(0.55, 0.75)),
        (key + 180.0 + rng.uniform(-45.0, 45.0), rng.uniform(5.0, 30.0), rng.uniform(0.2, 0.35)),
        (key + rng.choice([-1.0, 1.0]) * rng.uniform(90.0, 150.0), rng.uniform(20.0, 60.0), rng.uniform(0.15, 0.3)),
    )
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


def ambient_occlusion(
    verts: np.ndarray, faces: np.ndarray, directions: int = AO_DIRECTIONS, res: int = AO_RES
) -> np.ndarray:
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
