"""`dla bench`: accuracy and speed suites (results on stdout; JSON with --json)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

bench_app = typer.Typer(
    help="Benchmarks: accuracy against cost on synthetic subjects.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _ints(text: str, name: str, hi: int) -> list[int]:
    from dlacli.errors import DlaInputError

    if len(text) > 10_000:
        raise DlaInputError(name, "is too long")
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise DlaInputError(name, f"expected comma-separated integers, got {text[:40]!r}") from None
    if not values:
        raise DlaInputError(name, "is empty")
    if len(values) > 64 or not all(0 <= v <= hi for v in values):
        raise DlaInputError(name, f"expected at most 64 integers in [0, {hi}]")
    return values


@bench_app.command("pipeline")
def pipeline(
    seeds: str = typer.Option("1001,1002", "--seeds", help="Synthetic subjects (use seeds no test uses)."),
    steps: str = typer.Option("0,50,150", "--steps", help="Refinement steps to compare."),
    res: int = typer.Option(512, "--res", min=32, max=4096, help="Image size of the subjects."),
    as_json: bool = typer.Option(False, "--json", help="Print the full result as one JSON object."),
    jsonl: Optional[Path] = typer.Option(None, "--jsonl", help="Also append the runs as dla.bench/1 JSON lines to this file (`dla bench report` reads it)."),
) -> None:
    """synth -> lift -> render: PSNR (whole image and inside the mask), SSIM and alpha IoU on 12
    novel views and 8 novel poses per subject, lift time per steps setting, animate time."""
    import sys

    from dlacli.bench.pipeline import markdown_table, result_rows, run
    from dlacli.errors import DlaInputError

    if jsonl is not None and (jsonl.suffix.lower() != ".jsonl" or jsonl.is_dir()):
        raise DlaInputError(jsonl, "the results file is a .jsonl file")

    result = run(_ints(seeds, "--seeds", 2**32 - 1), _ints(steps, "--steps", 100_000), res=res,
                 log=lambda line: print(line, file=sys.stderr))  # fmt: skip
    if jsonl is not None:
        from dlacli.bench.results import append_rows

        append_rows(jsonl, result_rows(result))
    if as_json:
        typer.echo(json.dumps(result))
    else:
        typer.echo(markdown_table(result))
        typer.echo(f"animate {result['animate_frames']} frames (pose + USD): {result['animate_s_median']:.1f} s median")


@bench_app.command("regions")
def regions(
    seed: int = typer.Option(1001, "--seed", min=0, max=2**32 - 1, help="Synthetic subject (use a seed no test uses)."),
    steps: int = typer.Option(50, "--steps", min=0, max=100_000, help="Lift refinement steps."),
    res: int = typer.Option(512, "--res", min=32, max=4096, help="Image size of the subject."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="Error picture (.png): ground truth | render | error x4 | regions, an input view above a novel view."),
) -> None:
    """Where the error lives: synth -> lift, then masked PSNR per body region (face, hair, hands,
    arms, torso, legs, feet, off body, silhouette band) on the input views and the novel views."""
    import tempfile

    import numpy as np
    from PIL import Image

    from dlacli.bench.pipeline import render_split
    from dlacli.bench.regions import REGIONS, error_picture, pixel_regions, region_psnr
    from dlacli.body.model import get_body_model
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_path, check_outputs
    from dlacli.io.views import read_views
    from dlacli.stages.lift import LiftConfig, lift
    from dlacli.stages.synth import synth

    if output is not None and output.suffix.lower() != ".png":
        raise DlaInputError(output, "the error picture is a .png file")
    check_outputs(files=[output])
    rows, pictures = [], []
    with tempfile.TemporaryDirectory() as tmp:
        folder = synth(seed, Path(tmp) / "subject", res=res, novel_views=4, novel_poses=0)
        views = read_views(folder)
        avatar = lift(views, LiftConfig(steps=steps)).avatar
        verts = get_body_model().forward_body(views.body).vertices[0].numpy()
        for split, vs in (("input views", views), ("novel views", read_views(folder / "novel_views", require_body=False))):
            rgba, gt = render_split(avatar, vs)
            pred = rgba[..., :3]
            labels = pixel_regions(verts, vs.cameras, vs.masks)
            rows.append((split, region_psnr(pred, gt, labels)))
            pictures.append(error_picture(gt[0], pred[0], labels[0]))
    typer.echo("| region | " + " | ".join(f"{split}: masked PSNR / pixels / error share" for split, _ in rows) + " |")
    typer.echo("|---|" + "---|" * len(rows))
    for name in REGIONS:
        cells = [f"{r[name]['psnr']:.2f} / {r[name]['pixels']:.0%} / {r[name]['error']:.0%}" if name in r else "-" for _, r in rows]
        typer.echo(f"| {name} | " + " | ".join(cells) + " |")
    if output is not None:
        with atomic_path(output) as tmp:
            Image.fromarray(np.concatenate(pictures, axis=0)).save(tmp)


@bench_app.command("report")
def report(
    results: Path = typer.Argument(..., metavar="RESULTS", help="dla.bench/1 JSON lines (`dla bench pipeline --jsonl`)."),
    output: Path = typer.Option(Path("docs/benchmarks.md"), "--output", "-o", help="The markdown page; its chart is written beside it as <name>.png."),
) -> None:
    """Regenerate the benchmark page (tables per split, the Pareto frontier, the time-vs-accuracy
    chart) from result rows, so the page never drifts from the numbers."""
    from dlacli.bench.results import draw_chart, read_rows, report_markdown
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import atomic_path, check_outputs, output_group

    if output.suffix.lower() != ".md":
        raise DlaInputError(output, "the page is a .md file")
    chart = output.with_suffix(".png")
    check_outputs(files=[output, chart], inputs=[results])
    rows = read_rows(results)
    if not rows:
        raise DlaInputError(results, "holds no result rows")
    with output_group():
        draw_chart(rows, chart)
        with atomic_path(output) as tmp:
            tmp.write_text(report_markdown(rows, chart.name) + "\n", encoding="utf-8")
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")
