"""Animated Gaussians as OpenUSD (formats/usd.md): the stage conventions and the writer.

pxr is imported here, in dlacli.io.usd_read (reading back, summaries, validation) and in
dlacli.io.usd_rig (the rigged asset), lazily, and nowhere else.

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
the tolerance are left out. `dlacli.io.usd_read.read_usd` reads every layout back, including
files written before the points schema existed.

Quaternions are (w, x, y, z) everywhere in dla; `Vt.Quat*Array.FromNumpy` and `numpy.asarray` on
those arrays use (x, y, z, w). Only `dlacli.geometry.quat_wxyz_to_xyzw` / `quat_xyzw_to_wxyz` reorder.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
from pathlib import Path

import numpy as np

from dlacli.errors import EXCERPT_CHARS, DlaInputError, excerpt, one_line
from dlacli.io.atomic import atomic_path
from dlacli.limits import USD_SUFFIXES
from dlacli.types import SH_C0

FORMAT = "dla.usd/1"
FORMAT_KEY = "dla:format"
SCHEMAS = ("points", "instancer", "particlefield", "both")
SUFFIXES = USD_SUFFIXES
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


# --------------------------------------------------------------------------------------------
# pxr's diagnostics: warnings off the terminal, errors as one line


@contextlib.contextmanager
def pxr_quiet():
    """pxr's own warnings and status lines (e.g. `Warning: in _HelperGetNumericValueFromString ...`
    for an out-of-range integer literal) stay off the terminal, on runs that fail and on runs that
    succeed: what matters reaches the user as dla's one-line errors. pxr's errors still raise.
    Also a decorator (`@pxr_quiet()`)."""
    from pxr import Tf

    trap_type = getattr(Tf, "DiagnosticTrap", None)
    if trap_type is None:  # a usd-core without Tf.DiagnosticTrap prints them on file descriptor 2
        with _stderr_silenced():
            yield
        return
    with trap_type() as trap:
        try:
            yield
        finally:
            trap.Clear()  # dismissed, not reposted when the trap closes


@contextlib.contextmanager
def _stderr_silenced():
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def tf_message(err: BaseException, path: str | os.PathLike | None = None) -> str:
    """The human part of a pxr error ("Error in 'Func' at line N in file F : 'message'") as one
    line (`one_line`) of at most 4 * EXCERPT_CHARS characters: `path` (the file the error line names
    already) by its name, pxr's internal namespace left out, and what the message quotes from a file
    (a 20 KB literal, a long prim name, the parser's grammar rule) cut to excerpts."""
    text = " ".join(str(err).split())
    found = [m.strip() for m in re.findall(r" : '(.*?)'(?= Error in |$)", text)] or [text]
    found = [m for m in dict.fromkeys(found) if not any(m != other and m in other for other in found)]
    message = "; ".join(found)  # each message once, the longest form (pxr repeats some with a line number)
    if path is not None:
        message = message.replace(str(path), Path(path).name)
    message = re.sub(r"pxrInternal_v[0-9_]+?__pxrReserved__(?:::)?", "", message)
    rule = rf"(parse error matching )(.{{{EXCERPT_CHARS + 1},}}?)( at ')"  # a PEGTL grammar rule, often ~1 KB
    message = re.sub(rule, lambda m: m[1] + one_line(m[2], EXCERPT_CHARS) + m[3], message)
    message = re.sub(rf"(?<= at )'([^']{{{EXCERPT_CHARS + 1},}})'", lambda m: excerpt(m[1]), message)  # a value
    message = re.sub(rf"[^\s']{{{2 * EXCERPT_CHARS + 1},}}", lambda m: one_line(m[0], EXCERPT_CHARS), message)
    return one_line(message, 4 * EXCERPT_CHARS)


def export_layer(layer, tmp: Path, path: Path, fmt: str) -> None:
    """Export a layer to `tmp`, the temporary file of `path`'s atomic write. pxr's failures to write
    (the disk full, the file-size limit) are DlaInputError `path: cannot write (...)`."""
    try:
        with pxr_quiet():
            written = layer.Export(str(tmp), "", {"format": fmt})
    except Exception as err:  # pxr.Tf.ErrorException
        reason = re.search(r"writing file: (.*?)'", str(err))  # pxr quotes the OS error
        problem = one_line(reason.group(1), EXCERPT_CHARS) if reason else tf_message(err, tmp)
        raise DlaInputError(path, f"cannot write ({problem})") from None
    if not written:
        raise DlaInputError(path, "cannot write (pxr's export failed)")


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


@pxr_quiet()
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
        raise DlaInputError(path, f"unknown USD suffix {path.suffix!r} (use {', '.join(SUFFIXES)})")
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
            raise DlaInputError("--schema", f"{schema!r} needs UsdVol.ParticleField3DGaussianSplat: usd-core >= 26")

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
        export_layer(root, tmp, path, fmt)


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
    _set_track(
        inst.CreateOrientationsAttr(),
        part.quats,
        Vt.QuathArray,
        times,
        lambda q: quat_wxyz_to_xyzw(q).astype(np.float16),
    )
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
        (
            "displayColor",
            "UsdPrimvarReader_float3",
            Sdf.ValueTypeNames.Float3,
            ("diffuseColor", Sdf.ValueTypeNames.Color3f),
        ),
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
    _set_track(
        splats.CreateOrientationsAttr(),
        part.quats,
        Vt.QuatfArray,
        times,
        lambda q: quat_wxyz_to_xyzw(q).astype(np.float32),
    )
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
