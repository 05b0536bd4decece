"""The benchmark charts (PNG, matplotlib: extra `bench`): time against accuracy with its Pareto
frontier, the stability suite's degradation curves and the Gaussian budget's quality and cost.
Each is drawn from result rows (bench/rows.py) alone."""

from __future__ import annotations

import math
import os
from pathlib import Path

from dlacli.bench.rows import kind, level_text, pareto_front, points
from dlacli.errors import DlaInputError


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


def draw_chart(
    rows: list[dict],
    path: str | os.PathLike,
    metric: str = "psnr_masked",
    splits: tuple[str, ...] = ("novel_views", "novel_poses", "novel_view_pose", "dreamed_views"),
) -> Path:
    """Time (log) against `metric`, one panel per split present, one marker per point, the Pareto
    frontier as a line with its points' settings beside them (the tables name every point);
    written to a PNG (matplotlib, extra `bench`)."""
    plt = _pyplot()
    import matplotlib.ticker

    rows = [r for r in rows if kind(r) == "accuracy"]
    present = [s for s in splits if any(r["split"] == s for r in rows)]
    if not present:
        raise DlaInputError("chart", f"no rows for the splits {', '.join(splits)}")
    fig, axes = plt.subplots(1, len(present), figsize=(6 * len(present), 4.5), squeeze=False)
    # one marker and colour per group (the method, or "photo/BACKEND METHOD") in every panel
    groups = sorted({p["group"] for s in present for p in points(rows, s, metric)})
    style = {g: (marker, f"C{k % 10}") for k, (g, marker) in enumerate(zip(groups, "osD^v<>ph*"))}
    for ax, split in zip(axes[0], present):
        pts = points(rows, split, metric)
        front = pareto_front(pts)
        named = {id(p) for p in front}  # the frontier's points carry their settings; the tables name the rest
        for m in sorted({p["group"] for p in pts} & set(style)):
            marker, colour = style[m]
            sel = [p for p in pts if p["group"] == m]
            ax.scatter(
                [p["seconds"] for p in sel],
                [p["value"] for p in sel],
                marker=marker,
                color=colour,
                s=40,
                label=m,
                zorder=3,
            )
            words = [p["label"][len(m) :].split() for p in sel]
            shared = set.intersection(*map(set, words)) if len(sel) > 1 else set()  # said once, in the legend's sense
            for k, (p, w) in enumerate(zip(sel, words)):
                if id(p) not in named:
                    continue
                ax.annotate(
                    " ".join(x.strip("(),") for x in w if x not in shared),
                    (p["seconds"], p["value"]),
                    fontsize=7,
                    xytext=(4, 3 - 9 * (k % 3)),
                    textcoords="offset points",
                )
        ax.step(
            [p["seconds"] for p in front],
            [p["value"] for p in front],
            where="post",
            color="0.3",
            linewidth=1,
            zorder=2,
            label="Pareto frontier",
        )
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(
            matplotlib.ticker.FuncFormatter(  # label 2 and 5 of each decade
                lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v))) in (2, 5) else ""
            )
        )
        photo = any(p["group"].startswith("photo/") for p in pts)
        ax.set_xlabel("lift time per subject, s (log)" + ("; photo/*: dream + lift" if photo else ""))
        ax.set_ylabel({"psnr_masked": "PSNR inside the mask, dB", "psnr": "PSNR, dB"}.get(metric, metric))
        ax.set_title(split.replace("_", " "))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    return _save(fig, path)


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
    for ax in axes.flat[len(names) :]:
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
                ax.plot(
                    xs,
                    [v for _, v, *_ in curve],
                    style,
                    marker="o",
                    ms=3,
                    color=colours[m],
                    label=f"{m}, {split.replace('_', ' ')}",
                )
                bad |= {x_of[lv] for lv, _, _, fails in curve if fails}
                if split == "novel_views" and curve and curve[0][1] == curve[0][1]:  # its baseline - DROP_DB
                    ax.axhline(curve[0][1] - DROP_DB, color=colours[m], linestyle=":", linewidth=0.8)
        if bad:
            ax.scatter(sorted(bad), [ax.get_ylim()[0]] * len(bad), marker="x", color="red", zorder=4, clip_on=False)
        ax.set_xticks(range(len(levels)), [level_text(lv) for lv in levels])
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
                left.plot(
                    ns,
                    [data[key][n]["value"] for n in ns],
                    style,
                    marker="o",
                    ms=3,
                    color=colour,
                    label=f"{label}, {what}",
                )
        pick = picks.get(key, {}).get("inputs")
        if pick is not None and key in nv and pick in nv[key]:
            left.scatter([pick], [nv[key][pick]["value"]], s=120, facecolors="none", edgecolors=colour, zorder=4)
        data = nv.get(key) or inp[key]
        ns = sorted(data)
        right.plot(
            ns, [data[n]["render_ms"] for n in ns], "-", marker="o", ms=3, color=colour, label=f"{label}: render ms"
        )
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


def composite_heatmap(stats, path: str | os.PathLike, title: str) -> Path:
    """Where a frame's compositing time goes (dlacli.render.splat_stats.CompositeStats, camera 0),
    four panels: the Gaussians each 16 x 16 tile lists and the exact kernel's pixel evaluations
    per pixel of each tile (what the time follows), the Gaussians covering each pixel and those it
    composited before its transmittance ran out (what the image needs)."""
    import numpy as np

    from dlacli.render.splat import TILE

    plt = _pyplot()
    h, w = stats.covering.shape[1:]
    tiles = np.ones((TILE, TILE))
    per_tile = [np.kron(a[0], tiles)[:h, :w] for a in (stats.listed, stats.evaluations / (TILE * TILE))]
    s = stats.summary()
    panels = (
        ("Gaussians listed per tile", per_tile[0], f"mean {s.get('listed_per_tile', 0):.0f} over listed tiles"),
        (
            "kernel evaluations per pixel (tile mean)",
            per_tile[1],
            f"mean {s.get('evaluations_per_pixel', 0):.1f} over listed tiles",
        ),
        (
            "Gaussians covering each pixel",
            stats.covering[0],
            f"mean {s.get('covering_per_pixel', 0):.1f} where covered",
        ),
        (
            "Gaussians composited per pixel",
            stats.contributing[0],
            f"mean {s.get('contributing_per_pixel', 0):.1f} where covered",
        ),
    )
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.6))
    for ax, (name, img, mean) in zip(axes, panels, strict=True):
        shown = ax.imshow(img, cmap="magma", interpolation="nearest")
        ax.set_title(f"{name}\n{mean}, max {img.max():.0f}", fontsize=9)
        ax.axis("off")
        fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
    fig.suptitle(title, fontsize=11)
    return _save(fig, path, rect=(0, 0, 1, 0.95))
