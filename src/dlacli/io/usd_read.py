"""Reading dla's USD files back (formats/usd.md "Reading"), summarising and validating any USD file.

`read_usd` reads every layout `dlacli.io.usd.write_usd` writes (every schema, exact or compact)
and files written before the points schema existed; `summarize_usd` is `dla info` on any USD
file; `validate_usd` runs pxr's validators. Text layers are checked before pxr parses them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, one_line
from dlacli.io.usd import (
    FORMAT,
    FORMAT_KEY,
    INDICES,
    INSTANCER,
    PATHS,
    POINTS,
    PRIM_TYPES,
    SPLATS,
    SUFFIXES,
    pxr_quiet,
    tf_message,
)
from dlacli.types import SH_C0


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


def _open_stage(path: Path):
    from pxr import Usd

    from dlacli.io.files import check_input

    check_input(path)
    if _encoding(path) == "usda":
        _check_usda_text(path)
    if path.suffix.lower() not in SUFFIXES:
        raise DlaInputError(path, f"unknown USD suffix {excerpt(path.suffix)} (use {', '.join(SUFFIXES)})")
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Exception as err:  # pxr.Tf.ErrorException and friends
        raise DlaInputError(path, f"not a readable USD file ({tf_message(err, path)})") from None
    if stage is None:
        raise DlaInputError(path, "not a readable USD file")
    return stage


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
            where = one_line(str(prim.GetPath()))
            raise DlaInputError(path, f"{where}.{INDICES} is missing or does not match its points")
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
                    raise DlaInputError(path, f"{one_line(str(prim.GetPath()))}.{name} has no value")
                if arr.size != width * len(idx):
                    where = one_line(str(prim.GetPath()))
                    raise DlaInputError(path, f"{where}.{name} has {arr.size // width} entries for {len(idx)} points")
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
                raise DlaInputError(path, f"{one_line(str(attr.GetPath()))} has missing or uneven values")
            out[k, idx] = arr.reshape(-1, width)
    return out if timed else out[0]


@pxr_quiet()
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
        raise DlaInputError(path, f"customLayerData {FORMAT_KEY!r} is {excerpt(fmt)}, expected {FORMAT!r}")
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
            raise DlaInputError(
                path, f"{PATHS[colour_kind]} holds {sum(len(i) for i in indices)} points for {n} Gaussians"
            )
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


@pxr_quiet()
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


@pxr_quiet()
def validate_usd(path: str | os.PathLike) -> list[str]:
    """Run every registered `pxr.UsdValidation` validator; the messages of all errors (not warnings)."""
    from pxr import UsdValidation

    stage = _open_stage(Path(path))
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = context.Validate(stage)
    return [err.GetErrorAsString() for err in errors if err.GetType() == UsdValidation.ValidationErrorType.Error]
