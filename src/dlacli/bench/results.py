"""Benchmark results as JSON lines, the Pareto frontier of time against accuracy, and its chart.

One line per run of one method and setting on one subject and split (`dla.bench/1`):

    {"format": "dla.bench/1", "method": "unproject+refine", "config": {"steps": 50},
     "device": "cpu (2 threads)", "subject": 7003, "split": "novel_views",
     "seconds": 43.9, "peak_mb": 1482.8,
     "metrics": {"psnr": 28.75, "psnr_masked": 20.36, "ssim": 0.955, "iou": 0.944}}

`seconds` and `peak_mb` are the cost of making the avatar (lift); the metrics score its renders on
the split's ground truth. A "point" is one (method, config) on one split, its metrics and cost
aggregated over subjects (median seconds, mean metrics): what one marker on the chart shows.

Rows with a `kind` carry more (a row without one is an accuracy row, as above; `KINDS`):
- "stability" (`dla bench stability`): also `perturbation`, `level`, `status` ("ok", "nan",
  "empty", "error") and `error`; metrics are required only when the status is "ok";
- "budget" (`dla bench budget`): also `gaussians`, `render_size`, `render_ms` (per image),
  `usd_mib` / `usd_s` (a short animation at that count) and `noise` (the sampling noise s(n),
  dlacli.stages.budget);
- "speed" (`dla bench speed`): `suite`, `case`, `method`, `config`, `run` (one id per invocation,
  so ratios pair rows of one run), `seconds` (median per call), `repeats`, and optionally
  `min_seconds`, `first_seconds`, `peak_mb`, `size_mib`, `items` (work per call: frames, ...),
  `torch_loaded`, or `skipped` (why it was not measured; then `seconds` is null). No split, no
  subject, no metrics.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from pathlib import Path
from typing import Any, Iterable

from dlacli.errors import DlaInputError

FORMAT = "dla.bench/1"
METRICS = ("psnr", "psnr_masked", "ssim", "iou")
SPLITS = ("novel_views", "novel_poses", "novel_view_pose", "inputs")
_FIELDS = {"method": str, "config": dict, "device": str, "split": str, "seconds": (int, float),
           "peak_mb": (int, float, type(None)), "metrics": dict}  # fmt: skip


KINDS = ("accuracy", "stability", "budget", "speed")
STATUSES = ("ok", "nan", "empty", "error")
_NUMBER = (int, float)
_OPT_NUMBER = (int, float, type(None))
_STABILITY = {"perturbation": str, "level": _NUMBER, "status": str, "error": (str, type(None))}
_BUDGET = {"gaussians": int, "render_size": int, "render_ms": _NUMBER, "usd_mib": _OPT_NUMBER,
           "usd_s": _OPT_NUMBER, "noise": _OPT_NUMBER}  # fmt: skip
_SPEED = {"suite": str, "case": str, "method": str, "config": dict, "device": str, "run": str,
          "seconds": _OPT_NUMBER, "repeats": int}  # fmt: skip
_SPEED_OPTIONAL = {"min_seconds": _OPT_NUMBER, "first_seconds": _OPT_NUMBER, "peak_mb": _OPT_NUMBER,
                   "size_mib": _OPT_NUMBER, "items": _OPT_NUMBER, "torch_loaded": bool, "skipped": str}  # fmt: skip


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
        _check_cost(row, ("seconds", *[n for n in _SPEED_OPTIONAL if n not in ("torch_loaded", "skipped")]), where)
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
    _check_metrics(row["metrics"], where, required=True)
    return row


def make_row(method: str, config: dict, split: str, seconds: float, peak_mb: float | None,
             metrics: dict, subject: int | None = None, device: str | None = None) -> dict:  # fmt: skip
    """A validated row (device defaults to this process's: "cpu (N threads)" or the CUDA name)."""
    if device is None:
        import torch

        device = torch.cuda.get_device_name() if torch.cuda.is_available() else f"cpu ({torch.get_num_threads()} threads)"
    row = {"format": FORMAT, "method": method, "config": dict(config), "device": device, "subject": subject,
           "split": split, "seconds": float(seconds), "peak_mb": None if peak_mb is None else float(peak_mb),
           "metrics": {k: float(v) for k, v in metrics.items()}}  # fmt: skip
    return check_row(row)


def default_device() -> str:
    """This process's device: the CUDA device's name, else "cpu (N threads)"."""
    import torch

    return torch.cuda.get_device_name() if torch.cuda.is_available() else f"cpu ({torch.get_num_threads()} threads)"


def stability_row(method: str, config: dict, split: str, seconds: float, peak_mb: float | None, metrics: dict,
                  perturbation: str, level: float, status: str = "ok", error: str | None = None,
                  subject: int | None = None, device: str | None = None) -> dict:  # fmt: skip
    """A validated "stability" row: one method on one perturbed subject and split."""
    row = {"format": FORMAT, "kind": "stability", "method": method, "config": dict(config),
           "device": device or default_device(), "subject": subject, "split": split, "seconds": float(seconds),
           "peak_mb": None if peak_mb is None else float(peak_mb), "metrics": {k: float(v) for k, v in metrics.items()},
           "perturbation": perturbation, "level": float(level), "status": status, "error": error}  # fmt: skip
    return check_row(row)


def budget_row(method: str, config: dict, split: str, seconds: float, metrics: dict, gaussians: int,
               render_size: int, render_ms: float, usd_mib: float | None = None, usd_s: float | None = None,
               noise: float | None = None, subject: int | None = None, device: str | None = None) -> dict:  # fmt: skip
    """A validated "budget" row: one avatar drawn with `gaussians` Gaussians, scored on a split."""
    opt = lambda v: None if v is None else float(v)  # noqa: E731
    row = {"format": FORMAT, "kind": "budget", "method": method, "config": dict(config),
           "device": device or default_device(), "subject": subject, "split": split, "seconds": float(seconds),
           "peak_mb": None, "metrics": {k: float(v) for k, v in metrics.items()}, "gaussians": int(gaussians),
           "render_size": int(render_size), "render_ms": float(render_ms), "usd_mib": opt(usd_mib),
           "usd_s": opt(usd_s), "noise": opt(noise)}  # fmt: skip
    return check_row(row)


def speed_row(suite: str, case: str, method: str, config: dict, seconds: float | None, repeats: int, run: str,
              device: str | None = None, **optional) -> dict:  # fmt: skip
    """A validated "speed" row (optional fields: module doc; None values are left out)."""
    row = {"format": FORMAT, "kind": "speed", "suite": suite, "case": case, "method": method, "config": dict(config),
           "device": device or default_device(), "run": run, "seconds": None if seconds is None else float(seconds),
           "repeats": int(repeats)}  # fmt: skip
    unknown = set(optional) - set(_SPEED_OPTIONAL)
    if unknown:
        raise ValueError(f"speed_row: unknown fields {sorted(unknown)}")
    row.update({k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v)
                for k, v in optional.items() if v is not None})  # fmt: skip
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
        rows.append(check_row(row, f"{path}:{no}"))
    return rows


