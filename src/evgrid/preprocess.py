"""What is removed from a frame before any inverse sensor model sees it, in one place.

Three things are taken out of a :class:`~evgrid.data.frame.Frame` before the ISMs of the paper
(sec. V) read it, and the mapper (:class:`~evgrid.mapper.OccupancyMapper`) and Ev-Net's training
(:mod:`evgrid.learn.train`) must take out the same, or the deep IRM learns from other detections
and other targets than it is later given:

* **the pose gate** (:class:`PoseGate`): frames whose ego pose jumped or turned further than a
  vehicle can since the last accepted frame are skipped, counted and logged; radar sweeps whose
  own ego pose is implausible next to their frame's are dropped (odometry glitches);
* **the radar validity filter** (:class:`RadarFilter`): the ARS 408 validity fields of each
  detection (``invalid_state``, ``dyn_prop``, ``ambig_state``), as the nuScenes devkit filters;
* **the ego vehicle's own lidar returns** (:class:`SelfReturnFilter`): a roof lidar sees its own
  car; left in, those returns stop every ray of the ray ILM (paper sec. V-A) a metre from the
  sensor.

:class:`Preprocessor` holds the three, with their state over one scene (the last accepted pose,
the body learnt so far) and their counts. docs/rigs.md#self-returns defends the choices.

Self-return modes (:class:`SelfReturnParams`):

* ``"auto"`` (default): returns that stay *fixed in the ego frame while the vehicle moves* are
  the vehicle's. Near the sensor, the ego frame is cut into ``voxel_m`` voxels; a voxel hit in at
  least ``hit_fraction`` of the sweeps over which the vehicle travelled ``min_travel_m`` is part
  of the vehicle (the world slides through the ego frame; the vehicle does not). Sweeps enter the
  history only ``step_m`` apart along the path, so standing still proves nothing, and
  ``min_travel_m`` (20 m) is longer than any object that could drive or stand beside the vehicle
  at a constant offset by chance (a bus is 12 m). Learnt voxels are kept for the rest of the
  scene, and their bounding box (grown by ``margin_m``) is the vehicle's body box: a point inside
  it is removed too, which catches the sparse returns of edges no single voxel sees often enough.
  Until then ``prior`` (a passenger car, :data:`NUSCENES_BODY`) stands in for the body box, and
  it is *checked against what is seen* every ``grow_travel_m`` of driving: voxels fixed in the
  ego frame that touch the prior or the sensor's mount (``mount_reach_m`` around the sensor),
  within ``grow_gap_m`` (a roof box, a van's or a truck cab's taller body), are
  part of the vehicle at once, so a vehicle
  larger than the prior leaves no trail of its own body along a short drive either. What
  drives beside the vehicle is a gap away from its body, and is not grown into it. Until the
  first check, the prior reaches up to ``mount_reach_m`` above the sensor (and that far around
  it), and ``column_half_width_m`` to either side: what is right above the vehicle is its own,
  or something it passes under and saw from afar on the way.
* ``"box"``: remove returns inside ``body`` (ego frame; default :data:`NUSCENES_BODY`).
* ``"off"``: keep everything (the paper's ray ILM, literally).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np

from evgrid.data.frame import Frame, LidarSweep, RadarSweep, radar_column
from evgrid.data.mounts import NUSCENES_CAR
from evgrid.geometry import MAX_POSE_M, SE3
from evgrid.validation import check_choice, check_number

__all__ = [
    "Preprocessor",
    "PoseGate",
    "PoseError",
    "RadarFilter",
    "RADAR_FILTER_MODES",
    "check_trained_filter",
    "BodyBox",
    "NUSCENES_BODY",
    "SELF_RETURN_MODES",
    "SelfReturnParams",
    "SelfReturnFilter",
    "parse_body_box",
]

logger = logging.getLogger(__name__)


# --- the radar validity filter -------------------------------------------------------------------
# nuScenes radar ``.pcd`` files hold every cluster the sensor reported; the devkit's
# ``RadarPointCloud.from_file`` drops by default those whose ``invalid_state`` is not 0 (valid),
# whose ``dyn_prop`` is not in 0-6 (7: "stopped") or whose ``ambig_state`` is not 3 (unambiguous
# Doppler). evgrid's loaders keep everything (docs/conventions.md#sensor-data); a RadarFilter
# decides, and the same filter must be used to train Ev-Net and to map with it (the checkpoint
# records it; check_trained_filter warns on a mismatch).

RADAR_FILTER_MODES: tuple[str, ...] = ("none", "nuscenes", "custom")

#: The devkit's defaults (nuscenes-devkit 1.2.0, RadarPointCloud.from_file).
_NUSCENES = {"invalid_state": (0,), "dyn_prop": tuple(range(7)), "ambig_state": (3,)}


@dataclass(frozen=True, slots=True)
class RadarFilter:
    """Keep detections whose ``invalid_state``, ``dyn_prop`` and ``ambig_state`` are in the
    given sets.

    ``mode`` "none" keeps all; "nuscenes" uses the devkit's default sets (the fields given here
    are ignored); "custom" uses the sets given, where ``None`` accepts any value.
    """

    mode: str = "none"  #: which radar detections are kept: none (all)|nuscenes|custom
    invalid_state: tuple[int, ...] | None = None
    dyn_prop: tuple[int, ...] | None = None
    ambig_state: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.mode not in RADAR_FILTER_MODES:
            raise ValueError(
                f"RadarFilter.mode must be one of {RADAR_FILTER_MODES}, got {self.mode!r}"
            )
        for name in _NUSCENES:
            v = getattr(self, name)
            if v is None:
                continue
            if not isinstance(v, tuple) or not all(
                isinstance(x, int) and not isinstance(x, bool) for x in v
            ):
                raise ValueError(
                    f"RadarFilter.{name} must be a tuple of integers or None, got {v!r}"
                )

    @classmethod
    def named(cls, name: str) -> RadarFilter:
        """``"none"`` or ``"nuscenes"`` (the command line's choices)."""
        if name not in ("none", "nuscenes"):
            raise ValueError(f"radar filter must be 'none' or 'nuscenes', got {name!r}")
        return cls(name)

    def sets(self) -> dict[str, tuple[int, ...] | None]:
        """The accepted values of each field (None: any)."""
        if self.mode == "none":
            return {k: None for k in _NUSCENES}
        if self.mode == "nuscenes":
            return dict(_NUSCENES)
        return {k: getattr(self, k) for k in _NUSCENES}

    @property
    def is_identity(self) -> bool:
        """Whether the filter keeps every detection."""
        return all(v is None for v in self.sets().values())

    def describe(self) -> str:
        """A name for logs: ``none``, ``nuscenes`` or ``custom(field=values, ...)``."""
        if self.mode != "custom":
            return self.mode
        parts = [f"{k}={list(v)}" for k, v in self.sets().items() if v is not None]
        return f"custom({', '.join(parts)})"

    def keep(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the ``(n, 12)`` radar points (``RADAR_COLUMNS``) that pass."""
        ok = np.ones(len(points), dtype=bool)
        for name, allowed in self.sets().items():
            if allowed is not None:
                ok &= np.isin(np.rint(points[:, radar_column(name)]).astype(np.int64), allowed)
        return ok

    def __call__(self, sweep: RadarSweep) -> tuple[RadarSweep, int]:
        """(the sweep with only the passing detections, how many were dropped); the same sweep
        if none."""
        if self.is_identity or len(sweep.points) == 0:
            return sweep, 0
        ok = self.keep(sweep.points)
        n = int(len(ok) - ok.sum())
        if n == 0:
            return sweep, 0
        return RadarSweep(
            sweep.points[ok], sweep.sensor_to_ego, sweep.ego_pose, sweep.timestamp, sweep.channel
        ), n

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (lists for the sets), as stored in checkpoints (evgrid.serial)."""
        from evgrid.serial import to_dict

        return to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RadarFilter:
        """Inverse of :meth:`to_dict` (evgrid.serial; missing fields take their defaults)."""
        from evgrid.serial import from_dict

        return from_dict(cls, d)


def check_trained_filter(
    used: RadarFilter, extra: dict[str, Any] | None, checkpoint: str = "the checkpoint"
) -> bool:
    """Warn (and return False) if ``used`` differs from the filter a checkpoint's metadata says it
    was trained with; a checkpoint that records none was trained unfiltered."""
    rec = (extra or {}).get("radar_filter")
    trained = RadarFilter.from_dict(rec) if isinstance(rec, dict) else RadarFilter()
    if trained.sets() == used.sets():
        return True
    logger.warning(
        "radar filter %r differs from the one %s was trained with (%r); the deep IRM sees other "
        "detections than in training",
        used.describe(),
        checkpoint,
        trained.describe(),
    )
    return False


# --- the ego vehicle's own lidar returns ---------------------------------------------------------

SELF_RETURN_MODES: tuple[str, ...] = ("auto", "box", "off")


@dataclass(frozen=True, slots=True)
class BodyBox:
    """An axis-aligned box in the ego frame (m): ``x0 <= x <= x1``, ``y0 <= y <= y1``,
    ``z0 <= z <= z1``."""

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

    def union(self, lo: np.ndarray, hi: np.ndarray, margin: float) -> BodyBox:
        """The box grown to hold the box ``lo``-``hi`` (grown by ``margin``) too."""
        a = self.as_tuple()
        return BodyBox(
            *(min(a[i], float(lo[i]) - margin) for i in range(3)),
            *(max(a[i + 3], float(hi[i]) + margin) for i in range(3)),
        )


#: The nuScenes car's body box: the clearance box of :data:`evgrid.data.mounts.NUSCENES_CAR`
#: (the one description of that vehicle; the simulator's body parts lie inside it).
NUSCENES_BODY = BodyBox(*NUSCENES_CAR.clearance)


def parse_body_box(text: str) -> BodyBox:
    """``"x0,y0,z0,x1,y1,z1"`` (m, ego frame) -> :class:`BodyBox`; ValueError naming the text
    otherwise."""
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
    """How the ego vehicle's own lidar returns are found (see the module docstring). Lengths in
    metres."""

    #: the ego vehicle's own lidar returns: auto (learnt while driving), box (inside --body-box),
    #: off (keep every return); docs/rigs.md#self-returns
    mode: str = "auto"
    #: the vehicle's body box in the lidar's frame (m); none: nuScenes' car
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
    #: "auto" with a prior: every ``grow_travel_m`` of path until a body is learnt, voxels outside
    #: the body box that stayed fixed in the ego frame and lie within ``grow_gap_m`` of the prior
    #: or of the sensor's mount (or of such a voxel) join the body (0: never). Something beside
    #: the vehicle at a constant offset for a few metres is a gap away from it; the vehicle's
    #: own roof box or cab is not.
    grow_travel_m: float = 2.0
    grow_gap_m: float = 0.3
    #: The box this far around the sensor holds its mount: the body is grown from there too
    #: (and until the first check the body box reaches this far above and around the sensor).
    mount_reach_m: float = 0.75
    #: Until the first check, the body box is at least this wide to either side of the ego
    #: frame's x axis: half the widest road vehicle (2.55 m), mirrors aside.
    column_half_width_m: float = 1.3

    def __post_init__(self) -> None:
        check_choice(self, "mode", choices=SELF_RETURN_MODES)
        for name in ("voxel_m", "max_radius_m", "min_travel_m", "step_m"):
            check_number(self, name, min=0.0, min_open=True)
        check_number(self, "min_height_m")
        for name in (
            "margin_m",
            "grow_travel_m",
            "grow_gap_m",
            "mount_reach_m",
            "column_half_width_m",
        ):
            check_number(self, name, min=0.0)
        check_number(self, "hit_fraction", min=0.0, max=1.0, min_open=True)
        if self.step_m >= self.min_travel_m:
            raise ValueError(
                f"SelfReturnParams.step_m ({self.step_m}) must be below min_travel_m "
                f"({self.min_travel_m})"
            )
        if 0 < self.grow_travel_m < self.step_m:
            raise ValueError(
                f"SelfReturnParams.grow_travel_m ({self.grow_travel_m}) must be 0 (off) or at "
                f"least step_m ({self.step_m})"
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


class _Window:
    """In how many of the sweeps counted since the last reset each voxel was hit, and over how
    much path."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)  # voxels hit, sorted
        self.counts = np.zeros(0, dtype=np.int64)  # in how many of the sweeps
        self.sweeps = 0
        self.travel = 0.0

    def add(self, keys: np.ndarray, step: float) -> None:
        allk = np.concatenate([self.keys, keys])
        counts = np.concatenate([self.counts, np.ones(len(keys), dtype=np.int64)])
        self.keys, inv = np.unique(allk, return_inverse=True)
        self.counts = np.bincount(inv, weights=counts, minlength=len(self.keys)).astype(np.int64)
        self.sweeps += 1
        self.travel += step

    def fixed(self, hit_fraction: float) -> np.ndarray:
        """The voxels hit in at least ``hit_fraction`` of the sweeps."""
        return self.keys[self.counts >= math.ceil(hit_fraction * self.sweeps)]


class SelfReturnFilter:
    """Removes the ego vehicle's returns from lidar sweeps, sweep after sweep of one scene.

    ``n_removed`` / ``n_points`` count the points removed and seen; ``learnt_box`` is the body
    box learnt so far ("auto"; None before the vehicle has moved ``min_travel_m``);
    ``grown_box`` the prior grown by what was found attached to it (None: nothing yet).
    """

    def __init__(self, params: SelfReturnParams = SelfReturnParams()):
        if not isinstance(params, SelfReturnParams):
            raise TypeError(f"SelfReturnFilter needs SelfReturnParams, got {type(params).__name__}")
        self.params = params
        self.n_removed = 0
        self.n_points = 0
        self.n_sweeps = 0
        self.learnt_box: BodyBox | None = None
        self.grown_box: BodyBox | None = None
        self._checked = False  # whether the prior was checked against what is seen yet
        self._window = _Window()  # near voxels, for learning the body (min_travel_m)
        self._outside = _Window()  # near voxels outside the body box, for growing it
        self._last_xy: np.ndarray | None = None  # where the last sweep entered the windows
        self._learnt = np.zeros(0, dtype=np.int64)  # sorted voxel keys

    @property
    def body_box(self) -> BodyBox | None:
        """The box whose points are removed now ("auto": learnt, else the grown prior)."""
        p = self.params
        if p.mode == "box":
            return p.box
        if p.mode == "off":
            return None
        if self.learnt_box is not None:
            return self.learnt_box
        return self.grown_box if self.grown_box is not None else p.prior

    def __call__(self, sweep: LidarSweep) -> LidarSweep:
        """The sweep without the ego vehicle's returns (the same object when nothing is
        removed)."""
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
        box = self.body_box
        sensor = np.asarray(sweep.sensor_to_ego.translation, dtype=np.float64)
        position = np.asarray(sweep.ego_pose.translation[:2], dtype=np.float64)
        growing = self.learnt_box is None and box is not None and self.params.grow_travel_m > 0
        if self._enter(position):
            self._learn(np.unique(near_keys))
            if growing:
                self._grow(np.unique(keys[near & ~box.contains(xyz)]), box, sensor)
        box = self.body_box
        if growing and not self._checked:
            box = self._column(box, sensor)
        drop = box.contains(xyz) if box is not None else np.zeros(len(xyz), dtype=bool)
        if len(self._learnt):
            drop[near] |= np.isin(near_keys, self._learnt)
        return drop

    def _column(self, box: BodyBox, sensor: np.ndarray) -> BodyBox:
        """The prior's footprint (and the sensor's mount) up to above the sensor: the body box
        until the prior has been checked against what is seen. Whatever is right above the
        vehicle is either its own (a roof box, a van's roof) or something it passes under,
        which it saw on the way there; so removing it for the first metres loses nothing."""
        r, w = self.params.mount_reach_m, self.params.column_half_width_m
        return BodyBox(
            min(box.x0, sensor[0] - r),
            min(box.y0, sensor[1] - r, -w),
            box.z0,
            max(box.x1, sensor[0] + r),
            max(box.y1, sensor[1] + r, w),
            max(box.z1, sensor[2] + r),
        )

    def _enter(self, position: np.ndarray) -> bool:
        """Whether this sweep enters the windows: the vehicle moved ``step_m`` since the last one
        that did (standing still proves nothing)."""
        if self._last_xy is None:
            self._last_xy, self._step = position, 0.0
            return True
        step = float(np.hypot(*(position - self._last_xy)))
        if step < self.params.step_m:
            return False
        self._last_xy, self._step = position, step
        return True

    def _learn(self, keys: np.ndarray) -> None:
        """Count this sweep's voxels; after ``min_travel_m`` of path, learn the voxels hit in
        nearly every counted sweep."""
        p, w = self.params, self._window
        w.add(keys, self._step)
        if w.travel < p.min_travel_m:
            return
        fixed = w.fixed(p.hit_fraction)
        w.reset()
        new = np.union1d(self._learnt, fixed)
        if len(new) != len(self._learnt):
            self._learnt = new
            lo, hi = _voxel_bounds(new, p.voxel_m)
            m = p.margin_m
            self.learnt_box = BodyBox(
                lo[0] - m, lo[1] - m, lo[2] - m, hi[0] + m, hi[1] + m, hi[2] + m
            )

    def _grow(self, keys: np.ndarray, box: BodyBox, sensor: np.ndarray) -> None:
        """Count this sweep's voxels outside the body box; every ``grow_travel_m`` of path, the
        fixed ones attached to the prior or to the sensor's mount join the body (the prior
        checked against what is seen)."""
        p, w = self.params, self._outside
        w.add(keys, self._step)
        if w.travel < p.grow_travel_m:
            return
        fixed = w.fixed(p.hit_fraction)
        w.reset()
        self._checked = True
        # The sensor is mounted on the vehicle: whatever reaches up to it is the vehicle too (a
        # van's or a truck's roof lies above the prior, right under the lidar's blind cone). Only
        # around the sensor itself: a column down to the ground would reach past a bumper.
        r = p.mount_reach_m
        mount = (*(sensor - r), *(sensor + r))
        # Anchored on the prior and the mount only, not on what was grown before: a wall that
        # runs parallel to the path looks fixed over a few metres, and must not creep in along
        # a grown edge check after check.
        anchors = [(p.prior or box).as_tuple(), mount]
        attached = _attached(fixed, anchors, p.voxel_m, p.grow_gap_m)
        if len(attached):
            self._learnt = np.union1d(self._learnt, attached)
            lo, hi = _voxel_bounds(attached, p.voxel_m)
            self.grown_box = box.union(lo, hi, p.margin_m)
            logger.info(
                "self-returns: %d voxels fixed in the ego frame beside the body box %s; the "
                "body box is now %s",
                len(attached),
                tuple(round(v, 2) for v in box.as_tuple()),
                tuple(round(v, 2) for v in self.grown_box.as_tuple()),
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
    # One pass over the sweep (it ran as eight numpy passes): each point in the ego frame (rot,
    # trans: sensor_to_ego), whether it is near the sensor (horizontally within max_radius of it,
    # at least min_height up) and then its voxel key.
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
    """The sweep's points in the ego frame ``(n, 3)``, which are near the sensor, and their voxel
    keys (-1: not near)."""
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


def _voxel_ijk(keys: np.ndarray) -> np.ndarray:
    mask = 2**21 - 1
    return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], axis=1) - _OFF


def _voxel_bounds(keys: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    ijk = _voxel_ijk(keys)
    return ijk.min(axis=0) * voxel_m, (ijk.max(axis=0) + 1) * voxel_m


def _attached(
    keys: np.ndarray, anchors: list[tuple[float, ...]], voxel_m: float, gap_m: float
) -> np.ndarray:
    """The voxels of ``keys`` within ``gap_m`` of one of the ``anchors`` boxes (x0, y0, z0, x1,
    y1, z1) or, in a chain, of such a voxel."""
    if len(keys) == 0:
        return keys
    ijk = _voxel_ijk(keys)
    lo, hi = ijk * voxel_m, (ijk + 1) * voxel_m
    joined = np.zeros(len(keys), dtype=bool)
    for a in anchors:
        b = np.asarray(a, dtype=np.float64)
        d = np.maximum(0.0, np.maximum(b[:3] - hi, lo - b[3:]))
        joined |= np.sqrt((d * d).sum(axis=1)) <= gap_m + 1e-9
    reach = 1 + int(math.floor(gap_m / voxel_m + 1e-9))  # voxels apart, along each axis
    while True:
        near = np.abs(ijk[:, None, :] - ijk[joined][None, :, :]).max(axis=2) <= reach
        grown = joined | near.any(axis=1)
        if grown.sum() == joined.sum():
            return keys[joined]
        joined = grown


# --- the pose gate -------------------------------------------------------------------------------


class PoseError(ValueError):
    """An ego pose no map can use (non-finite, absurd, or a jump that never comes back)."""


def _planar(pose: SE3) -> tuple[float, float, float]:
    t = pose.translation
    return float(t[0]), float(t[1]), pose.yaw


def _where(frame: Frame) -> str:
    return f"scene {frame.scene!r} frame {frame.index} (t = {frame.timestamp} us)"


@dataclass(frozen=True)
class PoseLimits:
    """What a vehicle can do between two frames; a pose beyond it is an odometry glitch, not motion.

    A frame whose ego pose moved faster than ``max_speed_mps`` or turned faster than
    ``max_yaw_rate_dps`` since the last accepted frame (each plus a small slack for pose noise)
    is skipped and reported; if no plausible pose comes back within ``max_glitch_s`` the run
    stops with an error naming the time. Positions beyond ``max_position_m`` from the global
    origin are errors (no map frame is that large).
    """

    max_speed_mps: float = 100.0  #: a pose faster than this since the last one is a glitch
    max_yaw_rate_dps: float = 360.0
    slack_m: float = 1.0
    slack_deg: float = 10.0
    max_glitch_s: float = 2.0
    max_position_m: float = MAX_POSE_M

    def __post_init__(self) -> None:
        for name in ("max_speed_mps", "max_yaw_rate_dps", "max_glitch_s", "max_position_m"):
            check_number(self, name, min=0.0, min_open=True)
        for name in ("slack_m", "slack_deg"):
            check_number(self, name, min=0.0)


class PoseGate:
    """Odometry sanity: frames whose ego pose jumped or turned further than a vehicle can since
    the last accepted frame are skipped, counted, logged."""

    def __init__(self, limits: PoseLimits | None = None):
        if limits is None:
            limits = PoseLimits()
        self.limits = limits
        self._last: tuple[int, float, float, float] | None = None  # t_us, x, y, yaw last accepted
        self._glitch_since: int | None = None
        self.n_jumps = 0
        self.n_stale = 0
        self.n_radar_dropped = 0
        self.jumps: list[dict[str, Any]] = []  # the first few, for metrics.json

    def _check_finite(self, pose: SE3, what: str) -> None:
        t = pose.translation
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(pose.rotation)):
            raise PoseError(f"{what}: ego pose is not finite ({t.tolist()})")
        if np.max(np.abs(t)) > self.limits.max_position_m:
            raise PoseError(
                f"{what}: ego pose {t.tolist()} is more than {self.limits.max_position_m:g} m "
                "from the origin; no map frame is that large (check the odometry's units and "
                "frame)"
            )

    def _excess(
        self, dt_s: float, a: tuple[float, float, float], b: tuple[float, float, float]
    ) -> tuple[float, float, bool, bool]:
        """(distance m, turn deg, too far, turned too much) from pose ``a`` to ``b`` in ``dt_s``."""
        lim = self.limits
        dist = math.hypot(b[0] - a[0], b[1] - a[1])
        turn = math.degrees(abs(math.remainder(b[2] - a[2], 2 * math.pi)))
        far = not dist <= lim.max_speed_mps * dt_s + lim.slack_m
        turned = not turn <= lim.max_yaw_rate_dps * dt_s + lim.slack_deg
        return dist, turn, far, turned

    def _plausible(
        self, dt_s: float, a: tuple[float, float, float], b: tuple[float, float, float]
    ) -> bool:
        _, _, far, turned = self._excess(dt_s, a, b)
        return not (far or turned)

    def accept(self, frame: Frame) -> bool:
        """Whether ``frame``'s pose continues the trajectory; raises :class:`PoseError` for
        unusable poses."""
        self._check_finite(frame.ego_pose, _where(frame))
        now = (frame.timestamp, *_planar(frame.ego_pose))
        if self._last is None:
            self._last = now
            return True
        dt = (now[0] - self._last[0]) * 1e-6
        if dt <= 0:
            self.n_stale += 1
            logger.warning(
                "%s: timestamp not after the last mapped frame's; frame skipped", _where(frame)
            )
            return False
        dist, turn, far, turned = self._excess(dt, self._last[1:], now[1:])
        if not (far or turned):
            self._last = now
            self._glitch_since = None
            return True
        self.n_jumps += 1
        if self._glitch_since is None:
            self._glitch_since = self._last[0]
            self._record_jump(frame, dt, dist, turn, far, turned)
        if (frame.timestamp - self._glitch_since) * 1e-6 > self.limits.max_glitch_s:
            raise PoseError(
                f"{_where(frame)}: the ego pose jumped at t = {self._glitch_since} us and has not "
                f"come back within {self.limits.max_glitch_s:g} s; split the scene there or fix "
                "the odometry"
            )
        return False

    def _record_jump(
        self, frame: Frame, dt: float, dist: float, turn: float, far: bool, turned: bool
    ) -> None:
        """Keep the first jump of a glitch (up to 20 in all) and say in the log what was
        implausible: a 180 degree turn within a frame is not a "0.9 m jump"."""
        if len(self.jumps) < 20:
            self.jumps.append(
                {
                    "index": frame.index,
                    "timestamp": frame.timestamp,
                    "jump_m": dist,
                    "turn_deg": turn,
                    "dt_s": dt,
                }
            )
        what = (
            f"turned {turn:.0f} deg" + (f" and jumped {dist:.1f} m" if far else "")
            if turned
            else f"jumped {dist:.1f} m"
        )
        logger.warning(
            "%s: ego pose %s in %.3f s, more than a vehicle can %s; frame skipped",
            _where(frame),
            what,
            dt,
            "turn" if turned and not far else "move",
        )

    def sweep_ok(self, sweep: RadarSweep, frame: Frame) -> bool:
        """Whether a radar sweep's own ego pose is plausible next to its frame's; implausible
        ones are dropped."""
        pose = sweep.ego_pose
        ok = bool(np.all(np.isfinite(pose.translation)))
        if ok:
            dt = abs(frame.timestamp - sweep.timestamp) * 1e-6
            ok = self._plausible(dt, _planar(frame.ego_pose), _planar(pose))
        if not ok:
            self.n_radar_dropped += 1
            logger.warning(
                "%s: radar sweep %s at t = %d us has an implausible ego pose; sweep dropped",
                _where(frame),
                sweep.channel,
                sweep.timestamp,
            )
        return ok

    def counts(self) -> dict[str, int]:
        """Frames and sweeps skipped for their poses."""
        return {
            "frames_pose_jump": self.n_jumps,
            "frames_stale": self.n_stale,
            "radar_sweeps_bad_pose": self.n_radar_dropped,
        }


# --- the three together --------------------------------------------------------------------------


class Preprocessor:
    """What is removed from the frames of one scene before any ISM: the pose gate, the radar
    validity filter and the ego vehicle's own lidar returns, with their counts.

    The mapper and Ev-Net's training both call it, so both see the same detections and the same
    lidar returns. Without a ``pose_gate`` every frame is accepted (training takes the poses as
    given). Use :meth:`clean_frame` for the whole frame, or :meth:`accept`,
    :meth:`radar_sweeps` and :meth:`lidar` one after the other where the lidar is needed only on
    some frames (the mapper cleans the lidar sweep only of the frames it maps, so that the
    self-return filter learns from the same sweeps whatever the frame rate).
    """

    def __init__(
        self,
        self_returns: SelfReturnParams = SelfReturnParams(),
        radar_filter: RadarFilter | None = None,
        pose_gate: PoseGate | None = None,
    ):
        self.radar_filter = radar_filter if radar_filter is not None else RadarFilter()
        if not isinstance(self.radar_filter, RadarFilter):
            raise TypeError(
                f"Preprocessor needs a RadarFilter, got {type(self.radar_filter).__name__}"
            )
        self.self_returns = SelfReturnFilter(self_returns)
        self.poses = pose_gate
        self.n_radar_filtered = 0

    @classmethod
    def from_config(cls, config: Any, gate_poses: bool = True) -> Preprocessor:
        """From any config with ``self_returns`` and ``radar_filter`` (a
        :class:`~evgrid.config.MapperConfig` or a ``TrainConfig``); with ``gate_poses``, the pose
        gate with the config's ``poses`` limits (the defaults if it has none)."""
        gate = PoseGate(getattr(config, "poses", None)) if gate_poses else None
        return cls(config.self_returns, config.radar_filter, gate)

    def accept(self, frame: Frame) -> bool:
        """Whether the frame's ego pose continues the trajectory (the pose gate; True if off)."""
        return self.poses is None or self.poses.accept(frame)

    def radar_sweeps(self, frame: Frame) -> Iterator[RadarSweep]:
        """The frame's radar sweeps with a plausible ego pose, each through the radar validity
        filter (the filter the deep IRM was trained with)."""
        for sweep in frame.radar_sweeps():
            if self.poses is None or self.poses.sweep_ok(sweep, frame):
                sweep, dropped = self.radar_filter(sweep)
                self.n_radar_filtered += dropped
                yield sweep

    def lidar(self, sweep: LidarSweep) -> LidarSweep:
        """The lidar sweep without the ego vehicle's own returns."""
        return self.self_returns(sweep)

    def clean_frame(self, frame: Frame, lidar: bool = True) -> Frame | None:
        """The frame as the ISMs are to see it, or None when the pose gate skips it. ``lidar``:
        whether to clean its lidar sweep too (else it is passed on as it is)."""
        if not self.accept(frame):
            return None
        radar: dict[str, list[RadarSweep]] = {ch: [] for ch in frame.radar}
        for sweep in self.radar_sweeps(frame):
            radar[sweep.channel].append(sweep)
        return replace(
            frame,
            lidar=self.lidar(frame.lidar) if lidar else frame.lidar,
            radar={ch: tuple(s) for ch, s in radar.items()},
        )

    def counts(self) -> dict[str, int]:
        """What was removed and skipped, for metrics.json."""
        return {
            **(self.poses.counts() if self.poses is not None else {}),
            "radar_detections_filtered": self.n_radar_filtered,
            **self.self_returns.counts(),
        }
