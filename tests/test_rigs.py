"""Real sensor data, correct by default: self-returns, any rig, faulty sweeps, radar validity
fields (docs/rigs.md)."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np
import pytest

from evgrid.config import MapperConfig, RunConfig, from_dict
from evgrid.data import RadarSweep, radar_column
from evgrid.data.frame import LidarSweep
from evgrid.data.mounts import LIDAR_MOUNT, RADAR_MOUNTS
from evgrid.data.sweeps import GapCounter, RadarBuffer
from evgrid.geometry import SE3
from evgrid.ism import ray_ilm
from evgrid.mapper import OccupancyMapper
from evgrid.preprocess import (
    NUSCENES_BODY,
    BodyBox,
    RadarFilter,
    SelfReturnFilter,
    SelfReturnParams,
    check_trained_filter,
    parse_body_box,
)
from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim.config import LidarConfig, SimRadarRig, SweepFaults
from evgrid_sim.lidar import EGO_HIT
from tests.helpers import driving_sweeps, free_fraction_near_path

RIG = SimRadarRig(
    radar_channels=("RADAR_FRONT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT"), radar_rates_hz=(4.0,)
)


def free_near_path(mapper: OccupancyMapper, radius_m: float = 10.0) -> float:
    """Fraction of the ray_ilm map's cells within ``radius_m`` of the driven path that are free."""
    return free_fraction_near_path(mapper.maps["ray_ilm"], mapper.trajectory, radius_m)


# --- self-returns ---------------------------------------------------------------------------------


