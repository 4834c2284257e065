"""Maps out of evgrid: nav2 map_server (PGM + YAML), MCAP for Foxglove, rerun recordings.

:func:`export_map` writes a saved map; :class:`~evgrid.export.nav2.Nav2Exporter`,
:class:`~evgrid.export.mcap.McapExporter` and :class:`~evgrid.export.rerun.RerunRecorder` are
mapper observers (``on_update``, then ``close()``, or ``abort()`` when the run fails) that
record a whole run, each with a frozen dataclass of its parameters
(:class:`~evgrid.export.nav2.Nav2Params`, :class:`~evgrid.export.mcap.McapParams`,
:class:`~evgrid.export.rerun.RerunParams`). MCAP needs ``pip install -e '.[ros]'``, rerun
``pip install -e '.[rerun]'``; nav2 needs nothing beyond evgrid.

Every writer follows one policy (:mod:`evgrid.export._files`): an existing file is refused
unless ``overwrite``, a folder given as the target is written into, files are written under
a temporary name and renamed when complete, and every error names its file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from evgrid.export._files import EmptyMapError, ExportFileError
from evgrid.grid import EvidentialMap

__all__ = [
    "FORMATS",
    "EmptyMapError",
    "ExportFileError",
    "export_map",
    "make_observer",
    "params_class",
]

#: Export formats: map_server's PGM + YAML, an MCAP file, a rerun recording.
FORMATS = ("nav2", "mcap", "rerun")


def params_class(format: str) -> type:
    """The frozen dataclass of a format's parameters (``Nav2Params``, ``McapParams``,
    ``RerunParams``)."""
    if format == "nav2":
        from evgrid.export.nav2 import Nav2Params

        return Nav2Params
    if format == "mcap":
        from evgrid.export.mcap import McapParams

        return McapParams
    if format == "rerun":
        from evgrid.export.rerun import RerunParams

        return RerunParams
    raise ValueError(f"export format must be one of {FORMATS}, got {format!r}")


def export_map(
    m: EvidentialMap,
    path: str | os.PathLike,
    format: str,
    name: str | None = None,
    overwrite: bool = False,
) -> list[Path]:
    """Write one map as ``format`` (``nav2``, ``mcap`` or ``rerun``) at ``path``; returns the
    files written.

    ``path`` is a file stem for nav2 (``.pgm`` and ``.yaml`` are added) and a file otherwise
    (``.mcap`` / ``.rrd`` is added when missing); a folder is written into (``map.pgm`` +
    ``map.yaml``, ``maps.mcap``, ``maps.rrd``). ``name`` names the map's topic or entity
    (default: the map's rule). Existing files are refused unless ``overwrite``. The map's
    frame, first pose and stamp, as its file keeps them (``m.frame``), go into the export as a
    run's exports carry them: the frames' names, the nav2 YAML's comments, the MCAP's stamp,
    ``/tf`` and metadata, rerun's ``info``.
    """
    if format not in FORMATS:
        raise ValueError(f"export format must be one of {FORMATS}, got {format!r}")
    from evgrid.export._place import saved_placement

    # the frames, first pose and stamp the map's file keeps (m.frame), as a run's exports
    # carry them (docs/ros.md#frames)
    frame = getattr(m, "frame", None)
    map_frame, fixed_frame, placement = saved_placement(frame)
    stamp = 0 if frame is None or frame.stamp_us is None else int(frame.stamp_us)
    if format == "nav2":
        from evgrid.export.nav2 import write_nav2

        notes = [] if placement is None else placement.comments()
        if placement is None and frame is not None and frame.fixed_frame:
            notes.append(f"map frame '{map_frame}'; the recording's fixed frame '{fixed_frame}'")
        if frame is not None and frame.stamp_us is not None:
            notes.append(f"stamp {stamp} us (the last update)")
        return list(write_nav2(m, path, overwrite=overwrite, comments=notes))
    if format == "mcap":
        from evgrid.export.mcap import McapParams, write_map_mcap

        params = McapParams(map_frame=map_frame, fixed_frame=fixed_frame)
        return [write_map_mcap(m, path, name, params, overwrite, stamp, placement)]
    from evgrid.export.rerun import write_map_rrd

    return [write_map_rrd(m, path, name, overwrite, placement)]


def make_observer(
    format: str,
    path: str | os.PathLike | None,
    params: Any = None,
    overwrite: bool = False,
    **kwargs: Any,
):
    """A mapper observer that records a run; call its ``close()`` after the last frame, or its
    ``abort()`` when the run fails.

    ``nav2``: the final navigation map as ``path/map.pgm`` + ``map.yaml`` and the maps of
    ``params.maps`` beside it (``path`` a folder); ``mcap``: maps and poses while mapping
    (``path`` a ``.mcap`` file or a folder); ``rerun``: a ``.rrd`` recording at ``path``, or
    with ``path`` None a live viewer. ``params`` is the format's parameters
    (:func:`params_class`), or built from ``kwargs``.
    """
    cls = params_class(format)
    if params is None:
        params = cls(**kwargs)
    elif kwargs:
        raise ValueError(f"give either params or keyword parameters, not both ({sorted(kwargs)})")
    if not isinstance(params, cls):
        raise ValueError(f"the {format} export takes {cls.__name__}, got {type(params).__name__}")
    if format == "nav2":
        from evgrid.export.nav2 import Nav2Exporter

        if path is None:
            raise ValueError("the nav2 export needs a folder")
        return Nav2Exporter(path, params, overwrite)
    if format == "mcap":
        from evgrid.export.mcap import McapExporter

        if path is None:
            raise ValueError("the mcap export needs a file path")
        return McapExporter(path, params, overwrite)
    from evgrid.export.rerun import RerunRecorder

    return RerunRecorder(path, params, overwrite)
