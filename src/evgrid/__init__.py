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

__version__ = "0.2.0"

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


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` where this evgrid runs from: ``pip install -e
    '<checkout>[extra]'`` from a source checkout (the README's way), ``pip install
    'evgrid[extra]'`` from an installed wheel. Every install hint in evgrid comes from here."""
    root = source_checkout()
    if root is None:
        return f"pip install 'evgrid[{extra}]'"
    import os
    from pathlib import Path

    cwd = Path.cwd().resolve()
    if cwd == root:
        here = "."
    elif cwd in root.parents:  # the checkout below us: short and still right from here
        here = os.path.relpath(root, cwd)
    else:  # elsewhere an absolute path reads better than a climb of ../
        here = str(root)
    return f"pip install -e '{here}[{extra}]'"


def source_checkout():
    """The root of the source checkout evgrid is imported from (``<root>/src/evgrid`` with a
    ``pyproject.toml`` naming evgrid beside ``src``: an editable install or ``PYTHONPATH=src``),
    else None (an installed wheel, whose site-packages has no such file)."""
    import tomllib
    from pathlib import Path

    pkg = Path(__file__).resolve().parent
    if pkg.parent.name != "src":
        return None
    root = pkg.parent.parent
    try:
        with open(root / "pyproject.toml", "rb") as f:
            name = tomllib.load(f).get("project", {}).get("name")
    except (OSError, tomllib.TOMLDecodeError):
        return None
    return root if name == "evgrid" else None


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'evgrid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
