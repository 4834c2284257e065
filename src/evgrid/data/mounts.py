"""Sensor mounting positions of the nuScenes vehicles (rear-axle ego frame, x forward, y left): the one
table of mounts that the simulator and the synthetic test scans share.

Translations are those of the nuScenes ``calibrated_sensor`` records; the rotations are
reduced to their yaw (the real LIDAR_TOP record carries about 1 degree of roll and pitch,
which the simulator leaves out so that the ground stays level in the sensor frame). The lidar
frame of nuScenes is turned by -90 degrees: its x axis points to the vehicle's right, y forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evgrid.data.frame import LIDAR_CHANNEL, RADAR_CHANNELS
from evgrid.geometry import SE3

__all__ = ["SensorMount", "LIDAR_MOUNT", "RADAR_MOUNTS", "SENSOR_MOUNTS"]


@dataclass(frozen=True)
class SensorMount:
    """Where a sensor sits on the ego vehicle: translation (m) and yaw (deg) in the ego frame."""

    channel: str
    x: float
    y: float
    z: float
    yaw_deg: float

    @property
    def yaw(self) -> float:
        """Mounting yaw in radians."""
        return math.radians(self.yaw_deg)

    def sensor_to_ego(self) -> SE3:
        """The extrinsics as an :class:`SE3` (sensor -> ego)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return SE3(
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
            np.array([self.x, self.y, self.z]),
        )


LIDAR_MOUNT = SensorMount(LIDAR_CHANNEL, 0.943713, 0.0, 1.84023, -90.0)
RADAR_MOUNTS: dict[str, SensorMount] = {
    m.channel: m
    for m in (
        SensorMount("RADAR_FRONT", 3.412, 0.0, 0.5, 0.2),
        SensorMount("RADAR_FRONT_LEFT", 2.422, 0.8, 0.78, 89.5),
        SensorMount("RADAR_FRONT_RIGHT", 2.422, -0.8, 0.77, -89.7),
        SensorMount("RADAR_BACK_LEFT", -0.562, 0.628, 0.53, 174.7),
        SensorMount("RADAR_BACK_RIGHT", -0.562, -0.618, 0.53, -175.0),
    )
}
if tuple(RADAR_MOUNTS) != RADAR_CHANNELS:  # same order as the frame contract
    raise ImportError(
        f"RADAR_MOUNTS {tuple(RADAR_MOUNTS)} disagree with frame.RADAR_CHANNELS {RADAR_CHANNELS}"
    )
SENSOR_MOUNTS: dict[str, SensorMount] = {LIDAR_CHANNEL: LIDAR_MOUNT, **RADAR_MOUNTS}
