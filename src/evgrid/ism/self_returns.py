"""The ego vehicle's own lidar returns: found and removed before the ray ILM.

A roof lidar sees its own car (roof edge, sensor rack, bonnet, mirrors): thousands of returns
a sweep within 3 m of the sensor, many inside the ray ILM's height band. Left in, they are
detection cells that stop every ray of the ray ILM (paper sec. V-A) within a metre or two of
the sensor, and the reference map has hardly any free space. docs/rigs.md#self-returns
defends the choice made here.

Modes of :class:`SelfReturnParams`:

* ``"auto"`` (default): returns that stay *fixed in the ego frame while the vehicle moves* are
  the vehicle's. Near the sensor, the ego frame is cut into ``voxel_m`` voxels; a voxel hit in
  at least ``hit_fraction`` of the sweeps over which the vehicle travelled ``min_travel_m`` is
  part of the vehicle (the world slides through the ego frame; the vehicle does not). Sweeps enter the history only ``step_m`` apart along the path, so standing
  still proves nothing, and ``min_travel_m`` (20 m) is longer than any object that could drive
  or stand beside the vehicle at a constant offset by chance (a bus is 12 m). Learnt voxels are
  kept for the rest of the scene, and their bounding box
  (grown by ``margin_m``) is the vehicle's body box: a point inside it is removed too, which
  catches the sparse returns of edges no single voxel sees often enough. Until the vehicle has
  moved (a scene that starts at rest), ``prior`` (a passenger car, :data:`NUSCENES_BODY`)
  stands in for the body box. Nothing needs to know the vehicle's size.
* ``"box"``: remove returns inside ``body`` (ego frame; default :data:`NUSCENES_BODY`).
* ``"off"``: keep everything (the paper's ray ILM, literally).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from evgrid.data.frame import LidarSweep
from evgrid.validation import check_choice, check_number

__all__ = [
    "BodyBox",
    "NUSCENES_BODY",
    "SELF_RETURN_MODES",
    "SelfReturnParams",
    "SelfReturnFilter",
    "parse_body_box",
]

SELF_RETURN_MODES: tuple[str, ...] = ("auto", "box", "off")


@dataclass(frozen=True, slots=True)
class BodyBox:
    """An axis-aligned box in the ego frame (m): ``x0 <= x <= x1``, ``y0 <= y <= y1``, ``z0 <= z <= z1``."""

    x0: float
    y0: float
    z0: float
    x1: float
    y1: float
    z1: float

    def __post_init__(self) -> None:
        for name in ("x0", "y0", "z0", "x1", "y1", "z1"):
            check_number(self, name)
        if not (self.x0 < self.x1 and self.y0 < self.y1 and self.z0 < self.z1):
            raise ValueError(f"BodyBox needs x0 < x1, y0 < y1, z0 < z1, got {self.as_tuple()}")

    def as_tuple(self) -> tuple[float, ...]:
        return (self.x0, self.y0, self.z0, self.x1, self.y1, self.z1)

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """Which of the ``(n, 3)`` ego-frame points lie inside the box."""
        p = np.asarray(xyz)
        out = np.empty(len(p), dtype=np.bool_)
        _k_inside(p, *(float(v) for v in self.as_tuple()), out)
        return out


#: The nuScenes car (Renault Zoe, 4.1 m x 1.7 m, with its sensor rack) in the rear-axle ego
#: frame, with mirrors and 0.15 m to spare; up to just above the rack under LIDAR_TOP (1.84 m).
NUSCENES_BODY = BodyBox(-0.9, -1.1, 0.0, 3.6, 1.1, 1.8)


def parse_body_box(text: str) -> BodyBox:
    """``"x0,y0,z0,x1,y1,z1"`` (m, ego frame) -> :class:`BodyBox`; ValueError naming the text otherwise."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"body box {text!r}: expected six numbers x0,y0,z0,x1,y1,z1 (m)") from None
    if len(vals) != 6:
        raise ValueError(
            f"body box {text!r}: expected six numbers x0,y0,z0,x1,y1,z1 (m), got {len(vals)}"
        )
    return BodyBox(*vals)


