"""The online mapper: the paper's loop, frame by frame (sec. V-VI).

For each frame: keep the radar sweeps (the last N per radar), and at the map update rate compute
each inverse sensor model once in the current ego frame, warp it into the frame of the scene's
first ego pose, and fuse it into every map of Table I. Whatever else a run wants (truth,
convergence, pictures, exports) watches the updates as an observer (:mod:`evgrid.observers`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from evgrid.config import MapperConfig, PoseLimits
from evgrid.data.frame import Frame, RadarSweep
from evgrid.data.sweeps import GapCounter, RadarBuffer
from evgrid.fusion import MapSet
from evgrid.geometry import SE2, SE3
from evgrid.grid import MapWindow, warp_window

__all__ = ["OccupancyMapper", "MapUpdate", "Observer", "PoseGate", "PoseError", "UpdateSchedule"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, eq=False)
class MapUpdate:
    """One map update, as observers see it: the frame, the ego pose in the map, the ISMs and the maps."""

    frame: Frame
    pose: SE2  # ego pose in the first pose's frame (m, rad)
    isms: Mapping[str, np.ndarray]  # local ISM grids (n, n, 3), ego frame
    maps: MapSet

    @property
    def box(self) -> tuple[int, int, int, int]:
        """Map cells ``(r0, c0, h, w)`` that this update could change."""
        return warp_window(self.maps.grid, self.pose)

    @property
    def windows(self) -> dict[str, MapWindow]:
        """The ISMs warped into whole map windows, for observers that want them: computed on
        access (one warp per ISM) from the ISM grids the map set holds, so valid while observers
        handle this update (the maps are not updated from them)."""
        return self.maps.windows(self.pose)


class Observer(Protocol):
    """Anything that watches map updates (truth, scores, GIF, exporters)."""

    def on_update(self, update: MapUpdate) -> None: ...


class OccupancyMapper:
    """The maps of one scene, built online: call :meth:`process` with each :class:`Frame` in time order.

    ``deep`` is a :class:`~evgrid.ism.deep.DeepIrm` (loaded from ``config.checkpoint``, or the
    shipped checkpoint, when the maps need it and none is given). ``extra`` map sets are attached
    to the mapper's (:meth:`evgrid.fusion.MapSet.attach`): rows of the same one-pass update from
    the same ISM grids (the ``m_u_min`` sweep uses them).
    """

    def __init__(
        self,
        config: MapperConfig = MapperConfig(),
        deep: Any = None,
        observers: tuple[Observer, ...] = (),
        extra: tuple[MapSet, ...] = (),
    ):
        self.config = config
        self.maps = MapSet(config.grid, config.fusion, config.maps, config.tile_cells)
        self.extra = tuple(extra)
        for s in self.extra:  # extra rows of the same one-pass update
            self.maps.attach(s)
        self.observers = list(observers)
        self.buffer = RadarBuffer(max(config.radar.n_sweeps, config.image.n_sweeps))
        self.deep = deep
        if deep is None and "deep_irm" in self.maps.required_isms:
            from evgrid.ism.deep import DeepIrm

            self.deep = DeepIrm(
                config.checkpoint, config.grid, config.image, config.threads, config.runtime
            )
        if self.deep is not None:
            from evgrid.data.radar_filter import check_trained_filter

            check_trained_filter(
                config.radar_filter,
                getattr(self.deep, "info", None),
                str(getattr(self.deep, "checkpoint", "the checkpoint")),
            )
        from evgrid.ism.self_returns import SelfReturnFilter

        self.self_returns = SelfReturnFilter(config.self_returns)
        self.lidar_gaps = GapCounter()
        self.n_radar_filtered = 0
        self.poses = PoseGate(config.poses)
        self.schedule = UpdateSchedule(config.update_rate_hz)
        self.first_pose: SE3 | None = None
        self.timings: dict[str, list[float]] = {}
        self.trajectory: list[tuple[float, float, float]] = []
        self.last_isms: dict[str, np.ndarray] = {}
        self.n_frames = 0
        self.n_updates = 0

    def process(self, frame: Frame) -> bool:
        """Take one frame; at the update rate and at keyframes update the maps. Returns whether it did."""
        if not isinstance(frame, Frame):
            raise TypeError(f"process needs a Frame, got {type(frame).__name__}")
        t0 = time.perf_counter()
        self.n_frames += 1
        if not self.poses.accept(frame):  # an odometry glitch: nothing of this frame is mapped
            return False
        self.lidar_gaps.add(frame.timestamp)
        for sweep in frame.radar_sweeps():
            if self.poses.sweep_ok(sweep, frame):
                sweep, dropped = self.config.radar_filter(sweep)  # as in training
                self.n_radar_filtered += dropped
                self.buffer.push(sweep)
        if not self.schedule.due(frame.timestamp, frame.is_keyframe):
            return False
        pose = self.pose_in_map(frame.ego_pose)
        isms = self.local_isms(frame)  # each ISM once, in the current ego frame
        # into the map frame and through every map's update rule (paper Table I), in one pass;
        # the extra map sets are rows of the same pass
        self.maps.update(pose, isms)
        for k, ms in self.maps.last_ms.items():  # "warp": the ISMs checked; "fuse": the pass
            self.timings.setdefault(k, []).append(ms)
        self._time("step_total", t0)
        self.n_updates += 1
        self.last_isms = isms
        self.trajectory.append((pose.x, pose.y, pose.yaw))
        update = MapUpdate(frame, pose, isms, self.maps)
        for obs in self.observers:
            obs.on_update(update)
        return True

    def local_isms(self, frame: Frame) -> dict[str, np.ndarray]:
        """Each ISM the maps need, once, on the local grid of ``frame`` (radar buffer already updated)."""
        from evgrid.ism import ray_ilm, ray_irm

        cfg = self.config
        need = self.maps.required_isms
        out: dict[str, np.ndarray] = {}
        t = time.perf_counter()
        if "ray_ilm" in need:
            lidar = self.self_returns(frame.lidar)  # the vehicle's own returns stop no ray
            out["ray_ilm"] = ray_ilm(lidar, grid=cfg.grid, params=cfg.lidar, threads=cfg.threads)
            t = self._time("ray_ilm", t)
        if "ray_irm" in need:
            out["ray_irm"] = ray_irm(
                self.buffer.sweeps(cfg.radar.n_sweeps),
                frame.ego_pose,
                grid=cfg.grid,
                params=cfg.radar,
                threads=cfg.threads,
            )
            t = self._time("ray_irm", t)
        if "deep_irm" in need:
            # the fast path: pooled input from the detections, Ev-Net, upsampled masses in one pass
            out["deep_irm"] = self.deep.predict(
                self.buffer.sweeps(cfg.image.n_sweeps), frame.ego_pose, frame.timestamp
            )
            t = self._time("deep_irm", t)
        return out

    def pose_in_map(self, ego_pose: SE3) -> SE2:
        """The planar ego pose in the first pose's frame (m, rad)."""
        if self.first_pose is None:
            self.first_pose = ego_pose
        return (self.first_pose.inverse() @ ego_pose).to_se2()

    def timing_summary(self) -> dict[str, float]:
        """Median milliseconds per update of each component."""
        return {k: float(np.median(v)) for k, v in self.timings.items() if v}

    def counts(self) -> dict[str, int]:
        """What the mapper mapped, skipped, filtered and rejected, and why (``counts`` in metrics.json)."""
        return {
            "frames": self.n_frames,
            "updates": self.n_updates,
            **self.poses.counts(),
            "radar_sweeps_duplicate": self.buffer.n_duplicate,
            "radar_sweeps_out_of_order": self.buffer.n_out_of_order,
            "radar_sweeps_missing": self.buffer.n_missing,
            "lidar_frames_missing": self.lidar_gaps.n_missing,
            "radar_detections_filtered": self.n_radar_filtered,
            **self.self_returns.counts(),
            # invalid ISM cells taken as vacuous before the warp, and window cells a rule refused
            **{f"ism_cells_rejected_{k}": v for k, v in self.maps.n_rejected.items()},
            "map_cells_rejected": sum(self.maps.n_rejected_cells.values()),
            "radar_detections_out_of_range": getattr(self.deep, "n_dropped", 0),
        }

    def _time(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings.setdefault(name, []).append((t1 - t0) * 1e3)
        return t1


class UpdateSchedule:
    """Map updates at a rate in Hz on a fixed time grid from the first frame, and at every keyframe.

    Of the frames around each grid time the one nearest to it is mapped (a frame is due once it
    is less than half a frame interval, at most half a period, before the grid time), so sensor rates that do not divide
    the update rate and timestamp jitter keep the rate; after a gap the grid catches up instead of
    bursting.
    """

    def __init__(self, rate_hz: float):
        self.period_us = 1e6 / rate_hz
        self._next_us: float | None = None
        self._last_us: int | None = None

    def due(self, t_us: int, keyframe: bool = False) -> bool:
        """Whether the frame at ``t_us`` is to be mapped."""
        last, self._last_us = self._last_us, t_us
        if self._next_us is None:
            self._next_us = t_us + self.period_us
            return True
        tol = (
            min(0.5 * (t_us - last), 0.5 * self.period_us)
            if last is not None and t_us > last
            else 0.0
        )
        if t_us >= self._next_us - tol:
            while self._next_us - tol <= t_us:
                self._next_us += self.period_us
            return True
        return keyframe


class PoseError(ValueError):
    """An ego pose no map can use (non-finite, absurd, or a jump that never comes back)."""


def _planar(pose: SE3) -> tuple[float, float, float]:
    t = pose.translation
    return float(t[0]), float(t[1]), pose.yaw


def _where(frame: Frame) -> str:
    return f"scene {frame.scene!r} frame {frame.index} (t = {frame.timestamp} us)"


class PoseGate:
    """Odometry sanity: frames whose ego pose jumped further than a vehicle can move are skipped, counted, logged."""

    def __init__(self, limits: PoseLimits = PoseLimits()):
        self.limits = limits
        self._last: tuple[int, float, float, float] | None = (
            None  # t_us, x, y, yaw of the last accepted frame
        )
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
                f"{what}: ego pose {t.tolist()} is more than {self.limits.max_position_m:g} m from the "
                "origin; no map frame is that large (check the odometry's units and frame)"
            )

    def _plausible(
        self, dt_s: float, a: tuple[float, float, float], b: tuple[float, float, float]
    ) -> bool:
        lim = self.limits
        dist = math.hypot(b[0] - a[0], b[1] - a[1])
        dyaw = abs(math.remainder(b[2] - a[2], 2 * math.pi))
        return dist <= lim.max_speed_mps * dt_s + lim.slack_m and dyaw <= math.radians(
            lim.max_yaw_rate_dps * dt_s + lim.slack_deg
        )

    def accept(self, frame: Frame) -> bool:
        """Whether ``frame``'s pose continues the trajectory; raises :class:`PoseError` for unusable poses."""
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
        if self._plausible(dt, self._last[1:], now[1:]):
            self._last = now
            self._glitch_since = None
            return True
        self.n_jumps += 1
        if self._glitch_since is None:
            self._glitch_since = self._last[0]
            step = math.hypot(now[1] - self._last[1], now[2] - self._last[2])
            if len(self.jumps) < 20:
                self.jumps.append(
                    {"index": frame.index, "timestamp": frame.timestamp, "jump_m": step, "dt_s": dt}
                )
            logger.warning(
                "%s: ego pose jumped %.1f m in %.3f s, more than a vehicle can move; frame skipped",
                _where(frame),
                step,
                dt,
            )
        if (frame.timestamp - self._glitch_since) * 1e-6 > self.limits.max_glitch_s:
            raise PoseError(
                f"{_where(frame)}: the ego pose jumped at t = {self._glitch_since} us and has not come back "
                f"within {self.limits.max_glitch_s:g} s; split the scene there or fix the odometry"
            )
        return False

    def sweep_ok(self, sweep: RadarSweep, frame: Frame) -> bool:
        """Whether a radar sweep's own ego pose is plausible next to its frame's; implausible ones are dropped."""
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
