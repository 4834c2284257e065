"""The two errors of reading recordings: a recording or a rig file that cannot be used."""

from __future__ import annotations

__all__ = ["BagError", "RigError"]


class BagError(ValueError):
    """A recording that cannot be mapped as the rig file describes it (missing topic, frame or
    field)."""


class RigError(ValueError):
    """A rig file that is not valid."""
