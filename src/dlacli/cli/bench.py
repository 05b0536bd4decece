"""`dla bench`: accuracy and speed suites (results on stdout; JSON with --json)."""

from __future__ import annotations

import json

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
) -> None:
    """synth -> lift -> render: PSNR (whole image and inside the mask), SSIM and alpha IoU on 12
    novel views and 8 novel poses per subject, lift time per steps setting, animate time."""
    import sys

    from dlacli.bench.pipeline import markdown_table, run

    result = run(_ints(seeds, "--seeds", 2**32 - 1), _ints(steps, "--steps", 100_000), res=res,
                 log=lambda line: print(line, file=sys.stderr))  # fmt: skip
    if as_json:
        typer.echo(json.dumps(result))
    else:
        typer.echo(markdown_table(result))
        typer.echo(f"animate {result['animate_frames']} frames (pose + USD): {result['animate_s_median']:.1f} s median")


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")
