"""The ``evgrid`` command line: the application and shared options (``base``), the commands,
the one override parser with the option tables (``options``), the option groups (``groups``),
the live node's commands (``live``).
The library below it declares no command-line option."""

from evgrid.cli import live  # noqa: F401  (registers live and replay)
from evgrid.cli.commands import app

__all__ = ["app"]
