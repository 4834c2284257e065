"""The ``evgrid`` command line: the application and shared options (``base``), the commands,
the one override parser with the option tables (``options``), the option groups (``groups``).
The library below it declares no command-line option."""

from evgrid.cli.commands import app

__all__ = ["app"]
