"""The three cell classes, defined once for the ISMs' label grids, the evaluation and Ev-Net's
targets."""

from __future__ import annotations

from enum import IntEnum

__all__ = ["CellClass", "FREE", "OCCUPIED", "UNKNOWN", "CLASSES"]


class CellClass(IntEnum):
    """A cell's class; the values index ``[m_f, m_o, m_u]`` and :data:`CLASSES`."""

    FREE = 0
    OCCUPIED = 1
    UNKNOWN = 2


FREE, OCCUPIED, UNKNOWN = int(CellClass.FREE), int(CellClass.OCCUPIED), int(CellClass.UNKNOWN)

#: Class names in value order (keys of every per-class IoU dict).
CLASSES: tuple[str, ...] = tuple(c.name.lower() for c in CellClass)
