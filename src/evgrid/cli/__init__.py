"""The ``evgrid`` command line (typer): every command, option table, option check and the one
override parser live in this package; the library below it declares no command-line option.

:mod:`~evgrid.cli.app` (the application, shared options), :mod:`~evgrid.cli.commands` (the
commands), :mod:`~evgrid.cli.options` (the override parser and the option tables),
:mod:`~evgrid.cli.groups` (option groups, and the config files of simulate and bench).
"""

from evgrid.cli.commands import app

__all__ = ["app"]
