"""The `dsr-bench` command line: a typer app assembled from `dsr_bench.commands`."""

from __future__ import annotations

import importlib
import sys

import typer

from dsr_bench.errors import UserError, one_line

app = typer.Typer(
    name="dsr-bench",
    help="Dataset and benchmark toolkit for 3D dynamic scene representations (DSR, CoRL 2020).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

#: Command modules under dsr_bench.commands, each with a `register(app)` function.
_COMMAND_MODULES: tuple[str, ...] = ("generate", "data", "evaluate", "view", "train", "capture", "annotate")

for _name in _COMMAND_MODULES:
    importlib.import_module(f"dsr_bench.commands.{_name}").register(app)


def _print_version(value: bool) -> None:
    if value:
        from dsr_bench import __version__

        typer.echo(__version__)
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", help="Print the toolkit version and exit.", is_eager=True,
                                 callback=_print_version),
) -> None:
    """Dataset and benchmark toolkit for 3D dynamic scene representations (DSR, CoRL 2020)."""


def main(argv: list[str] | None = None) -> int:
    """Console entry point: user errors become one line on stderr and exit code 2."""
    try:
        rc = app(args=argv, standalone_mode=False)  # returns the code of typer.Exit when not standalone
    except UserError as exc:
        typer.echo(f"error: {one_line(exc)}", err=True)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        typer.echo("aborted", err=True)
        return 130
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        return 130
    except Exception as exc:  # click's usage errors (typer may vendor click) carry their own exit codes
        if hasattr(exc, "show") and isinstance(getattr(exc, "exit_code", None), int):
            exc.show()
            return exc.exit_code
        raise
    return rc if isinstance(rc, int) else 0


if __name__ == "__main__":
    sys.exit(main())
