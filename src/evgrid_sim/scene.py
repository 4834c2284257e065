"""``simulate_scene``: a seeded, deterministic nuScenes-like scene, generated lazily frame by frame.

Every sweep draws its random numbers from its own generator, seeded by (scene seed, sensor,
sweep index), so any frame can be produced alone, in any order, with the same bytes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from evgrid.data.frame import LIDAR_CHANNEL, RADAR_CHANNELS, Frame, LidarSweep, RadarSweep
from evgrid.data.mounts import LIDAR_MOUNT, RADAR_MOUNTS
from evgrid.geometry import SE2, SE3
from evgrid_sim.config import SimConfig, SweepFaults
from evgrid_sim.highway import build_highway
from evgrid_sim.lidar import LidarModel
from evgrid_sim.open_road import build_open_road
from evgrid_sim.radar import RadarModel
from evgrid_sim.raycast import pack_boxes, rasterize_boxes
from evgrid_sim.trajectory import Trajectory
from evgrid_sim.world import World, generate_world

__all__ = ["SimScene", "simulate_scene", "scene_name", "OCC_FREE", "OCC_STATIC", "OCC_DYNAMIC"]

#: Values of the true occupancy raster (``Frame.occupancy``).
OCC_FREE = 0
OCC_STATIC = 1
OCC_DYNAMIC = 2

_US_PER_DAY = 86_400_000_000
#: Radar sweeps whose labels a scene keeps (about 60 s of six radars at 13 Hz); keeping every
#: sweep's grew with the drive (about 65 MB in 30 minutes).
_LABELS_KEPT = 4096


def scene_name(seed: int) -> str:
    """The name of the simulated scene of a seed (``sim-000042``)."""
    return f"sim-{int(seed):06d}"


def sim_split(seed: int) -> str:
    """Split of a simulated seed: every fifth seed (seed % 5 == 4) is ``val``, the others
    ``train``."""
    return "val" if seed % 5 == 4 else "train"


def world_of(seed: int, config: SimConfig) -> tuple[World, Trajectory, Trajectory]:
    """A scene's world and drive -> (world, true trajectory (global), same in the city frame): a
    town (:func:`~evgrid_sim.world.generate_world`) or, with ``layout = "highway"``, a highway
    (:func:`~evgrid_sim.highway.build_highway`), with ``"open_road"`` an open road
    (:func:`~evgrid_sim.open_road.build_open_road`)."""
    if config.world.layout == "highway":
        return build_highway(seed, config)[:3]
    if config.world.layout == "open_road":
        return build_open_road(seed, config)
    return generate_world(seed, config)


@dataclass(frozen=True, eq=False)
class _Odometry:
    """Odometry with a constant yaw-rate bias and speed scale error, integrated from t = 0."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    scale: float
    bias: float


