"""Benchmark result rows as JSON lines, their labels, points and the Pareto frontier of time
against accuracy (bench/charts.py draws them, bench/report.py writes the page).

One line per run of one method and setting on one subject and split (`dla.bench/1`):

    {"format": "dla.bench/1", "method": "unproject", "config": {"steps": 50},
     "device": "cpu (2 threads)", "subject": 7003, "split": "novel_views",
     "seconds": 43.9, "peak_mb": 1482.8,
     "metrics": {"psnr": 28.75, "psnr_masked": 20.36, "ssim": 0.955, "iou": 0.944}}

`seconds` and `peak_mb` are the cost of making the avatar (lift); the metrics score its renders on
the split's ground truth. A "point" is one (method, config) on one split, its metrics and cost
aggregated over subjects (median seconds, mean metrics): what one marker on the chart shows.
`method` is the name of a lift method in dlacli.stages.lift.methods, `config` its options as the
spec set them (`MethodSpec.options`) plus the protocol's keys; rows written before the registry
say "refine", "unproject+refine" or "learned+refine", and `read_rows` reads them under the
registry's names (`upgrade`).

Accuracy rows of `dla bench accuracy --input photo` (bench/single_photo.py) have `input: "photo"`
and `backend` (the dream backend) in the config, `seconds` = dream + lift, and also `stages`
({dream_s, lift_s}), `alignment_mm` / `pose_alignment_mm` (the residual of the body alignment),
`alignment_scale`, `fit` (dream's fit numbers) and `dreamed_per_view`; their splits include
"dreamed_views". An accuracy row may carry `status` (STATUSES; "ok" when absent) and `error`:
a run that could not be scored (its dream found no person) has status "error" and no metrics,
and `points` leaves it out. `label` and `group` name photo rows "photo/BACKEND METHOD ...".

Rows with a `kind` carry more (a row without one is an accuracy row, as above; `KINDS`):
- "stability" (`dla bench stability`): also `perturbation`, `level`, `status` ("ok", "nan",
  "empty", "error") and `error`; metrics are required only when the status is "ok";
- "budget" (`dla bench budget`): also `gaussians`, `render_size`, `render_ms` (per image),
  `usd_mib` / `usd_s` (a short animation at that count) and `noise` (the sampling noise s(n),
  dlacli.stages.budget);
- "speed" (`dla bench speed`): `suite`, `case`, `method`, `config`, `run` (one id per invocation,
  so ratios pair rows of one run), `seconds` (median per call), `repeats`, and optionally
  `min_seconds`, `first_seconds`, `peak_mb`, `size_mib`, `items` (work per call: frames, ...),
  `torch_loaded`, `counts` (named finite numbers >= 0: the render suite's compositing counts per
  pixel, dlacli.render.splat_stats), or `skipped` (why it was not measured; then `seconds` is
  null). No split, no subject, no metrics.
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Iterable
from typing import Any

from dlacli.bench.score import METRICS
from dlacli.errors import DlaInputError

FORMAT = "dla.bench/1"
SPLITS = ("novel_views", "novel_poses", "novel_view_pose", "dreamed_views", "inputs")
_FIELDS = {
    "method": str,
    "config": dict,
    "device": str,
    "split": str,
    "seconds": (int, float),
    "peak_mb": (int, float, type(None)),
    "metrics": dict,
}


KINDS = ("accuracy", "stability", "budget", "speed")
STATUSES = ("ok", "nan", "empty", "error")
_NUMBER = (int, float)
_OPT_NUMBER = (int, float, type(None))
_STABILITY = {"perturbation": str, "level": _NUMBER, "status": str, "error": (str, type(None))}
_BUDGET = {
    "gaussians": int,
    "render_size": int,
    "render_ms": _NUMBER,
    "usd_mib": _OPT_NUMBER,
    "usd_s": _OPT_NUMBER,
    "noise": _OPT_NUMBER,
}
_SPEED = {
    "suite": str,
    "case": str,
    "method": str,
    "config": dict,
    "device": str,
    "run": str,
    "seconds": _OPT_NUMBER,
    "repeats": int,
}
_SPEED_OPTIONAL = {
    "min_seconds": _OPT_NUMBER,
    "first_seconds": _OPT_NUMBER,
    "peak_mb": _OPT_NUMBER,
    "size_mib": _OPT_NUMBER,
    "items": _OPT_NUMBER,
    "torch_loaded": bool,
    "counts": dict,
    "skipped": str,
}


def kind(row: dict) -> str:
    """The row's kind: its `kind` field, "accuracy" when it has none."""
    return row.get("kind", "accuracy")


