"""Animated Gaussians as OpenUSD (formats/usd.md). The only module that imports `pxr`.

`/Avatar` (Xform, the default prim) holds, by schema:
- `points` -> `/Avatar/Points`: UsdGeom.Points (colour per point through `primvars:displayColor`,
  a diameter per point in `widths`; no orientations), the one Blender shows in colour;
- `instancer` -> `/Avatar/Gaussians`: a UsdGeom.PointInstancer with one unit Sphere prototype, so
  the instance scales are the Gaussians' standard deviations; orientations as quath;
- `particlefield` -> `/Avatar/Splats`: a UsdVol.ParticleField3DGaussianSplat (usd-core >= 26)
  with linear scales, linear opacities and SH coefficients;
- `both` -> `/Avatar/Points` and `/Avatar/Splats`.

`tolerance` > 0 compacts the time samples (dlacli.io.usd_compact): the points and the instancer
are split into rigid parts (`/Avatar/Points/Part000`, ... each with its own time-sampled
`xformOp:transform` and `dla:indices`), and samples that USD's interpolation reproduces within
the tolerance are left out. `read_usd` reads every layout back, including files written before
the points schema existed.

Quaternions are (w, x, y, z) everywhere in dla; `Vt.Quat*Array.FromNumpy` and `numpy.asarray` on
those arrays use (x, y, z, w). Only `dlacli.geometry.quat_wxyz_to_xyzw` / `quat_xyzw_to_wxyz` reorder.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.io.atomic import atomic_path
from dlacli.types import SH_C0

FORMAT = "dla.usd/1"
FORMAT_KEY = "dla:format"
SCHEMAS = ("points", "instancer", "particlefield", "both")
SUFFIXES = (".usd", ".usda", ".usdc")
AVATAR = "/Avatar"
INSTANCER = "/Avatar/Gaussians"
POINTS = "/Avatar/Points"
SPLATS = "/Avatar/Splats"
LOOK = "/Avatar/Looks/GaussianColor"
PROTOTYPE = "Prototypes/Sphere"  # under each PointInstancer
INDICES = "dla:indices"  # a part's Gaussians, as indices into the full set
PARTICLE_FIELD_EXTENT_SIGMAS = 3.0  # the splats' extent covers 3 standard deviations
MAX_TOLERANCE = 1.0  # metres; compaction tolerances above this are refused
PRIM_TYPES = {"instancer": "PointInstancer", "points": "Points", "particlefield": "ParticleField3DGaussianSplat"}
PATHS = {"instancer": INSTANCER, "points": POINTS, "particlefield": SPLATS}


@dataclass
class UsdAnimation:
    """What `read_usd` returns: T frames of N Gaussians."""

    fps: float
    start_time_code: float
    end_time_code: float
    time_codes: np.ndarray  # [T] the time code of each frame
    positions: np.ndarray  # [T, N, 3] float32, metres
    quats: np.ndarray  # [T, N, 4] float32 (w, x, y, z), unit (identity from the points schema)
    scales: np.ndarray  # [T, N, 3] float32 standard deviations, metres (points: width / 2, isotropic)
    rgb: np.ndarray  # [N, 3] or [T, N, 3] float32 in [0, 1]
    opacities: np.ndarray  # [N] or [T, N] float32 in [0, 1]
    schema: str  # "points", "instancer", "particlefield", "both" or "instancer+particlefield" (older files)
    sh: np.ndarray | None = None  # [N, K, 3] float32, from the particle field when present

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]


# --------------------------------------------------------------------------------------------
# numpy helpers (functional core)


def instance_extent(
    positions: np.ndarray,  # [..., N, 3]
    quats: np.ndarray,  # [..., N, 4] (w, x, y, z), unit (used as given)
    scales: np.ndarray,  # [..., N, 3] half sizes (broadcast against positions)
    shape: str = "box",
) -> np.ndarray:
    """[..., 2, 3] axis-aligned box (min, max) around N rotated, scaled unit shapes.

    shape "box": the unit cube [-1, 1]^3 (how UsdGeomPointInstancer.ComputeExtentAtTime bounds an
    instance of a prototype whose extent is that cube): half size along axis i = sum_j |R_ij| s_j.
    shape "ellipsoid": the unit sphere, tight: half size along axis i = sqrt(sum_j (R_ij s_j)^2).
    """
    from dlacli.geometry import quat_rotation_rows

    rows = quat_rotation_rows(quats)
    s = [scales[..., j] for j in range(3)]
    if shape == "box":
        half = [sum(np.abs(rows[i][j]) * s[j] for j in range(3)) for i in range(3)]
    else:
        half = [np.sqrt(sum((rows[i][j] * s[j]) ** 2 for j in range(3))) for i in range(3)]
    lo = np.stack([(positions[..., i] - half[i]).min(axis=-1) for i in range(3)], -1)  # [..., 3]
    hi = np.stack([(positions[..., i] + half[i]).max(axis=-1) for i in range(3)], -1)  # [..., 3]
    return np.stack([lo, hi], axis=-2)


def _to_numpy(name: str, value, shapes: list[tuple]) -> np.ndarray:
    """float32 array matching one of `shapes` (None = any size); DlaInputError otherwise."""
    if hasattr(value, "detach"):  # torch tensor
        value = value.detach().cpu().numpy()
    arr = np.asarray(value, dtype=np.float32)
    for shape in shapes:
        if len(shape) == arr.ndim and all(s is None or s == a for s, a in zip(shape, arr.shape)):
            break
    else:
        want = " or ".join("[" + ", ".join("?" if s is None else str(s) for s in sh) + "]" for sh in shapes)
        raise DlaInputError(name, f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise DlaInputError(name, "contains NaN or Inf")
    return np.ascontiguousarray(arr)


def point_widths(scales: np.ndarray) -> np.ndarray:
    """[..., 3] standard deviations -> [...] Points diameter: 2 (s_0 s_1 s_2)^(1/3), the sphere
    with the volume (and the covariance determinant) of the Gaussian's 1-sigma ellipsoid."""
    return 2 * np.exp(np.log(np.maximum(scales, 1e-30)).mean(axis=-1))