class SimScene:
    """A simulated scene: a :class:`~evgrid.data.frame.Scene` (name, ``len``, iteration over
    frames) that also exposes the world, the true trajectory and radar ground truth."""

    def __init__(self, seed: int, config: SimConfig = SimConfig()) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        if not isinstance(config, SimConfig):
            raise ValueError(f"config must be a SimConfig, got {type(config).__name__}")
        self.seed = int(seed)
        self.config = config
        self.name = scene_name(self.seed)
        world, traj, _ = world_of(self.seed, config)
        self.world: World = world
        #: The true ego trajectory in the global frame (times in seconds since the first frame).
        self.trajectory: Trajectory = traj
        rng = np.random.default_rng([self.seed, 0x7173])
        self.t0_us = int(config.start_time_us + (self.seed % 10_000) * _US_PER_DAY)
        rig = config.rig
        faults = rig.faults
        # Faults draw from their own generator: a rig without faults gives the same bytes as before.
        frng = np.random.default_rng([self.seed, 0xFA17, faults.seed]) if faults.any else None
        n = config.n_frames
        lidar_period = 1e6 / config.lidar.rate_hz
        all_ts = self.t0_us + np.rint(np.arange(n) * lidar_period).astype(np.int64)
        ids = np.arange(n)
        if frng is not None and faults.lidar_drop > 0:
            lost = (frng.random(n) < faults.lidar_drop) & (ids % config.keyframe_step != 0)
            ids = ids[~lost]
        # : Index of each frame's lidar sweep among all the sweeps the lidar took (missing ones
        # skipped).
        self.lidar_sweep_ids = ids
        #: Timestamps (us) of the lidar sweeps, one frame each.
        self.lidar_timestamps = all_ts[ids]
        t_last = int(all_ts[-1])
        #: Radar channels of the rig, in the rig's order.
        self.radar_channels: tuple[str, ...] = tuple(rig.radar_channels)
        #: Timestamps (us) of each radar's sweeps; the first lies within one period before t0.
        self.radar_timestamps: dict[str, np.ndarray] = {
            ch: self._radar_clock(rng, rate, t_last)
            for ch, rate in zip(self.radar_channels, rig.rates(config.radar.rate_hz))
        }
        # (frame, sweep) of each delivery, as two int64 arrays in delivery order (frames never
        # go back): a frame's sweeps are one slice, found by bisection.
        self._delivery: dict[str, tuple[np.ndarray, np.ndarray]] = {
            ch: self._delivered(ts, faults, frng) for ch, ts in self.radar_timestamps.items()
        }
        self._odo = self._make_odometry(rng)
        self._lidar = LidarModel(config.lidar, LIDAR_MOUNT)
        self._mounts = {ch: RADAR_MOUNTS[m] for ch, m in zip(self.radar_channels, rig.mounts())}
        self._radars = {
            ch: RadarModel(config.radar, self._mounts[ch]) for ch in self.radar_channels
        }
        # The labels of the latest radar sweeps (most recent last); older ones are simulated
        # again when asked for (the same bytes: each sweep has its own generator).
        self._labels: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()

    def _radar_clock(self, rng: np.random.Generator, rate: float, t_last: int) -> np.ndarray:
        """Timestamps (us) of a radar's sweeps at ``rate`` Hz up to ``t_last``, at a phase drawn
        from ``rng``: the first lies within one period before t0."""
        radar_period = 1e6 / rate
        phase = float(rng.uniform(0.0, radar_period))
        first = self.t0_us - radar_period + phase
        m = int(math.floor((t_last - first) / radar_period)) + 1
        ts = np.rint(first + np.arange(m) * radar_period).astype(np.int64)
        return ts[ts <= t_last]

    def _delivered(
        self, ts: np.ndarray, faults: SweepFaults, frng: np.random.Generator | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(frames, sweeps), int64, in delivery order of a radar's sweeps at ``ts``: sweep j goes
        to the first frame whose lidar timestamp is >= its own; faults (drawn from ``frng``)
        drop, repeat or delay some (delivered in this order, frames never going back)."""
        frames = np.searchsorted(self.lidar_timestamps, ts, side="left")
        order = list(range(len(ts)))
        if frng is not None:
            order = _faulty_order(order, faults, frng)
        out: list[tuple[int, int]] = []
        for j in order:
            f = int(frames[j]) if not out else max(int(frames[j]), out[-1][0])
            if f < len(self.lidar_timestamps):
                out.append((f, j))
        pairs = np.array(out, dtype=np.int64).reshape(-1, 2)
        return pairs[:, 0].copy(), pairs[:, 1].copy()

    # --- Scene protocol ---------------------------------------------------------------------
    def __len__(self) -> int:
        return int(len(self.lidar_timestamps))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def __repr__(self) -> str:
        return f"SimScene({self.name!r}, {self.world.environment}, {len(self)} frames)"

    @property
    def description(self) -> str:
        """One line saying what this scene is."""
        env, seconds = self.world.environment, self.config.duration_s
        return f"evgrid simulated {env} scene, seed {self.seed}, {seconds:g} s"

    # --- times and poses --------------------------------------------------------------------
    def seconds(self, timestamp_us: int) -> float:
        """Seconds since the first frame."""
        return (int(timestamp_us) - self.t0_us) * 1e-6

    @property
    def keyframe_indices(self) -> np.ndarray:
        """Frame indices of the keyframes (2 Hz samples)."""
        return np.nonzero(self.lidar_sweep_ids % self.config.keyframe_step == 0)[0]

    def is_keyframe(self, i: int) -> bool:
        """Whether frame ``i`` is a keyframe."""
        return int(self.lidar_sweep_ids[i]) % self.config.keyframe_step == 0

    def _make_odometry(self, rng: np.random.Generator) -> _Odometry | None:
        eg = self.config.ego
        scale = float(rng.normal(0.0, eg.odometry_scale_std)) if eg.odometry_scale_std > 0 else 0.0
        bias = (
            float(np.radians(rng.normal(0.0, eg.odometry_yaw_bias_std_deg_s)))
            if eg.odometry_yaw_bias_std_deg_s > 0
            else 0.0
        )
        if scale == 0.0 and bias == 0.0:
            return None
        dt = 0.005
        t = np.arange(-0.5, self.config.duration_s + 0.5, dt)
        x, y, yaw = self.trajectory.pose_at(t)
        v = self.trajectory.speed_at(t) * (1.0 + scale)
        i0 = int(np.argmin(np.abs(t)))
        yaw_o = yaw + bias * (t - t[i0])
        vx, vy = v * np.cos(yaw_o), v * np.sin(yaw_o)
        # Trapezoid integration outward from t = 0, where odometry equals the true pose.
        cx = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * dt)])
        cy = np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * dt)])
        xo = x[i0] + cx - cx[i0]
        yo = y[i0] + cy - cy[i0]
        return _Odometry(t, xo, yo, yaw_o, scale, bias)

    def true_pose(self, timestamp_us: int) -> SE2:
        """The true ego pose (global frame) at a timestamp (us)."""
        return self.trajectory.se2_at(self.seconds(timestamp_us))

    def odometry_pose(self, timestamp_us: int) -> SE2:
        """The odometry ego pose (what frames report) at a timestamp (us); equals the true pose
        without drift."""
        if self._odo is None:
            return self.true_pose(timestamp_us)
        t = self.seconds(timestamp_us)
        o = self._odo
        yaw = float(np.interp(t, o.t, o.yaw))
        return SE2(
            float(np.interp(t, o.t, o.x)),
            float(np.interp(t, o.t, o.y)),
            math.remainder(yaw, 2 * math.pi),
        )

    def _ego_se3(self, timestamp_us: int) -> SE3:
        return SE3.from_se2(self.odometry_pose(timestamp_us), 0.0)

    # --- sensors ----------------------------------------------------------------------------
    def lidar_sweep(self, i: int) -> tuple[LidarSweep, np.ndarray]:
        """Lidar sweep of frame ``i`` and, per point, what it hit (static box index,
        ``world.n_static + k`` for moving object k, -1 ground)."""
        ts = int(self.lidar_timestamps[i])
        t = self.seconds(ts)
        boxes, _, _ = self.world.movers.state_at(t, self.trajectory)
        x, y, yaw = self.trajectory.pose_at(t)
        rng = np.random.default_rng([self.seed, 1, int(self.lidar_sweep_ids[i])])
        pts, hit = self._lidar.sweep(
            self.world,
            boxes,
            self.world.movers.classes,
            self.world.mover_reflectivity,
            (float(x), float(y), float(yaw)),
            rng,
        )
        sweep = LidarSweep(
            pts, self._lidar.mount.sensor_to_ego(), self._ego_se3(ts), ts, LIDAR_CHANNEL
        )
        return sweep, hit

    def radar_sweep(self, channel: str, j: int) -> tuple[RadarSweep, np.ndarray]:
        """Sweep ``j`` of a radar channel, and its true labels (0 real, 1 clutter, 2 ghost)."""
        if channel not in self._radars:
            raise ValueError(
                f"unknown radar channel {channel!r}; channels are {self.radar_channels}"
            )
        ts = int(self.radar_timestamps[channel][j])
        t = self.seconds(ts)
        w = self.world
        boxes, vel, _ = w.movers.state_at(t, self.trajectory)
        x, y, yaw = self.trajectory.pose_at(t)
        v = float(self.trajectory.speed_at(t))
        _, _, yr = self.trajectory.velocity_at(t)
        if self._odo is None:
            odo = (v, float(yr))
        else:
            odo = (v * (1.0 + self._odo.scale), float(yr) + self._odo.bias)
        k = self.radar_channels.index(channel)
        ci = RADAR_CHANNELS.index(channel) if channel in RADAR_CHANNELS else len(RADAR_CHANNELS) + k
        rng = np.random.default_rng([self.seed, 2, ci, j])
        pts, labels = self._radars[channel].sweep(
            w,
            boxes,
            w.movers.classes,
            vel,
            w.mover_rcs_offset_db,
            (float(x), float(y), float(yaw)),
            (v, float(yr)),
            odo,
            rng,
        )
        self._labels[(channel, j)] = labels
        self._labels.move_to_end((channel, j))
        while len(self._labels) > _LABELS_KEPT:
            self._labels.popitem(last=False)
        return RadarSweep(
            pts, self._mounts[channel].sensor_to_ego(), self._ego_se3(ts), ts, channel
        ), labels

    def radar_sweep_indices(self, i: int) -> dict[str, np.ndarray]:
        """For frame ``i``, the indices of each channel's sweeps delivered with it (oldest first,
        unless the rig's faults repeat or delay some)."""
        out = {}
        for ch, (frames, sweeps) in self._delivery.items():
            lo, hi = np.searchsorted(frames, [i, i + 1], side="left")
            out[ch] = sweeps[lo:hi].copy()
        return out

    def radar_labels(self, channel: str, timestamp_us: int) -> np.ndarray:
        """Ground-truth labels (0 real, 1 clutter, 2 ghost) of the radar sweep at a timestamp."""
        if channel not in self.radar_timestamps:
            raise ValueError(
                f"unknown radar channel {channel!r}; channels are {self.radar_channels}"
            )
        hits = np.nonzero(self.radar_timestamps[channel] == int(timestamp_us))[0]
        if len(hits) == 0:
            raise KeyError(f"no {channel} sweep at timestamp {timestamp_us}")
        j = int(hits[0])
        labels = self._labels.get((channel, j))
        if labels is None:
            _, labels = self.radar_sweep(channel, j)
        return labels

    def occupancy(self, i: int) -> np.ndarray:
        """True occupancy on the local grid of frame ``i``'s true ego pose (uint8: 0 free,
        1 static, 2 moving object). A box counts where its height range meets
        [occupancy_z_min_m, occupancy_z_max_m] above ground; the ego vehicle itself is not in it."""
        cfg = self.config
        grid = cfg.grid
        t = self.seconds(int(self.lidar_timestamps[i]))
        pose = self.trajectory.se2_at(t)
        w = self.world
        dboxes, _, dyaw = w.movers.state_at(t, self.trajectory)
        out = np.zeros(grid.shape, dtype=np.uint8)
        reach = grid.half_extent * math.sqrt(2.0)
        for boxes, yaw, label in ((w.boxes, w.yaw, OCC_STATIC), (dboxes, dyaw, OCC_DYNAMIC)):
            if len(boxes) == 0:
                continue
            rad = boxes[:, 4] + boxes[:, 5]
            dxy = boxes[:, :2] - np.array([pose.x, pose.y])
            sel = (
                (np.hypot(dxy[:, 0], dxy[:, 1]) <= reach + rad)
                & (boxes[:, 6] < cfg.occupancy_z_max_m)
                & (boxes[:, 7] > cfg.occupancy_z_min_m)
            )
            if not sel.any():
                continue
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            lx = c * dxy[sel, 0] + s * dxy[sel, 1]
            ly = -s * dxy[sel, 0] + c * dxy[sel, 1]
            b = boxes[sel]
            local = pack_boxes(lx, ly, yaw[sel] - pose.yaw, b[:, 4], b[:, 5], b[:, 6], b[:, 7])
            rasterize_boxes(
                local, np.full(len(local), label, np.uint8), grid.n_cells, grid.resolution, out
            )
        return out

    def frame(self, i: int) -> Frame:
        """Frame ``i``: its lidar sweep, the radar sweeps since frame ``i - 1``, and on
        keyframes the true occupancy."""
        n = len(self)
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range for a scene of {n} frames")
        lidar, _ = self.lidar_sweep(i)
        radar = {}
        for ch, js in self.radar_sweep_indices(i).items():
            radar[ch] = tuple(self.radar_sweep(ch, int(j))[0] for j in js)
        kf = self.is_keyframe(i)
        return Frame(
            scene=self.name,
            index=i,
            timestamp=int(self.lidar_timestamps[i]),
            ego_pose=lidar.ego_pose,
            is_keyframe=kf,
            lidar=lidar,
            radar=radar,
            occupancy=self.occupancy(i) if kf else None,
        )

    def true_poses(self) -> np.ndarray:
        """True ego poses (x, y, yaw) of every frame, ``(n, 3)``, global frame."""
        t = (self.lidar_timestamps - self.t0_us) * 1e-6
        x, y, yaw = self.trajectory.pose_at(t)
        return np.stack([x, y, np.remainder(yaw + np.pi, 2 * np.pi) - np.pi], axis=1)


def _faulty_order(order: list[int], faults, rng: np.random.Generator) -> list[int]:
    """Sweep indices in delivery order: some dropped, some twice, some after their successor."""
    u = rng.random((len(order), 3))
    out = [j for j in order if u[j, 0] >= faults.drop]
    k = 0
    while k + 1 < len(out):
        if u[out[k], 2] < faults.reorder:
            out[k], out[k + 1] = out[k + 1], out[k]
            k += 2
        else:
            k += 1
    return [j for j in out for _ in range(2 if u[j, 1] < faults.duplicate else 1)]


def simulate_scene(seed: int, config: SimConfig = SimConfig()) -> SimScene:
    """A simulated scene for a seed (non-negative integer); frames are generated lazily."""
    return SimScene(seed, config)
