"""The ``evgrid`` command line: the application (``base``), the commands (``commands``,
``live``), the one override parser and option tables (``options``), option groups (``groups``).
The library below it declares no command-line option."""

from evgrid.cli import live  # noqa: F401  (registers live and replay)
from evgrid.cli.commands import app

__all__ = ["app"]