# --------------------------------------------------------------------------------------------
# writing


def write_usd(
    path: str | os.PathLike,
    positions,  # [T, N, 3] metres
    quats,  # [T, N, 4] (w, x, y, z)
    scales,  # [N, 3] or [T, N, 3] standard deviations, metres
    rgb,  # [N, 3] or [T, N, 3] in [0, 1] (per frame from a pose-conditioned decoder)
    opacities,  # [N] or [T, N] in [0, 1]
    fps: float,
    *,
    sh=None,  # [N, K, 3] SH coefficients for the particle field, K = (degree + 1)^2
    schema: str = "instancer",
    start_frame: int = 0,
    tolerance: float = 0.0,  # metres; 0 = every frame exactly, > 0 = compact (formats/usd.md)
) -> None:
    """Write T frames of N Gaussians as USD (binary for .usdc and .usd, text for .usda), atomically."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"unknown USD suffix {path.suffix!r} (use .usd, .usda or .usdc)")
    if schema not in SCHEMAS:
        raise DlaInputError("--schema", f"unknown schema {schema!r} (use one of {', '.join(SCHEMAS)})")
    if not (np.isfinite(fps) and fps > 0):
        raise DlaInputError("fps", f"must be a positive number, got {fps}")
    if not (np.isfinite(tolerance) and 0 <= tolerance <= MAX_TOLERANCE):
        raise DlaInputError("tolerance", f"must be between 0 and {MAX_TOLERANCE} m, got {tolerance}")
    positions = _to_numpy("positions", positions, [(None, None, 3)])
    t, n = positions.shape[:2]
    if t < 1:
        raise DlaInputError("positions", "needs at least one frame")
    quats = _to_numpy("quats", quats, [(t, n, 4)])
    scales = _to_numpy("scales", scales, [(n, 3), (t, n, 3)])
    rgb = _to_numpy("rgb", rgb, [(n, 3), (t, n, 3)])
    opacities = _to_numpy("opacities", opacities, [(n,), (t, n)])
    if rgb.ndim == 3 and np.all(rgb == rgb[:1]):
        rgb = rgb[0]  # constant over time: no time samples
    if opacities.ndim == 2 and np.all(opacities == opacities[:1]):
        opacities = opacities[0]
    if sh is not None and rgb.ndim == 3:
        raise DlaInputError("sh", "per-frame colours take their SH from rgb (pass sh=None)")
    if sh is not None:
        sh = _to_numpy("sh", sh, [(n, None, 3)])
        if sh.shape[1] not in (1, 4, 9, 16):
            raise DlaInputError("sh", f"{sh.shape[1]} coefficients per channel is not (d+1)^2, d = 0..3")
    from dlacli.geometry import quat_normalize

    if np.any(np.all(quats == 0, axis=-1)):
        raise DlaInputError("quats", "contains a zero quaternion")
    quats = quat_normalize(quats, float(np.finfo(quats.dtype).tiny))
    if np.any(scales < 0):
        raise DlaInputError("scales", "contains negative values")
    scales = np.broadcast_to(scales, (t, n, 3))  # [T, N, 3]
    if n == 0:
        tolerance = 0.0  # nothing to compact: the exact layout holds an empty set as it is

    from pxr import Usd, UsdGeom

    splat_cls = None
    if schema in ("particlefield", "both"):
        from pxr import UsdVol

        splat_cls = getattr(UsdVol, "ParticleField3DGaussianSplat", None)
        if splat_cls is None:
            raise DlaInputError(
                "--schema", f"{schema!r} needs UsdVol.ParticleField3DGaussianSplat: usd-core >= 26"
            )

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(float(start_frame))
    stage.SetEndTimeCode(float(start_frame + t - 1))
    root = stage.GetRootLayer()
    root.customLayerData = {FORMAT_KEY: FORMAT}
    avatar = UsdGeom.Xform.Define(stage, AVATAR)
    stage.SetDefaultPrim(avatar.GetPrim())
    times = [Usd.TimeCode(float(start_frame + i)) for i in range(t)]
    colours = (rgb, opacities)

    if schema == "instancer":
        parts = _parts(positions, quats, scales, scales, tolerance, np.float16, rigid=True)
        _write_group(stage, "instancer", parts, colours, times)
    if schema in ("points", "both"):
        widths = point_widths(scales)[..., None]  # [T, N, 1]
        parts = _parts(positions, None, widths, scales, tolerance, None, rigid=True)
        _write_group(stage, "points", parts, colours, times)
    if splat_cls is not None:
        parts = _parts(positions, quats, scales, scales, tolerance, np.float32, rigid=False)
        _write_splats(stage, splat_cls, parts[0], opacities, rgb, sh, times)

    fmt = "usda" if path.suffix.lower() == ".usda" else "usdc"
    with atomic_path(path) as tmp:
        if not root.Export(str(tmp), "", {"format": fmt}):
            raise OSError(f"{path}: USD export failed")


def _parts(positions, quats, sizes, scales, tolerance, quat_dtype, rigid: bool):
    """The Part list of one schema: one world-space part of every frame (tolerance 0, the layout
    of earlier versions) or the compact parts (dlacli.io.usd_compact)."""
    from dlacli.io import usd_compact as uc

    t, n = positions.shape[:2]
    if tolerance > 0:
        return uc.compact(positions, quats, sizes, scales.max(axis=-1), tolerance, quat_dtype=quat_dtype, parts=rigid)
    every = np.arange(t)
    quat_track = None
    if quats is not None:
        quat_track = uc.Track(every, quats.astype(quat_dtype), False)
    return [uc.Part(np.arange(n), None, uc.Track(every, positions, False), quat_track, uc.exact_track(sizes))]


def _set_track(attr, track, array_type, times, convert=np.ascontiguousarray) -> None:
    """Author a Track: one value for all time, or a time sample at each kept frame."""
    if track.constant:
        attr.Set(array_type.FromNumpy(convert(track.values[0])))
        return
    for frame, value in zip(track.frames, track.values):
        attr.Set(array_type.FromNumpy(convert(value)), times[int(frame)])


def _set_maybe_timed(attr, values: np.ndarray, array_type, times, timed: bool) -> None:
    """One value for all time, or (timed: values[i] for frame i) one time sample per frame."""
    if timed:
        for i, time in enumerate(times):
            attr.Set(array_type.FromNumpy(np.ascontiguousarray(values[i])), time)
    else:
        attr.Set(array_type.FromNumpy(np.ascontiguousarray(values)))


def _write_group(stage, kind: str, parts, colours, times) -> None:
    """`kind` ("instancer" or "points") at its path: the prim itself when there is one world-space
    part, else an Xform holding one prim per part (Part000, ...), each with its rigid
    `xformOp:transform` at every frame and its `dla:indices`."""
    from pxr import Gf, Sdf, UsdGeom, UsdShade, Vt

    path = PATHS[kind]
    single = len(parts) == 1 and parts[0].transforms is None
    if not single:
        UsdGeom.Xform.Define(stage, path)
    look = _define_look(stage) if kind == "points" else None
    rgb, opacities = colours
    for k, part in enumerate(parts):
        prim_path = path if single else f"{path}/Part{k:03d}"
        idx = part.indices
        if kind == "instancer":
            geom = _define_instancer(stage, prim_path, part, times)
        else:
            geom = _define_points(stage, prim_path, part, times)
            UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(look)
        if not single:
            geom.GetPrim().CreateAttribute(INDICES, Sdf.ValueTypeNames.IntArray, True, Sdf.VariabilityUniform).Set(
                Vt.IntArray.FromNumpy(idx.astype(np.int32))
            )
            op = geom.AddTransformOp()
            for matrix, time in zip(part.transforms, times):
                op.Set(Gf.Matrix4d(matrix.tolist()), time)
        # "vertex" interpolation: one value per point (on a PointInstancer: per instance).
        primvars = UsdGeom.PrimvarsAPI(geom.GetPrim())
        color = primvars.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex)
        alpha = primvars.CreatePrimvar("displayOpacity", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
        _set_maybe_timed(color, rgb[..., idx, :], Vt.Vec3fArray, times, timed=rgb.ndim == 3)
        _set_maybe_timed(alpha, opacities[..., idx], Vt.FloatArray, times, timed=opacities.ndim == 2)
        _write_extents(geom, kind, times)


def _define_instancer(stage, path: str, part, times):
    from pxr import Gf, UsdGeom, Vt

    from dlacli.geometry import quat_wxyz_to_xyzw

    inst = UsdGeom.PointInstancer.Define(stage, path)
    UsdGeom.Scope.Define(stage, f"{path}/{PROTOTYPE.split('/')[0]}")
    sphere = UsdGeom.Sphere.Define(stage, f"{path}/{PROTOTYPE}")
    sphere.CreateRadiusAttr(1.0)
    sphere.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1, -1, -1), Gf.Vec3f(1, 1, 1)]))
    inst.CreatePrototypesRel().SetTargets([sphere.GetPath()])
    inst.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(len(part.indices), dtype=np.int32)))
    _set_track(inst.CreatePositionsAttr(), part.positions, Vt.Vec3fArray, times)
    _set_track(inst.CreateOrientationsAttr(), part.quats, Vt.QuathArray, times, lambda q: quat_wxyz_to_xyzw(q).astype(np.float16))
    _set_track(inst.CreateScalesAttr(), part.sizes, Vt.Vec3fArray, times)
    return inst


def _define_points(stage, path: str, part, times):
    from pxr import UsdGeom, Vt

    points = UsdGeom.Points.Define(stage, path)
    _set_track(points.CreatePointsAttr(), part.positions, Vt.Vec3fArray, times)
    _set_track(points.CreateWidthsAttr(), part.sizes, Vt.FloatArray, times, lambda w: np.ascontiguousarray(w[:, 0]))
    points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    return points


def _define_look(stage):
    """`/Avatar/Looks/GaussianColor`: a UsdPreviewSurface whose colour and opacity read the
    `displayColor` / `displayOpacity` primvars (Blender turns it into Attribute nodes)."""
    from pxr import Sdf, UsdGeom, UsdShade

    existing = UsdShade.Material.Get(stage, LOOK)
    if existing:
        return existing
    UsdGeom.Scope.Define(stage, LOOK.rsplit("/", 1)[0])
    material = UsdShade.Material.Define(stage, LOOK)
    surface = UsdShade.Shader.Define(stage, f"{LOOK}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
    for name, reader_id, value_type, target in (
        ("displayColor", "UsdPrimvarReader_float3", Sdf.ValueTypeNames.Float3, ("diffuseColor", Sdf.ValueTypeNames.Color3f)),
        ("displayOpacity", "UsdPrimvarReader_float", Sdf.ValueTypeNames.Float, ("opacity", Sdf.ValueTypeNames.Float)),
    ):
        reader = UsdShade.Shader.Define(stage, f"{LOOK}/{name}")
        reader.CreateIdAttr(reader_id)
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set(name)
        reader.CreateOutput("result", value_type)
        surface.CreateInput(*target).ConnectToSource(reader.ConnectableAPI(), "result")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def _write_extents(geom, kind: str, times) -> None:
    """The extent at every frame where the geometry is time-sampled, from the values pxr returns
    there (interpolated ones included). Instancer: what UsdGeomPointInstancer.ComputeExtentAtTime
    computes (the quaternions as stored, unnormalised); points: the points +- width / 2."""
    from pxr import Vt

    from dlacli.geometry import quat_xyzw_to_wxyz

    prim = geom.GetPrim()
    names = ("positions", "orientations", "scales") if kind == "instancer" else ("points", "widths")
    attrs = [prim.GetAttribute(name) for name in names]
    sampled = any(a.GetNumTimeSamples() > 0 for a in attrs)
    extent = geom.CreateExtentAttr()
    for time in times if sampled else times[:1]:
        values = [np.asarray(a.Get(time), dtype=np.float32) for a in attrs]
        if values[0].size == 0:
            return
        if kind == "instancer":
            box = instance_extent(values[0], quat_xyzw_to_wxyz(values[1]), values[2])
        else:
            half = values[1][:, None] / 2
            box = np.stack([(values[0] - half).min(axis=0), (values[0] + half).max(axis=0)])
        if sampled:
            extent.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(box)), time)
        else:
            extent.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(box)))


def _write_splats(stage, splat_cls, part, opacities, rgb, sh, times):
    from pxr import Vt

    from dlacli.geometry import quat_normalize, quat_wxyz_to_xyzw, quat_xyzw_to_wxyz

    splats = splat_cls.Define(stage, SPLATS)
    _set_track(splats.CreatePositionsAttr(), part.positions, Vt.Vec3fArray, times)
    _set_track(splats.CreateOrientationsAttr(), part.quats, Vt.QuatfArray, times, lambda q: quat_wxyz_to_xyzw(q).astype(np.float32))
    _set_track(splats.CreateScalesAttr(), part.sizes, Vt.Vec3fArray, times)
    # extent at each frame of the geometry, from the values pxr returns there
    attrs = [splats.GetPrim().GetAttribute(a) for a in ("positions", "orientations", "scales")]
    sampled = any(a.GetNumTimeSamples() > 0 for a in attrs)
    extent = splats.CreateExtentAttr()
    for time in times if sampled else times[:1]:
        pos, rot, scl = (np.asarray(a.Get(time), dtype=np.float32) for a in attrs)
        if pos.size == 0:
            break
        unit = quat_normalize(quat_xyzw_to_wxyz(rot), float(np.finfo(rot.dtype).tiny))
        box = instance_extent(pos, unit, PARTICLE_FIELD_EXTENT_SIGMAS * scl, "ellipsoid")
        extent.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(box)), *([time] if sampled else []))
    _set_maybe_timed(splats.CreateOpacitiesAttr(), opacities, Vt.FloatArray, times, timed=opacities.ndim == 2)
    if sh is None:
        sh = ((rgb - 0.5) / SH_C0)[..., None, :]  # [(T,) N, 1, 3] DC only
    degree = int(round(np.sqrt(sh.shape[-2]))) - 1
    splats.CreateRadianceSphericalHarmonicsDegreeAttr(degree)
    timed = sh.ndim == 4
    coeffs = np.ascontiguousarray(sh.reshape(*sh.shape[:-3], -1, 3), dtype=np.float32)  # [(T,) N * K, 3]
    _set_maybe_timed(splats.CreateRadianceSphericalHarmonicsCoefficientsAttr(), coeffs, Vt.Vec3fArray, times, timed)
    return splats


# --------------------------------------------------------------------------------------------
# reading


def _open_stage(path: Path):
    from pxr import Usd

    from dlacli.io.files import check_input

    check_input(path)
    if _encoding(path) == "usda":
        _check_usda_text(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"unknown USD suffix {path.suffix!r} (use .usd, .usda or .usdc)")
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Exception as err:  # pxr.Tf.ErrorException and friends
        raise DlaInputError(path, f"not a readable USD file ({_tf_message(err)})") from None
    if stage is None:
        raise DlaInputError(path, "not a readable USD file")
    return stage


def _tf_message(err: BaseException) -> str:
    """The human part of a pxr error ("Error in 'Func' at line N in file F : 'message'"), one line."""
    text = " ".join(str(err).split())
    found = re.findall(r" : '(.*?)'(?= Error in |$)", text)
    return "; ".join(found) if found else text[:300]


MAX_USDA_DEPTH = 256  # USD's text parser recurses per nesting level and crashes (SIGSEGV) far below 10^5


def _check_usda_text(path: Path) -> None:
    """A text layer must be UTF-8 and nest brackets at most MAX_USDA_DEPTH deep before pxr parses it
    (counted over the raw bytes: brackets inside strings only make the count larger)."""
    from dlacli.io.files import MAX_TEXT_BYTES, read_bytes

    data = read_bytes(path, MAX_TEXT_BYTES)
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise DlaInputError(path, f"is not UTF-8 text (byte {err.start})") from None
    step = np.zeros(256, np.int64)
    step[list(b"([{")], step[list(b")]}")] = 1, -1
    depth, chunk = 0, 1 << 24  # 16 MiB at a time: memory stays bounded for large layers
    for start in range(0, len(data), chunk):
        running = depth + np.cumsum(step[np.frombuffer(data, np.uint8, min(chunk, len(data) - start), start)])
        if running.size and int(running.max()) > MAX_USDA_DEPTH:
            raise DlaInputError(path, f"nests brackets deeper than {MAX_USDA_DEPTH} levels; not a USD layer dla reads")
        depth = int(running[-1]) if running.size else depth


def _encoding(path: Path) -> str:
    with open(path, "rb") as f:
        head = f.read(8)
    if head.startswith(b"PXR-USDC"):
        return "usdc"
    if head.startswith(b"#usda"):
        return "usda"
    if head.startswith(b"PK"):
        return "usdz"
    return "unknown"


def _array(attr, time, dtype=np.float32) -> np.ndarray | None:
    """attr's value at time (None: the default) as an array, or None when it has none."""
    from pxr import Usd

    value = (attr.Get(Usd.TimeCode.Default() if time is None else time)) if attr else None
    return None if value is None else np.asarray(value, dtype=dtype)


