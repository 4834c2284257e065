"""The ego vehicle, described once: where its sensors sit and what its body is.

:class:`Vehicle` holds a vehicle's sensor mounts (rear-axle ego frame, x forward, y left, z up
from the ground), its body as axis-aligned boxes (what the simulated lidar sees of it) and the
clearance box that holds the whole body (what the self-return filter removes by default). The
nuScenes car, :data:`NUSCENES_CAR`, is the one such description; the simulator's mounts and body
(``evgrid_sim``), the synthetic test scans (:mod:`evgrid_sim.synthetic`) and the
self-return filter's prior (:data:`evgrid.preprocess.NUSCENES_BODY`) are derived from it.

Translations are those of the nuScenes ``calibrated_sensor`` records; the rotations are
reduced to their yaw (the real LIDAR_TOP record carries about 1 degree of roll and pitch,
which the simulator leaves out so that the ground stays level in the sensor frame). The lidar
frame of nuScenes is turned by -90 degrees: its x axis points to the vehicle's right, y forward.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from evgrid.data.frame import LIDAR_CHANNEL, RADAR_CHANNELS
from evgrid.geometry import SE3

__all__ = [
    "SensorMount",
    "Vehicle",
    "NUSCENES_CAR",
    "OTHER_VEHICLES",
    "LIDAR_MOUNT",
    "RADAR_MOUNTS",
    "SENSOR_MOUNTS",
]

#: An axis-aligned box in the ego frame: (x0, y0, z0, x1, y1, z1), metres.
Box = tuple[float, float, float, float, float, float]


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


def _inside(inner: Box, outer: Box) -> bool:
    return all(outer[i] <= inner[i] for i in range(3)) and all(
        inner[i] <= outer[i] for i in range(3, 6)
    )


@dataclass(frozen=True)
class Vehicle:
    """An ego vehicle: its lidar and radar mounts, its body as boxes, and the clearance box that
    holds every part of the body (checked here, so the two cannot drift apart)."""

    name: str
    lidar: SensorMount
    radars: Mapping[str, SensorMount]
    #: The body as axis-aligned boxes, each with what it is.
    parts: tuple[tuple[str, Box], ...]
    #: A box around the whole body, with some room to spare, below the roof lidar.
    clearance: Box

    def __post_init__(self) -> None:
        for what, box in self.parts:
            if not _inside(box, self.clearance):
                raise ValueError(
                    f"vehicle {self.name!r}: part {what!r} {box} is not inside the clearance "
                    f"box {self.clearance}"
                )

    @property
    def body_boxes(self) -> np.ndarray:
        """The body's parts as an ``(n, 6)`` float64 array (the simulator's ray-cast input)."""
        return np.array([box for _, box in self.parts], dtype=np.float64)

    @property
    def mounts(self) -> dict[str, SensorMount]:
        """Every sensor's mount by channel: the lidar, then the radars."""
        return {self.lidar.channel: self.lidar, **self.radars}


#: The nuScenes car: a Renault Zoe (4.1 m x 1.7 m) with a sensor rack under LIDAR_TOP.
NUSCENES_CAR = Vehicle(
    name="nuScenes Renault Zoe",
    lidar=SensorMount(LIDAR_CHANNEL, 0.943713, 0.0, 1.84023, -90.0),
    radars={
        m.channel: m
        for m in (
            SensorMount("RADAR_FRONT", 3.412, 0.0, 0.5, 0.2),
            SensorMount("RADAR_FRONT_LEFT", 2.422, 0.8, 0.78, 89.5),
            SensorMount("RADAR_FRONT_RIGHT", 2.422, -0.8, 0.77, -89.7),
            SensorMount("RADAR_BACK_LEFT", -0.562, 0.628, 0.53, 174.7),
            SensorMount("RADAR_BACK_RIGHT", -0.562, -0.618, 0.53, -175.0),
        )
    },
    parts=(
        ("body up to the bonnet and boot lid", (-0.70, -0.88, 0.20, 3.45, 0.88, 1.00)),
        ("cabin up to the window line", (0.10, -0.80, 1.00, 2.30, 0.80, 1.20)),
        # narrower: the windows lean in
        ("upper cabin and roof", (0.10, -0.58, 1.20, 2.30, 0.58, 1.48)),
        ("sensor rack, front bar: 0.1 m below the lidar", (1.94, -0.78, 1.64, 2.45, 0.78, 1.74)),
        ("sensor rack, rear bar", (-0.55, -0.78, 1.64, -0.06, 0.78, 1.74)),
        ("left mirror", (2.00, 0.88, 0.85, 2.20, 1.05, 1.10)),
        ("right mirror", (2.00, -1.05, 0.85, 2.20, -0.88, 1.10)),
    ),
    # with mirrors and 0.15 m to spare; up to just above the rack under LIDAR_TOP (1.84 m)
    clearance=(-0.9, -1.1, 0.0, 3.6, 1.1, 1.8),
)

