"""The `dsr-bench` command line: a typer app assembled from the library's command modules
(`dsr_bench.cli.data`, `.scoring`, `.view`, `.train`) and the commands that the packages above the
library register through the `dsr_bench.commands` entry point (`generators.cli`: generate,
generate-captures, generate-plan-tasks, plan; `annotator.cli`: annotate, import-capture). The library never
imports those packages itself.
Each command module defines `register(app)` and imports heavy libraries inside its commands, so
`dsr-bench --help` is fast."""

from __future__ import annotations

import importlib
import inspect
import sys
from collections.abc import Callable
from pathlib import Path

import typer

from dsr_bench import __version__
from dsr_bench.errors import UserError, one_line

app = typer.Typer(
    name="dsr-bench",
    help="Dataset and benchmark toolkit for 3D dynamic scene representations (DSR, CoRL 2020).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

#: The library's command modules under dsr_bench.cli, each with a `register(app)` function.
_COMMAND_MODULES: tuple[str, ...] = ("data", "scoring", "view", "train")
#: The order of the commands in `dsr-bench --help` (others follow in the order they were registered).
COMMAND_ORDER: tuple[str, ...] = ("generate", "validate", "info", "manifest", "import-official", "real-split",
                                  "predict", "evaluate", "view", "train", "generate-plan-tasks", "plan",
                                  "generate-captures", "annotate")
ENTRY_POINT_GROUP = "dsr_bench.commands"


def _register_commands() -> None:
    from importlib.metadata import entry_points

    for name in _COMMAND_MODULES:
        importlib.import_module(f"dsr_bench.cli.{name}").register(app)
    for entry in entry_points(group=ENTRY_POINT_GROUP):
        register = load_plugin(entry)
        if register is not None:
            register(app)
    rank = {name: i for i, name in enumerate(COMMAND_ORDER)}
    app.registered_commands.sort(key=lambda c: rank.get(c.name or "", len(rank)))
    for group in [app, *(g.typer_instance for g in app.registered_groups if g.typer_instance is not None)]:
        for command in group.registered_commands:
            command.help = reflow(command.help or inspect.getdoc(command.callback) or "")


def load_plugin(entry) -> Callable | None:
    """The `register` function of a command plugin (an entry point of ENTRY_POINT_GROUP), or None, with one line
    on stderr naming the cause and the fix, when its module cannot be imported: commonly a source checkout of
    dsr-bench in the working directory shadowing the installed package (its `dsr_bench/` folder lacks the
    `generators` and `annotator` packages that the install maps into it). The other commands still work."""
    try:
        return entry.load()
    except ImportError as exc:
        import dsr_bench

        where = Path(dsr_bench.__file__).resolve().parent
        print(f"dsr-bench: the commands of {entry.value} are unavailable ({exc}); dsr_bench is imported from "
              f"{where}: when that is a checkout of dsr-bench, install it with `pip install -e .` or run from "
              "another directory", file=sys.stderr)
        return None


def reflow(text: str) -> str:
    """A command's help with each paragraph on one line (typer's rich help keeps a docstring's line breaks, so the
    command list and --help would break where the source does); blank lines and list items ("- ...") stay."""
    paragraphs = []
    for paragraph in text.strip().split("\n\n"):
        lines: list[str] = []
        for line in paragraph.splitlines():
            if lines and not line.lstrip().startswith(("- ", "* ")):
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.rstrip())
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


_register_commands()


def _print_version(value: bool) -> None:
    if value:
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
        code = getattr(exc, "exit_code", None)
        if hasattr(exc, "show") and isinstance(code, int):
            exc.show()
            return code
        raise
    return rc if isinstance(rc, int) else 0


if __name__ == "__main__":
    sys.exit(main())
