"""MakeHuman garments (.mhclo + .obj) on the anny body: parse, bind, pose (docs/synth.md).

A .mhclo file binds every vertex of a garment mesh (its .obj) to the hm08 base mesh, the mesh
anny is built from; anny's "anny-full" topology keeps all 19,158 hm08 vertices with their
original indices (the suits and shoes bind to the hidden "tights" helper, 15328-18001, which
anny skins like the rest).

.mhclo semantics (MakeHuman's proxy fitting): after the header, line k of the `verts` section is
either `i` (garment vertex k copies base vertex i) or `i1 i2 i3 w1 w2 w3 ox oy oz`, meaning
    x_k = w1 b[i1] + w2 b[i2] + w3 b[i3] + S o,   S = diag(s_x, s_y, s_z),
    s_a = |b[v1][a] - b[v2][a]| / dist          for the header line `<a>_scale v1 v2 dist`,
all in MakeHuman's frame (Y up, the body faces +Z, decimetres). `delete_verts` lists base-mesh
vertices hidden under the garment (`a - b` is an inclusive range).

Frame: anny's vertices are MH_TO_ANNY @ (MakeHuman vertices), a 90 degree turn about +X and a
0.1 scale: (x, y, z)_MH -> 0.1 (x, -z, y). anny builds its model with exactly this transform, and
its template vertices equal hm08's base.obj mapped by it to 3e-8 m (tests/body/test_garments.py).

Posing: a garment is fitted (the formula above) on the subject's unposed rest vertices and then
carried to any pose by a rigid per-vertex transfer: each garment vertex is stored in the frame of
its three reference vertices (origin at the barycentric point, axes: first edge, in-plane
perpendicular, normal) and rebuilt from the posed triangle; single-index vertices copy their
base vertex.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dlacli.errors import DlaInputError

HM08_VERTICES = 19158
# MakeHuman (Y up, faces +Z, decimetres) -> anny (Z up, faces -Y, metres): x_anny = MH_TO_ANNY @ x_mh
MH_TO_ANNY = 0.1 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# hm08 vertex ranges (inclusive start, exclusive end) of the parts the renderer shows.
HM08_BODY = (0, 13380)
HM08_EYES = (14598, 14742)
ASSET_DIR = Path(__file__).resolve().parent.parent / "assets" / "garments"
# Every shipped garment and what it is (assets/garments/LICENSE.md lists the files and their sources).
GARMENT_KIND = {
    "female_casualsuit01": "suit",
    "female_casualsuit02": "suit",
    "female_elegantsuit01": "suit",
    "male_casualsuit01": "suit",
    "male_casualsuit02": "suit",
    "male_casualsuit03": "suit",
    "male_casualsuit04": "suit",
    "male_casualsuit05": "suit",
    "male_casualsuit06": "suit",
    "male_elegantsuit01": "suit",
    "shoes01": "shoes",
    "shoes02": "shoes",
    "afro01": "hair",
    "bob01": "hair",
    "braid01": "hair",
    "long01": "hair",
    "ponytail01": "hair",
    "short01": "hair",
    "short02": "hair",
    "short03": "hair",
    "short04": "hair",
}
SHIPPED = tuple(GARMENT_KIND)


# ---------------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class Mhclo:
    """The binding of a garment to hm08 (.mhclo content), MakeHuman frame."""

    name: str
    obj_file: str
    ref_indices: np.ndarray  # [G, 3] int64 hm08 indices (i, i, i for single-index vertices)
    weights: np.ndarray  # [G, 3] float64 barycentric weights ((1, 0, 0) for single-index ones)
    offsets: np.ndarray  # [G, 3] float64 offsets, MakeHuman frame, before scaling
    single: np.ndarray  # [G] bool: vertex copies ref_indices[:, 0]
    scale_refs: np.ndarray  # [3, 2] int64 reference pair per MakeHuman axis x, y, z
    scale_dists: np.ndarray  # [3] float64 stored distance per axis
    delete_verts: np.ndarray  # [D] int64 sorted hm08 indices hidden under the garment
    z_depth: int


@dataclass(frozen=True)
class ObjMesh:
    """A Wavefront .obj mesh, triangulated (polygons fanned from their first corner)."""

    vertices: np.ndarray  # [V, 3] float64, the file's frame
    faces: np.ndarray  # [F, 3] int64 vertex indices
    uv: np.ndarray  # [Vt, 2] float64 texture coordinates (empty [0, 2] when none)
    face_uv: np.ndarray  # [F, 3] int64 indices into uv (-1 where a corner has none)


@dataclass(frozen=True)
class Garment:
    """A garment mesh with its hm08 binding (rest vertices in MakeHuman's frame)."""

    name: str
    binding: Mhclo
    mesh: ObjMesh

    @property
    def num_vertices(self) -> int:
        return self.mesh.vertices.shape[0]


def _err(path, line_no: int | None, problem: str) -> DlaInputError:
    return DlaInputError(path, f"line {line_no}: {problem}" if line_no else problem)


def parse_mhclo(path: str | os.PathLike) -> Mhclo:
    """Read a .mhclo file; any malformed content raises DlaInputError naming the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DlaInputError(path, f"cannot read ({exc.__class__.__name__}: {exc})") from None
    header: dict[str, str] = {}
    scales: dict[int, tuple[int, int, float]] = {}
    refs, weights, offsets, single, deleted = [], [], [], [], []
    section = "header"
    axis_of = {"x_scale": 0, "y_scale": 1, "z_scale": 2}
    range_open = False
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        words = line.split()
        key = words[0]
        if key == "verts":
            section = "verts"
            continue
        if key == "delete_verts":
            section = "delete"
            continue
        if section == "verts" and _is_number(key):
            if len(words) == 1:
                i = _index(words[0], path, no)
                refs.append((i, i, i))
                weights.append((1.0, 0.0, 0.0))
                offsets.append((0.0, 0.0, 0.0))
                single.append(True)
            elif len(words) in (6, 9):
                refs.append(tuple(_index(w, path, no) for w in words[:3]))
                nums = [_float(w, path, no) for w in words[3:]]
                weights.append(tuple(nums[:3]))
                offsets.append(tuple(nums[3:6]) if len(nums) == 6 else (0.0, 0.0, 0.0))
                single.append(False)
            else:
                raise _err(path, no, f"a vertex line needs 1, 6 or 9 numbers, found {len(words)}")
            continue
        if section == "delete" and (_is_number(key) or key == "-"):
            for w in words:
                if w == "-":
                    if range_open or not deleted:
                        raise _err(path, no, "'-' must stand between two indices")
                    range_open = True
                    continue
                i = _index(w, path, no)
                if range_open:
                    if i < deleted[-1]:
                        raise _err(path, no, f"range {deleted[-1]} - {i} runs backwards")
                    deleted.extend(range(deleted[-1] + 1, i + 1))
                    range_open = False
                else:
                    deleted.append(i)
            continue
        # a keyword line: header content wherever it stands (MakeHuman reads keys in any section;
        # some files put `material` after `verts 0`)
        if key in axis_of:
            if len(words) != 4:
                raise _err(path, no, f"{key} needs 'v1 v2 dist', found {len(words) - 1} values")
            dist = _float(words[3], path, no)
            if not dist > 0:
                raise _err(path, no, f"{key} distance must be > 0, found {dist}")
            scales[axis_of[key]] = (_index(words[1], path, no), _index(words[2], path, no), dist)
        else:
            header[key] = " ".join(words[1:])
    if range_open:
        raise DlaInputError(path, "delete_verts ends with an open '-' range")
    if header.get("basemesh", "hm08") != "hm08":
        raise DlaInputError(path, f"basemesh {header['basemesh']!r} is not supported (only hm08)")
    if "obj_file" not in header:
        raise DlaInputError(path, "missing 'obj_file' in the header")
    missing = [a for a, k in (("x", 0), ("y", 1), ("z", 2)) if k not in scales]
    if missing:
        raise DlaInputError(path, f"missing {', '.join(m + '_scale' for m in missing)} in the header")
    if not refs:
        raise DlaInputError(path, "no vertex lines (after 'verts 0')")
    try:
        z_depth = int(header.get("z_depth", "50"))
    except ValueError:
        raise DlaInputError(path, f"z_depth {header['z_depth']!r} is not an integer") from None
    return Mhclo(
        name=header.get("name", path.stem),
        obj_file=header["obj_file"],
        ref_indices=np.asarray(refs, np.int64).reshape(-1, 3),
        weights=np.asarray(weights, np.float64).reshape(-1, 3),
        offsets=np.asarray(offsets, np.float64).reshape(-1, 3),
        single=np.asarray(single, bool),
        scale_refs=np.asarray([scales[k][:2] for k in range(3)], np.int64),
        scale_dists=np.asarray([scales[k][2] for k in range(3)], np.float64),
        delete_verts=np.unique(np.asarray(deleted, np.int64)),
        z_depth=z_depth,
    )


def _is_number(word: str) -> bool:
    return word.lstrip("+-").replace(".", "", 1).replace("e", "", 1).replace("E", "", 1).isdigit()


def _index(word: str, path, no: int) -> int:
    try:
        i = int(word)
    except ValueError:
        raise _err(path, no, f"{word!r} is not a vertex index") from None
    if not 0 <= i < HM08_VERTICES:
        raise _err(path, no, f"vertex index {i} is outside hm08's [0, {HM08_VERTICES})")
    return i


def _float(word: str, path, no: int) -> float:
    try:
        x = float(word)
    except ValueError:
        raise _err(path, no, f"{word!r} is not a number") from None
    if not np.isfinite(x):
        raise _err(path, no, f"{word!r} is not finite")
    return x


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read the v / vt / f records of a Wavefront .obj (other records are ignored)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DlaInputError(path, f"cannot read ({exc.__class__.__name__}: {exc})") from None
    verts, uvs, faces, face_uv = [], [], [], []
    for no, raw in enumerate(lines, start=1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        if words[0] == "v":
            if len(words) < 4:
                raise _err(path, no, "a 'v' record needs 3 coordinates")
            verts.append([_float(w, path, no) for w in words[1:4]])
        elif words[0] == "vt":
            if len(words) < 3:
                raise _err(path, no, "a 'vt' record needs 2 coordinates")
            uvs.append([_float(w, path, no) for w in words[1:3]])
        elif words[0] == "f":
            if len(words) < 4:
                raise _err(path, no, "a face needs at least 3 corners")
            corners = []
            for w in words[1:]:
                parts = w.split("/")
                try:
                    vi = int(parts[0])
                    ti = int(parts[1]) if len(parts) > 1 and parts[1] else 0
                except ValueError:
                    raise _err(path, no, f"bad face corner {w!r}") from None
                vi = vi - 1 if vi > 0 else len(verts) + vi
                ti = ti - 1 if ti > 0 else (len(uvs) + ti if ti < 0 else -1)
                corners.append((vi, ti))
            for k in range(1, len(corners) - 1):
                tri = (corners[0], corners[k], corners[k + 1])
                faces.append([c[0] for c in tri])
                face_uv.append([c[1] for c in tri])
    v = np.asarray(verts, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    ft = np.asarray(face_uv, np.int64).reshape(-1, 3)
    uv = np.asarray(uvs, np.float64).reshape(-1, 2)
    if v.shape[0] == 0 or f.shape[0] == 0:
        raise DlaInputError(path, "no vertices or no faces")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise DlaInputError(path, f"face vertex index out of range [1, {v.shape[0]}]")
    if ft.max() >= uv.shape[0]:
        raise DlaInputError(path, f"face texture index out of range [1, {uv.shape[0]}]")
    return ObjMesh(v, f, uv, ft)


def load_garment(name_or_path: str | os.PathLike) -> Garment:
    """A shipped garment by name (see SHIPPED) or a .mhclo path (its obj_file beside it)."""
    path = Path(name_or_path)
    if path.suffix != ".mhclo":
        if str(name_or_path) not in SHIPPED:
            raise DlaInputError("garment", f"unknown garment {name_or_path!r} (shipped: {', '.join(SHIPPED)})")
        path = ASSET_DIR / f"{name_or_path}.mhclo"
    binding = parse_mhclo(path)
    mesh = read_obj(path.parent / binding.obj_file)
    if mesh.vertices.shape[0] != binding.ref_indices.shape[0]:
        raise DlaInputError(
            path,
            f"{binding.ref_indices.shape[0]} vertex lines but {binding.obj_file} has {mesh.vertices.shape[0]} vertices",
        )
    return Garment(binding.name, binding, mesh)


@functools.cache
def shipped_garment(name: str) -> Garment:
    """A shipped garment, parsed once per process."""
    return load_garment(name)


# ---------------------------------------------------------------------------------- fitting


def mh_to_anny(points: np.ndarray) -> np.ndarray:
    """[..., 3] MakeHuman frame -> [..., 3] anny frame (metres, +Z up, facing -Y)."""
    return np.asarray(points, np.float64) @ MH_TO_ANNY.T


def anny_to_mh(points: np.ndarray) -> np.ndarray:
    """[..., 3] anny frame -> [..., 3] MakeHuman frame."""
    return np.asarray(points, np.float64) @ np.linalg.inv(MH_TO_ANNY).T


def fit_garment(binding: Mhclo, base_mh: np.ndarray) -> np.ndarray:
    """MakeHuman's proxy fitting: base_mh [19158, 3] hm08 vertices (MakeHuman frame) ->
    [G, 3] garment vertices (MakeHuman frame)."""
    base_mh = np.asarray(base_mh, np.float64)
    if base_mh.shape != (HM08_VERTICES, 3):
        raise DlaInputError("base_mh", f"expected shape [{HM08_VERTICES}, 3], got {list(base_mh.shape)}")
    pairs = base_mh[binding.scale_refs]  # [3, 2, 3]
    scale = np.abs(pairs[np.arange(3), 0, np.arange(3)] - pairs[np.arange(3), 1, np.arange(3)])
    scale = scale / binding.scale_dists  # [3]
    tri = base_mh[binding.ref_indices]  # [G, 3, 3]
    return np.einsum("gk,gkd->gd", binding.weights, tri) + binding.offsets * scale


def fit_garment_anny(binding: Mhclo, base_anny: np.ndarray) -> np.ndarray:
    """fit_garment in anny's frame: base_anny [19158, 3] -> [G, 3]."""
    return mh_to_anny(fit_garment(binding, anny_to_mh(base_anny)))


def _triangle_frames(tri: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """tri [..., G, 3, 3] corner positions, weights [G, 3] -> (origins [..., G, 3],
    frames [..., G, 3, 3] with columns edge, in-plane perpendicular, normal)."""
    origin = (weights[..., None] * tri).sum(dim=-2)
    e1 = tri[..., 1, :] - tri[..., 0, :]
    e2 = tri[..., 2, :] - tri[..., 0, :]
    n = torch.linalg.cross(e1, e2)
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = torch.linalg.cross(n, e1)
    return origin, torch.stack([e1, b, n], dim=-1)


@dataclass
class BoundGarment:
    """A garment fitted to one body at rest, ready to follow that body's poses."""

    garment: Garment
    rest: torch.Tensor  # [G, 3] garment vertices on the unposed body, anny frame
    local: torch.Tensor  # [G, 3] each vertex in its reference triangle's rest frame

    def pose(self, body_vertices: torch.Tensor) -> torch.Tensor:
        """body_vertices [T, 19158, 3] or [19158, 3] (anny-full, posed) -> [T, G, 3] or [G, 3]."""
        if body_vertices.shape[-2:] != (HM08_VERTICES, 3):
            raise DlaInputError("body_vertices", f"expected [..., {HM08_VERTICES}, 3], got {list(body_vertices.shape)}")
        b = self.garment.binding
        idx = torch.from_numpy(b.ref_indices).to(body_vertices.device)
        w = torch.from_numpy(b.weights).to(body_vertices)
        tri = body_vertices[..., idx, :]  # [..., G, 3, 3]
        origin, frame = _triangle_frames(tri, w)
        out = origin + (frame @ self.local.to(body_vertices)[..., None])[..., 0]
        single = torch.from_numpy(b.single).to(body_vertices.device)
        return torch.where(single[:, None], tri[..., 0, :], out)


def bind_garment(garment: Garment, rest_vertices, fitted=None) -> BoundGarment:
    """Fit `garment` on rest_vertices [19158, 3] (anny-full, unposed, anny frame) and store each
    vertex in its reference triangle's frame. `fitted` [G, 3] replaces the fit (e.g. after
    resolve_layers)."""
    rest_np = np.asarray(
        rest_vertices.detach().cpu().numpy() if isinstance(rest_vertices, torch.Tensor) else rest_vertices,
        np.float64,
    )
    if fitted is None:
        fitted = fit_garment_anny(garment.binding, rest_np)
    fitted = torch.from_numpy(np.asarray(fitted, np.float64))  # [G, 3]
    base = torch.from_numpy(rest_np)
    tri = base[torch.from_numpy(garment.binding.ref_indices)]  # [G, 3, 3]
    origin, frame = _triangle_frames(tri, torch.from_numpy(garment.binding.weights))
    local = (frame.transpose(-1, -2) @ (fitted - origin)[..., None])[..., 0]
    return BoundGarment(garment, fitted.float(), local.float())


# ---------------------------------------------------------------------------------- the body


class FullBody:
    """anny "anny-full": hm08 vertex indices, posed like dlacli.body.model.BodyModel."""

    def __init__(self) -> None:
        from dlacli.body.model import build_anny, get_body_model

        self._anny = build_anny("anny-full", "loading the anny-full body model (first run: ~1 min)")
        self._body = get_body_model()
        self.faces = self._anny.faces.detach().cpu().numpy().astype(np.int64)  # [F, 3]
        assert int(self._anny.template_vertices.shape[0]) == HM08_VERTICES
        assert list(self._anny.bone_labels) == self._body.bone_labels

    @property
    def bone_labels(self) -> list[str]:
        return list(self._body.bone_labels)

    @property
    def dominant_bone(self) -> np.ndarray:
        """[19158] int64: the bone with the largest skinning weight of each vertex."""
        idx = self._anny.vertex_bone_indices.detach().cpu().numpy()  # [V, K]
        w = self._anny.vertex_bone_weights.detach().cpu().numpy()  # [V, K]
        return idx[np.arange(idx.shape[0]), w.argmax(axis=1)].astype(np.int64)

    @property
    def template_vertices(self) -> np.ndarray:
        """[19158, 3] anny's template: hm08's base mesh in anny's frame."""
        return self._anny.template_vertices.detach().cpu().numpy().astype(np.float64)

    @torch.no_grad()
    def forward(
        self,
        phenotype: dict[str, float],
        rotations: torch.Tensor,  # [T, J, 3] axis-angle, local-ref
        root_rotation: torch.Tensor,  # [T, 3]
        root_translation: torch.Tensor,  # [T, 3]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (posed vertices [T, 19158, 3], unposed rest vertices [19158, 3]), float32."""
        from dlacli.body.model import axis_angle_to_pose_params

        rotations = torch.as_tensor(rotations, dtype=torch.float32)
        if rotations.ndim != 3 or rotations.shape[1:] != (self._body.num_bones, 3):
            raise ValueError(f"rotations must be [T, {self._body.num_bones}, 3], got {tuple(rotations.shape)}")
        rr = torch.as_tensor(root_rotation, dtype=torch.float32).reshape(-1, 3)
        rt = torch.as_tensor(root_translation, dtype=torch.float32).reshape(-1, 3)
        params = axis_angle_to_pose_params(rotations, rr, rt)
        out = self._anny(params, self._body._phenotype_kwargs(phenotype, rotations))
        return out["vertices"], out["rest_vertices"][0]


@functools.lru_cache(maxsize=1)
def get_full_body() -> FullBody:
    """The process-wide anny-full model (built once, then cached)."""
    return FullBody()
