"""Small synthetic street scans for the ISMs' tests, benchmark and examples (not the simulator).

A straight street in the ego frame of the first pose: building facades on both sides, parked
cars, a truck ahead, poles; all axis-aligned boxes standing on the ground (z = 0). The lidar
is a 32-beam spinning sensor shaped like the nuScenes ``LIDAR_TOP`` (HDL-32E: elevations
-30.67 to +10.67 degrees, about 1085 azimuth steps at 20 Hz, so about 34,000 returns); the
radars are the five nuScenes corner radars, seeing the boxes' footprints in 2-D. Units are
metres, radians where not said otherwise, microseconds for timestamps.
"""

from __future__ import annotations

import math

import numpy as np

from evgrid.data.frame import RADAR_CHANNELS, RADAR_COLUMNS, LidarSweep, RadarSweep
from evgrid.data.mounts import LIDAR_MOUNT, RADAR_MOUNTS
from evgrid.geometry import SE3

__all__ = [
    "street_boxes",
    "LIDAR_TOP_EXTRINSICS",
    "RADAR_EXTRINSICS",
    "cast_lidar",
    "street_lidar_sweep",
    "street_radar_sweeps",
]

#: The nuScenes LIDAR_TOP and radar mountings (the one table in :mod:`evgrid.data.mounts`).
LIDAR_TOP_EXTRINSICS = LIDAR_MOUNT.sensor_to_ego()
RADAR_EXTRINSICS: dict[str, SE3] = {ch: m.sensor_to_ego() for ch, m in RADAR_MOUNTS.items()}


def street_boxes(seed: int = 0) -> np.ndarray:
    """Axis-aligned boxes ``(k, 6)`` = [x0, y0, z0, x1, y1, z1] in metres: a street scene."""
    rng = np.random.default_rng(seed)
    boxes = [
        # facades with gaps (side streets) on both sides
        [-60.0, 7.5, 0.0, -12.0, 20.0, 12.0],
        [-4.0, 7.5, 0.0, 25.0, 20.0, 12.0],
        [31.0, 7.5, 0.0, 90.0, 20.0, 12.0],
        [-60.0, -20.0, 0.0, 5.0, -8.0, 9.0],
        [11.0, -20.0, 0.0, 90.0, -8.0, 9.0],
        # a truck ahead in the lane and an oncoming car
        [17.0, -1.3, 0.0, 24.0, 1.3, 3.5],
        [-14.0, 2.0, 0.0, -9.5, 3.8, 1.5],
    ]
    # parked cars along both kerbs
    for side, yc in ((1, 5.6), (-1, -6.1)):
        x = -30.0 + rng.uniform(0, 3)
        while x < 40.0:
            length = rng.uniform(4.0, 4.8)
            if rng.uniform() < 0.8:
                boxes.append([x, yc - 0.9, 0.0, x + length, yc + 0.9, rng.uniform(1.4, 1.7)])
            x += length + rng.uniform(0.8, 4.0)
    # poles on the pavement
    for x in np.arange(-28.0, 40.0, 9.0):
        for yc in (6.9, -7.4):
            boxes.append([x - 0.12, yc - 0.12, 0.0, x + 0.12, yc + 0.12, 4.0])
    return np.asarray(boxes, dtype=np.float64)