PROTOCOL_KEYS = ("res", "appearance", "wardrobe", "checkpoint")  # what the subjects were / the weights' hash


def label(row: dict) -> str:
    """A method and its setting, for tables and legends: "unproject+refine steps=50" (the
    protocol's keys, the same for every row of a run, and the checkpoint's hash are left out)."""
    cfg = " ".join(f"{k}={v}" for k, v in sorted(row["config"].items()) if k not in PROTOCOL_KEYS)
    return f"{row['method']} {cfg}".strip()


def points(rows: list[dict], split: str, metric: str = "psnr_masked") -> list[dict]:
    """One point per (method, config) on `split`: median seconds, mean metric, subject count."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        if row["split"] == split:
            key = json.dumps([row["method"], row["config"]], sort_keys=True)  # the full config, not the label
            groups.setdefault(key, []).append(row)
    pts = [{"label": label(rs[0]), "method": rs[0]["method"], "seconds": statistics.median(r["seconds"] for r in rs),
            "value": statistics.fmean(r["metrics"][metric] for r in rs), "subjects": len(rs)}
           for rs in groups.values()]  # fmt: skip
    return sorted(pts, key=lambda p: p["label"])


def pareto_front(pts: list[dict]) -> list[dict]:
    """The points no other point beats: none is at most as slow and at least as accurate with one
    of the two strictly better. Sorted by time (then accuracy falls never: each next point on the
    frontier is slower and more accurate)."""
    front = []
    for p in pts:
        beaten = any(q["seconds"] <= p["seconds"] and q["value"] >= p["value"]
                     and (q["seconds"] < p["seconds"] or q["value"] > p["value"]) for q in pts)  # fmt: skip
        if not beaten:
            front.append(p)
    return sorted(front, key=lambda p: (p["seconds"], p["value"]))


def draw_chart(rows: list[dict], path: str | os.PathLike, metric: str = "psnr_masked",
               splits: tuple[str, ...] = ("novel_views", "novel_poses", "novel_view_pose")) -> Path:  # fmt: skip
    """Time (log) against `metric`, one panel per split present, one marker per point, the Pareto
    frontier as a line; written to a PNG (matplotlib, extra `bench`)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        raise DlaInputError("chart", "drawing the chart needs matplotlib (pip install 'dla[bench]')") from None
    from dlacli.io.atomic import atomic_path

    rows = [r for r in rows if kind(r) == "accuracy"]
    present = [s for s in splits if any(r["split"] == s for r in rows)]
    if not present:
        raise DlaInputError("chart", f"no rows for the splits {', '.join(splits)}")
    fig, axes = plt.subplots(1, len(present), figsize=(6 * len(present), 4.5), squeeze=False)
    for ax, split in zip(axes[0], present):
        pts = points(rows, split, metric)
        methods = sorted({p["method"] for p in pts})
        for m, marker in zip(methods, "osD^v<>ph*"):
            sel = [p for p in pts if p["method"] == m]
            ax.scatter([p["seconds"] for p in sel], [p["value"] for p in sel], marker=marker, s=40, label=m, zorder=3)
            words = [p["label"][len(m):].split() for p in sel]
            shared = set.intersection(*map(set, words)) if len(sel) > 1 else set()  # said once, in the legend's sense
            for k, (p, w) in enumerate(zip(sel, words)):
                ax.annotate(" ".join(x for x in w if x not in shared), (p["seconds"], p["value"]), fontsize=7,
                            xytext=(4, 3 - 9 * (k % 3)), textcoords="offset points")  # fmt: skip
        front = pareto_front(pts)
        ax.step([p["seconds"] for p in front], [p["value"] for p in front], where="post", color="0.3",
                linewidth=1, zorder=2, label="Pareto frontier")  # fmt: skip
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.FuncFormatter(  # label 2 and 5 of each decade
            lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v))) in (2, 5) else ""))
        ax.set_xlabel("lift time per subject, s (log)")
        ax.set_ylabel({"psnr_masked": "PSNR inside the mask, dB", "psnr": "PSNR, dB"}.get(metric, metric))
        ax.set_title(split.replace("_", " "))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def report_markdown(rows: list[dict], chart_name: str | None, metric: str = "psnr_masked",
                    stability_chart: str | None = None, budget_chart: str | None = None) -> str:  # fmt: skip
    """The benchmark page: per split a table of every point (frontier points in bold) and the
    chart, all computed from `rows`, so the page never drifts from the numbers; then, when the
    rows hold them, the stability, budget and speed sections (`stability_markdown`, ...)."""
    acc = [r for r in rows if kind(r) == "accuracy"]
    others = [r for r in rows if kind(r) != "accuracy"]
    lines = ["# Benchmarks", ""]
    if acc:
        lines += ["Generated by `dla bench report` from the JSON lines of `dla bench accuracy --jsonl` (or",
                  "`dla bench pipeline --jsonl`); do not edit by hand. Time is the median lift wall time per",
                  "subject; metrics are means over subjects (PSNR inside the mask, alpha IoU at 0.5; renders",
                  "on black). LPIPS is absent: it needs AlexNet weights dla does not ship.", ""]  # fmt: skip
    else:
        lines += ["Generated by `dla bench report` from dla.bench/1 JSON lines; do not edit by hand.", ""]
    if others:
        made = ", ".join(f"`dla bench {k}`" for k in KINDS[1:] if any(kind(r) == k for r in others))
        lines += [f"Also from {made} (`--jsonl`): the sections after the accuracy tables.", ""]
    if chart_name and acc:
        lines += [f"![time against masked PSNR]({chart_name})", ""]
    devices = sorted({r["device"] for r in rows})
    lines += [f"Devices: {', '.join(devices)}.", ""]
    for split in SPLITS:
        sel = [r for r in acc if r["split"] == split]
        if not sel:
            continue
        front = {p["label"] for p in pareto_front(points(sel, split, metric))}
        lines += [f"## {split.replace('_', ' ')}", "",
                  "| method and setting | subjects | lift s | PSNR | masked PSNR | SSIM | IoU |", "|---|---|---|---|---|---|---|"]  # fmt: skip
        per = {m: {p["label"]: p for p in points(sel, split, m)} for m in METRICS}
        for p in sorted(per[metric].values(), key=lambda p: p["seconds"]):
            name = f"**{p['label']}**" if p["label"] in front else p["label"]
            vals = [per[m][p["label"]]["value"] for m in METRICS]
            lines.append(f"| {name} | {p['subjects']} | {p['seconds']:.1f} | {vals[0]:.2f} | {vals[1]:.2f} | {vals[2]:.3f} | {vals[3]:.3f} |")
        lines += ["", "Bold: on the Pareto frontier of time against masked PSNR.", ""]
    if any(kind(r) == "stability" for r in rows):
        lines += stability_markdown(rows, stability_chart)
    if any(kind(r) == "budget" for r in rows):
        lines += budget_markdown(rows, budget_chart)
    if any(kind(r) == "speed" for r in rows):
        lines += speed_markdown(rows)
    return "\n".join(lines)


