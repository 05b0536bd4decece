"""Animated Gaussians as OpenUSD (formats/usd.md). The only module that imports `pxr`.

`/Avatar` (Xform, the default prim) holds
- `/Avatar/Gaussians`: a UsdGeom.PointInstancer with one unit Sphere prototype, so the instance
  scales are the Gaussians' standard deviations; positions and orientations (quath) time-sampled,
  scales time-sampled only when they change; per-instance `primvars:displayColor` / `displayOpacity`;
- and/or `/Avatar/Splats`: a UsdVol.ParticleField3DGaussianSplat (usd-core >= 26) with linear
  scales, linear opacities and SH coefficients.

Quaternions are (w, x, y, z) everywhere in dla; `Vt.Quat*Array.FromNumpy` and `numpy.asarray` on
those arrays use (x, y, z, w). Only `_wxyz_to_xyzw` / `_xyzw_to_wxyz` below reorder.
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
SCHEMAS = ("instancer", "particlefield", "both")
SUFFIXES = (".usd", ".usda", ".usdc")
AVATAR = "/Avatar"
INSTANCER = "/Avatar/Gaussians"
PROTOTYPE = "/Avatar/Gaussians/Prototypes/Sphere"
SPLATS = "/Avatar/Splats"
PARTICLE_FIELD_EXTENT_SIGMAS = 3.0  # the splats' extent covers 3 standard deviations


@dataclass
class UsdAnimation:
    """What `read_usd` returns: T frames of N Gaussians."""

    fps: float
    start_time_code: float
    end_time_code: float
    time_codes: np.ndarray  # [T] the time code of each frame
    positions: np.ndarray  # [T, N, 3] float32, metres
    quats: np.ndarray  # [T, N, 4] float32 (w, x, y, z), unit
    scales: np.ndarray  # [T, N, 3] float32 standard deviations, metres
    rgb: np.ndarray  # [N, 3] float32 in [0, 1]
    opacities: np.ndarray  # [N] float32 in [0, 1]
    schema: str  # "instancer", "particlefield" or "both"
    sh: np.ndarray | None = None  # [N, K, 3] float32, from the particle field when present

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]


# --------------------------------------------------------------------------------------------
# numpy helpers (functional core)


def _wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """[..., 4] (w, x, y, z) -> [..., 4] (x, y, z, w)."""
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """[..., 4] (x, y, z, w) -> [..., 4] (w, x, y, z)."""
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def _normalized(q: np.ndarray) -> np.ndarray:
    """[..., 4] -> [..., 4] unit length (zero rows stay zero)."""
    norm = np.sqrt(np.einsum("...i,...i->...", q, q))[..., None]
    return q / np.maximum(norm, np.finfo(q.dtype).tiny)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """[..., 4] unit (w, x, y, z) -> [..., 3, 3] rotation matrices."""
    return np.stack([np.stack(row, -1) for row in _rotation_rows(q)], -2)


def _rotation_rows(q: np.ndarray) -> list[list[np.ndarray]]:
    """[..., 4] unit (w, x, y, z) -> R[i][j] as 9 arrays [...] (elementwise, no [..., 3, 3] temporaries)."""
    w, x, y, z = (q[..., k] for k in range(4))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]


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
    rows = _rotation_rows(quats)
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
) -> None:
    """Write T frames of N Gaussians as USD (binary for .usdc and .usd, text for .usda), atomically."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"unknown USD suffix {path.suffix!r} (use .usd, .usda or .usdc)")
    if schema not in SCHEMAS:
        raise DlaInputError("--schema", f"unknown schema {schema!r} (use one of {', '.join(SCHEMAS)})")
    if not (np.isfinite(fps) and fps > 0):
        raise DlaInputError("fps", f"must be a positive number, got {fps}")
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
    if np.any(np.all(quats == 0, axis=-1)):
        raise DlaInputError("quats", "contains a zero quaternion")
    quats = _normalized(quats)
    if scales.ndim == 3 and np.all(scales == scales[:1]):
        scales = scales[0]  # constant over time: no time samples
    if np.any(scales < 0):
        raise DlaInputError("scales", "contains negative values")

    from pxr import Sdf, Usd, UsdGeom

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

    if schema in ("instancer", "both"):
        instancer = _write_instancer(stage, positions, quats, scales, rgb, opacities, times)
    if splat_cls is not None:
        splats = _write_splats(stage, splat_cls, positions, quats, scales, opacities, rgb, sh, times)
    if schema == "both":
        # One look per purpose: viewers that show proxies draw the spheres, renderers the splats.
        instancer.CreatePurposeAttr(UsdGeom.Tokens.proxy)
        splats.CreatePurposeAttr(UsdGeom.Tokens.render)
        splats.GetPrim().CreateRelationship("proxyPrim").SetTargets([Sdf.Path(INSTANCER)])

    fmt = "usda" if path.suffix.lower() == ".usda" else "usdc"
    with atomic_path(path) as tmp:
        if not root.Export(str(tmp), "", {"format": fmt}):
            raise OSError(f"{path}: USD export failed")