def _ray_boxes(
    origins: np.ndarray, dirs: np.ndarray, boxes: np.ndarray, max_range: float
) -> np.ndarray:
    """Range (m) of the first hit of rays ``origins + t dirs`` (2-D or 3-D) with boxes ``[lo, hi]``
    (and the ground z = 0 in 3-D); inf: none."""
    best = np.full(len(dirs), np.inf)
    if origins.shape[1] == 3:
        dz = dirs[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = np.where(dz < -1e-9, -origins[:, 2] / dz, np.inf)
        best = np.minimum(best, tg)
    d = origins.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
    for b in boxes:
        t0 = (b[:d][None, :] - origins) * inv
        t1 = (b[d : 2 * d][None, :] - origins) * inv
        tn = np.nanmax(np.minimum(t0, t1), axis=1)
        tf = np.nanmin(np.maximum(t0, t1), axis=1)
        hit = (tf >= np.maximum(tn, 0.0)) & (tn > 1e-6)
        best = np.where(hit & (tn < best), tn, best)
    best[best > max_range] = np.inf
    return best


def cast_lidar(
    sensor_to_global: SE3,
    boxes: np.ndarray,
    n_azimuth: int = 1085,
    elevations_deg: np.ndarray | None = None,
    max_range: float = 70.0,
    range_noise: float = 0.02,
    seed: int = 0,
) -> np.ndarray:
    """Spin a 32-beam lidar at ``sensor_to_global`` in a box world: returns ``(n, 5)`` float32
    sensor-frame points."""
    rng = np.random.default_rng(seed)
    if elevations_deg is None:
        elevations_deg = np.linspace(-30.67, 10.67, 32)
    el = np.radians(np.asarray(elevations_deg, dtype=np.float64))
    az = np.arange(n_azimuth) * (2 * math.pi / n_azimuth) + rng.uniform(0, 2 * math.pi / n_azimuth)
    ring, a = np.meshgrid(np.arange(len(el)), az, indexing="ij")
    e = el[ring]
    d_sensor = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(
        -1, 3
    )
    d_world = d_sensor @ sensor_to_global.rotation.T
    o = np.broadcast_to(sensor_to_global.translation, d_world.shape)
    rng_m = _ray_boxes(np.ascontiguousarray(o), d_world, boxes, max_range)
    ok = np.isfinite(rng_m)
    r = rng_m[ok] + rng.normal(0, range_noise, ok.sum())
    pts = d_sensor[ok] * r[:, None]
    out = np.empty((len(pts), 5), dtype=np.float32)
    out[:, :3] = pts
    out[:, 3] = rng.uniform(0, 100, len(pts))
    out[:, 4] = ring.reshape(-1)[ok]
    return out


def street_lidar_sweep(
    ego_pose: SE3 | None = None, seed: int = 0, timestamp: int = 0
) -> LidarSweep:
    """A ~34,000-point 32-beam lidar sweep of :func:`street_boxes` from ``ego_pose`` (default
    identity)."""
    ego_pose = SE3.identity() if ego_pose is None else ego_pose
    pts = cast_lidar(ego_pose @ LIDAR_TOP_EXTRINSICS, street_boxes(seed), seed=seed)
    return LidarSweep(pts, LIDAR_TOP_EXTRINSICS, ego_pose, timestamp)


def _radar_points(r: np.ndarray, az: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Radar detections at range ``r`` and azimuth ``az`` (sensor frame) as nuScenes radar
    records: a random RCS, stationary, unambiguous, few false alarms."""
    pts = np.zeros((len(r), len(RADAR_COLUMNS)), dtype=np.float32)
    pts[:, 0] = r * np.cos(az)
    pts[:, 1] = r * np.sin(az)
    pts[:, 3] = rng.uniform(-5, 20, len(r))
    pts[:, 8] = 1.0  # dyn_prop: stationary
    pts[:, 9] = 3.0  # ambig_state: unambiguous
    pts[:, 11] = 1.0  # pdh0: < 25 % false alarm
    return pts


def street_radar_sweeps(
    n_sweeps: int = 10,
    n_detections: int = 100,
    speed_mps: float = 8.0,
    seed: int = 0,
    fov_deg: float = 120.0,
    max_range: float = 80.0,
) -> tuple[list[RadarSweep], SE3]:
    """The last ``n_sweeps`` sweeps (13 Hz) of each of the 5 radars, ego driving +x; returns
    (sweeps, current ego pose).

    Each sweep has ``n_detections`` detections: box footprints hit by 2-D rays at random
    azimuths in the field of view (range noise 0.15 m, azimuth noise 0.3 degrees), 10 %
    clutter at random ranges.
    """
    rng = np.random.default_rng(seed)
    boxes = street_boxes(seed)
    b2 = boxes[:, [0, 1, 3, 4]]
    dt_us = 76_923
    t_now = 10_000_000
    sweeps: list[RadarSweep] = []
    for ch in RADAR_CHANNELS:
        s2e = RADAR_EXTRINSICS[ch]
        yaw0 = s2e.yaw
        for k in range(n_sweeps - 1, -1, -1):
            t = t_now - k * dt_us - int(rng.integers(0, dt_us // 2))
            ego = SE3.from_quaternion([1, 0, 0, 0], [speed_mps * (t - t_now) * 1e-6, 0.0, 0.0])
            s2g = ego @ s2e
            o = s2g.translation[:2]
            n_clutter = n_detections // 10
            az = rng.uniform(
                -math.radians(fov_deg) / 2, math.radians(fov_deg) / 2, 4 * n_detections
            )
            ga = az + yaw0
            dirs = np.stack([np.cos(ga), np.sin(ga)], axis=1)
            r = _ray_boxes(np.broadcast_to(o, dirs.shape).copy(), dirs, b2, max_range)
            ok = np.flatnonzero(np.isfinite(r))[: n_detections - n_clutter]
            r_det = np.concatenate(
                [r[ok] + rng.normal(0, 0.15, len(ok)), rng.uniform(2.0, max_range, n_clutter)]
            )
            az_det = np.concatenate(
                [
                    az[ok],
                    rng.uniform(-math.radians(fov_deg) / 2, math.radians(fov_deg) / 2, n_clutter),
                ]
            )
            az_det = az_det + rng.normal(0, math.radians(0.3), len(az_det))
            sweeps.append(RadarSweep(_radar_points(r_det, az_det, rng), s2e, ego, t, ch))
    return sweeps, SE3.identity()
