"""Maps out of evgrid: nav2 map_server (PGM + YAML), MCAP for Foxglove, rerun recordings.

:func:`export_map` writes a saved map; :class:`~evgrid.export.mcap.McapExporter` and
:class:`~evgrid.export.rerun.RerunRecorder` are mapper observers (``on_update``, then
``close()``) that record a whole run. MCAP needs ``pip install 'evgrid[ros]'``, rerun
``pip install 'evgrid[rerun]'``; nav2 needs nothing beyond evgrid.
"""

from __future__ import annotations

import os
from pathlib import Path

from evgrid.grid import EvidentialMap

__all__ = ["FORMATS", "export_map", "make_observer"]

#: Export formats: map_server's PGM + YAML, an MCAP file, a rerun recording.
FORMATS = ("nav2", "mcap", "rerun")
_SUFFIX = {"mcap": ".mcap", "rerun": ".rrd"}


def export_map(
    m: EvidentialMap, path: str | os.PathLike, format: str, name: str | None = None
) -> list[Path]:
    """Write one map as ``format`` (``nav2``, ``mcap`` or ``rerun``) at ``path``; returns the files written.

    ``path`` is a file stem for nav2 (``.pgm`` and ``.yaml`` are added) and a file otherwise
    (``.mcap`` / ``.rrd`` is added when missing). ``name`` names the map's topic or entity
    (default: the map's rule).
    """
    if format not in FORMATS:
        raise ValueError(f"export format must be one of {FORMATS}, got {format!r}")
    path = Path(path)
    if format == "nav2":
        from evgrid.export.nav2 import write_nav2

        return list(write_nav2(m, path))
    if path.suffix != _SUFFIX[format]:
        path = path.with_name(path.name + _SUFFIX[format])
    if format == "mcap":
        from evgrid.export.mcap import write_map_mcap

        return [write_map_mcap(m, path, name)]
    from evgrid.export.rerun import write_map_rrd

    return [write_map_rrd(m, path, name)]


def make_observer(format: str, path: str | os.PathLike | None, **kwargs):
    """A mapper observer that records a run; call its ``close()`` after the last frame.

    ``nav2``: the final maps as ``path/NAME.pgm`` + ``.yaml`` (``path`` a folder);
    ``mcap``: maps and poses while mapping (``path`` a ``.mcap`` file);
    ``rerun``: a ``.rrd`` recording at ``path``, or with ``path`` None a live viewer.
    ``kwargs`` go to :class:`~evgrid.export.nav2.Nav2Exporter`,
    :class:`~evgrid.export.mcap.McapExporter` or :class:`~evgrid.export.rerun.RerunRecorder`.
    """
    if format == "nav2":
        from evgrid.export.nav2 import Nav2Exporter

        if path is None:
            raise ValueError("the nav2 export needs a folder")
        return Nav2Exporter(path, **kwargs)
    if format == "mcap":
        from evgrid.export.mcap import McapExporter

        if path is None:
            raise ValueError("the mcap export needs a file path")
        return McapExporter(path, **kwargs)
    if format == "rerun":
        from evgrid.export.rerun import RerunRecorder

        return RerunRecorder(path, **kwargs)
    raise ValueError(f"export format must be one of {FORMATS}, got {format!r}")
