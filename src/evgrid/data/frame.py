"""The frame contract: what every data source (simulator, nuScenes) yields, one frame a lidar sweep.

A scene is an iterable of :class:`Frame` in time order. One frame per lidar sweep
(``LIDAR_TOP`` at 20 Hz in nuScenes); ``is_keyframe`` marks the 2 Hz nuScenes samples, where
maps are evaluated (and updated, as they are between keyframes too:
docs/decisions.md#map-update-rate).
Each frame carries the radar sweeps of every radar (any number, any channel names;
nuScenes has the five of ``RADAR_CHANNELS``) whose timestamps fall in
``(previous frame's timestamp, this frame's timestamp]``, oldest first, so that a consumer
that keeps the last N sweeps of each radar sees every sweep exactly once.

All points are in their *sensor* frame, with the sensor's extrinsics (``sensor_to_ego``) and
the ego pose at the sweep's own timestamp (``ego_pose``, ego -> global), exactly as nuScenes
stores them. Units: metres, seconds as integer microseconds, m/s, dBsm.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from evgrid.geometry import SE3

__all__ = [
    "RADAR_CHANNELS",
    "LIDAR_CHANNEL",
    "LIDAR_COLUMNS",
    "RADAR_COLUMNS",
    "LidarSweep",
    "RadarSweep",
    "Frame",
    "Scene",
    "radar_column",
    "channel_order",
]

LIDAR_CHANNEL = "LIDAR_TOP"
RADAR_CHANNELS: tuple[str, ...] = (
    "RADAR_FRONT",
    "RADAR_FRONT_LEFT",
    "RADAR_FRONT_RIGHT",
    "RADAR_BACK_LEFT",
    "RADAR_BACK_RIGHT",
)

#: Columns of ``LidarSweep.points`` (float32): metres, metres, metres, intensity 0-255, ring 0-31.
LIDAR_COLUMNS: tuple[str, ...] = ("x", "y", "z", "intensity", "ring")
#: A point closer than this to its sensor (m) is no return: drivers of organised clouds mark a
#: beam without one as (0, 0, 0), and no sensor measures a range of a millimetre.
NO_RETURN_RANGE_M = 1e-3

#: Columns of ``RadarSweep.points`` (float32), named as in the nuScenes radar ``.pcd`` files:
#: position (m, sensor frame), radar cross-section (dBsm), raw and ego-motion compensated
#: Doppler velocity (m/s, sensor frame), and the validity fields of the Continental ARS 408
#: (``dyn_prop`` 0-7, ``ambig_state`` 0-4, 3 = unambiguous; ``invalid_state`` 0-17, 0 = valid;
#: ``pdh0`` 0-7, false-alarm probability class, 1 = < 25 %).
RADAR_COLUMNS: tuple[str, ...] = (
    "x",
    "y",
    "z",
    "rcs",
    "vx",
    "vy",
    "vx_comp",
    "vy_comp",
    "dyn_prop",
    "ambig_state",
    "invalid_state",
    "pdh0",
)


def radar_column(name: str) -> int:
    """Index of a named column in ``RadarSweep.points``."""
    try:
        return RADAR_COLUMNS.index(name)
    except ValueError:
        raise KeyError(f"unknown radar column {name!r}; columns are {RADAR_COLUMNS}") from None


def channel_order(channel: str) -> tuple[int, str]:
    """Sort key of radar channels: nuScenes' five in their usual order, then any others by name."""
    known = RADAR_CHANNELS.index(channel) if channel in RADAR_CHANNELS else len(RADAR_CHANNELS)
    return known, channel


_KINDS = {
    "U": "strings",
    "S": "bytes",
    "c": "complex numbers",
    "O": "Python objects",
    "b": "booleans",
}


def _check_points(points: np.ndarray, n_cols: int, what: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != n_cols:
        raise ValueError(
            f"{what}.points must have shape (n, {n_cols}), got {p.shape}"
            + (" (transposed? pass points.T)" if p.ndim == 2 and p.shape[0] < p.shape[1] else "")
        )
    if p.dtype.kind not in "fiu":
        # numpy would turn strings ('1.5') into numbers and drop an imaginary part silently
        raise ValueError(
            f"{what}.points must hold real numbers (float or integer), got dtype {p.dtype} "
            f"({_KINDS.get(p.dtype.kind, 'not numbers')})"
        )
    return np.ascontiguousarray(p, dtype=np.float32)


def _check_sweep(sweep: LidarSweep | RadarSweep, what: str) -> None:
    # checked here, at construction: a None pose would otherwise surface as an AttributeError
    # deep inside an ISM, naming nothing
    for name in ("sensor_to_ego", "ego_pose"):
        v = getattr(sweep, name)
        if not isinstance(v, SE3):
            raise ValueError(
                f"{what}.{name} must be an SE3 (the sensor's extrinsics and the ego pose at the "
                f"sweep's stamp), got {type(v).__name__}"
            )
    t = sweep.timestamp
    if isinstance(t, bool) or not isinstance(t, (int, np.integer)):
        raise ValueError(f"{what}.timestamp must be an integer number of microseconds, got {t!r}")


@dataclass(frozen=True, slots=True, eq=False)
class LidarSweep:
    """One lidar sweep: ``points`` (n, 5) float32 in the sensor frame, see ``LIDAR_COLUMNS``."""

    points: np.ndarray
    sensor_to_ego: SE3
    ego_pose: SE3
    timestamp: int
    channel: str = LIDAR_CHANNEL

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "points", _check_points(self.points, len(LIDAR_COLUMNS), "LidarSweep")
        )
        _check_sweep(self, "LidarSweep")


@dataclass(frozen=True, slots=True, eq=False)
class RadarSweep:
    """One radar sweep: ``points`` (n, 12) float32 in the sensor frame, see ``RADAR_COLUMNS``."""

    points: np.ndarray
    sensor_to_ego: SE3
    ego_pose: SE3
    timestamp: int
    channel: str

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "points", _check_points(self.points, len(RADAR_COLUMNS), "RadarSweep")
        )
        _check_sweep(self, "RadarSweep")
        if not isinstance(self.channel, str) or not self.channel:
            raise ValueError(f"RadarSweep.channel must be a non-empty name, got {self.channel!r}")


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One time step: a lidar sweep, the radar sweeps since the previous frame, the ego pose.

    ``occupancy`` is the true occupancy on the local grid of this frame's ego pose (``(n, n)``
    uint8: 0 free, 1 occupied static, 2 occupied dynamic), given by the simulator on
    keyframes and ``None`` elsewhere (nuScenes has no such raster).

    ``lidar_skipped``: lidar sweeps the source skipped just before this one (a bad stamp, a
    malformed cloud, no pose, a damaged file), counted in its own report under their reasons;
    the gap they leave is not counted again as missing sweeps.
    """

    scene: str
    index: int
    timestamp: int
    ego_pose: SE3
    is_keyframe: bool
    lidar: LidarSweep
    radar: Mapping[str, tuple[RadarSweep, ...]] = field(default_factory=dict)
    occupancy: np.ndarray | None = None
    lidar_skipped: int = 0

    def radar_sweeps(self) -> Iterator[RadarSweep]:
        """All radar sweeps of this frame, channel by channel (nuScenes' order, then by name),
        oldest first."""
        for ch in sorted(self.radar, key=channel_order):
            yield from self.radar[ch]


class Scene(Protocol):
    """A named, finite sequence of frames (what loaders and the simulator return)."""

    name: str

    def __iter__(self) -> Iterator[Frame]: ...

    def __len__(self) -> int: ...