@dataclass(frozen=True, slots=True)
class SelfReturnParams:
    """How the ego vehicle's own lidar returns are found (see the module docstring). Lengths in metres."""

    mode: str = "auto"
    #: "box": the body; None = NUSCENES_BODY.
    body: BodyBox | None = None
    #: "auto": the body box used until one is learnt (None: none, keep everything until then).
    prior: BodyBox | None = NUSCENES_BODY
    voxel_m: float = 0.2
    #: Only returns this close to the sensor (horizontally) and this high above the ground can be
    #: the vehicle's: the ground, always at the same height, must not look like a fixed object.
    max_radius_m: float = 4.0
    min_height_m: float = 0.25
    step_m: float = 0.5
    hit_fraction: float = 0.9
    min_travel_m: float = 20.0
    margin_m: float = 0.1

    def __post_init__(self) -> None:
        check_choice(self, "mode", choices=SELF_RETURN_MODES)
        for name in ("voxel_m", "max_radius_m", "min_travel_m", "step_m"):
            check_number(self, name, min=0.0, min_open=True)
        check_number(self, "min_height_m")
        check_number(self, "margin_m", min=0.0)
        check_number(self, "hit_fraction", min=0.0, max=1.0, min_open=True)
        if self.step_m >= self.min_travel_m:
            raise ValueError(
                f"SelfReturnParams.step_m ({self.step_m}) must be below min_travel_m ({self.min_travel_m})"
            )
        for name in ("body", "prior"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, BodyBox):
                raise ValueError(f"SelfReturnParams.{name} must be a BodyBox or None, got {v!r}")

    @property
    def box(self) -> BodyBox:
        """The body box of mode "box"."""
        return self.body if self.body is not None else NUSCENES_BODY

    def describe(self) -> str:
        """One line for logs and metrics."""
        if self.mode == "box":
            return f"box {self.box.as_tuple()}"
        return self.mode


class SelfReturnFilter:
    """Removes the ego vehicle's returns from lidar sweeps, sweep after sweep of one scene.

    ``n_removed`` / ``n_points`` count the points removed and seen; ``learnt_box`` is the body
    box learnt so far ("auto"; None before the vehicle has moved ``min_travel_m``).
    """

    def __init__(self, params: SelfReturnParams = SelfReturnParams()):
        if not isinstance(params, SelfReturnParams):
            raise TypeError(f"SelfReturnFilter needs SelfReturnParams, got {type(params).__name__}")
        self.params = params
        self.n_removed = 0
        self.n_points = 0
        self.n_sweeps = 0
        self.learnt_box: BodyBox | None = None
        self._window_keys = np.zeros(0, dtype=np.int64)  # voxels hit in the current window, sorted
        self._window_counts = np.zeros(0, dtype=np.int64)  # in how many of its sweeps
        self._window_sweeps = 0
        self._travel = 0.0  # path length of the current window, m
        self._last_xy: np.ndarray | None = None  # where the last sweep entered the window
        self._learnt = np.zeros(0, dtype=np.int64)  # sorted voxel keys

    def __call__(self, sweep: LidarSweep) -> LidarSweep:
        """The sweep without the ego vehicle's returns (the same object when nothing is removed)."""
        p = self.params
        self.n_sweeps += 1
        self.n_points += len(sweep.points)
        if p.mode == "off" or len(sweep.points) == 0:
            return sweep
        xyz, near, keys = _ego_points(sweep, p)
        if p.mode == "box":
            drop = p.box.contains(xyz)
        else:
            drop = self._auto(sweep, xyz, near, keys)
        n = int(drop.sum())
        if n == 0:
            return sweep
        self.n_removed += n
        return LidarSweep(
            sweep.points[~drop], sweep.sensor_to_ego, sweep.ego_pose, sweep.timestamp, sweep.channel
        )

    def _auto(
        self, sweep: LidarSweep, xyz: np.ndarray, near: np.ndarray, keys: np.ndarray
    ) -> np.ndarray:
        near_keys = keys[near]
        self._learn(
            np.unique(near_keys), np.asarray(sweep.ego_pose.translation[:2], dtype=np.float64)
        )
        box = self.learnt_box if self.learnt_box is not None else self.params.prior
        drop = box.contains(xyz) if box is not None else np.zeros(len(xyz), dtype=bool)
        if len(self._learnt):
            drop[near] |= np.isin(near_keys, self._learnt)
        return drop

    def _learn(self, keys: np.ndarray, position: np.ndarray) -> None:
        """Count this sweep's voxels if the vehicle moved ``step_m`` since the last one counted;
        after ``min_travel_m`` of path, learn the voxels hit in nearly every counted sweep."""
        p = self.params
        if self._last_xy is not None:
            step = float(np.hypot(*(position - self._last_xy)))
            if step < p.step_m:
                return
            self._travel += step
        self._last_xy = position
        allk = np.concatenate([self._window_keys, keys])
        counts = np.concatenate([self._window_counts, np.ones(len(keys), dtype=np.int64)])
        self._window_keys, inv = np.unique(allk, return_inverse=True)
        self._window_counts = np.bincount(
            inv, weights=counts, minlength=len(self._window_keys)
        ).astype(np.int64)
        self._window_sweeps += 1
        if self._travel < p.min_travel_m:
            return
        fixed = self._window_keys[
            self._window_counts >= math.ceil(p.hit_fraction * self._window_sweeps)
        ]
        self._window_keys = np.zeros(0, dtype=np.int64)
        self._window_counts = np.zeros(0, dtype=np.int64)
        self._window_sweeps = 0
        self._travel = 0.0
        new = np.union1d(self._learnt, fixed)
        if len(new) != len(self._learnt):
            self._learnt = new
            lo, hi = _voxel_bounds(new, p.voxel_m)
            m = p.margin_m
            self.learnt_box = BodyBox(
                lo[0] - m, lo[1] - m, lo[2] - m, hi[0] + m, hi[1] + m, hi[2] + m
            )

    def counts(self) -> dict[str, int]:
        """For metrics.json."""
        return {
            "lidar_self_returns_removed": self.n_removed,
            "lidar_self_return_voxels": int(len(self._learnt)),
        }


