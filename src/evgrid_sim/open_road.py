"""The open-road world family (``WorldConfig.layout = "open_road"``; docs/simulator.md#open-roads).

A held-out family: Ev-Net is never trained on it (training draws the default irregular towns),
so its deep IRM has no street shape to fall back on. A two-lane country road along the city
frame's x axis, 6-7.5 m wide, bent by a gentle warp; no buildings, fences or kerbs, only sparse
objects on the verges 2-25 m beyond the road's edge (a tree, a bush or a pole every 40 m on
average on each side) and now and then oncoming traffic. The ego drives the right-hand lane
(y < 0, +x) at 12-20 m/s.

Everything draws from the scene's own generator (its own stream, not the towns' or the
highway's): the same seed and configuration give the same road, byte for byte.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from evgrid_sim import materials as M
from evgrid_sim.config import SimConfig
from evgrid_sim.raycast import pack_boxes
from evgrid_sim.trajectory import Route, StreetGrid, Trajectory, Warp, build_trajectory
from evgrid_sim.world import (
    TownLayout,
    World,
    _Builder,
    _city_to_global,
    _driven_path,
    _global_world,
    _mover,
    _MoverSet,
    _rows_array,
    _split_rows,
    _Town,
    _tree,
    _vehicle_dims,
    _warp_rows,
)

__all__ = ["OPEN_ROAD_SPEED_MPS", "OPEN_ROAD_OBJECT_SPACING_M", "build_open_road"]

#: The ego's cruise speed on an open road is drawn per scene in this range, m/s.
OPEN_ROAD_SPEED_MPS = (12.0, 20.0)
#: Mean spacing along the road of the objects on each verge, metres.
OPEN_ROAD_OBJECT_SPACING_M = 40.0
#: Verge objects lie this far beyond the road's edge, metres.
_VERGE_M = (2.0, 25.0)
_PREROLL_M = 60.0
_REACH_M = 130.0


def _verges(rng: np.random.Generator, half_width: float, x0: float, x1: float) -> np.ndarray:
    b = _Builder()
    for s in (1.0, -1.0):
        for _ in range(rng.poisson((x1 - x0) / OPEN_ROAD_OBJECT_SPACING_M)):
            p = np.array([rng.uniform(x0, x1), s * (half_width + rng.uniform(*_VERGE_M))])
            r = rng.random()
            if r < 0.5:
                _tree(b, rng, p, street=False)
            elif r < 0.8:
                w = rng.uniform(0.5, 1.5)  # half sizes: a bush ends beyond the edge
                b.add(float(p[0]), float(p[1]), rng.uniform(0, math.pi), w, w * 0.8, 0.0,
                      rng.uniform(0.8, 2.0), M.BUSH)  # fmt: skip
            else:
                b.add(float(p[0]), float(p[1]), 0.0, 0.12, 0.12, 0.0, rng.uniform(5.0, 9.0), M.POLE)
    return _split_rows(_rows_array(b.rows))


def build_open_road(seed: int, config: SimConfig) -> tuple[World, Trajectory, Trajectory]:
    """An open road around the ego's drive -> (world, true trajectory (global), the same in the
    city frame)."""
    rng = np.random.default_rng([int(seed), 0x5EED, 0x0BE7])
    half = float(rng.uniform(3.0, 3.75))  # half the road's width
    cruise = float(rng.uniform(*OPEN_ROAD_SPEED_MPS))
    wavelength = float(rng.uniform(400.0, 1200.0))
    k = 2.0 * math.pi / wavelength
    amp = float(rng.uniform(0.3, 1.0)) * 0.1 / k * (1.0 if rng.random() < 0.5 else -1.0)
    warp = Warp(0.0, 0.0, 0.0, amp, k, float(rng.uniform(0.0, 2.0 * math.pi)))
    need = config.duration_s * cruise * 1.2 + 80.0
    start = np.array([float(rng.uniform(-50.0, 50.0)), -0.5 * half])
    heading = np.array([1.0, 0.0])
    route = Route([start - heading * _PREROLL_M, start + heading * need], [], [], [], start)
    ego = replace(config.ego, start_at_rest_probability=0.0, stop_probability=0.0)
    traj = build_trajectory(rng, route, ego, cruise, config.duration_s, warp=warp)
    pts = _driven_path(traj, config, warp)
    x0, x1 = float(pts[:, 0].min()) - _REACH_M, float(pts[:, 0].max()) + _REACH_M
    rows = _warp_rows(_verges(rng, half, x0, x1), warp)
    static = pack_boxes(
        rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 5], rows[:, 6]
    )
    e = np.zeros(0)
    streets = StreetGrid(
        "open_road", e, e, e, e.astype(bool), np.zeros(1), np.array([half]), np.zeros(1),
        np.zeros(1, bool),
    )  # fmt: skip
    town = _Town(rng, "open_road", streets, warp, config.world.traffic_density, pts,
                 TownLayout(warp))  # fmt: skip
    movers = _MoverSet(traj, config.duration_s, static, warp)
    lo, hi = float(pts[:, 0].min()) - _REACH_M, float(pts[:, 0].max()) + _REACH_M
    speed = float(rng.uniform(12.0, 20.0))  # oncoming traffic, one speed (none run into another)
    span = hi - lo + speed * config.duration_s
    for x in np.sort(rng.uniform(lo, lo + span, size=rng.poisson(span / 300.0))):
        kd, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
        movers.offer(_mover(kd, length, width, z0, z1, np.array([x, 0.5 * half]), math.pi, speed))
    tf = _city_to_global(rng, config, traj)
    return _global_world(town, rows, movers.movers(), tf), traj.transformed(tf), traj
