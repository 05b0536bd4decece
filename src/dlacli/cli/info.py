"""`dla info PATH`: summarise any artifact."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def _format_value(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)) and len(value) > 8:
        head = ", ".join(_format_value(v) for v in value[:8])
        return f"[{head}, ... ({len(value)} items)]"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_format_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_format_value(v)}" for k, v in value.items()) + "}"
    return str(value)


def info(
    path: Path = typer.Argument(
        ...,
        help=(
            "A view folder, body.json, motion/avatar .npz, .ply/.spz/.splat, .usd/.usda/.usdc, or a "
            "BVH/ASF/AMC/AMASS motion."
        ),
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    """Summarise an artifact: what it is, its format version, sizes and ranges."""
    from dlacli.io.inspect import summarize

    summary = summarize(path)
    if as_json:
        typer.echo(json.dumps(summary, indent=None, sort_keys=False))
        return
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        typer.echo(f"{key:<{width}}  {_format_value(value)}")


def register(app: typer.Typer) -> None:
    app.command("info")(info)