def _schema_prims(stage) -> tuple[dict[str, list], str | None]:
    """({kind: [part prims]} for the kinds present, schema name or None). A kind's prim is the
    geometry itself, or an Xform whose children of that type are its parts (compact files)."""
    found = {}
    for kind, path in PATHS.items():
        prim = stage.GetPrimAtPath(path)
        if not prim:
            continue
        if prim.GetTypeName() == PRIM_TYPES[kind]:
            found[kind] = [prim]
        elif prim.GetTypeName() == "Xform":
            parts = [c for c in prim.GetChildren() if c.GetTypeName() == PRIM_TYPES[kind]]
            if parts:
                found[kind] = parts
    kinds = tuple(k for k in ("points", "instancer", "particlefield") if k in found)
    names = {("points", "particlefield"): "both", ("instancer", "particlefield"): "instancer+particlefield"}
    name = names.get(kinds, "+".join(kinds)) if kinds else None
    return found, name


def _frame_times(stage, prims) -> list[float]:
    """The time code of each frame: every integer time code of the stage's range (compact files
    leave samples out), else the union of the geometry's position samples."""
    if stage.HasAuthoredTimeCodeRange():
        start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
        if end >= start and end - start < 1e6:
            return [start + i for i in range(int(np.floor(end - start)) + 1)]
    samples = sorted({s for p in prims for s in p.GetAttribute(_position_name(p)).GetTimeSamples()})
    return samples


