"""The built-in nuScenes-like driving simulator (docs/decisions.md#simulated-data): seeded,
deterministic, numba-fast.

>>> from evgrid_sim import simulate_scene, SimConfig
>>> scene = simulate_scene(seed=0, config=SimConfig(duration_s=1.0))
>>> frame = next(iter(scene))   # a Frame: lidar sweep, radar sweeps, ego pose, true occupancy
"""

from evgrid.data.mounts import LIDAR_MOUNT, RADAR_MOUNTS, SENSOR_MOUNTS, SensorMount
from evgrid_sim.config import EgoConfig, LidarConfig, RadarConfig, SimConfig, WorldConfig
from evgrid_sim.radar import RADAR_CLUTTER, RADAR_GHOST, RADAR_LABEL_NAMES, RADAR_REAL
from evgrid_sim.scene import (
    OCC_DYNAMIC,
    OCC_FREE,
    OCC_STATIC,
    SimScene,
    scene_name,
    simulate_scene,
)
from evgrid_sim.world import World

__all__ = [
    "EgoConfig",
    "LidarConfig",
    "RadarConfig",
    "SimConfig",
    "WorldConfig",
    "SimScene",
    "simulate_scene",
    "scene_name",
    "World",
    "SensorMount",
    "LIDAR_MOUNT",
    "RADAR_MOUNTS",
    "SENSOR_MOUNTS",
    "RADAR_REAL",
    "RADAR_CLUTTER",
    "RADAR_GHOST",
    "RADAR_LABEL_NAMES",
    "OCC_FREE",
    "OCC_STATIC",
    "OCC_DYNAMIC",
]
