"""The ``evgrid`` command line (typer). Heavy modules are imported inside each command."""

from __future__ import annotations

import typer

import evgrid

app = typer.Typer(
    name="evgrid",
    help="Evidential occupancy grid maps from lidar and radar, with deep inverse sensor models as priors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"evgrid {evgrid.__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """evgrid: evidential occupancy mapping (Bauer et al., deep ISMs as priors)."""