def _check_fields(row: dict, fields: dict, where: str, optional: bool = False) -> None:
    for name, types in fields.items():
        if optional and name not in row:
            continue
        v = row.get(name, _MISSING)
        bad = v is _MISSING or not isinstance(v, types) or (isinstance(v, bool) and bool not in _as_tuple(types))
        if bad:
            raise DlaInputError(where, f"field {name!r} is missing or not a {getattr(types, '__name__', 'number')}")


_MISSING = object()


def _as_tuple(types) -> tuple:
    return types if isinstance(types, tuple) else (types,)


def _check_cost(row: dict, names, where: str) -> None:
    import math

    for name in names:
        v = row.get(name)
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise DlaInputError(where, f"{name} = {v!r} is not a finite number >= 0")


def _check_metrics(metrics: dict, where: str, required: bool) -> None:
    import math

    for name in METRICS if required else [k for k in METRICS if k in metrics]:
        v = metrics.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DlaInputError(where, f"metric {name!r} is missing or not a finite number")


def check_row(row: Any, where: str = "row") -> dict:
    """A result row, validated: every field present with its type, a known split, finite
    non-negative cost, every metric in METRICS a finite number (LPIPS optional); rows with a
    `kind` (KINDS) also their kind's fields (module doc)."""
    import math

    if not isinstance(row, dict):
        raise DlaInputError(where, "a result row is a JSON object")
    if row.get("format") != FORMAT:
        raise DlaInputError(where, f"format {row.get('format')!r} is not {FORMAT!r}")
    k = row.get("kind", "accuracy")
    if k not in KINDS:
        raise DlaInputError(where, f"unknown kind {k!r} (one of {', '.join(KINDS)})")
    if k == "speed":
        _check_fields(row, _SPEED, where)
        _check_fields(row, _SPEED_OPTIONAL, where, optional=True)
        if row["seconds"] is None and "skipped" not in row:
            raise DlaInputError(where, "seconds is null but the row does not say why (skipped)")
        if row["repeats"] < 0:
            raise DlaInputError(where, f"repeats = {row['repeats']!r} is negative")
        _check_cost(
            row, ("seconds", *[n for n in _SPEED_OPTIONAL if n not in ("torch_loaded", "counts", "skipped")]), where
        )
        counts = row.get("counts", {})
        for name, v in counts.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise DlaInputError(where, f"counts[{name!r}] = {v!r} is not a number")
        _check_cost(counts, list(counts), where)
        return row
    for name, types in _FIELDS.items():
        if name not in row or not isinstance(row[name], types) or isinstance(row[name], bool):
            raise DlaInputError(where, f"field {name!r} is missing or not a {getattr(types, '__name__', 'number')}")
    if row["split"] not in SPLITS:
        raise DlaInputError(where, f"unknown split {row['split']!r} (one of {', '.join(SPLITS)})")
    _check_cost(row, ("seconds", "peak_mb"), where)
    if k == "stability":
        _check_fields(row, _STABILITY, where)
        if row["status"] not in STATUSES:
            raise DlaInputError(where, f"unknown status {row['status']!r} (one of {', '.join(STATUSES)})")
        if not math.isfinite(row["level"]):
            raise DlaInputError(where, f"level = {row['level']!r} is not a finite number")
        _check_metrics(row["metrics"], where, required=row["status"] == "ok")
        return row
    if k == "budget":
        _check_fields(row, _BUDGET, where)
        if row["gaussians"] < 2 or row["render_size"] < 1:
            raise DlaInputError(where, "gaussians must be >= 2 and render_size >= 1")
        _check_cost(row, ("render_ms", "usd_mib", "usd_s", "noise"), where)
    status = row.get("status", "ok")
    if status not in STATUSES:
        raise DlaInputError(where, f"unknown status {status!r} (one of {', '.join(STATUSES)})")
    _check_metrics(row["metrics"], where, required=status == "ok")
    return row


