"""Sensor data: the frame contract, the built-in simulator and the nuScenes loader."""

from evgrid.data.frame import (
    LIDAR_CHANNEL,
    LIDAR_COLUMNS,
    RADAR_CHANNELS,
    RADAR_COLUMNS,
    Frame,
    LidarSweep,
    RadarSweep,
    Scene,
    keyframes,
    radar_column,
)

__all__ = [
    "LIDAR_CHANNEL",
    "LIDAR_COLUMNS",
    "RADAR_CHANNELS",
    "RADAR_COLUMNS",
    "Frame",
    "LidarSweep",
    "RadarSweep",
    "Scene",
    "keyframes",
    "radar_column",
]
