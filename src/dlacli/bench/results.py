"""Benchmark results as JSON lines, the Pareto frontier of time against accuracy, and its chart.

One line per run of one method and setting on one subject and split (`dla.bench/1`):

    {"format": "dla.bench/1", "method": "unproject+refine", "config": {"steps": 50},
     "device": "cpu (2 threads)", "subject": 7003, "split": "novel_views",
     "seconds": 43.9, "peak_mb": 1482.8,
     "metrics": {"psnr": 28.75, "psnr_masked": 20.36, "ssim": 0.955, "iou": 0.944}}

`seconds` and `peak_mb` are the cost of making the avatar (lift); the metrics score its renders on
the split's ground truth. A "point" is one (method, config) on one split, its metrics and cost
aggregated over subjects (median seconds, mean metrics): what one marker on the chart shows.
"""

from __future__ import annotations

import json
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


def check_row(row: Any, where: str = "row") -> dict:
    """A result row, validated: every field present with its type, a known split, finite
    non-negative cost, every metric in METRICS a finite number (LPIPS optional)."""
    import math

    if not isinstance(row, dict):
        raise DlaInputError(where, "a result row is a JSON object")
    if row.get("format") != FORMAT:
        raise DlaInputError(where, f"format {row.get('format')!r} is not {FORMAT!r}")
    for name, kind in _FIELDS.items():
        if name not in row or not isinstance(row[name], kind) or isinstance(row[name], bool):
            raise DlaInputError(where, f"field {name!r} is missing or not a {getattr(kind, '__name__', 'number')}")
    if row["split"] not in SPLITS:
        raise DlaInputError(where, f"unknown split {row['split']!r} (one of {', '.join(SPLITS)})")
    for name in ("seconds", "peak_mb"):
        v = row[name]
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise DlaInputError(where, f"{name} = {v!r} is not a finite number >= 0")
    for name in METRICS:
        v = row["metrics"].get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DlaInputError(where, f"metric {name!r} is missing or not a finite number")
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


def label(row: dict) -> str:
    """A method and its setting, for tables and legends: "unproject+refine steps=50"."""
    cfg = " ".join(f"{k}={v}" for k, v in sorted(row["config"].items()))
    return f"{row['method']} {cfg}".strip()


def points(rows: list[dict], split: str, metric: str = "psnr_masked") -> list[dict]:
    """One point per (method, config) on `split`: median seconds, mean metric, subject count."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        if row["split"] == split:
            groups.setdefault(label(row), []).append(row)
    return [{"label": name, "method": rs[0]["method"], "seconds": statistics.median(r["seconds"] for r in rs),
             "value": statistics.fmean(r["metrics"][metric] for r in rs), "subjects": len(rs)}
            for name, rs in sorted(groups.items())]  # fmt: skip


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
               splits: tuple[str, ...] = ("novel_views", "novel_poses")) -> Path:  # fmt: skip
    """Time (log) against `metric`, one panel per split present, one marker per point, the Pareto
    frontier as a line; written to a PNG (matplotlib, extra `bench`)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise DlaInputError("chart", "drawing the chart needs matplotlib (pip install 'dla[bench]')") from None
    from dlacli.io.atomic import atomic_path

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
            for p in sel:
                ax.annotate(p["label"][len(m):].strip(), (p["seconds"], p["value"]), fontsize=7,
                            xytext=(4, 3), textcoords="offset points")  # fmt: skip
        front = pareto_front(pts)
        ax.step([p["seconds"] for p in front], [p["value"] for p in front], where="post", color="0.3",
                linewidth=1, zorder=2, label="Pareto frontier")  # fmt: skip
        ax.set_xscale("log")
        ax.set_xlabel("lift time per subject, s (log)")
        ax.set_ylabel({"psnr_masked": "PSNR inside the mask, dB", "psnr": "PSNR, dB"}.get(metric, metric))
        ax.set_title(split.replace("_", " "))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def report_markdown(rows: list[dict], chart_name: str | None, metric: str = "psnr_masked") -> str:
    """The benchmark page: per split a table of every point (frontier points in bold) and the
    chart, all computed from `rows`, so the page never drifts from the numbers."""
    lines = ["# Benchmarks", "",
             "Generated by `dla bench report` from the JSON lines of `dla bench pipeline --jsonl`;",
             "do not edit by hand. Time is the median lift wall time per subject; metrics are means",
             "over subjects (PSNR inside the mask, alpha IoU at 0.5; renders on black).", ""]  # fmt: skip
    if chart_name:
        lines += [f"![time against masked PSNR]({chart_name})", ""]
    devices = sorted({r["device"] for r in rows})
    lines += [f"Devices: {', '.join(devices)}.", ""]
    for split in SPLITS:
        sel = [r for r in rows if r["split"] == split]
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
    return "\n".join(lines)
