"""The `dla` typer application: one module per command, registered here."""

from __future__ import annotations

import re
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
    from dlacli.cli import (
        animate,
        bench,
        body,
        dream,
        edit,
        export,
        info,
        interp,
        lift,
        motion,
        render,
        synth,
        train,
        view,
    )

    for module in (dream, lift, animate, render, view, export, edit, interp, synth, train, motion, body, info, bench):
        module.register(app)


_register()


class _Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwind (so atomic writers remove their temporaries), then exit."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum, frame) -> None:
    import signal

    for sig in (signal.SIGTERM, signal.SIGHUP):  # a second signal must not interrupt the cleanup
        signal.signal(sig, signal.SIG_IGN)
    raise _Terminated(signum)


def _usage_line(err) -> str:
    """A click usage error (missing or bad option, unknown command) as `<option>: <problem>`."""
    message = " ".join(err.format_message().split())
    param = getattr(err, "param", None)
    where = None
    if param is not None:
        opts = getattr(param, "opts", None) or []
        if getattr(param, "param_type_name", "") == "option" and opts:
            where = max(opts, key=len)
        else:
            where = getattr(param, "metavar", None) or (param.name or "argument").upper()
        prefix = r"^(Invalid value|Missing (parameter|option|argument))( for)? ?'?[^':]*'?: ?"
        message = re.sub(prefix, "", message) or message
    elif getattr(err, "option_name", None):
        where = err.option_name
    ctx = getattr(err, "ctx", None)
    command = ctx.command_path if ctx is not None else "dla"
    hint = f" (see {command} --help)"
    return f"{where or command}: {message}{hint}"


def main(argv: list[str] | None = None) -> None:
    """Console entry point: bad input and usage errors are one line on stderr and exit code 2;
    SIGTERM/SIGHUP/Ctrl-C leave no temporary files; an unexpected failure is one line too
    (DLA_DEBUG=1 shows the traceback)."""
    import os
    import signal
    import warnings

    if not os.environ.get("DLA_DEBUG"):  # numpy's overflow/invalid-value warnings are not messages for users
        warnings.simplefilter("ignore", RuntimeWarning)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _on_signal)
    try:
        code = app(args=argv, standalone_mode=False)
    except DlaInputError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
    except _Terminated as err:
        print(f"error: terminated by signal {err.signum}", file=sys.stderr)
        sys.exit(128 + err.signum)
    except Exception as err:
        if hasattr(err, "format_message") and hasattr(err, "exit_code"):  # click's usage errors
            if type(err).__name__ == "Abort":
                print("error: aborted", file=sys.stderr)
                sys.exit(1)
            print(f"error: {_usage_line(err)}", file=sys.stderr)
            sys.exit(err.exit_code if isinstance(err.exit_code, int) and err.exit_code else 2)
        if isinstance(err, OSError) and err.errno is not None:
            where = err.filename or "dla"
            print(f"error: {where}: {err.strerror or err}", file=sys.stderr)
            sys.exit(2)
        if os.environ.get("DLA_DEBUG"):
            raise
        print(
            f"error: internal error ({type(err).__name__}: {' '.join(str(err).split())[:200]}); "
            "please report it (DLA_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        sys.exit(1)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