# ------------------------------------------------------------------------------ charts


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise DlaInputError("chart", "drawing the chart needs matplotlib (pip install 'dla[bench]')") from None
    return plt


def _save(fig, path, rect=(0, 0, 1, 1)) -> Path:
    from dlacli.io.atomic import atomic_path

    plt = _pyplot()
    fig.tight_layout(rect=rect)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def _level_text(level: float) -> str:
    return f"{level:g}"


def draw_stability_chart(rows: list[dict], path: str | os.PathLike, metric: str = "psnr_masked") -> Path:
    """Degradation curves: one panel per perturbation, `metric` (mean over subjects) against the
    level (evenly spaced, the clean baseline first), one colour per method, novel views solid and
    novel poses dashed, a dotted line DROP_DB below each method's clean novel-view score; a red x
    where a level failed (NaN, empty or an exception) on any subject."""
    from dlacli.bench.stability import DROP_DB, PERTURBATIONS, curves

    plt = _pyplot()
    per_split = {split: curves(rows, split, metric) for split in ("novel_views", "novel_poses")}
    names = list(dict.fromkeys(list(per_split["novel_views"]) + list(per_split["novel_poses"])))
    if not names:
        raise DlaInputError("chart", "no stability rows")
    methods = sorted({m for c in per_split.values() for p in c.values() for m in p})
    colours = {m: f"C{i}" for i, m in enumerate(methods)}
    cols = min(5, len(names))
    nrows = -(-len(names) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 3.0 * nrows), squeeze=False)
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    for ax, name in zip(axes.flat, names):
        levels: list[float] = []
        for split in ("novel_views", "novel_poses"):
            for curve in per_split[split].get(name, {}).values():
                levels += [lv for lv, *_ in curve if lv not in levels]
        x_of = {lv: i for i, lv in enumerate(levels)}
        bad: set[int] = set()
        for split, style in (("novel_views", "-"), ("novel_poses", "--")):
            for m, curve in sorted(per_split[split].get(name, {}).items()):
                xs = [x_of[lv] for lv, *_ in curve]
                ax.plot(xs, [v for _, v, *_ in curve], style, marker="o", ms=3, color=colours[m],
                        label=f"{m}, {split.replace('_', ' ')}")  # fmt: skip
                bad |= {x_of[lv] for lv, _, _, fails in curve if fails}
                if split == "novel_views" and curve and curve[0][1] == curve[0][1]:  # its baseline - DROP_DB
                    ax.axhline(curve[0][1] - DROP_DB, color=colours[m], linestyle=":", linewidth=0.8)
        if bad:
            ax.scatter(sorted(bad), [ax.get_ylim()[0]] * len(bad), marker="x", color="red", zorder=4, clip_on=False)
        ax.set_xticks(range(len(levels)), [_level_text(lv) for lv in levels])
        unit = PERTURBATIONS[name].unit if name in PERTURBATIONS else ""
        ax.set_xlabel(unit, fontsize=8)
        ax.set_title(name.replace("_", " "), fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=8)
    axes.flat[0].set_ylabel({"psnr_masked": "masked PSNR, dB"}.get(metric, metric))
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=max(1, len(labels)), fontsize=8, bbox_to_anchor=(0.5, 0.0))
    return _save(fig, path, rect=(0, 0.5 / (3.0 * nrows), 1, 1))