def _position_name(prim) -> str:
    return "points" if prim.GetTypeName() == "Points" else "positions"


def _part_indices(path: Path, prims, n_of) -> list[np.ndarray]:
    """Each part's Gaussian indices (`dla:indices`, or all in order for a single prim); together
    they must be a permutation of 0..N-1."""
    if len(prims) == 1 and not prims[0].GetAttribute(INDICES):
        return [np.arange(n_of(prims[0]))]
    out = []
    for prim in prims:
        value = _array(prim.GetAttribute(INDICES), None, np.int64)
        if value is None or value.size != n_of(prim):
            raise DlaInputError(path, f"{prim.GetPath()}.{INDICES} is missing or does not match its points")
        out.append(value)
    allidx = np.concatenate(out)
    if not np.array_equal(np.sort(allidx), np.arange(allidx.size)):
        raise DlaInputError(path, f"the parts' {INDICES} are not a permutation of 0..{allidx.size - 1}")
    return out


def _read_parts(path: Path, prims, times) -> dict[str, np.ndarray]:
    """World positions [T, N, 3], quats [T, N, 4] (w, x, y, z) and scales [T, N, 3] of one kind's
    parts, each composed with its prim's local-to-world transform at that time."""
    from pxr import Usd, UsdGeom

    from dlacli.geometry import matrix_to_quat, quat_multiply, quat_normalize, quat_xyzw_to_wxyz

    points = prims[0].GetTypeName() == "Points"
    tcs = [Usd.TimeCode(s) for s in times] or [Usd.TimeCode.Default()]

    def n_of(prim) -> int:
        attr = prim.GetAttribute(_position_name(prim))
        samples = attr.GetTimeSamples()
        value = attr.Get(samples[0] if samples else Usd.TimeCode.Default())
        return 0 if value is None else len(value)

    indices = _part_indices(path, prims, n_of)
    n, t = sum(len(i) for i in indices), len(tcs)
    pos = np.empty((t, n, 3), np.float32)
    quat = np.zeros((t, n, 4), np.float32)
    quat[..., 0] = 1
    scale = np.empty((t, n, 3), np.float32)
    for prim, idx in zip(prims, indices):
        xformable = UsdGeom.Xformable(prim)

        def frames(name: str, width: int, prim=prim, idx=idx) -> np.ndarray:  # [T, n, width]
            attr = prim.GetAttribute(name)
            out = []
            for time in tcs:
                arr = _array(attr, time)
                if arr is None:
                    raise DlaInputError(path, f"{prim.GetPath()}.{name} has no value")
                if arr.size != width * len(idx):
                    raise DlaInputError(path, f"{prim.GetPath()}.{name} has {arr.size // width} entries for {len(idx)} points")
                out.append(arr.reshape(-1, width))
            return np.stack(out)

        local = frames(_position_name(prim), 3)
        m = np.stack([np.asarray(xformable.ComputeLocalToWorldTransform(time)) for time in tcs])  # [T, 4, 4]
        world = np.einsum("tni,tij->tnj", local.astype(np.float64), m[:, :3, :3]) + m[:, None, 3, :3]
        pos[:, idx] = world
        if points:
            widths = frames("widths", 1) if prim.GetAttribute("widths").HasValue() else np.full((t, len(idx), 1), 2.0)
            scale[:, idx] = widths / 2
            continue
        q = frames("orientations", 4)
        q = quat_normalize(quat_xyzw_to_wxyz(q), float(np.finfo(q.dtype).tiny))  # [T, n, 4] in the prim's frame
        if not np.allclose(m[:, :3, :3], np.eye(3)):
            r = np.swapaxes(m[:, :3, :3], 1, 2)  # column-vector rotation of each frame
            r = r / np.linalg.norm(r, axis=1, keepdims=True)
            q = quat_multiply(np.broadcast_to(matrix_to_quat(r)[:, None], q.shape), q.astype(np.float64))
        quat[:, idx] = quat_normalize(np.asarray(q, np.float32), float(np.finfo(np.float32).tiny))
        scale[:, idx] = frames("scales", 3) if prim.GetAttribute("scales").HasValue() else 1.0
    return {"positions": pos, "quats": quat, "scales": scale, "indices": indices}


