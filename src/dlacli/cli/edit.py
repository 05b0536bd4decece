"""`dla edit swap`: replace a body region of one avatar with another's."""

from __future__ import annotations

from pathlib import Path

import typer

from dlacli.cli import options

edit_app = typer.Typer(
    help="Edit avatars in their UV-aligned latent space.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)


@edit_app.command("swap")
def swap(
    a: Path = options.avatar("The avatar to edit (avatar.npz).", metavar="A"),
    b: Path = options.avatar("The avatar that gives the region (avatar.npz).", metavar="B"),
    region: str = typer.Option(
        ..., "--region", "-r", help="Region name, e.g. face, hair, hands, upper_body (see `dla body regions`)."
    ),
    output: Path = options.output("Where to write the edited avatar.npz.", (".npz",), "avatar"),
    feather: float = typer.Option(
        0.0,
        "--feather",
        min=0.0,
        max=1024.0,
        callback=options.finite,
        help="Blend over this many UV texels (at Z's resolution) outside the region.",
    ),
) -> None:
    """Replace REGION of avatar A with avatar B's; everything else stays A's (body included)."""
    from dlacli.body.regions import REGION_NAMES
    from dlacli.errors import DlaInputError
    from dlacli.io.atomic import check_outputs
    from dlacli.io.avatar import read_avatar, write_avatar
    from dlacli.stages.edit import swap_region

    if region not in REGION_NAMES:
        raise DlaInputError("--region", f"unknown region {region!r} (known: {', '.join(REGION_NAMES)})")
    check_outputs(files=[output], inputs=[a, b])
    avatar = swap_region(read_avatar(a), read_avatar(b), region, feather, where_a=str(a), where_b=str(b))
    write_avatar(avatar, output)
    typer.echo(str(output))


def register(app: typer.Typer) -> None:
    app.add_typer(edit_app, name="edit")
