"""evgrid.preprocess: what is removed from a frame before any ISM (pose gate, radar validity
filter, self-returns), in one place for the mapper and for training; the body grown from the
prior so that vehicles other than the nuScenes car leave no trail of their own body."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from evgrid.config import MapperConfig
from evgrid.data.mounts import LIDAR_MOUNT, NUSCENES_CAR, OTHER_VEHICLES
from evgrid.geometry import SE2, SE3
from evgrid.mapper import OccupancyMapper
from evgrid.preprocess import (
    NUSCENES_BODY,
    BodyBox,
    PoseGate,
    Preprocessor,
    RadarFilter,
    SelfReturnFilter,
    SelfReturnParams,
)
from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim.config import LidarConfig

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from rigs_self_returns import occupied_near_path, vehicle_scene  # noqa: E402

from tests.helpers import driving_sweeps  # noqa: E402


@pytest.fixture(scope="module")
def frames():
    return list(simulate_scene(5, SimConfig(duration_s=1.0)))


def test_the_mapper_hands_on_the_pose_gate_of_preprocess():
    from evgrid.mapper import PoseError as MapperPoseError
    from evgrid.mapper import PoseGate as MapperPoseGate
    from evgrid.preprocess import PoseError

    assert MapperPoseGate is PoseGate and MapperPoseError is PoseError


def test_the_vehicle_is_described_once():
    from evgrid_sim.lidar import EGO_BODY_BOXES

    assert NUSCENES_BODY.as_tuple() == NUSCENES_CAR.clearance
    assert np.array_equal(EGO_BODY_BOXES, NUSCENES_CAR.body_boxes)
    assert LIDAR_MOUNT is NUSCENES_CAR.lidar
    with pytest.raises(ValueError, match="'roof' .* is not inside the clearance box"):
        dataclasses.replace(NUSCENES_CAR, parts=(("roof", (0, 0, 0, 1, 1, 2.5)),))


def test_clean_frame_is_what_the_mapper_maps(frames):
    cfg = MapperConfig(maps=("ray_ilm",), radar_filter=RadarFilter("nuscenes"))
    mapper = OccupancyMapper(cfg)
    pre = Preprocessor.from_config(cfg)
    bad = 4
    glitched = [
        dataclasses.replace(f, ego_pose=f.ego_pose @ SE3.from_se2(SE2(500.0, 0.0, 0.0)))
        if f.index == bad
        else f
        for f in frames
    ]
    cleaned = []
    for f in glitched:
        mapper.process(f)
        cleaned.append(pre.clean_frame(f))
    assert cleaned[bad] is None and all(c is not None for i, c in enumerate(cleaned) if i != bad)
    want = {k: v for k, v in mapper.counts().items() if k in pre.counts()}
    assert pre.counts()["radar_detections_filtered"] > 0 and pre.counts()["frames_pose_jump"] == 1
    # the mapper cleans the lidar of the frames it maps only; the rest agrees
    assert {k: v for k, v in pre.counts().items() if "lidar" not in k} == {
        k: v for k, v in want.items() if "lidar" not in k
    }
    c = cleaned[0]
    n_kept = sum(len(s.points) for s in c.radar_sweeps())
    n_all = sum(len(s.points) for s in frames[0].radar_sweeps())
    assert n_kept < n_all and len(c.lidar.points) < len(frames[0].lidar.points)
    assert Preprocessor().clean_frame(frames[1], lidar=False).lidar is frames[1].lidar


def _sweeps(n, step_m, parts, rng):
    """Sweeps of a vehicle driving along x with posts 3.5 m beside the road, one per
    microsecond."""
    return driving_sweeps(n, step_m, parts, rng, posts_y_m=3.5, dt_us=1)


def test_the_prior_grows_by_what_is_attached_not_by_what_drives_beside():
    rng = np.random.default_rng(3)
    # a roof box on the roof, 0.1 m above the prior's top, and a car driving alongside at the
    # same speed 1 m from the body's side for the whole drive
    roof = np.column_stack(
        [rng.uniform(-0.5, 0.5, 200), rng.uniform(-0.5, 0.5, 200), np.full(200, 1.9)]
    )
    beside = np.column_stack(
        [rng.uniform(0.0, 3.0, 200), np.full(200, 2.1 + 1.0), rng.uniform(0.4, 1.4, 200)]
    )
    f = SelfReturnFilter(SelfReturnParams())
    kept = []
    for sweep in _sweeps(12, 0.6, [roof, beside], rng):
        out = f(sweep)
        ego = out.sensor_to_ego.apply(out.points[:, :3].astype(np.float64))
        kept.append((np.abs(ego[:, 2] - 1.9) < 0.05).sum())
    assert f.grown_box is not None and f.grown_box.z1 >= 1.9 > NUSCENES_BODY.z1
    assert f.grown_box.y1 < 2.5  # the car alongside is not the body
    assert kept == [0] * len(kept)  # the roof box never reaches the ray ILM, not even at first
    # the car alongside is never removed
    last = f(next(_sweeps(13, 0.6, [roof, beside], rng)))
    ego = last.sensor_to_ego.apply(last.points[:, :3].astype(np.float64))
    assert ((ego[:, 1] > 2.5) & (ego[:, 1] < 3.5) & (ego[:, 0] < 3.5)).sum() >= 200


def test_standing_still_grows_nothing():
    rng = np.random.default_rng(4)
    roof = np.column_stack(
        [rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.5, 0.5, 50), np.full(50, 1.9)]
    )
    f = SelfReturnFilter(SelfReturnParams())
    for sweep in _sweeps(60, 0.01, [roof], rng):
        f(sweep)
    assert f.grown_box is None and f.learnt_box is None


@pytest.mark.parametrize("name", ["van", "car with a roof box"])
def test_no_phantom_trail_on_a_short_drive_of_another_vehicle(name):
    vehicle = OTHER_VEHICLES[name]
    cfg = SimConfig(duration_s=3.0, lidar=LidarConfig(self_returns=True))
    counts = {}
    for label, params in (
        ("before", SelfReturnParams(grow_travel_m=0.0)),
        ("after", SelfReturnParams()),
    ):
        mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm",), self_returns=params))
        for f in vehicle_scene(4, cfg, vehicle):
            mapper.process(f)
        counts[label] = occupied_near_path(mapper)
    assert counts["before"] > 100 and counts["after"] == 0, counts


def test_body_box_of_mode_box_and_off():
    assert SelfReturnFilter(SelfReturnParams(mode="box")).body_box == NUSCENES_BODY
    assert SelfReturnFilter(SelfReturnParams(mode="off")).body_box is None
    box = BodyBox(0, -1, 0, 1, 1, 2)
    assert box.union(np.array([0.5, 0, 0]), np.array([3.0, 0.5, 2.5]), 0.1).as_tuple() == (
        0,
        -1,
        -0.1,
        3.1,
        1,
        2.6,
    )
    with pytest.raises(ValueError, match="grow_travel_m"):
        SelfReturnParams(grow_travel_m=0.1)
