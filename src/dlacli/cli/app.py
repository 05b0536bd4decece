"""The `dla` typer application: one module per command, registered here."""

from __future__ import annotations

import sys

import typer

from dlacli import __version__
from dlacli.errors import DlaInputError

app = typer.Typer(
    name="dla",
    help="Dream, Lift, Animate: one photo of a person to an animatable 3D Gaussian avatar.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"dla {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Dream, Lift, Animate: one photo of a person to an animatable 3D Gaussian avatar."""


def _register() -> None:
    """Commands in the order a user meets them: the stages, then tools."""
    from dlacli.cli import animate, bench, body, dream, edit, info, interp, lift, motion, render, synth

    for module in (dream, lift, animate, render, edit, interp, synth, motion, body, info, bench):
        module.register(app)


_register()


def main() -> None:
    """Console entry point: bad input is one line on stderr and exit code 2."""
    try:
        app()
    except DlaInputError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
