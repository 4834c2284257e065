"""Helpers shared by several test modules."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from evgrid.classes import FREE
from evgrid.data.frame import LidarSweep
from evgrid.data.mounts import LIDAR_MOUNT
from evgrid.evaluate import classify
from evgrid.geometry import SE3
from evgrid.grid import EvidentialMap


def driving_sweeps(
    n: int,
    step_m: float,
    parts: Sequence[np.ndarray],
    rng: np.random.Generator,
    *,
    posts_y_m: float,
    dt_us: int,
) -> Iterator[LidarSweep]:
    """Lidar sweeps of a vehicle driving along x, ``step_m`` and ``dt_us`` apart: fixed ``parts``
    (ego-frame points, ``(n, 3)`` each) and posts every 5 m at ``posts_y_m`` beside the road, with
    1 cm noise, in the nuScenes lidar frame (what the self-return filter must tell apart: the parts
    stay put in the ego frame, the posts slide through it)."""
    s2e = LIDAR_MOUNT.sensor_to_ego()
    for k in range(n):
        x = k * step_m
        posts = np.arange(np.floor(x / 5) * 5 - 10, x + 10, 5.0)
        world = np.column_stack(
            [
                np.repeat(posts - x, 20),
                np.full(20 * len(posts), posts_y_m),
                np.tile(np.linspace(0.4, 1.5, 20), len(posts)),
            ]
        )
        ego = np.concatenate([*parts, world])
        ego = ego + rng.normal(0, 0.01, ego.shape)
        pts = np.column_stack([s2e.inverse().apply(ego), np.zeros((len(ego), 2))])
        pose = SE3(np.eye(3), np.array([x, 0.0, 0.0]))
        yield LidarSweep(pts.astype(np.float32), s2e, pose, k * dt_us)


def free_fraction_near_path(
    m: EvidentialMap, trajectory: Iterable[tuple[float, float, float]], radius_m: float = 10.0
) -> float:
    """Fraction of the map's cells within ``radius_m`` of the driven path (map-frame ``(x, y, yaw)``
    poses) classified free: how much free space a reference map holds around the vehicle."""
    import cv2

    masses, _, r0, c0 = m.to_dense()
    res = m.grid.resolution
    path = np.full(masses.shape[:2], 255, np.uint8)
    for x, y, _ in trajectory:
        rc, cc = m.grid.map_xy_to_cell(x, y)
        i, j = int(rc) - r0, int(cc) - c0
        if 0 <= i < path.shape[0] and 0 <= j < path.shape[1]:
            path[i, j] = 0
    near = cv2.distanceTransform(path, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res <= radius_m
    return float((classify(masses)[near] == FREE).mean())
