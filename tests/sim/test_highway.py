"""The highway world family (evgrid_sim.highway): a dual carriageway with barriers and a
median, traffic and the ego at highway speeds, nothing overlapping."""

from __future__ import annotations

import numpy as np
import pytest

from evgrid_sim import OCC_FREE, OCC_STATIC, SimConfig, WorldConfig, simulate_scene
from evgrid_sim import materials as M
from evgrid_sim.highway import HIGHWAY_TRAFFIC_MPS, build_highway
from evgrid_sim.scene import world_of
from evgrid_sim.world import _aabbs, _ego_boxes, _overlap, _touch

SEEDS = range(4)


def _cfg(duration: float = 6.0, **world) -> SimConfig:
    return SimConfig(duration_s=duration, world=WorldConfig(layout="highway", **world))


@pytest.fixture(scope="module")
def highways():
    return {seed: build_highway(seed, _cfg()) for seed in SEEDS}


def _any_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    ia, ib = np.nonzero(_touch(_aabbs(a)[:, None, :], _aabbs(b)[None, :, :]))
    return bool(len(ia)) and bool(_overlap(a[ia], b[ib]).any())


def test_highway_is_what_a_scene_builds_and_is_seeded(highways):
    w, traj, _, _ = highways[1]
    again, traj2, _ = world_of(1, _cfg())
    assert w.environment == again.environment == "highway"
    np.testing.assert_array_equal(w.boxes, again.boxes)
    np.testing.assert_array_equal(w.movers.p0, again.movers.p0)
    np.testing.assert_array_equal(traj.pose_at(3.0), traj2.pose_at(3.0))
    assert not np.array_equal(w.boxes[:5], highways[2][0].boxes[:5])


def test_cross_section_barriers_and_median(highways):
    """In the ego frame along the drive: barriers left (the median, then the far side's) and
    right (the outer edge) at the cross-section's offsets; nothing static in the ego's lanes."""
    for seed, (w, traj, _, c) in highways.items():
        assert 2 <= c.lanes <= 4 and 3.5 <= c.lane_width <= 3.75
        assert c.barrier_offset > c.edge + c.outer_shoulder
        barrier = w.boxes[w.classes == M.BARRIER]
        for t in (1.0, 3.0, 5.0):
            x, y, yaw = (float(v) for v in traj.pose_at(t))
            d = barrier[:, :2] - [x, y]
            fwd = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
            lat = -d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)
            near = np.abs(fwd) < 8.0
            ego_y = -c.lane_centre(c.ego_lane)  # the ego's lateral place in the cross-section
            right = ego_y + lat[near & (lat < 0)].max()
            left = ego_y + lat[near & (lat > 0)].min()
            assert right == pytest.approx(-c.barrier_offset, abs=0.5), seed
            assert abs(left) <= c.median_half + 0.5, seed  # the median's barrier
        static = w.boxes[(w.boxes[:, 6] < 1.6) & (w.boxes[:, 7] > 0.2)]
        ego = _ego_boxes(traj, np.arange(0.0, 6.0, 0.13), margin=-0.1)
        assert not _any_overlap(ego, static), seed


def test_traffic_and_ego_at_highway_speeds(highways):
    lo, hi = HIGHWAY_TRAFFIC_MPS
    for seed, (w, traj, _, _) in highways.items():
        v = traj.speed_at(np.arange(0.0, 6.0, 0.1))
        # the towns' cruise wobble: +-8 % around a speed drawn from 25-35 m/s
        assert 0.9 * lo <= v.min() and v.max() <= 1.1 * hi, seed
        linear = ~w.movers.follow
        assert linear.sum() >= 10, seed
        assert (w.movers.speed[linear] >= lo).all() and (w.movers.speed[linear] <= hi).all()
        boxes, vel, _ = w.movers.state_at(3.0, traj)
        ego = _ego_boxes(traj, np.array([3.0]), margin=-0.1)
        assert not _any_overlap(boxes, ego), seed
    w, traj, _, _ = build_highway(0, _cfg(highway_speed_mps=(30.0, 30.0)))
    assert traj.speed_at(np.arange(0.0, 6.0, 0.1)).mean() == pytest.approx(30.0, rel=0.09)
    with pytest.raises(ValueError, match="highway_speed_mps"):
        WorldConfig(highway_speed_mps=(50.0, 60.0))


def test_a_highway_scene_has_a_free_road_and_occupied_barriers():
    scene = simulate_scene(2, _cfg(0.5))
    frame = next(iter(scene))
    occ, g = frame.occupancy, scene.config.grid
    n = g.n_cells
    # row = n/2 - x/res, col = n/2 - y/res (ego frame): 5 m ahead in the ego's lane is road
    r, col = int(n / 2 - 5.0 / g.resolution), n // 2
    assert occ[r, col] == OCC_FREE
    assert (occ == OCC_STATIC).any() and frame.lidar.points.shape[0] > 1000