def draw_budget_chart(rows: list[dict], path: str | os.PathLike) -> Path:
    """Quality and cost against the number of Gaussians (log x): left, masked PSNR on the novel
    views (solid) and the input views (dashed), one colour per (method, UV resolution), the counts
    lift --gaussians auto picks circled; right, render time per image (solid) and USD size
    (dashed, right axis)."""
    from dlacli.bench.budget import choices, curve

    plt = _pyplot()
    nv, inp = curve(rows, "novel_views"), curve(rows, "inputs")
    keys = sorted(set(nv) | set(inp))
    if not keys:
        raise DlaInputError("chart", "no budget rows")
    picks = choices(rows)
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    size_ax = right.twinx()
    for i, key in enumerate(keys):
        colour, label = f"C{i}", f"{key[0]} UV {key[1]}"
        for data, style, what in ((nv, "-", "novel views"), (inp, "--", "inputs")):
            if key in data:
                ns = sorted(data[key])
                left.plot(ns, [data[key][n]["value"] for n in ns], style, marker="o", ms=3, color=colour, label=f"{label}, {what}")
        pick = picks.get(key, {}).get("inputs")
        if pick is not None and key in nv and pick in nv[key]:
            left.scatter([pick], [nv[key][pick]["value"]], s=120, facecolors="none", edgecolors=colour, zorder=4)
        data = nv.get(key) or inp[key]
        ns = sorted(data)
        right.plot(ns, [data[n]["render_ms"] for n in ns], "-", marker="o", ms=3, color=colour, label=f"{label}: render ms")
        usd = [(n, data[n]["usd_mib"]) for n in ns if data[n]["usd_mib"] is not None]
        if usd:
            size_ax.plot(*zip(*usd), "--", marker="s", ms=3, color=colour, label=f"{label}: USD MiB")
    for ax in (left, right):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("Gaussians (log)")
        ax.grid(True, which="both", alpha=0.3)
    right.set_yscale("log")
    size_ax.set_yscale("log")
    left.set_ylabel("masked PSNR, dB")
    right.set_ylabel("render time per image, ms (solid)")
    size_ax.set_ylabel("USD size, MiB (dashed)")
    size = sorted({r["render_size"] for r in rows if kind(r) == "budget"})
    left.set_title(f"quality at {', '.join(map(str, size))} px (circle: lift --gaussians auto)")
    right.set_title("cost")
    left.legend(fontsize=7, loc="lower right")
    h1, l1 = right.get_legend_handles_labels()
    h2, l2 = size_ax.get_legend_handles_labels()
    right.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper left")
    return _save(fig, path)