def _primvar_frames(path: Path, prims, indices, name: str, width: int, times, n: int) -> np.ndarray | None:
    """[N, width], or [T, N, width] when time-sampled, of a per-point primvar over the parts."""
    from pxr import Usd

    attrs = [p.GetAttribute(name) for p in prims]
    if not all(a and a.HasValue() for a in attrs):
        return None
    timed = any(a.GetNumTimeSamples() > 0 for a in attrs)
    tcs = [Usd.TimeCode(s) for s in times] if timed else [Usd.TimeCode.Default()]
    out = np.empty((len(tcs), n, width), np.float32)
    for attr, idx in zip(attrs, indices):
        for k, time in enumerate(tcs):
            arr = _array(attr, time)
            if arr is None or arr.size != width * len(idx):
                raise DlaInputError(path, f"{attr.GetPath()} has missing or uneven values")
            out[k, idx] = arr.reshape(-1, width)
    return out if timed else out[0]


def read_usd(path: str | os.PathLike) -> UsdAnimation:
    """Read a dla USD file back (any schema and layout), one frame per time code of the stage's
    range, at which pxr interpolates between the samples a compact file kept. Geometry comes from
    /Avatar/Splats when present (full float precision), else /Avatar/Gaussians (quath
    orientations), else /Avatar/Points (no orientations: identity rotations, isotropic scales
    width / 2)."""
    path = Path(path)
    stage = _open_stage(path)
    fmt = stage.GetRootLayer().customLayerData.get(FORMAT_KEY)
    if fmt != FORMAT:
        raise DlaInputError(path, f"customLayerData {FORMAT_KEY!r} is {fmt!r}, expected {FORMAT!r}")
    found, schema = _schema_prims(stage)
    if schema is None:
        raise DlaInputError(path, f"no Gaussians: none of {POINTS}, {INSTANCER}, {SPLATS} (nor parts under them)")
    kind = next(k for k in ("particlefield", "instancer", "points") if k in found)
    times = _frame_times(stage, found[kind])
    geom = _read_parts(path, found[kind], times)
    n = geom["positions"].shape[1]

    sh = opacities = None
    if kind == "particlefield":
        splats = found[kind][0]
        opacities = _primvar_frames(path, [splats], geom["indices"], "opacities", 1, times, n)
        coeffs = _array(splats.GetAttribute("radiance:sphericalHarmonicsCoefficients"), None)
        degree = splats.GetAttribute("radiance:sphericalHarmonicsDegree").Get()
        k = (int(degree) + 1) ** 2 if degree is not None else 1
        if coeffs is not None and coeffs.size == 3 * n * k:
            sh = coeffs.reshape(n, k, 3)
    colour_kind = next((k for k in ("points", "instancer") if k in found), None)
    rgb = None
    if colour_kind is not None:
        prims = found[colour_kind]
        indices = geom["indices"] if colour_kind == kind else _read_parts(path, prims, times[:1])["indices"]
        if sum(len(i) for i in indices) != n:
            raise DlaInputError(path, f"{PATHS[colour_kind]} holds {sum(len(i) for i in indices)} points for {n} Gaussians")
        rgb = _primvar_frames(path, prims, indices, "primvars:displayColor", 3, times, n)
        if opacities is None:
            opacities = _primvar_frames(path, prims, indices, "primvars:displayOpacity", 1, times, n)
    if rgb is None:
        rgb = np.clip(sh[:, 0] * SH_C0 + 0.5, 0, 1) if sh is not None else np.full((n, 3), 0.5, np.float32)
    opacities = np.ones(n, np.float32) if opacities is None else opacities[..., 0]
    return UsdAnimation(
        fps=float(stage.GetTimeCodesPerSecond()),
        start_time_code=float(stage.GetStartTimeCode()),
        end_time_code=float(stage.GetEndTimeCode()),
        time_codes=np.asarray(times if times else [stage.GetStartTimeCode()], dtype=np.float64),
        positions=geom["positions"],
        quats=geom["quats"],
        scales=geom["scales"],
        rgb=np.asarray(rgb, np.float32),
        opacities=np.asarray(opacities, np.float32),
        schema=schema,
        sh=sh,
    )


