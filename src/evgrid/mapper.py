"""The online mapper: the paper's loop, frame by frame (sec. V-VI).

For each frame: keep the radar sweeps (the last N per radar), and at the map update rate compute
each inverse sensor model once in the current ego frame, warp it into the map frame (the
recording's fixed frame, or with ``frame="first_pose"`` the scene's first ego pose as in the
paper), and fuse it into every map of Table I. Whatever else a run wants (truth,
convergence, pictures, exports) watches the updates as an observer (:mod:`evgrid.observers`).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from evgrid.config import MapperConfig
from evgrid.data.frame import Frame
from evgrid.data.sweeps import GapCounter, RadarBuffer
from evgrid.fusion import RULES, MapSet
from evgrid.geometry import SE2, SE3
from evgrid.grid import MapWindow, warp_window
from evgrid.ism.prior_guard import (
    Trail,
    clear_path,
    detections_xy,
    driven_cells,
    keep_supported,
)
from evgrid.preprocess import PoseError, PoseGate, Preprocessor
from evgrid.store import TileStore

#: How far (m) the vehicle moves between two looks for tiles to page out.
PAGE_STEP_M = 2.0

__all__ = ["OccupancyMapper", "MapUpdate", "Observer", "PoseGate", "PoseError", "UpdateSchedule"]

logger = logging.getLogger(__name__)


def release_freed_memory() -> None:
    """Give the heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere nothing).

    Tiles are under glibc's mmap threshold once it has grown, so a tile freed stays in the heap
    for the process's next allocations of its size; the large arrays an export makes are
    mmapped afresh, and would come on top of those free pages in the resident memory."""
    import ctypes

    try:
        trim = ctypes.CDLL(None).malloc_trim  # the C library the process runs on
    except (OSError, AttributeError):  # not glibc (musl, macOS, Windows): no malloc_trim
        return
    trim(0)


@dataclass(frozen=True, slots=True, eq=False)
class MapUpdate:
    """One map update, as observers see it: the frame, the ego pose in the map, the ISMs and the
    maps."""

    frame: Frame
    pose: SE2  # ego pose in the map frame (m, rad)
    isms: Mapping[str, np.ndarray]  # local ISM grids (n, n, 3), ego frame
    maps: MapSet

    @property
    def box(self) -> tuple[int, int, int, int]:
        """Map cells ``(r0, c0, h, w)`` that this update could change: its window, grown by
        the navigation map's margin when the set has one (nav reads a neighbourhood)."""
        r0, c0, h, w = warp_window(self.maps.grid, self.pose)
        g = self.maps.reach
        return r0 - g, c0 - g, h + 2 * g, w + 2 * g

    @property
    def windows(self) -> dict[str, MapWindow]:
        """The ISMs warped into whole map windows, for observers that want them: computed on
        access (one warp per ISM) from the ISM grids the map set holds, so valid while observers
        handle this update (the maps are not updated from them)."""
        return self.maps.windows(self.pose)


class Observer(Protocol):
    """Anything that watches map updates (truth, scores, GIF, exporters)."""

    def on_update(self, update: MapUpdate) -> None: ...


def deep_irm(config: MapperConfig) -> Any:
    """The deep IRM of ``config`` (its checkpoint, else the shipped one)."""
    from evgrid.ism.deep import DeepIrm

    return DeepIrm(config.checkpoint, config.grid, config.image, config.threads, config.runtime)


