"""The open-road world family (evgrid_sim.open_road): the held-out family Ev-Net never trains on."""

from __future__ import annotations

import numpy as np

from evgrid.sources import SimSource
from evgrid_sim import SimConfig, WorldConfig
from evgrid_sim.open_road import OPEN_ROAD_SPEED_MPS, _verges
from evgrid_sim.scene import world_of


def _cfg() -> SimConfig:
    return SimConfig(duration_s=4.0, world=WorldConfig(layout="open_road"))


def test_open_road_is_seeded_and_sparse():
    w, traj, city = world_of(3, _cfg())
    again, traj2, _ = world_of(3, _cfg())
    assert w.environment == "open_road"
    np.testing.assert_array_equal(w.boxes, again.boxes)
    np.testing.assert_array_equal(traj.pose_at(2.0), traj2.pose_at(2.0))
    assert not np.array_equal(w.boxes[:3], world_of(4, _cfg())[0].boxes[:3])
    # sparse: a few dozen boxes along a few hundred metres of road, nothing like a town
    assert 0 < len(w.boxes) < 150
    lo, hi = OPEN_ROAD_SPEED_MPS
    v = np.hypot(*np.diff([city.pose_at(1.0)[:2], city.pose_at(2.0)[:2]], axis=0)[0])
    assert lo - 1.0 <= v <= hi + 1.0


def test_verge_objects_stay_off_the_road():
    rows = _verges(np.random.default_rng(0), 3.5, 0.0, 2000.0)
    trunks = rows[rows[:, 5] == 0.0]  # what stands on the ground (not a tree's crown)
    assert len(trunks) > 40
    assert (np.abs(trunks[:, 1]) - np.hypot(trunks[:, 3], trunks[:, 4]) > 3.5).all()


def test_training_never_draws_the_held_out_family():
    # training's source is SimSource.split("train", ...): the default irregular towns
    src = SimSource.split("train", 5)
    assert {src.config(s).world.layout for s in src.seeds} == {"irregular"}