# ------------------------------------------------------------------------------ sections


def stability_markdown(rows: list[dict], chart_name: str | None = None, metric: str = "psnr_masked",
                       intro: bool = True) -> list[str]:  # fmt: skip
    """The stability section: per perturbation, masked PSNR per level and method (novel views;
    novel poses in brackets), the first level at which it has dropped by DROP_DB, and every run
    that produced NaN, an exception or an empty avatar."""
    from dlacli.bench.stability import DROP_DB, PERTURBATIONS, curves, drop_level

    nv, npose = curves(rows, "novel_views", metric), curves(rows, "novel_poses", metric)
    lines = ["## Stability", "",
             f"`dla bench stability`: each method lifts perturbed inputs of synthetic subjects; cells are masked PSNR on",
             "the novel views [novel poses], means over subjects (the first level is the clean input). \"drop at\" is",
             f"the first level at which novel-view masked PSNR has fallen by {DROP_DB:g} dB or more (or every subject failed).", ""]  # fmt: skip
    lines = lines if intro else []
    if chart_name:
        lines += [f"![stability curves]({chart_name})", ""]
    for name in nv:
        unit = PERTURBATIONS[name].unit if name in PERTURBATIONS else ""
        levels = list(dict.fromkeys(lv for c in nv[name].values() for lv, *_ in c))
        lines += [f"### {name.replace('_', ' ')} ({unit})", "",
                  "| method | " + " | ".join(_level_text(lv) for lv in levels) + f" | drop {DROP_DB:g} dB at | failed runs |",
                  "|---|" + "---|" * (len(levels) + 2)]  # fmt: skip
        for m, c in sorted(nv[name].items()):
            by = {lv: v for lv, v, *_ in c}
            pose = {lv: v for lv, v, *_ in npose.get(name, {}).get(m, [])}
            cells = [(f"{by[lv]:.2f}" if lv in by and by[lv] == by[lv] else "-")
                     + (f" [{pose[lv]:.2f}]" if lv in pose and pose[lv] == pose[lv] else "") for lv in levels]  # fmt: skip
            drop = drop_level(c)
            fails = sum(f for *_, f in c)
            lines.append(f"| {m} | " + " | ".join(cells) + f" | {'none' if drop is None else _level_text(drop)} | {fails} |")
        lines.append("")
    bad = {}
    for r in rows:
        if kind(r) == "stability" and r["status"] != "ok":
            bad[(r["method"], r["perturbation"], r["level"], r["subject"])] = r
    lines += ["### Failures", ""]
    if not bad:
        lines += ["No run produced NaN, an exception or an empty avatar.", ""]
    else:
        lines += ["| method | perturbation | level | subject | status | error |", "|---|---|---|---|---|---|"]
        for (m, p, lv, subj), r in sorted(bad.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2], str(kv[0][3]))):
            lines.append(f"| {m} | {p} | {_level_text(lv)} | {subj} | {r['status']} | {(r['error'] or '').replace('|', '/')} |")
        lines.append("")
    return lines


