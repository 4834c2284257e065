"""evgrid: evidential occupancy grid maps from lidar and radar, with deep ISMs as priors.

The names a user needs, loaded on first use so that ``import evgrid`` stays light::

    import evgrid
    mapper = evgrid.OccupancyMapper(evgrid.MapperConfig())
    for frame in evgrid.SimSource((4,), duration_s=1.0).load("sim-000004"):
        mapper.process(frame)
    evgrid.save_map(mapper.maps["fused"], "fused.npz")
"""

from __future__ import annotations

import importlib
from typing import Any

from evgrid.package import __version__, install_hint, source_checkout

_PUBLIC = {
    # the online mapper and its configuration
    "OccupancyMapper": "evgrid.mapper",
    "MapperConfig": "evgrid.config",
    "RunConfig": "evgrid.config",
    "map_scene": "evgrid.runs",
    "map_scenes": "evgrid.runs",
    # inverse sensor models
    "ray_ilm": "evgrid.ism",
    "RayIlmParams": "evgrid.ism",
    "ray_irm": "evgrid.ism",
    "RayIrmParams": "evgrid.ism",
    "DeepIrm": "evgrid.ism.deep",
    # maps
    "EvidentialMap": "evgrid.grid",
    "MapSet": "evgrid.fusion",
    "load_map": "evgrid.grid",
    "MapFrame": "evgrid.grid",
    "save_map": "evgrid.grid",
    "GridSpec": "evgrid.geometry",
    # data
    "Frame": "evgrid.data",
    "SimSource": "evgrid.sources",
    "SimFilesSource": "evgrid.sources",
    "NuScenesSource": "evgrid.sources",
    "BagSource": "evgrid.sources",
    # exports
    "export_map": "evgrid.export",
}

__all__ = ["__version__", "install_hint", "source_checkout", *_PUBLIC]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'evgrid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