def _body_points(n: int, rng: np.random.Generator) -> np.ndarray:
    """Returns from a roof rack 0.1 m below the lidar and from the bonnet, in the lidar frame."""
    ego = np.concatenate(
        [
            np.column_stack(
                [
                    rng.uniform(-0.5, 2.4, n),
                    rng.uniform(-0.75, 0.75, n),
                    np.full(n, LIDAR_MOUNT.z - 0.1),
                ]
            ),
            np.column_stack(
                [
                    rng.uniform(2.5, 3.4, n // 4),
                    rng.uniform(-0.8, 0.8, n // 4),
                    np.full(n // 4, 0.95),
                ]
            ),
        ]
    )
    xyz = LIDAR_MOUNT.sensor_to_ego().inverse().apply(ego)
    return np.column_stack([xyz, np.full(len(xyz), 50.0), np.zeros(len(xyz))]).astype(np.float32)


@pytest.mark.parametrize(
    "params", [SelfReturnParams(), SelfReturnParams(mode="box")], ids=["auto", "box"]
)
def test_self_returns_leave_the_ray_ilm_outside_the_body_unchanged(params):
    clean, _ = simulate_scene(
        4, SimConfig(duration_s=1.0, lidar=LidarConfig(self_returns=False))
    ).lidar_sweep(3)
    dirty = LidarSweep(
        np.concatenate([clean.points, _body_points(3000, np.random.default_rng(0))]),
        clean.sensor_to_ego,
        clean.ego_pose,
        clean.timestamp,
    )
    f = SelfReturnFilter(params)
    want = ray_ilm(clean)
    assert np.array_equal(ray_ilm(f(dirty)), want)
    assert f.n_removed == 3000 + 750
    raw = ray_ilm(dirty)  # the paper's ray ILM, literally: the body stops the rays
    assert (raw[..., 0] > 0).mean() < 0.5 * (want[..., 0] > 0).mean()
    off = SelfReturnFilter(SelfReturnParams(mode="off"))
    assert off(dirty) is dirty and off.n_removed == 0


def _moving_sweeps(n: int, step_m: float, body: np.ndarray, rng: np.random.Generator):
    """Sweeps of a vehicle driving along x: fixed body points plus posts every 5 m 2.5 m beside
    the road, 0.1 s apart."""
    return driving_sweeps(n, step_m, [body], rng, posts_y_m=2.5, dt_us=100_000)


def test_auto_learns_the_body_of_a_vehicle_it_was_not_told_about():
    rng = np.random.default_rng(1)
    # a van: a rack from 1.0 m behind to 2.0 m ahead of the lidar, 1.2 m wide each side
    body = np.column_stack(
        [rng.uniform(-0.1, 2.9, 400), rng.uniform(-1.2, 1.2, 400), np.full(400, 1.7)]
    )
    f = SelfReturnFilter(SelfReturnParams(prior=None))
    removed = []
    for sweep in _moving_sweeps(60, 0.6, body, rng):
        out = f(sweep)
        removed.append(len(sweep.points) - len(out.points))
    assert removed[0] == 0  # nothing is known before the vehicle has moved
    assert f.learnt_box is not None
    b = f.learnt_box
    assert (
        b.x0 <= -0.1 and b.x1 >= 2.9 and b.y0 <= -1.2 and b.y1 >= 1.2 and b.y1 < 2.4
    )  # the posts are not the body
    assert removed[-1] == len(body)


def test_auto_learns_nothing_while_standing_still():
    rng = np.random.default_rng(2)
    body = np.column_stack([rng.uniform(0, 2, 100), rng.uniform(-0.5, 0.5, 100), np.full(100, 1.7)])
    f = SelfReturnFilter(SelfReturnParams(prior=None))
    for sweep in _moving_sweeps(100, 0.01, body, rng):
        f(sweep)
    assert f.learnt_box is None and f.n_removed == 0


def test_simulated_lidar_sees_its_own_car():
    sc = simulate_scene(4, SimConfig(duration_s=0.5))
    sweep, hit = sc.lidar_sweep(2)
    body = hit == EGO_HIT
    r = np.hypot(sweep.points[:, 0], sweep.points[:, 1])
    assert 1500 < body.sum() < 8000 and np.all(r[body] < 3.0)
    z = sweep.points[body, 2]
    assert ((z > -0.15) & (z < -0.05)).sum() > 500  # the rack, 0.1 m below the sensor
    ego = sweep.sensor_to_ego.apply(sweep.points[body, :3].astype(np.float64))
    assert NUSCENES_BODY.contains(ego).all()
    # the rest of the sweep is what the lidar sees without the body, less what the body hides
    clean, _ = simulate_scene(
        4, SimConfig(duration_s=0.5, lidar=LidarConfig(self_returns=False))
    ).lidar_sweep(2)
    assert len(clean.points) > (~body).sum()


@pytest.fixture(scope="module")
def rig_maps(tmp_path_factory):
    """A 10 Hz lidar with three 4 Hz radars, with and without self-returns, through the nuScenes
    layout."""
    from evgrid.data.nuscenes import load_nuscenes
    from evgrid.data.nuscenes_format import write_nuscenes

    out = {}
    for sr in (False, True):
        root = tmp_path_factory.mktemp(f"rig{int(sr)}")
        cfg = SimConfig(duration_s=5.0, lidar=LidarConfig(rate_hz=10.0, self_returns=sr), rig=RIG)
        write_nuscenes([simulate_scene(4, cfg)], root, splits={"val": ["sim-000004"]})
        (scene,) = load_nuscenes(root, "v1.0-sim", split="val")
        mapper = OccupancyMapper(
            replace(MapperConfig(), maps=("ray_ilm", "ray_irm"))
        )  # default filters
        for frame in scene:
            mapper.process(frame)
        out[sr] = (scene, mapper)
    return out


def test_rig_with_self_returns_maps_free_space_as_without(rig_maps):
    (_, clean), (scene, dirty) = rig_maps[False], rig_maps[True]
    assert scene.radar_channels == RIG.radar_channels
    assert len(scene) == 50 and scene.stats["radar_sweeps"] == pytest.approx(3 * 4 * 5, abs=3)
    want = free_near_path(clean)
    assert want > 0.3
    assert abs(free_near_path(dirty) - want) <= 0.02
    assert dirty.counts()["lidar_self_returns_removed"] > 1000 * dirty.n_updates
    assert clean.counts()["lidar_self_returns_removed"] == 0


# --- any rig, faulty sweeps -----------------------------------------------------------------------


def test_faulty_rig_maps_and_counts(tmp_path):
    from evgrid.data.nuscenes import load_nuscenes
    from evgrid.data.nuscenes_format import write_nuscenes

    faults = SweepFaults(drop=0.2, duplicate=0.2, reorder=0.3, lidar_drop=0.15, seed=3)
    rig = SimRadarRig(
        radar_channels=("FRONT", "REAR"),
        radar_mounts=("RADAR_FRONT", "RADAR_BACK_LEFT"),
        radar_rates_hz=(20.0, 7.0),
        faults=faults,
    )
    cfg = SimConfig(duration_s=2.5, lidar=LidarConfig(rate_hz=10.0), rig=rig)
    sc = simulate_scene(9, cfg)
    assert len(sc) < 25 and all(sc.is_keyframe(int(i)) for i in sc.keyframe_indices)
    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm", "ray_irm")))
    for frame in sc:
        mapper.process(frame)
    c = mapper.counts()
    assert c["radar_sweeps_duplicate"] > 0 and c["radar_sweeps_out_of_order"] > 0
    assert c["radar_sweeps_missing"] > 0 and c["lidar_frames_missing"] > 0
    assert set(mapper.buffer.channels) == {"FRONT", "REAR"}
    write_nuscenes([sc], tmp_path, splits={"val": [sc.name]})
    (scene,) = load_nuscenes(tmp_path, "v1.0-sim", split="val")
    assert scene.radar_channels == ("FRONT", "REAR")
    s = scene.stats
    assert (
        s["radar_sweeps_duplicate"] > 0
        and s["radar_sweeps_out_of_order"] > 0
        and s["radar_sweeps_missing"] > 0
    )
    assert s["lidar_sweeps_missing"] > 0


def test_simulator_rig_without_faults_is_the_default_scene():
    a = simulate_scene(3, SimConfig(duration_s=0.5))
    b = simulate_scene(3, SimConfig(duration_s=0.5, rig=SimRadarRig(radar_rates_hz=(13.0,))))
    fa, fb = a.frame(4), b.frame(4)
    assert np.array_equal(fa.lidar.points, fb.lidar.points)
    assert all(
        np.array_equal(x.points, y.points) for x, y in zip(fa.radar_sweeps(), fb.radar_sweeps())
    )
    with pytest.raises(ValueError, match="radar mount"):
        SimRadarRig(radar_channels=("X",))


def test_gap_counter_and_buffer_count_missing_sweeps():
    g = GapCounter()
    missing = [g.add(t) for t in (0, 100, 200, 300, 600, 700, 1000)]
    assert missing == [0, 0, 0, 0, 2, 0, 2] and g.n_missing == 4
    # an older stamp counts nothing and does not move the last one back: 1100 is no gap
    assert (g.add(500), g.last, g.add(1100), g.n_missing) == (0, 1000, 0, 4)
    buf = RadarBuffer(3)
    pts = np.zeros((1, 12), np.float32)
    for t in (0, 75_000, 150_000, 225_000, 525_000, 525_000, 450_000):
        buf.push(RadarSweep(pts, SE3.identity(), SE3.identity(), t, "R"))
    assert (buf.n_missing, buf.n_duplicate, buf.n_out_of_order) == (3, 1, 1)


# --- radar validity fields ------------------------------------------------------------------------


def _sweep_with_states() -> RadarSweep:
    pts = np.zeros((6, 12), np.float32)
    pts[:, 0] = 10.0
    pts[:, radar_column("invalid_state")] = [0, 0, 0, 1, 0, 0]
    pts[:, radar_column("dyn_prop")] = [0, 3, 7, 0, 1, 0]
    pts[:, radar_column("ambig_state")] = [3, 3, 3, 3, 3, 2]
    return RadarSweep(
        pts, RADAR_MOUNTS["RADAR_FRONT"].sensor_to_ego(), SE3.identity(), 1, "RADAR_FRONT"
    )


def test_radar_filter_modes():
    s = _sweep_with_states()
    assert RadarFilter()(s) == (s, 0)
    kept, n = RadarFilter.named("nuscenes")(s)
    assert n == 3 and kept.points[:, radar_column("dyn_prop")].tolist() == [0, 3, 1]
    kept, n = RadarFilter("custom", invalid_state=(0,))(s)
    assert n == 1
    assert RadarFilter("custom", invalid_state=(0,)).describe() == "custom(invalid_state=[0])"
    with pytest.raises(ValueError, match="mode"):
        RadarFilter("strict")


def test_radar_filter_applies_in_training_and_mapping():
    from evgrid.learn.train import TrainConfig, scene_samples

    sc = simulate_scene(4, SimConfig(duration_s=0.6))
    frames = list(sc)
    n_all = sum(len(s.points) for f in frames for s in f.radar_sweeps())
    nus = RadarFilter.named("nuscenes")
    n_kept = sum(int(nus.keep(s.points).sum()) for f in frames for s in f.radar_sweeps())
    assert 0 < n_kept < n_all  # the simulator writes plausible validity fields
    dets = {}
    for name in ("none", "nuscenes"):
        cfg = TrainConfig(frame_stride=len(frames) - 1, radar_filter=RadarFilter.named(name))
        dets[name] = [d for d, _, _ in scene_samples(frames, cfg)][-1]
    assert len(dets["nuscenes"]) < len(dets["none"])
    mapper = OccupancyMapper(MapperConfig(maps=("ray_irm",), radar_filter=nus))
    for f in frames:
        mapper.process(f)
    assert mapper.counts()["radar_detections_filtered"] == n_all - n_kept


class _FakeDeep:
    def __init__(self, extra):
        self.info = extra
        self.checkpoint = "fake.safetensors"


def test_mapping_with_another_filter_than_training_warns(caplog):
    trained = {"radar_filter": RadarFilter.named("nuscenes").to_dict()}
    with caplog.at_level(logging.WARNING, logger="evgrid.data.radar_filter"):
        OccupancyMapper(MapperConfig(maps=("deep_acc",)), deep=_FakeDeep(trained))
    assert (
        "'none'" in caplog.text
        and "'nuscenes'" in caplog.text
        and "fake.safetensors" in caplog.text
    )
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="evgrid.data.radar_filter"):
        OccupancyMapper(
            MapperConfig(maps=("deep_acc",), radar_filter=RadarFilter.named("nuscenes")),
            deep=_FakeDeep(trained),
        )
        assert check_trained_filter(
            RadarFilter(), {}
        )  # a checkpoint without a record was trained unfiltered
    assert caplog.text == ""


# --- configs and options --------------------------------------------------------------------------


def test_config_round_trip_with_rig_fields():
    mc = MapperConfig(
        self_returns=SelfReturnParams(mode="box", body=BodyBox(-1, -1, 0, 4, 1, 2), prior=None),
        radar_filter=RadarFilter("custom", invalid_state=(0, 1), ambig_state=(3,)),
    )
    text = json.dumps(RunConfig(mapper=mc).to_dict(), allow_nan=False)
    assert RunConfig.from_dict(json.loads(text)).mapper == mc
    assert (
        from_dict(MapperConfig, json.loads(json.dumps(MapperConfig().to_dict(), allow_nan=False)))
        == MapperConfig()
    )
    sim = SimConfig(
        lidar=LidarConfig(rate_hz=10.0), rig=replace(RIG, faults=SweepFaults(drop=0.1, seed=2))
    )
    assert SimConfig.from_dict(json.loads(json.dumps(sim.to_dict()))) == sim
    assert sim.keyframe_step == 5 and SimConfig().keyframe_step == 10


def test_cli_options_reach_the_mapper_config():
    # the command line's options are overrides of the config (evgrid.cli.options.config_from_args)
    from evgrid.cli.options import config_from_args
    from evgrid_lab.options import SimulateOptions

    def mapper(*args):
        return config_from_args(RunConfig, list(args)).mapper

    cfg = mapper("--self-returns", "off", "--radar-filter", "nuscenes")
    assert cfg.self_returns.mode == "off" and cfg.radar_filter == RadarFilter("nuscenes")
    cfg = mapper("--body-box", "-1,-1,0,5,1,2.5")
    assert cfg.self_returns.mode == "box" and cfg.self_returns.box == parse_body_box(
        "-1,-1,0,5,1,2.5"
    )
    with pytest.raises(ValueError, match="six numbers"):
        parse_body_box("1,2,3")
    sim = SimulateOptions(
        duration=4.0,
        environment="urban",
        lidar_rate=10.0,
        radar_channels="RADAR_FRONT,SIDE=RADAR_FRONT_LEFT",
        radar_rate="4,8",
        ego_returns=False,
        sweep_faults=0.1,
    ).sim_config()
    assert sim.rig.radar_channels == ("RADAR_FRONT", "SIDE") and sim.rig.mounts() == (
        "RADAR_FRONT",
        "RADAR_FRONT_LEFT",
    )
    assert (
        sim.rig.rates(13.0) == (4.0, 8.0)
        and not sim.lidar.self_returns
        and sim.rig.faults.reorder == 0.1
    )


def test_body_hits_hand_computed():
    from evgrid_sim.lidar import body_hits

    box = np.array([[0.0, -1.0, 0.0, 2.0, 1.0, 1.0]])
    dirs = np.array(
        [
            [0.0, 0.0, -1.0],  # straight down onto the top face from 3 m up: 2 m, cos 1
            [1.0, 0.0, 0.0],  # level, above the box: a miss
            [0.6, 0.0, -0.8],  # slanting down onto the top face: 2 / 0.8 = 2.5 m, cos 0.8
            [-1.0, 0.0, 0.0],  # away from the box: a miss
        ]
    )
    t, cos = body_hits(np.array([0.2, 0.0, 3.0]), dirs, box)
    np.testing.assert_allclose(t, [2.0, np.inf, 2.5, np.inf])
    np.testing.assert_allclose(cos, [1.0, 0.0, 0.8, 0.0])
    # from inside a slab, level rays leave through the side faces: the nearer box wins
    t, _ = body_hits(
        np.array([-1.0, 0.0, 0.5]),
        np.array([[1.0, 0.0, 0.0]]),
        np.vstack([box, box + [3, 0, 0, 3, 0, 0]]),
    )
    assert t[0] == 1.0