_OFF = 1 << 20  # voxel indices are offset to be non-negative, 21 bits each


@numba.njit(cache=True)
def _k_ego_points(points, rot, trans, max_radius, min_height, voxel_m, xyz, near, keys):
    # One pass over the sweep (it ran as eight numpy passes, 5 ms a 30,000-point sweep): each
    # point in the ego frame (rot, trans: sensor_to_ego), whether it is near the sensor
    # (horizontally within max_radius of it, at least min_height up) and then its voxel key.
    for i in range(points.shape[0]):
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        x = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
        y = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
        z = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = x, y, z
        nr = math.hypot(x - trans[0], y - trans[1]) <= max_radius and z >= min_height
        near[i] = nr
        if nr:
            ix = np.int64(math.floor(x / voxel_m)) + _OFF
            iy = np.int64(math.floor(y / voxel_m)) + _OFF
            iz = np.int64(math.floor(z / voxel_m)) + _OFF
            keys[i] = (ix << 42) | (iy << 21) | iz
        else:
            keys[i] = -1


@numba.njit(cache=True)
def _k_inside(xyz, x0, y0, z0, x1, y1, z1, out):
    for i in range(xyz.shape[0]):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        out[i] = x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1


def _ego_points(
    sweep: LidarSweep, p: SelfReturnParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sweep's points in the ego frame ``(n, 3)``, which are near the sensor, and their voxel keys (-1: not near)."""
    n = len(sweep.points)
    xyz = np.empty((n, 3), dtype=np.float64)
    near = np.empty(n, dtype=np.bool_)
    keys = np.empty(n, dtype=np.int64)
    m = sweep.sensor_to_ego
    _k_ego_points(
        sweep.points,
        np.asarray(m.rotation, dtype=np.float64),
        np.asarray(m.translation, dtype=np.float64),
        float(p.max_radius_m),
        float(p.min_height_m),
        float(p.voxel_m),
        xyz,
        near,
        keys,
    )
    return xyz, near, keys


def _voxel_bounds(keys: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    ijk = (
        np.stack(
            [(keys >> 42) & (2**21 - 1), (keys >> 21) & (2**21 - 1), keys & (2**21 - 1)], axis=1
        )
        - _OFF
    )
    return ijk.min(axis=0) * voxel_m, (ijk.max(axis=0) + 1) * voxel_m
