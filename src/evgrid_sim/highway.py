"""The highway world family (``WorldConfig.layout = "highway"``; docs/simulator.md#highways).

A dual carriageway along the city frame's x axis: 2-4 lanes each way, a median with a concrete
barrier or a double guardrail (and lamp posts now and then), shoulders, guardrails or concrete
barriers at both outer edges, and beyond them verges with bushes, trees and noise walls. The
whole road is bent by a gentle warp (curve radii of kilometres). The ego drives one lane of the
+x carriageway at ``WorldConfig.highway_speed_mps``; traffic drives every lane at 25-35 m/s (one
speed a lane, so no vehicle runs into the one ahead), and movers that would touch the ego, each
other or a static box are dropped as in the towns.

Everything draws from the scene's own generator (its own stream, not the towns'): the same seed
and configuration give the same highway, byte for byte.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

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

__all__ = ["Carriageway", "HIGHWAY_TRAFFIC_MPS", "build_highway"]

#: Speeds of the traffic on a highway, m/s (one drawn per lane).
HIGHWAY_TRAFFIC_MPS = (25.0, 35.0)
#: Path kept before the start (poses for t < 0), as in the towns, metres.
_PREROLL_M = 60.0
#: Static objects are built this far along the road beyond the driven path, metres.
_REACH_M = 130.0


@dataclass(frozen=True)
class Carriageway:
    """The highway's cross-section in the unwarped city frame (y = 0 the median's centre line,
    the ego's carriageway at y < 0 driving +x). Metres."""

    lanes: int  # per direction
    lane_width: float
    median_half: float  # from the centre line to the inner edge of the inner shoulder
    inner_shoulder: float
    outer_shoulder: float
    barrier_offset: float  # |y| of the outer barriers' centre lines
    median: str  # "concrete" or "guardrail"
    ego_lane: int  # 0 = the innermost lane

    def lane_centre(self, lane: int) -> float:
        """|y| of a lane's centre line."""
        return self.median_half + self.inner_shoulder + (lane + 0.5) * self.lane_width

    @property
    def edge(self) -> float:
        """|y| of the carriageway's outer edge (the outer shoulder starts here)."""
        return self.median_half + self.inner_shoulder + self.lanes * self.lane_width


def _cross_section(rng: np.random.Generator) -> Carriageway:
    lanes = int(rng.choice([2, 3, 4], p=[0.45, 0.4, 0.15]))
    lane_w = float(rng.uniform(3.5, 3.75))
    median_half = float(rng.uniform(0.8, 2.5))
    inner = float(rng.uniform(0.5, 1.0))
    outer = float(rng.uniform(2.5, 3.5))
    c = Carriageway(
        lanes,
        lane_w,
        median_half,
        inner,
        outer,
        0.0,
        "concrete" if rng.random() < 0.6 else "guardrail",
        int(rng.integers(lanes)),
    )
    return replace(c, barrier_offset=c.edge + outer + 0.3)


def _barrier(b: _Builder, x0: float, x1: float, y: float, kind: str) -> None:
    """A barrier along x from x0 to x1 at y: concrete (0.6 m wide, 0.85 m tall) or a guardrail
    (a steel beam 0.45-0.8 m above the ground on posts every 2 m)."""
    if kind == "concrete":
        b.add(0.5 * (x0 + x1), y, 0.0, 0.5 * (x1 - x0), 0.3, 0.0, 0.85, M.BARRIER)
        return
    b.add(0.5 * (x0 + x1), y, 0.0, 0.5 * (x1 - x0), 0.08, 0.45, 0.8, M.BARRIER)
    for x in np.arange(x0 + 1.0, x1, 2.0):
        b.add(float(x), y, 0.0, 0.08, 0.08, 0.0, 0.45, M.POLE)


def _verge(b: _Builder, rng: np.random.Generator, x0: float, x1: float, y0: float, s: float):
    """Beyond an outer barrier at |y| = y0 on side s (+1 left, -1 right): in pieces of 60-200 m,
    a noise wall, a row of bushes and trees, or open ground."""
    x = x0
    while x < x1:
        length = float(rng.uniform(60.0, 200.0))
        r = rng.random()
        if r < 0.25:  # noise wall 2-6 m beyond the barrier
            y = s * (y0 + rng.uniform(2.0, 6.0))
            b.add(x + 0.5 * length, y, 0.0, 0.5 * length, 0.15, 0.0, rng.uniform(3.0, 5.0), M.WALL)
        elif r < 0.75:  # bushes and trees on the embankment
            for _ in range(rng.poisson(length / 12.0)):
                p = np.array([x + rng.uniform(0.0, length), s * (y0 + rng.uniform(3.0, 14.0))])
                if rng.random() < 0.5:
                    _tree(b, rng, p, street=False)
                else:
                    w = rng.uniform(1.0, 3.0)
                    b.add(float(p[0]), float(p[1]), rng.uniform(0, math.pi), w, w * 0.8, 0.0,
                          rng.uniform(0.8, 2.2), M.BUSH)  # fmt: skip
        x += length