def summarize_usd(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of any USD file (used by `dla info`); dla files also say their format."""
    from pxr import UsdGeom

    path = Path(path)
    stage = _open_stage(path)
    prims, time_sampled = [], []
    instances = None
    for prim in stage.Traverse():
        prims.append(f"{prim.GetPath()} ({prim.GetTypeName() or 'untyped'})")
        for attr in prim.GetAttributes():
            if attr.GetNumTimeSamples() > 0:
                time_sampled.append(str(attr.GetPath()))
    found, schema = _schema_prims(stage)
    if found:
        instances = 0
        for prim in next(iter(found.values())):
            attr = prim.GetAttribute(_position_name(prim))
            samples = attr.GetTimeSamples()
            value = attr.Get(samples[0]) if samples else attr.Get()
            instances += len(value) if value is not None else 0
    start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    return {
        "kind": "usd",
        "format": stage.GetRootLayer().customLayerData.get(FORMAT_KEY),
        "encoding": _encoding(path),
        "up_axis": str(UsdGeom.GetStageUpAxis(stage)),
        "meters_per_unit": float(UsdGeom.GetStageMetersPerUnit(stage)),
        "fps": float(stage.GetTimeCodesPerSecond()),
        "start_time_code": float(start),
        "end_time_code": float(end),
        "frames": int(round(end - start)) + 1 if stage.HasAuthoredTimeCodeRange() else 1,
        "instances": instances,
        "parts": max((len(v) for v in found.values()), default=0),
        "prims": prims,
        "time_sampled": time_sampled,
        "schema": schema,
    }


def validate_usd(path: str | os.PathLike) -> list[str]:
    """Run every registered `pxr.UsdValidation` validator; the messages of all errors (not warnings)."""
    from pxr import UsdValidation

    stage = _open_stage(Path(path))
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = context.Validate(stage)
    return [
        err.GetErrorAsString()
        for err in errors
        if err.GetType() == UsdValidation.ValidationErrorType.Error
    ]