def budget_markdown(rows: list[dict], chart_name: str | None = None, intro: bool = True) -> list[str]:
    """The Gaussian-budget section: per (method, UV resolution) quality and cost per count, the
    count each `--gaussians auto` rule picks, and what the pick saves against 131,072."""
    from dlacli.bench.budget import DEFAULT_COUNT, choices, curve
    from dlacli.stages.budget import TOLERANCE_DB

    split_curves = {s: curve(rows, s) for s in ("inputs", "novel_views", "novel_poses")}
    sizes = sorted({r["render_size"] for r in rows if kind(r) == "budget"})
    lines = ["## The Gaussian budget", "",
             f"`dla bench budget` at {', '.join(map(str, sizes))} px: masked PSNR (means over subjects) of an avatar drawn with",
             "n Gaussians on its input views, novel views and novel poses; render time per image and the size of a",
             "short walk as USD (animate's defaults) are medians; s(n) is the sampling noise that `--gaussians auto`",
             "sees without a lift-time budget (dlacli.stages.budget). Each rule picks the smallest count within",
             f"{TOLERANCE_DB:g} dB of its best: \"novel views\" and \"novel poses\" are the oracle (ground truth the method",
             "never saw), \"inputs\" is `dla lift --gaussians auto`, \"self-consistency\" what `dla render` / `dla animate",
             "--gaussians auto` pick for an avatar that records no budget.", ""]  # fmt: skip
    lines = lines if intro else []
    if chart_name:
        lines += [f"![the Gaussian budget]({chart_name})", ""]
    keys = sorted(set().union(*[set(c) for c in split_curves.values()]))
    for key in keys:
        counts = sorted(set().union(*[set(c.get(key, {})) for c in split_curves.values()]))
        lines += [f"### {key[0]}, UV resolution {key[1]}", "",
                  "| Gaussians | inputs | novel views | novel poses | render ms / image | USD MiB | s(n) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
        for n in counts:
            cells = [f"{split_curves[s][key][n]['value']:.2f}" if n in split_curves[s].get(key, {}) else "-"
                     for s in ("inputs", "novel_views", "novel_poses")]  # fmt: skip
            p = next(split_curves[s][key][n] for s in ("novel_views", "inputs", "novel_poses") if n in split_curves[s].get(key, {}))
            usd = "-" if p["usd_mib"] is None else f"{p['usd_mib']:.2f}"
            noise = "-" if p["noise"] is None else f"{p['noise']:.2e}"
            lines.append(f"| {n:,} | " + " | ".join(cells) + f" | {p['render_ms']:.1f} | {usd} | {noise} |")
        lines.append("")
    picks = choices(rows)
    if picks:
        rules = ("novel views", "novel poses", "inputs", "self-consistency")
        lines += [f"### What `--gaussians auto` picks, and what it saves against {DEFAULT_COUNT:,}", "",
                  "| method, UV | " + " | ".join(rules) + " | pick's novel-view loss vs best, dB | render time saved | USD size saved |",
                  "|---|" + "---|" * (len(rules) + 3)]  # fmt: skip
        for key, got in sorted(picks.items()):
            ref_curve = split_curves["novel_views"].get(key) or split_curves["inputs"][key]
            pick = got.get("inputs")
            base = ref_curve.get(DEFAULT_COUNT) or ref_curve[max(ref_curve)]
            loss, t_saved, s_saved = "-", "-", "-"
            if pick in ref_curve:
                best = max(p["value"] for p in ref_curve.values())
                loss = f"{best - ref_curve[pick]['value']:.2f}"
                t_saved = f"{1 - ref_curve[pick]['render_ms'] / base['render_ms']:.0%}"
                if base["usd_mib"] and ref_curve[pick]["usd_mib"] is not None:
                    s_saved = f"{1 - ref_curve[pick]['usd_mib'] / base['usd_mib']:.0%}"
            cells = [f"{got[r]:,}" if r in got else "-" for r in rules]
            lines.append(f"| {key[0]}, {key[1]} | " + " | ".join(cells) + f" | {loss} | {t_saved} | {s_saved} |")
        has_default = all(DEFAULT_COUNT in (split_curves["novel_views"].get(k) or split_curves["inputs"][k]) for k in picks)
        against = f"{DEFAULT_COUNT:,} Gaussians" if has_default else "the largest count"
        lines += ["", f"Savings and loss are for the \"inputs\" pick (what lift records), against {against}.", ""]
    return lines


def speed_markdown(rows: list[dict], intro: bool = True) -> list[str]:
    """The speed section: the latest run of each suite, medians per case with the same-run ratios
    (splat: how many times faster than the pure-torch renderer, and current / baseline)."""
    from dlacli.bench.speed import SUITES, ratios

    speed = [r for r in rows if kind(r) == "speed"]
    lines = ["## Speed", "",
             "`dla bench speed`: medians per call after a warm-up (repeats = 1: one timed run); the latest run of each",
             "suite. Ratios pair rows of the same run.", ""]  # fmt: skip
    lines = lines if intro else []
    ratio_torch = {(q["run"], q["case"], json.dumps(q["config"], sort_keys=True), q["method"]): q["ratio"]
                   for q in ratios(speed, "torch")}  # fmt: skip
    ratio_base = {(q["run"], q["case"], json.dumps(q["config"], sort_keys=True)): q["ratio"]
                  for q in ratios(speed, "numba_baseline") if q["method"] == "numba"}  # fmt: skip
    for suite in [s for s in SUITES if any(r["suite"] == s for r in speed)] + sorted({r["suite"] for r in speed} - set(SUITES)):
        sel = [r for r in speed if r["suite"] == suite]
        latest = max(r["run"] for r in sel)
        sel = [r for r in sel if r["run"] == latest]
        lines += [f"### {suite}", "", f"Run {latest} on {', '.join(sorted({r['device'] for r in sel}))}.", "",
                  "| case | setting | method | median ms | min ms | more |", "|---|---|---|---|---|---|"]  # fmt: skip
        for r in sel:
            cfg = {k: v for k, v in r["config"].items() if k != "round"}
            setting = " ".join(f"{k}={v}" for k, v in sorted(cfg.items()))
            if r["seconds"] is None:
                lines.append(f"| {r['case']} | {setting} | {r['method']} | - | - | skipped: {r.get('skipped', '')} |")
                continue
            more = []
            key = json.dumps(cfg, sort_keys=True)
            if (r["run"], r["case"], key, r["method"]) in ratio_torch:
                more.append(f"{ratio_torch[(r['run'], r['case'], key, r['method'])]:.3g}x torch")
            if r["method"] == "numba" and (r["run"], r["case"], key) in ratio_base:
                more.append(f"baseline / current {ratio_base[(r['run'], r['case'], key)]:.3f}")
            for name, fmt in (("first_seconds", "first call {:.0f} ms"), ("peak_mb", "peak {:.0f} MB"), ("size_mib", "{:.1f} MiB")):
                if r.get(name) is not None:
                    more.append(fmt.format(r[name] * (1e3 if name == "first_seconds" else 1)))
            if suite == "usd" and r.get("items"):
                more.append(f"{r['items'] / r['seconds'] / 1e6:.1f} M Gaussian-frames/s")
            if suite == "render" and r["case"] == "animation_frame":
                more.append(f"{1 / r['seconds']:.1f} fps")
            if "torch_loaded" in r:
                more.append("loads torch" if r["torch_loaded"] else "no torch")
            lo = "-" if r.get("min_seconds") is None else f"{r['min_seconds'] * 1e3:.1f}"
            lines.append(f"| {r['case']} | {setting} | {r['method']} | {r['seconds'] * 1e3:.1f} | {lo} | {', '.join(more)} |")
        lines.append("")
    return lines