def make_row(
    method: str,
    config: dict,
    split: str,
    seconds: float,
    peak_mb: float | None,
    metrics: dict,
    subject: int | None = None,
    device: str | None = None,
    status: str = "ok",
    error: str | None = None,
) -> dict:
    """A validated row (device defaults to this process's: "cpu (N threads)" or the CUDA name);
    a run that failed before it could be scored: status "error", `error` why, metrics {}."""
    if device is None:
        import torch

        device = (
            torch.cuda.get_device_name() if torch.cuda.is_available() else f"cpu ({torch.get_num_threads()} threads)"
        )
    row = {
        "format": FORMAT,
        "method": method,
        "config": dict(config),
        "device": device,
        "subject": subject,
        "split": split,
        "seconds": float(seconds),
        "peak_mb": None if peak_mb is None else float(peak_mb),
        "metrics": {k: float(v) for k, v in metrics.items()},
    }
    if status != "ok":
        row.update(status=status, error=error)
    return check_row(row)


def default_device() -> str:
    """This process's device: the CUDA device's name, else "cpu (N threads)"."""
    import torch

    return torch.cuda.get_device_name() if torch.cuda.is_available() else f"cpu ({torch.get_num_threads()} threads)"


def stability_row(
    method: str,
    config: dict,
    split: str,
    seconds: float,
    peak_mb: float | None,
    metrics: dict,
    perturbation: str,
    level: float,
    status: str = "ok",
    error: str | None = None,
    subject: int | None = None,
    device: str | None = None,
) -> dict:
    """A validated "stability" row: one method on one perturbed subject and split."""
    row = {
        "format": FORMAT,
        "kind": "stability",
        "method": method,
        "config": dict(config),
        "device": device or default_device(),
        "subject": subject,
        "split": split,
        "seconds": float(seconds),
        "peak_mb": None if peak_mb is None else float(peak_mb),
        "metrics": {k: float(v) for k, v in metrics.items()},
        "perturbation": perturbation,
        "level": float(level),
        "status": status,
        "error": error,
    }
    return check_row(row)


def budget_row(
    method: str,
    config: dict,
    split: str,
    seconds: float,
    metrics: dict,
    gaussians: int,
    render_size: int,
    render_ms: float,
    usd_mib: float | None = None,
    usd_s: float | None = None,
    noise: float | None = None,
    subject: int | None = None,
    device: str | None = None,
) -> dict:
    """A validated "budget" row: one avatar drawn with `gaussians` Gaussians, scored on a split."""
    opt = lambda v: None if v is None else float(v)  # noqa: E731
    row = {
        "format": FORMAT,
        "kind": "budget",
        "method": method,
        "config": dict(config),
        "device": device or default_device(),
        "subject": subject,
        "split": split,
        "seconds": float(seconds),
        "peak_mb": None,
        "metrics": {k: float(v) for k, v in metrics.items()},
        "gaussians": int(gaussians),
        "render_size": int(render_size),
        "render_ms": float(render_ms),
        "usd_mib": opt(usd_mib),
        "usd_s": opt(usd_s),
        "noise": opt(noise),
    }
    return check_row(row)


def speed_row(
    suite: str,
    case: str,
    method: str,
    config: dict,
    seconds: float | None,
    repeats: int,
    run: str,
    device: str | None = None,
    **optional,
) -> dict:
    """A validated "speed" row (optional fields: module doc; None values are left out)."""
    row = {
        "format": FORMAT,
        "kind": "speed",
        "suite": suite,
        "case": case,
        "method": method,
        "config": dict(config),
        "device": device or default_device(),
        "run": run,
        "seconds": None if seconds is None else float(seconds),
        "repeats": int(repeats),
    }
    unknown = set(optional) - set(_SPEED_OPTIONAL)
    if unknown:
        raise ValueError(f"speed_row: unknown fields {sorted(unknown)}")
    row.update(
        {
            k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v)
            for k, v in optional.items()
            if v is not None
        }
    )
    return check_row(row)


def append_rows(path: str | os.PathLike, rows: Iterable[dict]) -> None:
    """Append rows to a JSON-lines file (created if absent); a run adds to earlier runs' rows."""
    with open(path, "a", encoding="utf-8") as f:
        for row in rows:
            f.write(json.dumps(check_row(row), sort_keys=True) + "\n")