LIDAR_MOUNT = NUSCENES_CAR.lidar
RADAR_MOUNTS: dict[str, SensorMount] = dict(NUSCENES_CAR.radars)
if tuple(RADAR_MOUNTS) != RADAR_CHANNELS:  # same order as the frame contract
    raise ImportError(
        f"RADAR_MOUNTS {tuple(RADAR_MOUNTS)} disagree with frame.RADAR_CHANNELS {RADAR_CHANNELS}"
    )
SENSOR_MOUNTS: dict[str, SensorMount] = NUSCENES_CAR.mounts


def _lidar_at(x: float, z: float) -> SensorMount:
    return SensorMount(LIDAR_CHANNEL, x, 0.0, z, -90.0)


#: Vehicles that are not the nuScenes car, for the simulator's rigs with other bodies (the
#: self-return benchmarks and tests: what the default filter does on a body it was not told
#: about). Their radars sit where the nuScenes car's do; only the lidar and the body differ.
OTHER_VEHICLES: dict[str, Vehicle] = {
    v.name: v
    for v in (
        Vehicle(
            name="car with a roof box",
            lidar=NUSCENES_CAR.lidar,
            radars=NUSCENES_CAR.radars,
            # a roof box behind the lidar (beyond its 0.8 m minimum range), 0.1 m taller than
            # it: returns at about 1.9 m
            parts=(*NUSCENES_CAR.parts, ("roof box", (-0.80, -0.55, 1.48, 0.05, 0.55, 1.95))),
            clearance=(-0.9, -1.1, 0.0, 3.6, 1.1, 2.05),
        ),
        Vehicle(
            name="van",
            lidar=_lidar_at(2.0, 2.75),  # on a rack 0.25 m above the roof
            radars=NUSCENES_CAR.radars,
            parts=(
                ("body up to the bonnet", (-1.30, -1.00, 0.30, 4.00, 1.00, 1.10)),
                ("cab and cargo box", (-1.30, -1.00, 1.10, 2.90, 1.00, 2.50)),
                ("rack bar under the lidar", (1.80, -0.80, 2.50, 2.20, 0.80, 2.60)),
                ("left mirror", (2.80, 1.00, 1.20, 3.00, 1.22, 1.50)),
                ("right mirror", (2.80, -1.22, 1.20, 3.00, -1.00, 1.50)),
            ),
            clearance=(-1.45, -1.35, 0.0, 4.15, 1.35, 2.7),
        ),
        Vehicle(
            name="truck cab",
            lidar=_lidar_at(3.6, 3.2),  # on the cab roof, at its front
            radars=NUSCENES_CAR.radars,
            parts=(
                ("cab", (1.80, -1.25, 0.50, 4.30, 1.25, 3.00)),
                ("chassis", (-2.00, -0.50, 0.60, 1.80, 0.50, 1.10)),
                ("air deflector", (2.00, -1.10, 3.00, 3.00, 1.10, 3.40)),
                ("left mirror", (3.90, 1.25, 1.60, 4.10, 1.50, 2.20)),
                ("right mirror", (3.90, -1.50, 1.60, 4.10, -1.25, 2.20)),
            ),
            clearance=(-2.1, -1.6, 0.0, 4.4, 1.6, 3.5),
        ),
    )
}