def _static(rng: np.random.Generator, c: Carriageway, x0: float, x1: float) -> np.ndarray:
    b = _Builder()
    if c.median == "concrete":
        _barrier(b, x0, x1, 0.0, "concrete")
    else:
        for s in (1.0, -1.0):
            _barrier(b, x0, x1, s * (c.median_half - 0.3), "guardrail")
    if rng.random() < 0.5:  # lamp posts in the median
        gap = float(rng.uniform(40.0, 60.0))
        for x in np.arange(x0 + rng.uniform(0.0, gap), x1, gap):
            b.add(float(x), 0.0, 0.0, 0.12, 0.12, 0.0, 10.0, M.POLE)
    for s in (1.0, -1.0):
        _barrier(b, x0, x1, s * c.barrier_offset, "concrete" if rng.random() < 0.3 else "guardrail")
        _verge(b, rng, x0, x1, c.barrier_offset + 0.3, s)
    return _split_rows(_rows_array(b.rows))


def _traffic(
    town: _Town, movers: _MoverSet, c: Carriageway, x_lo: float, x_hi: float, duration: float
) -> None:
    """Vehicles in every lane of both carriageways at one speed a lane, and a vehicle ahead of
    the ego in its lane now and then."""
    rng, density = town.rng, town.density
    v_lo, v_hi = HIGHWAY_TRAFFIC_MPS
    for d in (1, -1):  # +x: the ego's carriageway (y < 0), -x: the other
        for lane in range(c.lanes):
            speed = float(rng.uniform(v_lo, v_hi))
            y = -d * c.lane_centre(lane)
            # where a vehicle starts so that it is near the drive at some time of the scene
            lo, hi = x_lo - _REACH_M - speed * duration, x_hi + _REACH_M + speed * duration
            n = rng.poisson(density * (hi - lo) / 60.0)
            for x in np.sort(rng.uniform(lo, hi, size=n)):
                end = x + d * speed * duration
                if max(x, end) < x_lo - _REACH_M or min(x, end) > x_hi + _REACH_M:
                    continue
                k, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
                heading = 0.0 if d > 0 else math.pi
                movers.offer(_mover(k, length, width, z0, z1, np.array([x, y]), heading, speed))
    if rng.random() < 0.5 * min(density, 1.0):  # the ego's lane: a vehicle ahead, keeping 1-2 s
        k, length, width, z0, z1 = _vehicle_dims(rng, moving=True)
        gap = float(rng.uniform(30.0, 60.0)) + length / 2
        movers.offer(_mover(k, length, width, z0, z1, np.zeros(2), 0.0, 0.0, follow=True, gap=gap))


def build_highway(
    seed: int, config: SimConfig
) -> tuple[World, Trajectory, Trajectory, Carriageway]:
    """A highway around the ego's drive -> (world, true trajectory (global), the same in the city
    frame, the cross-section)."""
    rng = np.random.default_rng([int(seed), 0x5EED, 0x4A7])
    c = _cross_section(rng)
    lo, hi = config.world.highway_speed_mps
    cruise = float(rng.uniform(lo, hi))
    # a gentle bend across the road's axis: slope at most 0.06, wavelengths 1.2-3 km
    wavelength = float(rng.uniform(1200.0, 3000.0))
    k = 2.0 * math.pi / wavelength
    amp = float(rng.uniform(0.3, 1.0)) * 0.06 / k * (1.0 if rng.random() < 0.5 else -1.0)
    warp = Warp(0.0, 0.0, 0.0, amp, k, float(rng.uniform(0.0, 2.0 * math.pi)))
    need = config.duration_s * cruise * 1.2 + 80.0
    start = np.array([float(rng.uniform(-50.0, 50.0)), -c.lane_centre(c.ego_lane)])
    heading = np.array([1.0, 0.0])
    route = Route([start - heading * _PREROLL_M, start + heading * need], [], [], [], start)
    ego = replace(config.ego, start_at_rest_probability=0.0, stop_probability=0.0)
    traj = build_trajectory(rng, route, ego, cruise, config.duration_s, warp=warp)
    pts = _driven_path(traj, config, warp)
    x0, x1 = float(pts[:, 0].min()) - _REACH_M, float(pts[:, 0].max()) + _REACH_M
    rows = _warp_rows(_static(rng, c, x0, x1), warp)
    static = pack_boxes(
        rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 5], rows[:, 6]
    )
    # the road as a street grid of one street along x (no cross streets)
    e = np.zeros(0)
    y_hw, y_sw = np.array([c.edge]), np.array([c.outer_shoulder])
    streets = StreetGrid(
        "highway", e, e, e, e.astype(bool), np.zeros(1), y_hw, y_sw, np.zeros(1, bool)
    )
    town = _Town(rng, "highway", streets, warp, config.world.traffic_density, pts, TownLayout(warp))
    movers = _MoverSet(traj, config.duration_s, static, warp)
    _traffic(town, movers, c, float(pts[:, 0].min()), float(pts[:, 0].max()), config.duration_s)
    mv = movers.movers()
    tf = _city_to_global(rng, config, traj)
    return _global_world(town, rows, mv, tf), traj.transformed(tf), traj, c