def read_rows(path: str | os.PathLike) -> list[dict]:
    """Every row of a JSON-lines file, validated (blank lines skipped); errors name the line."""
    from dlacli.io.files import read_text

    rows = []
    for no, line in enumerate(read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as err:
            raise DlaInputError(f"{path}:{no}", f"not JSON ({err.msg})") from None
        rows.append(upgrade(check_row(row, f"{path}:{no}")))
    return rows


def upgrade(row: dict) -> dict:
    """A row as the method registry names it: a method name from before the registry
    (stages.methods.LEGACY_NAMES) becomes the registry's, and an "unproject" row that records no
    steps (the stability and budget suites' unprojection) gains steps 0, what it ran."""
    from dlacli.stages.lift.methods import LEGACY_NAMES

    if kind(row) == "speed" or (row["method"] not in LEGACY_NAMES and row["method"] != "unproject"):
        return row
    method = LEGACY_NAMES.get(row["method"], row["method"])
    config = row["config"] if method != "unproject" or "steps" in row["config"] else {**row["config"], "steps": 0}
    return {**row, "method": method, "config": config}


PROTOCOL_KEYS = ("res", "appearance", "wardrobe", "checkpoint")  # what the subjects were / the weights' hash


def group(row: dict) -> str:
    """What made the avatar, for chart markers: the method ("unproject") from the 4 true views,
    or "photo/BACKEND METHOD" from one photo through that dream backend (config `input`)."""
    cfg = row["config"]
    if cfg.get("input", "views") == "views":
        return row["method"]
    oracle = f" oracle={cfg['oracle']}" if cfg.get("oracle") else ""
    return f"{cfg['input']}/{cfg.get('backend', '?')} {row['method']}{oracle}"


SUBJECT_KEYS = ("appearance", "wardrobe", "res")  # the protocol keys that say what the subjects were


def subjects_of(row: dict) -> tuple:
    """What the subjects of a row were: its SUBJECT_KEYS values (None where absent)."""
    return tuple(row["config"].get(k) for k in SUBJECT_KEYS)


def label(row: dict, leave_out: tuple[str, ...] = (), subjects: bool = False) -> str:
    """A method and its setting, for tables and legends: "unproject steps=50", "photo/template
    unproject steps=50" (`group`; the protocol's keys, the same for every row of a run, the
    checkpoint's hash, what a stability row measured of its subject (`subject_*`) and `leave_out`
    are left out). `subjects`: what the subjects were too, "unproject steps=50 (albedo, heldout,
    512 px)", for rows of several kinds of subject side by side."""
    hidden = PROTOCOL_KEYS + ("input", "backend", "oracle") + tuple(leave_out)
    shown = [(k, v) for k, v in sorted(row["config"].items()) if k not in hidden]
    cfg = " ".join(f"{k}={v}" for k, v in shown if not k.startswith("subject_"))
    text = f"{group(row)} {cfg}".strip()
    if subjects:
        what = [f"{v} px" if k == "res" else str(v) for k, v in zip(SUBJECT_KEYS, subjects_of(row)) if v is not None]
        text += f" ({', '.join(what)})" if what else ""
    return text


def level_text(level: float) -> str:
    """A perturbation's level as tables and axes show it."""
    return f"{level:g}"


def points(rows: list[dict], split: str, metric: str = "psnr_masked") -> list[dict]:
    """One point per (method, config) on `split`: median seconds, mean metric, subject count
    (rows whose status is not "ok" left out). Where the points' subjects differ (lit and albedo,
    say) every label says what its subjects were, so no two points share a label."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        if row["split"] == split and row.get("status", "ok") == "ok":
            key = json.dumps([row["method"], row["config"]], sort_keys=True)  # the full config, not the label
            groups.setdefault(key, []).append(row)
    mixed = len({subjects_of(rs[0]) for rs in groups.values()}) > 1  # labels then say what the subjects were
    pts = [
        {
            "label": label(rs[0], subjects=mixed),
            "method": rs[0]["method"],
            "group": group(rs[0]),
            "seconds": statistics.median(r["seconds"] for r in rs),
            "value": statistics.fmean(r["metrics"][metric] for r in rs),
            "subjects": len(rs),
        }
        for rs in groups.values()
    ]
    return sorted(pts, key=lambda p: p["label"])


def pareto_front(pts: list[dict]) -> list[dict]:
    """The points no other point beats: none is at most as slow and at least as accurate with one
    of the two strictly better. Sorted by time (then accuracy falls never: each next point on the
    frontier is slower and more accurate)."""
    front = []
    for p in pts:
        beaten = any(
            q["seconds"] <= p["seconds"]
            and q["value"] >= p["value"]
            and (q["seconds"] < p["seconds"] or q["value"] > p["value"])
            for q in pts
        )
        if not beaten:
            front.append(p)
    return sorted(front, key=lambda p: (p["seconds"], p["value"]))
