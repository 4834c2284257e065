"""The typer application: the root command, the one-line failures, the options commands share.

A command that fails prints one line, ``evgrid: error: ...``, and exits with status 1; ``evgrid
--debug COMMAND`` (or ``EVGRID_DEBUG=1``) shows the traceback instead. Ctrl-C exits with 130.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any

import typer

import evgrid

# rich markup off: it would eat the [extra] names of install hints ("evgrid[ros]")
app = typer.Typer(
    name="evgrid",
    help="Evidential occupancy grid maps from lidar and radar, with deep ISMs as priors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
    rich_markup_mode=None,
)
config_app = typer.Typer(help="Show the resolved config of a run.", rich_markup_mode=None)
app.add_typer(config_app, name="config")
_STATE = {"debug": os.environ.get("EVGRID_DEBUG", "") not in ("", "0")}
#: The options of a command's help beyond its own: option groups and config overrides.
_EXTRA = {"allow_extra_args": True, "ignore_unknown_options": True}


def _version(value: bool) -> None:
    if value:
        typer.echo(f"evgrid {evgrid.__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback when a command fails."),
) -> None:
    """evgrid: evidential occupancy mapping (Bauer et al., deep ISMs as priors)."""
    _STATE["debug"] = debug or os.environ.get("EVGRID_DEBUG", "") not in ("", "0")


class _Command(typer.core.TyperCommand):
    """A command whose help ends with the options it takes from the config (written when asked
    for: the config's modules are slow to import)."""

    def format_epilog(self, ctx: Any, formatter: Any) -> None:
        from evgrid.cli.options import command_options_help

        for title, rows in command_options_help(self.name):
            with formatter.section(title):
                formatter.write_dl(rows)


def command(*args: Any, typer_app: typer.Typer = app, **kwargs: Any) -> Callable:
    """``app.command`` whose failures print one line (see the module docstring); ``extra=True``:
    the command also takes the options of its config (:mod:`evgrid.cli.options`)."""

    def register(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def run(*a: Any, **k: Any) -> Any:
            try:
                return fn(*a, **k)
            except (typer.Exit, typer.Abort, typer.BadParameter):
                raise
            except KeyboardInterrupt as e:
                typer.echo(f"evgrid: {e or 'interrupted'}", err=True)
                raise typer.Exit(130) from None
            except Exception as e:
                if _STATE["debug"]:
                    raise
                from evgrid.console import error_line

                typer.echo(f"evgrid: error: {error_line(e)}", err=True)
                raise typer.Exit(1) from None

        if kwargs.pop("extra", False):
            kwargs.update(context_settings=_EXTRA, cls=_Command)
        return typer_app.command(*args, **kwargs)(run)

    return register


# The options several commands share.
OUT = typer.Option(None, "--out", help="Results folder; default: new out/COMMAND/TIME (latest).")
CONFIG = typer.Option(None, "--config", help="A run's config.json: the same run (options win).")
SET = typer.Option(None, "--set", help="KEY=VALUE: any config field, e.g. mapper.threads=2.")
OVERWRITE = typer.Option(False, "--overwrite", help="Write into --out even if it holds results.")
RESUME = typer.Option(False, "--resume", help="Continue the run in --out (or the latest).")
ENGINE = typer.Option("local", "--engine", help="local (a process pool) or ray (the ray extra).")
CHECKPOINT = typer.Option(None, "--checkpoint", help="Default: the shipped one.")


def workers(n: int) -> Any:
    """``--workers`` with its default ``n``."""
    return typer.Option(n, "--workers", min=1, help="Scenes run at once (one process each).")
