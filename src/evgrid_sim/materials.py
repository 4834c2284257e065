"""Object classes of the simulated world and how each one looks to the lidar and the radar.

Every table is a float64/bool array indexed by class id, so that numba kernels can read it.
The numbers are plausible orders of magnitude, not measurements: lidar reflectivity in [0, 1]
(Lambertian albedo at 905 nm), radar RCS per beam-hit in dBsm at normal incidence.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "GROUND",
    "BUILDING",
    "WALL",
    "FENCE",
    "HEDGE",
    "TRUNK",
    "CANOPY",
    "POLE",
    "CAR",
    "TRUCK",
    "PEDESTRIAN",
    "CYCLIST",
    "BARRIER",
    "BUSH",
    "CLASS_NAMES",
    "N_CLASSES",
    "LIDAR_REFLECTIVITY",
    "LIDAR_DENSITY",
    "LIDAR_PASS",
    "RADAR_RCS_DB",
    "RADAR_SPECULAR",
    "RADAR_SCATTER",
    "RADAR_TRANSMIT",
    "RADAR_OPAQUE",
    "RADAR_MIRROR",
    "DYNAMIC_CAPABLE",
]

GROUND = 0
BUILDING = 1
WALL = 2
FENCE = 3
HEDGE = 4
TRUNK = 5
CANOPY = 6
POLE = 7
CAR = 8
TRUCK = 9
PEDESTRIAN = 10
CYCLIST = 11
BARRIER = 12
BUSH = 13

CLASS_NAMES: tuple[str, ...] = (
    "ground",
    "building",
    "wall",
    "fence",
    "hedge",
    "trunk",
    "canopy",
    "pole",
    "car",
    "truck",
    "pedestrian",
    "cyclist",
    "barrier",
    "bush",
)
N_CLASSES = len(CLASS_NAMES)


def _table(values: dict[int, float], default: float = 0.0) -> np.ndarray:
    t = np.full(N_CLASSES, default, dtype=np.float64)
    for k, v in values.items():
        t[k] = v
    return t


#: Lambertian reflectivity; ground = asphalt/pavement. Barriers carry retro-reflective foil.
LIDAR_REFLECTIVITY = _table(
    {
        GROUND: 0.12,
        BUILDING: 0.35,
        WALL: 0.30,
        FENCE: 0.25,
        HEDGE: 0.40,
        TRUNK: 0.25,
        CANOPY: 0.45,
        POLE: 0.50,
        CAR: 0.40,
        TRUCK: 0.45,
        PEDESTRIAN: 0.30,
        CYCLIST: 0.30,
        BARRIER: 0.90,
        BUSH: 0.40,
    }
)
#: Vegetation is a volume, not a surface: a beam penetrates an exponentially distributed depth
#: with this many interactions per metre (0 = solid surface).
LIDAR_DENSITY = _table({HEDGE: 2.5, CANOPY: 1.0, BUSH: 3.0})
#: Probability that a beam passes a (thin, porous) surface: chain-link and picket fences.
LIDAR_PASS = _table({FENCE: 0.35})

#: Radar cross-section of one beam-sized patch at normal incidence, dBsm.
RADAR_RCS_DB = _table(
    {
        BUILDING: 12.0,
        WALL: 10.0,
        FENCE: 5.0,
        HEDGE: -4.0,
        TRUNK: 2.0,
        CANOPY: -8.0,
        POLE: 6.0,
        CAR: 9.0,
        TRUCK: 14.0,
        PEDESTRIAN: -6.0,
        CYCLIST: -2.0,
        BARRIER: 4.0,
        BUSH: -7.0,
    }
)
#: How strongly the return falls off away from normal incidence (1 = flat specular plate).
RADAR_SPECULAR = _table({BUILDING: 1.0, WALL: 1.0, FENCE: 0.6, CAR: 0.5, TRUCK: 0.8, BARRIER: 0.6})
#: Chance that a strip of surface ``RadarConfig.scatter_strip_m`` wide (or a narrower object)
#: holds a resolvable scattering centre (times ``RadarConfig.scatter_probability``).
RADAR_SCATTER = _table(
    {
        BUILDING: 0.45,
        WALL: 0.45,
        FENCE: 0.45,
        HEDGE: 0.3,
        TRUNK: 0.8,
        CANOPY: 0.2,
        POLE: 0.9,
        CAR: 0.8,
        TRUCK: 0.85,
        PEDESTRIAN: 0.7,
        CYCLIST: 0.7,
        BARRIER: 0.7,
        BUSH: 0.3,
    }
)
#: Probability that a beam goes on past the object (under vehicles, through foliage and fences).
RADAR_TRANSMIT = _table(
    {
        FENCE: 0.5,
        HEDGE: 0.5,
        TRUNK: 0.3,
        CANOPY: 0.7,
        POLE: 0.6,
        CAR: 0.25,
        TRUCK: 0.1,
        PEDESTRIAN: 0.7,
        CYCLIST: 0.6,
        BARRIER: 0.4,
        BUSH: 0.6,
    }
)
#: Classes a radar beam never passes (used to stop the search early).
RADAR_OPAQUE = np.array([RADAR_TRANSMIT[k] == 0.0 and k != GROUND for k in range(N_CLASSES)])
#: How mirror-like a surface is for the radar (0-1): flat facades and walls are; the curved
#: sides of cars less so. Scales the chance that a bounce off it creates a multipath ghost.
RADAR_MIRROR = _table({BUILDING: 1.0, WALL: 0.8, CAR: 0.35, TRUCK: 0.6, BARRIER: 0.5})
#: Classes that can be moving objects.
DYNAMIC_CAPABLE = np.zeros(N_CLASSES, dtype=bool)
DYNAMIC_CAPABLE[[CAR, TRUCK, PEDESTRIAN, CYCLIST]] = True