class OccupancyMapper:
    """The maps of one scene, built online: call :meth:`process` with each :class:`Frame` in time
    order.

    ``deep`` is a :class:`~evgrid.ism.deep.DeepIrm` (loaded from ``config.checkpoint``, or the
    shipped checkpoint, when the maps need it and none is given). ``extra`` map sets are attached
    to the mapper's (:meth:`evgrid.fusion.MapSet.attach`): rows of the same one-pass update from
    the same ISM grids (the ``m_u_min`` sweep uses them). ``store``: where tiles farther than
    ``config.store.resident_m`` from the vehicle go (docs/store.md): a
    :class:`~evgrid.store.TileStore` or a folder (a store already there continues), by default
    a temporary folder that :meth:`close` removes.
    """

    def __init__(
        self,
        config: MapperConfig = MapperConfig(),
        deep: Any = None,
        observers: tuple[Observer, ...] = (),
        extra: tuple[MapSet, ...] = (),
        store: TileStore | str | os.PathLike | None = None,
    ):
        self.config = config
        self.maps = MapSet(
            config.grid, config.fusion, config.maps, config.tile_cells, config.dynamic, config.nav
        )
        self.extra = tuple(extra)
        for s in self.extra:  # extra rows of the same one-pass update
            self.maps.attach(s)
        self.observers = list(observers)
        self.buffer = RadarBuffer(max(config.radar.n_sweeps, config.image.n_sweeps))
        self.deep = deep
        if deep is None and "deep_irm" in self.maps.required_isms:
            self.deep = deep_irm(config)
        if self.deep is not None:
            from evgrid.preprocess import check_trained_filter

            check_trained_filter(
                config.radar_filter,
                getattr(self.deep, "info", None),
                str(getattr(self.deep, "checkpoint", "the checkpoint")),
            )
        # the pose gate, the radar validity filter and the self-returns, as in training
        self.preprocess = Preprocessor.from_config(config)
        self.poses: PoseGate = self.preprocess.poses
        self.lidar_gaps = GapCounter()
        self.lidar_frames_missing = 0  # sweeps missing for no reason counted elsewhere
        self._lidar_explained = 0  # sweeps skipped for a known reason since the last frame mapped
        self.schedule = UpdateSchedule(config.update_rate_hz)
        self.first_pose: SE3 | None = None
        self.timings: dict[str, list[float]] = {}
        self.trajectory: list[tuple[float, float, float]] = []
        self.last_isms: dict[str, np.ndarray] = {}
        # the vehicle's path within reach of the local grid: the deep IRM's prior never paints it
        # occupied (MapperConfig.prior_guard.path_m)
        g = config.prior_guard
        self.trail = Trail(
            g.trail_step_m, config.grid.half_extent * math.sqrt(2.0) + (g.path_m or 0)
        )
        # the maps only the deep IRM enters, of this set and the extra ones: where the stretch
        # driven is cleared at each update (clear_driven)
        mapped = {n for s in (self.maps, *self.extra) for n in s.names}
        self._deep_only = tuple(n for n in mapped if RULES[n].isms == ("deep_irm",))
        self._doppler_seen: dict[str, int] = {}  # per radar, the sweep the Doppler cue last used
        self.n_frames = 0
        self.n_updates = 0
        self.n_lidar_at_origin = 0  # lidar points at the sensor origin: no returns, dropped
        self.last_update_us: int | None = None  # the last update's frame time (us)
        # the last update's time (us) and planar position (m): the distance seen since it
        # decides the geometric ISMs' free mass (MapperConfig.evidence)
        self._last_seen: tuple[int, float, float] | None = None
        self.last_step_m: float | None = None  # the metres of new viewpoint of the last update
        # the tile store (docs/store.md): tiles beyond config.store.resident_m go to disk, into
        # ``store`` (a TileStore or its folder), else a temporary folder
        self.store: TileStore | None = None
        self._paged_at: tuple[float, float] | None = None
        if config.store.paging:
            self.store = store if isinstance(store, TileStore) else TileStore(store)
            self.maps.attach_store(self.store)
            reach = (
                self.maps.grid.length_m / math.sqrt(2.0) + self.maps.reach * config.grid.resolution
            )
            if config.store.resident_m < reach:
                logger.warning(
                    "mapper.store.resident_m %g m is less than one update's reach (%.1f m): tiles "
                    "will leave memory and come back at every update (the maps are the same, "
                    "the run slower)",
                    config.store.resident_m,
                    reach,
                )

    def process(self, frame: Frame) -> bool:
        """Take one frame; at the update rate and at keyframes update the maps. Returns whether it
        did."""
        if not isinstance(frame, Frame):
            raise TypeError(f"process needs a Frame, got {type(frame).__name__}")
        t0 = time.perf_counter()
        self.n_frames += 1
        if not self.preprocess.accept(frame):  # an odometry glitch: nothing of it is mapped
            last = self.lidar_gaps.last
            if last is None or frame.timestamp > last:  # not stale: its gap is the pose gate's
                self._lidar_explained += frame.lidar_skipped + 1
            return False
        self._count_lidar_gap(frame)
        for sweep in self.preprocess.radar_sweeps(frame):  # pose-checked and filtered
            self.buffer.push(sweep)
        if not self.schedule.due(frame.timestamp, frame.is_keyframe):
            return False
        pose = self.pose_in_map(frame.ego_pose)
        isms = self.local_isms(frame, *self._travel(frame))  # each ISM once, in the ego frame
        if "deep_irm" in isms:
            isms["deep_irm"] = self.guard_prior(isms["deep_irm"], frame, pose)
        # into the map frame and through every map's update rule (paper Table I), in one pass;
        # the extra map sets are rows of the same pass
        self.maps.update(pose, isms, self.moving_detections())
        self.clear_driven()
        for k, ms in self.maps.last_ms.items():  # "warp": the ISMs checked; "fuse": the pass
            self.timings.setdefault(k, []).append(ms)
        self._time("step_total", t0)
        self.n_updates += 1
        self.last_update_us = frame.timestamp  # the maps' stamp
        self.last_isms = isms
        self.trajectory.append((pose.x, pose.y, pose.yaw))
        update = MapUpdate(frame, pose, isms, self.maps)
        for obs in self.observers:
            obs.on_update(update)
        nav_ms = self.maps.last_ms.get("nav")  # nav computed when an observer read it
        if nav_ms is not None:
            self.timings.setdefault("nav", []).append(nav_ms)
        if self.store is not None:
            self._page_out(pose)
        return True

    def _page_out(self, pose: SE2) -> None:
        """Tiles farther than ``config.store.resident_m`` from the vehicle to the store: the
        maps', and those of observers that keep tiled rasters (``page_out(store, x, y, r)``).
        Looked at each time the vehicle has moved :data:`PAGE_STEP_M` since the last look."""
        last = self._paged_at
        if last is not None and math.hypot(pose.x - last[0], pose.y - last[1]) < PAGE_STEP_M:
            return
        self._paged_at = (pose.x, pose.y)
        t = time.perf_counter()
        r = self.config.store.resident_m
        n = self.maps.page_out(pose.x, pose.y, r)
        for obs in self.observers:
            page = getattr(obs, "page_out", None)
            if page is not None:
                n += page(self.store, pose.x, pose.y, r)
        if n:
            self.timings.setdefault("page_out", []).append((time.perf_counter() - t) * 1e3)

    def page_out_all(self) -> int:
        """Move every tile in memory, of the maps and of the observers that keep tiled rasters,
        to the store (none: nothing to do), and give the memory they held back to the system;
        returns how many moved. For a drive that is over: what reads the maps then (the
        exports' final maps, figures, ``--save-maps``, the scores) reads them tile by tile, so
        its own memory comes on top of the drive's fixed costs only, not of its resident tiles
        too. The maps are unchanged, and an update after it brings back the tiles it writes."""
        if self.store is None:
            return 0
        n = self.maps.page_out(0.0, 0.0, -1.0)  # every tile lies at 0 m or more
        for obs in self.observers:
            page = getattr(obs, "page_out", None)
            if page is not None:
                n += page(self.store, 0.0, 0.0, -1.0)
        self._paged_at = None
        release_freed_memory()
        return n

    def close(self) -> None:
        """Remove the tile store when it is a temporary folder (a run's own folder keeps it)."""
        if self.store is not None:
            self.store.close()

    def local_isms(
        self, frame: Frame, travelled_m: float | None = None, dt_s: float | None = None
    ) -> dict[str, np.ndarray]:
        """Each ISM the maps need, once, on the local grid of ``frame`` (radar buffer already
        updated). ``travelled_m`` and ``dt_s`` since the last update set the geometric ISMs'
        free mass (``config.evidence``); None: the ISMs' own per-look masses."""
        from evgrid.ism import ray_ilm_with_stats, ray_irm

        cfg = self.config
        need = self.maps.required_isms
        lidar_params, radar_params = cfg.lidar, cfg.radar
        if cfg.evidence.mode != "per_look" and travelled_m is not None and dt_s is not None:
            ev = cfg.evidence
            lidar_params = replace(
                lidar_params, m_free=ev.free_mass(lidar_params.m_free, travelled_m, dt_s)
            )
            radar_params = replace(
                radar_params, m_free=ev.free_mass(radar_params.m_free, travelled_m, dt_s)
            )
        out: dict[str, np.ndarray] = {}
        t = time.perf_counter()
        if "ray_ilm" in need:
            lidar = self.preprocess.lidar(frame.lidar)  # the vehicle's own returns stop no ray
            ilm = ray_ilm_with_stats(lidar, grid=cfg.grid, params=lidar_params, threads=cfg.threads)
            self.n_lidar_at_origin += ilm.n_at_origin
            out["ray_ilm"] = ilm.masses
            t = self._time("ray_ilm", t)
        if "ray_irm" in need:
            out["ray_irm"] = ray_irm(
                self.buffer.sweeps(cfg.radar.n_sweeps),
                frame.ego_pose,
                grid=cfg.grid,
                params=radar_params,
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

    def guard_prior(self, masses: np.ndarray, frame: Frame, pose: SE2) -> np.ndarray:
        """The deep IRM's masses with what its prior may not say moved away
        (``config.prior_guard``, :mod:`evgrid.ism.prior_guard`): occupied mass without radar
        support, occupied mass on the vehicle's trail (which takes ``pose`` first). One home
        for both, before the deep masses enter any map."""
        g, grid = self.config.prior_guard, self.config.grid
        if g.path_m is not None:
            self.trail.add(pose)
        if g.off:
            return masses
        t = time.perf_counter()
        if g.support_m is not None:
            xy = detections_xy(self.buffer.sweeps(self.config.image.n_sweeps), frame.ego_pose)
            masses = keep_supported(masses, xy, grid, g.support_m)
        if g.path_m is not None:
            radius = g.path_m + self.trail.margin_m  # the trail's cells stand for the path
            masses = clear_path(masses, self.trail.in_ego(pose), grid, radius)
        self._time("prior_guard", t)
        return masses

    def clear_driven(self) -> None:
        """The stretch of path driven since the last update, within ``prior_guard.path_m``,
        cleared of occupied mass in the maps only the deep IRM enters: what the prior painted
        there before the vehicle arrived (the guard on the prediction keeps it from painting
        the path from then on): the trail's last stretch, which :meth:`guard_prior` added."""
        g = self.config.prior_guard
        if g.path_m is None or not self._deep_only:
            return
        t = time.perf_counter()
        a, b = self.trail.stretch
        r0, c0, mask = driven_cells(self.maps.grid, tuple(a), tuple(b), g.path_m)
        self.maps.clear_occupied(r0, c0, mask, self._deep_only)
        self._time("path_clear", t)

    def _travel(self, frame: Frame) -> tuple[float, float]:
        """Metres travelled (planar) and seconds since the last update; the first update counts
        one update period standing. Keeps the update's step (``last_step_m``)."""
        t = frame.ego_pose.translation
        x, y = float(t[0]), float(t[1])
        if self._last_seen is None:
            travelled, dt = 0.0, 1.0 / self.config.update_rate_hz
        else:
            t0, x0, y0 = self._last_seen
            travelled, dt = float(np.hypot(x - x0, y - y0)), max(frame.timestamp - t0, 0) * 1e-6
        self._last_seen = (frame.timestamp, x, y)
        self.last_step_m = self.config.evidence.step_m(travelled, dt)
        return travelled, dt

    def moving_detections(self) -> np.ndarray | None:
        """The Doppler cue of the dynamic score: ``(k, 5)`` map-frame positions, speeds and radar
        positions of the detections in the newest sweep of each radar faster than the lowest
        ``doppler_mps`` of the map sets updated (this one and those attached: each keeps those
        faster than its own), each sweep once (a sweep already used by an earlier update adds
        nothing); None where no map set has the cue."""
        mps = self.maps.doppler_mps_min
        if mps is None or self.first_pose is None:
            return None
        from evgrid.doppler import moving_detections

        new = [s for s in self.buffer.sweeps(1) if self._doppler_seen.get(s.channel) != s.timestamp]
        for s in new:
            self._doppler_seen[s.channel] = s.timestamp
        to_map = SE3.identity() if self.config.frame == "world" else self.first_pose.inverse()
        return moving_detections(new, to_map, mps)

    def pose_in_map(self, ego_pose: SE3) -> SE2:
        """The planar ego pose in the map frame (m, rad).

        ``config.frame == "world"``: the map frame is the recording's fixed frame, so the pose
        is the ego pose's planar part (x, y, yaw about z), and maps, files and exports need no
        transform; poses up to :data:`evgrid.geometry.MAX_POSE_M` from its origin keep the
        warp's precision in float64 (docs/conventions.md#map-frame). ``"first_pose"``: the
        first ego pose's frame, as in the paper's figures. ``first_pose`` keeps the first
        ego pose in the fixed frame either way.
        """
        if self.first_pose is None:
            self.first_pose = ego_pose
        if self.config.frame == "world":
            return ego_pose.to_se2()
        return (self.first_pose.inverse() @ ego_pose).to_se2()

    def timing_summary(self) -> dict[str, float]:
        """Median milliseconds per update of each component."""
        return {k: float(np.median(v)) for k, v in self.timings.items() if v}

    def counts(self) -> dict[str, int]:
        """What the mapper mapped, skipped, filtered and rejected, and why (``counts`` in
        metrics.json)."""
        return {
            "frames": self.n_frames,
            "updates": self.n_updates,
            **self.poses.counts(),
            "radar_sweeps_duplicate": self.buffer.n_duplicate,
            "radar_sweeps_out_of_order": self.buffer.n_out_of_order,
            "radar_sweeps_missing": self.buffer.n_missing,
            "lidar_frames_missing": self.lidar_frames_missing,
            "lidar_points_at_origin": self.n_lidar_at_origin,
            "radar_detections_filtered": self.preprocess.n_radar_filtered,
            **self.preprocess.self_returns.counts(),
            # invalid ISM cells taken as vacuous before the warp, and window cells a rule refused
            **{f"ism_cells_rejected_{k}": v for k, v in self.maps.n_rejected.items()},
            "map_cells_rejected": sum(self.maps.n_rejected_cells.values()),
            "radar_detections_out_of_range": getattr(self.deep, "n_dropped", 0),
        }

    def _count_lidar_gap(self, frame: Frame) -> None:
        """Count the lidar sweeps missing before ``frame``: the gap since the last frame mapped,
        less the sweeps skipped in it for a known reason (the source's report, the pose gate),
        so that each skipped sweep is counted once, under that reason."""
        missing = self.lidar_gaps.add(frame.timestamp)
        explained = self._lidar_explained + frame.lidar_skipped
        self._lidar_explained = 0
        self.lidar_frames_missing += max(missing - explained, 0)

    def _time(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings.setdefault(name, []).append((t1 - t0) * 1e3)
        return t1


class UpdateSchedule:
    """Map updates at a rate in Hz on a fixed time grid from the first frame, and at every keyframe.

    Of the frames around each grid time the one nearest to it is mapped (a frame is due once it
    is less than half a frame interval, at most half a period, before the grid time), so sensor
    rates that do not divide the update rate and timestamp jitter keep the rate; after a gap the
    grid catches up instead of bursting.
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
