"""``python -m evgrid.cli`` (and ``torchrun -m evgrid.cli``): the ``evgrid`` command."""

from evgrid.cli import app

app()