def _write_instancer(stage, positions, quats, scales, rgb, opacities, times):
    from pxr import Gf, Sdf, UsdGeom, Vt

    n = positions.shape[1]
    inst = UsdGeom.PointInstancer.Define(stage, INSTANCER)
    protos = UsdGeom.Scope.Define(stage, PROTOTYPE.rsplit("/", 1)[0])
    sphere = UsdGeom.Sphere.Define(stage, PROTOTYPE)
    sphere.CreateRadiusAttr(1.0)
    sphere.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1, -1, -1), Gf.Vec3f(1, 1, 1)]))
    assert protos.GetPrim().IsValid()
    inst.CreatePrototypesRel().SetTargets([sphere.GetPath()])
    inst.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(n, dtype=np.int32)))

    # quath keeps ~3 significant digits. The extent uses the rounded quaternions the file holds,
    # unnormalised, as UsdGeomPointInstancer does when it builds instance transforms.
    quats_h = _wxyz_to_xyzw(quats).astype(np.float16)  # [T, N, 4] (x, y, z, w)
    if n:
        boxes = instance_extent(positions, _xyzw_to_wxyz(quats_h.astype(np.float32)), scales)
    pos_attr = inst.CreatePositionsAttr()
    rot_attr = inst.CreateOrientationsAttr()
    scale_attr = inst.CreateScalesAttr()
    extent_attr = inst.CreateExtentAttr()
    if scales.ndim == 2:
        scale_attr.Set(Vt.Vec3fArray.FromNumpy(scales))
    for i, time in enumerate(times):
        pos_attr.Set(Vt.Vec3fArray.FromNumpy(positions[i]), time)
        rot_attr.Set(Vt.QuathArray.FromNumpy(quats_h[i]), time)
        if scales.ndim == 3:
            scale_attr.Set(Vt.Vec3fArray.FromNumpy(scales[i]), time)
        if n:
            extent_attr.Set(Vt.Vec3fArray.FromNumpy(boxes[i]), time)

    # "vertex" interpolation on a PointInstancer primvar means one value per instance.
    primvars = UsdGeom.PrimvarsAPI(inst.GetPrim())
    color = primvars.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex)
    alpha = primvars.CreatePrimvar("displayOpacity", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
    _set_maybe_timed(color, rgb, Vt.Vec3fArray, times, timed=rgb.ndim == 3)
    _set_maybe_timed(alpha, opacities, Vt.FloatArray, times, timed=opacities.ndim == 2)
    return inst


def _set_maybe_timed(attr, values: np.ndarray, array_type, times, timed: bool) -> None:
    """One value for all time, or (timed: values[i] for frame i) one time sample per frame."""
    if timed:
        for i, time in enumerate(times):
            attr.Set(array_type.FromNumpy(np.ascontiguousarray(values[i])), time)
    else:
        attr.Set(array_type.FromNumpy(np.ascontiguousarray(values)))


def _write_splats(stage, splat_cls, positions, quats, scales, opacities, rgb, sh, times):
    from pxr import Vt

    n = positions.shape[1]
    splats = splat_cls.Define(stage, SPLATS)
    pos_attr = splats.CreatePositionsAttr()
    rot_attr = splats.CreateOrientationsAttr()
    scale_attr = splats.CreateScalesAttr()
    extent_attr = splats.CreateExtentAttr()
    quats_f = np.ascontiguousarray(_wxyz_to_xyzw(quats))  # [T, N, 4] (x, y, z, w)
    if scales.ndim == 2:
        scale_attr.Set(Vt.Vec3fArray.FromNumpy(scales))
    if n:
        boxes = instance_extent(positions, quats, PARTICLE_FIELD_EXTENT_SIGMAS * scales, "ellipsoid")
    for i, time in enumerate(times):
        pos_attr.Set(Vt.Vec3fArray.FromNumpy(positions[i]), time)
        rot_attr.Set(Vt.QuatfArray.FromNumpy(quats_f[i]), time)
        if scales.ndim == 3:
            scale_attr.Set(Vt.Vec3fArray.FromNumpy(scales[i]), time)
        if n:
            extent_attr.Set(Vt.Vec3fArray.FromNumpy(boxes[i]), time)
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
    value = attr.Get(time) if attr else None
    return None if value is None else np.asarray(value, dtype=dtype)


def _schema_prims(stage):
    """(instancer prim or None, splat prim or None, schema name or None) of a stage."""
    inst = stage.GetPrimAtPath(INSTANCER)
    splats = stage.GetPrimAtPath(SPLATS)
    inst = inst if inst and inst.GetTypeName() == "PointInstancer" else None
    splats = splats if splats and splats.GetTypeName() == "ParticleField3DGaussianSplat" else None
    names = {(True, False): "instancer", (False, True): "particlefield", (True, True): "both"}
    return inst, splats, names.get((inst is not None, splats is not None))


def read_usd(path: str | os.PathLike) -> UsdAnimation:
    """Read a dla USD file back (any schema). Geometry comes from /Avatar/Splats when present
    (full float precision), else from /Avatar/Gaussians (quath orientations)."""
    from pxr import Usd

    path = Path(path)
    stage = _open_stage(path)
    fmt = stage.GetRootLayer().customLayerData.get(FORMAT_KEY)
    if fmt != FORMAT:
        raise DlaInputError(path, f"customLayerData {FORMAT_KEY!r} is {fmt!r}, expected {FORMAT!r}")
    inst, splats, schema = _schema_prims(stage)
    if schema is None:
        raise DlaInputError(path, f"no PointInstancer at {INSTANCER} (nor a Gaussian splat field at {SPLATS})")
    geom = splats if splats is not None else inst
    samples = geom.GetAttribute("positions").GetTimeSamples()
    times = [Usd.TimeCode(s) for s in samples] or [Usd.TimeCode.Default()]
    default = Usd.TimeCode.Default()

    def frames(name: str, width: int) -> np.ndarray:  # [T, N, width]
        attr = geom.GetAttribute(name)
        out = []
        for time in times:
            arr = _array(attr, time)
            if arr is None:
                raise DlaInputError(path, f"{geom.GetPath()}.{name} has no value")
            out.append(arr.reshape(-1, width))
        if len({a.shape[0] for a in out}) != 1:
            raise DlaInputError(path, f"{geom.GetPath()}.{name} changes length over time")
        return np.stack(out)

    positions = frames("positions", 3)  # [T, N, 3]
    n = positions.shape[1]
    quats = _normalized(_xyzw_to_wxyz(frames("orientations", 4)))  # [T, N, 4]
    has_scales = geom.GetAttribute("scales").HasValue()
    scales = frames("scales", 3) if has_scales else np.ones_like(positions)  # [T, N, 3]

    def constant_or_frames(attr, width: int) -> np.ndarray | None:  # [N, width] or [T, N, width]
        if attr and attr.GetNumTimeSamples() > 0:
            got = [_array(attr, time) for time in times]
            if any(a is None for a in got) or len({a.size for a in got}) != 1:
                raise DlaInputError(path, f"{attr.GetPath()} has missing or uneven time samples")
            return np.stack([a.reshape(-1, width) for a in got])
        arr = _array(attr, default) if attr else None
        return None if arr is None else arr.reshape(-1, width)

    sh = None
    if splats is not None:
        opacities = constant_or_frames(splats.GetAttribute("opacities"), 1)
        coeffs = _array(splats.GetAttribute("radiance:sphericalHarmonicsCoefficients"), default)
        degree = splats.GetAttribute("radiance:sphericalHarmonicsDegree").Get()
        k = (int(degree) + 1) ** 2 if degree is not None else 1
        if coeffs is not None and coeffs.size == 3 * n * k:
            sh = coeffs.reshape(n, k, 3)
    else:
        opacities = constant_or_frames(inst.GetAttribute("primvars:displayOpacity"), 1)
    if inst is not None:
        rgb = constant_or_frames(inst.GetAttribute("primvars:displayColor"), 3)
    else:
        rgb = np.clip(sh[:, 0] * SH_C0 + 0.5, 0, 1) if sh is not None else None
    rgb = np.full((n, 3), 0.5, np.float32) if rgb is None else rgb
    opacities = np.ones(n, np.float32) if opacities is None else opacities[..., 0]
    for name, arr in (("quats", quats), ("scales", scales), ("rgb", rgb), ("opacities", opacities)):
        per_frame = arr.ndim == 3 or (name == "opacities" and arr.ndim == 2)
        if arr.shape[1 if per_frame else 0] != n:
            raise DlaInputError(path, f"{name} has {arr.shape} entries for {n} instances")
    return UsdAnimation(
        fps=float(stage.GetTimeCodesPerSecond()),
        start_time_code=float(stage.GetStartTimeCode()),
        end_time_code=float(stage.GetEndTimeCode()),
        time_codes=np.asarray(samples if samples else [stage.GetStartTimeCode()], dtype=np.float64),
        positions=positions,
        quats=quats.astype(np.float32),
        scales=scales,
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
    inst, splats, schema = _schema_prims(stage)
    geom = inst if inst is not None else splats
    if geom is not None:
        pos = geom.GetAttribute("positions")
        samples = pos.GetTimeSamples()
        value = pos.Get(samples[0]) if samples else pos.Get()
        instances = len(value) if value is not None else 0
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
