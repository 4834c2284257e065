"""The deep IRM's guards (evgrid.ism.prior_guard): occupied mass needs radar support, and the
vehicle's own path is never painted occupied by the prior."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.classes import OCCUPIED
from evgrid.config import MapperConfig
from evgrid.data.frame import Frame, LidarSweep, RadarSweep
from evgrid.evaluate import classify
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.ism.prior_guard import (
    _SUPPORT_POOL,
    PriorGuardParams,
    Trail,
    _stamp,
    clear_path,
    driven_cells,
    keep_supported,
)
from evgrid.mapper import OccupancyMapper

GRID = GridSpec(n_cells=128, length_m=19.2)  # 0.15 m cells
OCC = np.array([0.1, 0.7, 0.2], np.float32)


def _cell(grid: GridSpec, x: float, y: float) -> tuple[int, int]:
    r, c = grid.xy_to_cell(np.array([x]), np.array([y]))
    return int(r[0]), int(c[0])


def test_support_keeps_occupied_mass_only_near_a_detection():
    m = np.broadcast_to(OCC, GRID.shape + (3,)).copy()
    out = keep_supported(m, np.array([[5.0, 0.0]]), GRID, 1.0)
    near, far = _cell(GRID, 5.0, 0.5), _cell(GRID, 5.0, 3.0)
    np.testing.assert_array_equal(out[near], OCC)  # 0.5 m from the detection: kept
    np.testing.assert_allclose(out[far], [0.1, 0.0, 0.9])  # 3 m: to unknown, free untouched
    np.testing.assert_allclose(out.sum(-1), 1.0, atol=1e-6)
    assert (keep_supported(m, np.zeros((0, 2)), GRID, 1.0)[..., 1] == 0).all()


def test_path_clears_occupied_mass_within_the_radius_only():
    m = np.broadcast_to(OCC, GRID.shape + (3,)).copy()
    trail = np.array([[-2.0, 0.0], [-1.5, 0.0], [-1.0, 0.0]])
    out = clear_path(m, trail, GRID, 1.0)
    np.testing.assert_allclose(out[_cell(GRID, -1.5, 0.9)], [0.8, 0.0, 0.2])
    np.testing.assert_array_equal(out[_cell(GRID, -1.5, 1.2)], OCC)
    np.testing.assert_array_equal(out[_cell(GRID, 0.5, 0.0)], OCC)  # ahead: not driven yet


def test_trail_memory_is_bounded_however_long_the_drive():
    step = 0.5
    trail = Trail(step_m=step, reach_m=30.0)
    for k in range(20000):  # 40 laps of a 10 m circle, then 1 km straight on
        a = 2 * math.pi * k / 500
        trail.add(SE2(10 * math.cos(a), 10 * math.sin(a), a))
    # every centre kept lies within margin_m of the circle: at most the annulus' area in cells
    assert len(trail.xy) <= 2 * math.pi * 10 * 2 * trail.margin_m / step**2
    for k in range(2000):
        trail.add(SE2(10.0 + 0.5 * k, 0.0, 0.0))
    assert len(trail.xy) <= 30.0 / step + 2 and trail.xy[:, 0].min() >= 1009.5 - 30.0
    ego = trail.in_ego(SE2(1009.5, 0.0, math.pi / 2))
    behind = ego[np.argsort(-trail.xy[:, 0])][2]  # the third cell from the front: 0.75 m back
    # facing +y, the path driven along +x lies to the vehicle's left (ego y > 0)
    np.testing.assert_allclose(behind, [0.25, 0.75], atol=1e-9)


def test_every_point_of_the_path_lies_within_the_margin_of_the_trail_at_any_speed():
    # highway speed at 10 Hz (3.3 m an update), a turn, a crawl: the path between poses counts
    rng = np.random.default_rng(7)
    trail = Trail(step_m=0.25, reach_m=30.0)
    x, y, yaw, poses = 0.0, 0.0, 0.0, []
    for k in range(60):
        yaw += rng.uniform(-0.3, 0.3)
        d = 3.3 if k < 30 else rng.uniform(0.0, 0.4)
        x, y = x + d * math.cos(yaw), y + d * math.sin(yaw)
        poses.append((x, y))
        trail.add(SE2(x, y, yaw))
    p = np.asarray(poses)
    t = np.linspace(0.0, 1.0, 50)[:, None, None]
    path = (p[:-1] + t * (p[1:] - p[:-1])).reshape(-1, 2)
    path = path[np.hypot(*(path - p[-1]).T) <= 30.0 - trail.margin_m]
    d = np.hypot(*(path[:, None, :] - trail.xy[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert d.max() <= trail.margin_m + 1e-9


class _Occupied:
    """A deep IRM that calls every cell occupied, or (``road_ahead``) every cell but the road
    ahead of the vehicle (x > 0, |y| < 2 m), which it calls free: a prior that paints the
    road behind the vehicle and beside it."""

    def __init__(self, road_ahead: bool = False):
        m = np.broadcast_to(OCC, GRID.shape + (3,)).copy()
        if road_ahead:
            x, y = GRID.cell_to_xy(*np.indices(GRID.shape))
            m[(x > 0) & (np.abs(y) < 2.0)] = (0.7, 0.0, 0.3)
        self.masses = m

    def predict(self, sweeps, ego_pose, now_us=None):
        return self.masses.copy()


def _frames(n: int = 25, speed: float = 8.0):
    empty_lidar = np.zeros((0, 5), np.float32)
    for k in range(n):
        t = 100_000 * k
        pose = SE3.from_se2(SE2(speed * 0.1 * k, 0.0, 0.0))
        radar = np.zeros((1, 12), np.float32)
        radar[0, 0:2] = (15.0, 6.0)  # one detection, ahead and to the left
        sweep = RadarSweep(radar, SE3.identity(), pose, t, "RADAR_FRONT")
        lidar = LidarSweep(empty_lidar, SE3.identity(), pose, t)
        yield Frame("straight", k, t, pose, k % 5 == 0, lidar, {"RADAR_FRONT": (sweep,)})


DEEP = ("deep_acc", "deep_replace", "deep_disc")


def _deep_maps(path_m: float | None, deep, x_end: float, speed: float = 8.0):
    """The classes along the path driven (x from 0 to ``x_end``, y = 0; the cells within 0.75 m
    of it) and on a line 5 m beside it, in each deep map."""
    guard = PriorGuardParams(support_m=None, path_m=path_m)
    config = MapperConfig(grid=GRID, maps=DEEP, frame="first_pose", prior_guard=guard)
    mapper = OccupancyMapper(config, deep=deep)
    for f in _frames(speed=speed):
        mapper.process(f)
    x = np.arange(0.0, x_end, 0.05)
    rows, cols = GRID.map_xy_to_cell(x, np.zeros(len(x)))
    side = GRID.map_xy_to_cell(x, np.full(len(x), 5.0))
    r0, c0 = rows.min(), min(cols.min(), side[1].min()) - 6
    out = {}
    for name in DEEP:
        cls = classify(mapper.maps[name].read(r0, c0, rows.max() - r0 + 1, 60)[0])
        path = np.stack([cls[rows - r0, cols - c0 + d] for d in range(-5, 6)])
        out[name] = path, cls[side[0] - r0, side[1] - c0]
    return out


def test_a_prior_painting_the_road_behind_never_paints_the_path_driven():
    guarded = _deep_maps(1.0, _Occupied(road_ahead=True), 16.0)
    plain = _deep_maps(None, _Occupied(road_ahead=True), 16.0)
    for name in DEEP:
        path, beside = guarded[name]
        assert not (path == OCCUPIED).any(), name
        assert (beside == OCCUPIED).all(), name  # the rule does not reach 5 m aside
        assert (plain[name][0] == OCCUPIED).any(), name  # without it, the prior paints the path


@pytest.mark.parametrize("speed", [8.0, 33.0])  # 0.8 m and 3.3 m an update
def test_the_path_painted_ahead_is_cleared_in_every_deep_map_as_the_vehicle_drives_it(speed):
    # A prior calling everything occupied paints the road before the vehicle reaches it, and
    # the guard on the prediction cannot take it back in deep_replace (the trail's free mass is
    # no less unknown, both at m_u_min) nor deep_disc (it discounts the conflicting free mass):
    # the stretch driven at each update is cleared in the deep maps (MapperConfig.prior_guard).
    x_end = 0.1 * speed * 24  # the last pose
    guarded = _deep_maps(1.0, _Occupied(), x_end, speed)
    for name in DEEP:
        assert not (guarded[name][0] == OCCUPIED).any(), name
        assert (guarded[name][1] == OCCUPIED).all(), name  # 5 m aside: not driven


def test_the_default_support_keeps_occupied_mass_only_in_the_detections_support_cell():
    # 0.25 m is below one support cell (4 local cells: 0.6 m on this grid), so only the 4 x 4
    # block of local cells holding the detection keeps its occupied mass
    p = _SUPPORT_POOL
    assert p == 4 and PriorGuardParams().support_m < p * GRID.resolution
    m = np.broadcast_to(OCC, GRID.shape + (3,)).copy()
    r, c = _cell(GRID, 5.0, 0.0)
    out = keep_supported(m, np.array([[5.0, 0.0]]), GRID, PriorGuardParams().support_m)
    kept = out[..., 1] > 0
    block = np.zeros(GRID.shape, bool)
    block[r // p * p : r // p * p + p, c // p * p : c // p * p + p] = True
    np.testing.assert_array_equal(kept, block)
    np.testing.assert_allclose(out[~block], np.broadcast_to([0.1, 0.0, 0.9], ((~block).sum(), 3)))


def test_driven_cells_are_those_within_the_radius_of_the_segment():
    grid = GridSpec(n_cells=64, length_m=6.4)  # 0.1 m cells; map cell (R, C) centre -(R+.5)/10
    r0, c0, mask = driven_cells(grid, (-1.0, -1.0), (-2.0, -1.0), 0.3)
    rows, cols = np.nonzero(mask)
    x, y = grid.map_cell_to_xy(rows + r0, cols + c0)
    # by hand: x from -1.0 to -2.0, y within 0.3 of -1.0 (centres -0.75 .. -1.25), and the
    # caps: beyond the ends, within 0.3 of the end point
    inside = (x <= -1.0) & (x >= -2.0)
    assert np.all(np.abs(y[inside] + 1.0) <= 0.3 + 1e-9)
    assert set(np.round(y[inside], 2)) == {-0.75, -0.85, -0.95, -1.05, -1.15, -1.25}
    caps = ~inside
    d = np.minimum(np.hypot(x + 1.0, y + 1.0), np.hypot(x + 2.0, y + 1.0))
    assert caps.any() and np.all(d[caps] <= 0.3 + 1e-9)
    assert mask.sum() == inside.sum() + caps.sum()
    # a cell just outside the radius beside the segment's middle is not driven
    rr, cc = grid.map_xy_to_cell(np.array([-1.55]), np.array([-1.35]))
    assert not mask[rr[0] - r0, cc[0] - c0]
    # a standing vehicle (a == b): the disc around it
    _, _, disc = driven_cells(grid, (-1.0, -1.0), (-1.0, -1.0), 0.3)
    # centres 0.05, 0.15, 0.25 m from a cell corner along each axis: of the 9 pairs a quadrant,
    # all but (0.25, 0.25) (0.354 m) lie within 0.3 m
    assert disc.sum() == 4 * 8


@pytest.mark.parametrize("step", [0.0, 1e-6, 0.04, 2.5, float("nan"), True])
def test_a_trail_step_outside_5_cm_to_2_m_is_refused_naming_the_value(step):
    with pytest.raises(ValueError, match=r"trail_step_m must be .*got " + re.escape(repr(step))):
        PriorGuardParams(trail_step_m=step)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.integers(-25, 65), st.integers(-25, 65)), max_size=12),
    st.floats(0.0, 20.0),
)
def test_a_stamp_is_the_cells_within_the_radius_of_any_cell_given(points, radius):
    # by the distance to every point, independent of the spans the stamp adds up
    n = 40
    rows = np.array([p[0] for p in points], np.int64)
    cols = np.array([p[1] for p in points], np.int64)
    i, j = np.indices((n, n))
    want = np.zeros((n, n), bool)
    for r, c in points:
        want |= (i - r) ** 2 + (j - c) ** 2 <= radius * radius
    np.testing.assert_array_equal(_stamp(n, rows, cols, radius), want)


def test_the_trails_stretch_is_the_last_step_and_a_jump_only_its_last_reach():
    # the stretch the mapper clears in the deep maps (OccupancyMapper.clear_driven)
    trail = Trail(step_m=0.25, reach_m=30.0)
    trail.add(SE2(1.0, 2.0, 0.0))
    a, b = trail.stretch
    np.testing.assert_array_equal(a, b)  # the first pose: the vehicle standing there
    trail.add(SE2(4.0, 6.0, 0.0))
    np.testing.assert_allclose(np.stack(trail.stretch), [[1.0, 2.0], [4.0, 6.0]])
    trail.add(SE2(4.0, 106.0, 0.0))  # a 100 m gap in the poses
    np.testing.assert_allclose(np.stack(trail.stretch), [[4.0, 76.0], [4.0, 106.0]])
    assert trail.xy[:, 1].min() >= 76.0 - trail.margin_m  # nothing kept before the last reach
