"""Sensor data: the frame contract, recordings and the nuScenes loader (the simulator is the
package ``evgrid_sim``).

The frame contract (:mod:`evgrid.data.frame`) is imported eagerly; the nuScenes modules load
on first use of one of their names, so ``import evgrid.data`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

from evgrid.data.frame import (
    LIDAR_CHANNEL,
    LIDAR_COLUMNS,
    RADAR_CHANNELS,
    RADAR_COLUMNS,
    Frame,
    LidarSweep,
    RadarSweep,
    Scene,
    radar_column,
)
from evgrid.data.sweeps import RadarBuffer, last_sweeps

_LAZY = {
    "write_nuscenes": "evgrid.data.nuscenes_format",
    "load_nuscenes": "evgrid.data.nuscenes",
    "nuscenes_splits": "evgrid.data.nuscenes",
    "NuScenesScene": "evgrid.data.nuscenes",
}

__all__ = [
    "LIDAR_CHANNEL",
    "LIDAR_COLUMNS",
    "RADAR_CHANNELS",
    "RADAR_COLUMNS",
    "Frame",
    "LidarSweep",
    "RadarSweep",
    "Scene",
    "radar_column",
    "RadarBuffer",
    "last_sweeps",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'evgrid.data' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
