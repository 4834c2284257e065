"""The driving simulator (evgrid_sim): determinism, the frame contract, sensor statistics,
geometry against the true occupancy, radar physics on hand-made worlds, configuration."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.data import RADAR_CHANNELS, RADAR_COLUMNS, Frame, radar_column
from evgrid.preprocess import NUSCENES_BODY
from evgrid_sim import (
    LIDAR_MOUNT,
    RADAR_CLUTTER,
    RADAR_GHOST,
    RADAR_MOUNTS,
    RADAR_REAL,
    EgoConfig,
    LidarConfig,
    RadarConfig,
    SimConfig,
    WorldConfig,
    simulate_scene,
)
from evgrid_sim import materials as M
from evgrid_sim.lidar import LidarModel
from evgrid_sim.radar import RadarModel
from evgrid_sim.raycast import pack_boxes
from evgrid_sim.store import load_sim_scene, save_sim_scene
from evgrid_sim.world import Movers, World, plan_drive

SHORT = 3.0  # seconds: 60 frames, 6 keyframes, about 39 sweeps a radar


def _cfg(env: str, duration: float = SHORT, **kw) -> SimConfig:
    return SimConfig(duration_s=duration, world=WorldConfig(environment=env), **kw)


@pytest.fixture(scope="module")
def urban():
    scene = simulate_scene(0, _cfg("urban"))
    return scene, list(scene)


@pytest.fixture(scope="module")
def suburban():
    scene = simulate_scene(6, _cfg("suburban"))
    return scene, list(scene)


def _frames_equal(a: Frame, b: Frame) -> None:
    assert a.timestamp == b.timestamp and a.index == b.index and a.is_keyframe == b.is_keyframe
    assert a.lidar.points.tobytes() == b.lidar.points.tobytes()
    assert a.ego_pose.matrix().tobytes() == b.ego_pose.matrix().tobytes()
    for ch in RADAR_CHANNELS:
        assert [s.timestamp for s in a.radar[ch]] == [s.timestamp for s in b.radar[ch]]
        for sa, sb in zip(a.radar[ch], b.radar[ch]):
            assert sa.points.tobytes() == sb.points.tobytes()
            assert sa.ego_pose.matrix().tobytes() == sb.ego_pose.matrix().tobytes()
    if a.occupancy is None:
        assert b.occupancy is None
    else:
        assert a.occupancy.tobytes() == b.occupancy.tobytes()


# --- determinism ----------------------------------------------------------------------------
def test_same_seed_same_bytes_in_any_order():
    cfg = _cfg("mixed", duration=0.6)
    a = list(simulate_scene(11, cfg))
    b = simulate_scene(11, cfg)
    # Random access, out of order: every sweep has its own generator.
    for i in (7, 0, 11, 3):
        _frames_equal(a[i], b.frame(i))
    for fa, fb in zip(a, b):
        _frames_equal(fa, fb)


def test_different_seeds_give_different_scenes():
    cfg = _cfg("urban", duration=0.2)
    a, b = simulate_scene(1, cfg), simulate_scene(2, cfg)
    assert a.world.boxes.shape != b.world.boxes.shape or not np.array_equal(
        a.world.boxes, b.world.boxes
    )
    fa, fb = a.frame(0), b.frame(0)
    assert fa.lidar.points.shape != fb.lidar.points.shape or not np.array_equal(
        fa.lidar.points, fb.lidar.points
    )
    assert not np.allclose(fa.ego_pose.translation, fb.ego_pose.translation)


# --- the frame contract ----------------------------------------------------------------------
def test_frames_follow_the_contract(urban):
    scene, frames = urban
    cfg = scene.config
    assert len(scene) == len(frames) == round(SHORT * cfg.lidar.rate_hz)
    assert scene.name == "sim-000000"
    prev_ts = -math.inf
    n_sweeps = {ch: 0 for ch in RADAR_CHANNELS}
    for i, f in enumerate(frames):
        assert isinstance(f, Frame) and f.index == i and f.scene == scene.name
        if i:
            assert f.timestamp - frames[i - 1].timestamp == 50_000  # 20 Hz in microseconds
        assert f.is_keyframe == (i % 10 == 0)
        if f.is_keyframe:
            assert f.occupancy.shape == cfg.grid.shape and f.occupancy.dtype == np.uint8
            assert set(np.unique(f.occupancy)) <= {0, 1, 2}
        else:
            assert f.occupancy is None
        assert f.lidar.timestamp == f.timestamp and f.lidar.ego_pose is f.ego_pose
        np.testing.assert_allclose(
            f.lidar.sensor_to_ego.matrix(), LIDAR_MOUNT.sensor_to_ego().matrix()
        )
        assert set(f.radar) == set(RADAR_CHANNELS)
        for ch, sweeps in f.radar.items():
            ts = [s.timestamp for s in sweeps]
            assert ts == sorted(ts)
            for s in sweeps:
                # A sweep belongs to the first frame whose lidar timestamp is >= its own.
                assert prev_ts < s.timestamp <= f.timestamp
                assert s.channel == ch
                np.testing.assert_allclose(
                    s.sensor_to_ego.matrix(), RADAR_MOUNTS[ch].sensor_to_ego().matrix()
                )
                pose = scene.odometry_pose(s.timestamp)
                np.testing.assert_allclose(s.ego_pose.translation[:2], [pose.x, pose.y], atol=1e-9)
            n_sweeps[ch] += len(sweeps)
        prev_ts = f.timestamp
    for ch, n in n_sweeps.items():
        assert n == len(scene.radar_timestamps[ch])
        assert abs(n - SHORT * cfg.radar.rate_hz) <= 2  # about 13 Hz


def test_keyframe_occupancy_matches_the_world(urban):
    scene, frames = urban
    g = scene.config.grid
    w = scene.world
    in_band = (w.boxes[:, 6] < 3.0) & (w.boxes[:, 7] > 0.3)
    n_checked = 0
    for i in scene.keyframe_indices:
        f = frames[i]
        t = scene.seconds(f.timestamp)
        pose = scene.trajectory.se2_at(t)
        inv = pose.inverse()
        # Every static box in the height band marks its centre cell (rows = -x, cols = -y).
        xy = inv.apply(w.boxes[in_band, :2])
        r, c = g.xy_to_cell(xy[:, 0], xy[:, 1])
        ok = g.contains_cell(r, c)
        assert (f.occupancy[r[ok], c[ok]] >= 1).all()
        # Every moving object's centre cell is dynamic.
        dboxes, _, _ = w.movers.state_at(t, scene.trajectory)
        if len(dboxes):
            dxy = inv.apply(dboxes[:, :2])
            r, c = g.xy_to_cell(dxy[:, 0], dxy[:, 1])
            ok = g.contains_cell(r, c)
            assert (f.occupancy[r[ok], c[ok]] == 2).all()
            n_checked += int(ok.sum())
        # The ego vehicle's own footprint is free.
        assert (
            f.occupancy[
                g.n_cells // 2 - 10 : g.n_cells // 2, g.n_cells // 2 - 5 : g.n_cells // 2 + 5
            ].max()
            == 0
        )
    assert n_checked > 0


# --- sensor statistics ----------------------------------------------------------------------
def _lidar_vs_truth(scene, frames):
    g = scene.config.grid
    prec, boundary_recall, seen = [], [], []
    for i in scene.keyframe_indices:
        f = frames[i]
        occ = (f.occupancy > 0).astype(np.uint8)
        p = f.lidar.sensor_to_ego.apply(f.lidar.points[:, :3])
        band = (
            (p[:, 2] > 0.3) & (p[:, 2] < 3.0) & ~NUSCENES_BODY.contains(p)
        )  # the ego car is not in the truth
        r, c = g.xy_to_cell(p[band, 0], p[band, 1])
        ok = g.contains_cell(r, c)
        r, c = r[ok], c[ok]
        k3 = np.ones((3, 3), np.uint8)
        prec.append(cv2.dilate(occ, k3)[r, c].mean())
        hit = np.zeros(g.shape, np.uint8)
        hit[r, c] = 1
        boundary = occ & (1 - cv2.erode(occ, k3))
        boundary_recall.append(cv2.dilate(hit, k3)[boundary > 0].mean())
        seen.append(hit[occ > 0].mean())
    return float(np.mean(prec)), float(np.mean(boundary_recall)), float(np.mean(seen))


@pytest.mark.parametrize("which", ["urban", "suburban"])
def test_lidar_statistics(which, request):
    scene, frames = request.getfixturevalue(which)
    counts = np.array([len(f.lidar.points) for f in frames])
    # HDL-32E: 32 x ~1080 firings; most beams return (nuScenes: about 34k points a sweep), but
    # the car's roof hides some of the steepest ones.
    assert 25_000 <= counts.mean() <= 34_560
    pts = np.concatenate([f.lidar.points for f in frames[:5]])
    assert set(np.unique(pts[:, 4])) == set(range(32))
    assert (
        pts[:, 3].min() >= 0 and pts[:, 3].max() <= 255 and np.all(pts[:, 3] == np.rint(pts[:, 3]))
    )
    rng = np.linalg.norm(pts[:, :3], axis=1)
    assert rng.min() >= 0.7 and rng.max() <= 100.2  # 0.8 m blind zone, range noise
    ego = frames[0].lidar.sensor_to_ego.apply(pts[:, :3])
    ego = ego[~NUSCENES_BODY.contains(ego)]  # the car's own returns are neither road nor world
    ground = np.abs(ego[:, 2]) < 0.1
    assert 0.3 < ground.mean() < 0.9  # most downward beams hit the road


@pytest.mark.parametrize("which", ["urban", "suburban"])
def test_lidar_hits_what_is_truly_occupied(which, request):
    scene, frames = request.getfixturevalue(which)
    precision, boundary_recall, seen = _lidar_vs_truth(scene, frames)
    # Points at obstacle heights land on true obstacles (noise and cell edges aside) ...
    assert precision > 0.97
    # ... and see a good part of the obstacles' outlines, the near faces (not the far ones,
    # and not the insides of buildings, which is why `seen` is small).
    assert 0.2 < boundary_recall < 0.9
    assert 0.0 < seen < 0.2


def _radar_stats(scene, frames):
    counts = {ch: [] for ch in RADAR_CHANNELS}
    labels = []
    pts = []
    for f in frames:
        for s in f.radar_sweeps():
            counts[s.channel].append(len(s.points))
            labels.append(scene.radar_labels(s.channel, s.timestamp))
            pts.append(s.points)
    return counts, np.concatenate(labels), np.concatenate(pts)


@pytest.mark.parametrize("which,ghost_range", [("urban", (0.03, 0.25)), ("suburban", (0.0, 0.15))])
def test_radar_statistics(which, ghost_range, request):
    scene, frames = request.getfixturevalue(which)
    counts, labels, pts = _radar_stats(scene, frames)
    for ch, c in counts.items():
        assert 10 <= np.mean(c) <= 80, (ch, np.mean(c))  # tens of detections a sweep
        assert max(c) <= 125  # the ARS 408 cluster list limit
    frac = np.bincount(labels, minlength=3) / len(labels)
    assert frac[RADAR_REAL] > 0.6
    assert 0.03 < frac[RADAR_CLUTTER] < 0.3
    assert ghost_range[0] <= frac[RADAR_GHOST] <= ghost_range[1]
    assert np.all(pts[:, radar_column("z")] == 0.0)  # 2-D radar, as in nuScenes
    rng = np.hypot(pts[:, 0], pts[:, 1])
    assert rng.max() <= RadarConfig().far_range_m + 1.0
    # the field of view (+-60 deg) plus four sigmas of the datasheet's azimuth noise at its edge
    cfg = RadarConfig()
    assert np.all(
        np.abs(np.degrees(np.arctan2(pts[:, 1], pts[:, 0])))
        <= cfg.fov_deg + 4 * cfg.azimuth_noise_edge_deg
    )


def test_radar_validity_fields(urban):
    scene, frames = urban
    _, labels, pts = _radar_stats(scene, frames)
    col = {n: pts[:, radar_column(n)] for n in RADAR_COLUMNS}
    for name, hi in (("dyn_prop", 7), ("ambig_state", 4), ("invalid_state", 17), ("pdh0", 7)):
        v = col[name]
        assert np.all(v == np.rint(v)) and v.min() >= 0 and v.max() <= hi
    valid_states = {0, 4, 8, 9, 10, 11, 12, 15, 16, 17}
    invalid = ~np.isin(col["invalid_state"], list(valid_states))
    # The sensor flags artefacts more often than real targets, but far from always.
    assert invalid[labels == RADAR_REAL].mean() < 0.02
    assert 0.05 < invalid[labels == RADAR_CLUTTER].mean() < 0.8
    assert 0.05 < invalid[labels == RADAR_GHOST].mean() < 0.8
    # Stationary world: most real detections have near-zero compensated radial speed.
    vcomp = np.hypot(col["vx_comp"], col["vy_comp"])
    assert np.mean(vcomp[labels == RADAR_REAL] < 0.5) > 0.7
    moving_flag = np.isin(col["dyn_prop"], [0, 2])
    assert np.all(vcomp[moving_flag] >= 0.39)


# --- physics on hand-made worlds --------------------------------------------------------------
def _world(static: list[tuple], movers: Movers | None = None) -> World:
    """A world of boxes (cx, cy, yaw, length, width, z0, z1, class) in the global frame."""
    return World.from_boxes(static, movers)


def test_lidar_sees_a_wall_at_its_distance():
    world = _world([(20.0, 0.0, 0.0, 1.0, 40.0, 0.0, 30.0, M.BUILDING)])  # face at x = 19.5
    lidar = LidarModel(LidarConfig(range_noise_m=0.0, dropout=0.0))
    pts, hit = lidar.sweep(
        world,
        np.zeros((0, 8)),
        np.zeros(0, np.int32),
        np.zeros(0),
        (0.0, 0.0, 0.0),
        np.random.default_rng(0),
    )
    ego = LIDAR_MOUNT.sensor_to_ego().apply(pts[:, :3])
    on_wall = hit == 0
    assert on_wall.sum() > 1000
    np.testing.assert_allclose(ego[on_wall, 0], 19.5, atol=1e-3)
    ground = hit == -1
    np.testing.assert_allclose(ego[ground, 2], 0.0, atol=1e-3)
    behind = ground & (np.abs(ego[:, 1]) < 15.0)
    assert ego[behind, 0].max() < 19.5  # nothing seen through the wall


_NO_AZIMUTH_NOISE = dict(
    azimuth_noise_deg=0.0,
    azimuth_noise_mid_deg=0.0,
    azimuth_noise_edge_deg=0.0,
    far_azimuth_noise_deg=0.0,
)


def test_radar_doppler_of_static_and_moving_targets():
    world_static = _world([(30.0, 0.0, 0.0, 1.0, 60.0, 0.0, 10.0, M.BUILDING)])
    # A car 15 m ahead driving away at 5 m/s along +x.
    mv = Movers(
        np.array([M.CAR], np.int32),
        np.array([2.2]),
        np.array([0.9]),
        np.array([0.15]),
        np.array([1.5]),
        np.array([[15.0, 0.0]]),
        np.array([0.0]),
        np.array([5.0]),
        np.array([-1e9]),
        np.array([1e9]),
        np.array([False]),
        np.array([0.0]),
        np.array([0.0]),
    )
    world = _world([(30.0, 0.0, 0.0, 1.0, 60.0, 0.0, 10.0, M.BUILDING)], mv)
    cfg = RadarConfig(
        clutter_rate=0.0,
        road_clutter_rate=0.0,
        doppler_noise_mps=0.0,
        range_noise_m=0.0,
        far_range_noise_m=0.0,
        **_NO_AZIMUTH_NOISE,
    )
    radar = RadarModel(cfg, RADAR_MOUNTS["RADAR_FRONT"])
    speed = 10.0
    dboxes, dvel, _ = mv.state_at(0.0, None)
    ci = {n: radar_column(n) for n in RADAR_COLUMNS}
    for k in range(5):
        rng = np.random.default_rng(k)
        pts, lab = radar.sweep(
            world_static,
            np.zeros((0, 8)),
            np.zeros(0, np.int32),
            np.zeros((0, 2)),
            np.zeros(0),
            (0.0, 0.0, 0.0),
            (speed, 0.0),
            (speed, 0.0),
            rng,
        )
        real = lab == RADAR_REAL
        assert real.sum() > 3
        az = np.arctan2(pts[real, 1], pts[real, 0])
        v_raw = pts[real, ci["vx"]] * np.cos(az) + pts[real, ci["vy"]] * np.sin(az)
        # A static target closes at the sensor's speed projected on the line of sight.
        np.testing.assert_allclose(
            v_raw,
            -speed * np.cos(az + math.radians(RADAR_MOUNTS["RADAR_FRONT"].yaw_deg)),
            atol=0.05,
        )
        np.testing.assert_allclose(pts[real, ci["vx_comp"]], 0.0, atol=0.05)
        pts, lab = radar.sweep(
            world,
            dboxes,
            mv.classes,
            dvel,
            np.zeros(1),
            (0.0, 0.0, 0.0),
            (speed, 0.0),
            (speed, 0.0),
            rng,
        )
        on_car = (lab == RADAR_REAL) & (pts[:, 0] < 14.0)
        if on_car.any():
            vc = pts[on_car, ci["vx_comp"]]
            assert np.all((vc > 4.0) & (vc < 5.1))  # the car's 5 m/s along the line of sight
            assert np.all(pts[on_car, ci["dyn_prop"]] == 0)  # moving (away)


def test_multipath_ghosts_appear_behind_the_mirror():
    # A long facade left of the road (face at y = 6) and a truck ahead on the road.
    world = _world(
        [
            (20.0, 11.0, 0.0, 80.0, 10.0, 0.0, 20.0, M.BUILDING),
            (18.0, -1.0, 0.0, 7.0, 2.4, 0.3, 3.0, M.TRUCK),
        ]
    )
    radar = RadarModel(
        RadarConfig(
            clutter_rate=0.0,
            road_clutter_rate=0.0,
            range_noise_m=0.0,
            far_range_noise_m=0.0,
            **_NO_AZIMUTH_NOISE,
        ),
        RADAR_MOUNTS["RADAR_FRONT_LEFT"],
    )
    ghosts = []
    for k in range(40):
        pts, lab = radar.sweep(
            world,
            np.zeros((0, 8)),
            np.zeros(0, np.int32),
            np.zeros((0, 2)),
            np.zeros(0),
            (0.0, 0.0, 0.0),
            (0.0, 0.0),
            (0.0, 0.0),
            np.random.default_rng(k),
        )
        ghosts.append(
            RADAR_MOUNTS["RADAR_FRONT_LEFT"].sensor_to_ego().apply(pts[lab == RADAR_GHOST, :3])
        )
    g = np.concatenate(ghosts)
    assert len(g) >= 5
    # Mirror images of the truck (y in [-2.2, 0.2]) across y = 6 lie in y in [11.8, 14.2].
    assert np.all(g[:, 1] > 6.0)
    assert np.mean((g[:, 1] > 11.0) & (g[:, 1] < 15.0)) > 0.8


# --- trajectory and odometry ------------------------------------------------------------------
def test_ego_drives_like_a_car():
    stops = turns = 0
    for seed in range(6):
        _, _, _, traj = plan_drive(seed, SimConfig(duration_s=20.0))
        t = np.arange(0.0, 20.0, 0.05)
        v = traj.speed_at(t)
        x, y, yaw = traj.pose_at(t)
        step = np.hypot(np.diff(x), np.diff(y)) / 0.05
        np.testing.assert_allclose(step, 0.5 * (v[1:] + v[:-1]), atol=0.3)  # poses and speeds agree
        assert v.max() <= 16.0 and v.min() >= 0.0
        acc = np.diff(v) / 0.05
        assert acc.max() <= 2.5 and acc.min() >= -3.5
        _, _, yr = traj.velocity_at(t)
        assert np.all(np.abs(yr * v) <= 3.0)  # lateral acceleration
        stops += bool(np.any(v[20:] < 0.05))
        turns += bool(np.ptp(yaw) > math.radians(60))
    assert stops >= 1 and turns >= 1


def test_odometry_drift_moves_poses_not_sensors():
    base = _cfg("urban", duration=1.0)
    drift = _cfg(
        "urban",
        duration=1.0,
        ego=EgoConfig(odometry_yaw_bias_std_deg_s=2.0, odometry_scale_std=0.05),
    )
    a, b = simulate_scene(5, base), simulate_scene(5, drift)
    fa, fb = a.frame(19), b.frame(19)
    assert fa.lidar.points.tobytes() == fb.lidar.points.tobytes()  # the world is measured the same
    np.testing.assert_allclose(
        a.frame(0).ego_pose.matrix(), b.frame(0).ego_pose.matrix(), atol=1e-9
    )
    err = np.linalg.norm(fa.ego_pose.translation - fb.ego_pose.translation) + abs(
        fa.ego_pose.yaw - fb.ego_pose.yaw
    )
    assert err > 1e-3
    true = a.true_pose(fa.timestamp)
    np.testing.assert_allclose(
        fa.ego_pose.translation[:2], [true.x, true.y], atol=1e-9
    )  # no drift: odometry = truth


# --- configuration and files --------------------------------------------------------------------
@pytest.mark.parametrize(
    "make,field",
    [
        (lambda: SimConfig(duration_s=-1.0), "duration_s"),
        (lambda: SimConfig(keyframe_every=0), "keyframe_every"),
        (lambda: LidarConfig(n_beams=0), "n_beams"),
        (lambda: LidarConfig(dropout=1.5), "dropout"),
        (lambda: RadarConfig(rate_hz=0.0), "rate_hz"),
        (lambda: RadarConfig(far_fov_deg=70.0), "far_fov_deg"),
        (lambda: EgoConfig(cruise_speed_mps=(10.0, 5.0)), "cruise_speed_mps"),
        (lambda: WorldConfig(environment="desert"), "environment"),
    ],
)
def test_bad_config_is_named(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_bad_seed_is_named():
    with pytest.raises(ValueError, match="seed"):
        simulate_scene(-1)


def test_config_round_trips_through_a_dict():
    cfg = SimConfig(
        duration_s=7.5, lidar=LidarConfig(n_azimuth=720), ego=EgoConfig(stop_duration_s=(1.0, 2.0))
    )
    assert SimConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="bogus"):
        SimConfig.from_dict({**cfg.to_dict(), "bogus": 1})


def test_npz_scene_file_round_trip(tmp_path):
    scene = simulate_scene(3, _cfg("mixed", duration=0.6))
    path = save_sim_scene(scene, tmp_path / f"{scene.name}.npz")
    back = load_sim_scene(path)
    assert back.name == scene.name and len(back) == len(scene)
    for i in range(len(scene)):
        fo, fb = scene.frame(i), back.frame(i)
        _frames_equal(fo, fb)
        for s in fo.radar_sweeps():
            np.testing.assert_array_equal(
                back.radar_labels(s.channel, s.timestamp),
                scene.radar_labels(s.channel, s.timestamp),
            )
    np.testing.assert_array_equal(back.true_poses, scene.true_poses())
    again = save_sim_scene(simulate_scene(3, _cfg("mixed", duration=0.6)), tmp_path / "again.npz")
    assert again.read_bytes() == path.read_bytes()  # same seed, same file
    with pytest.raises(ValueError, match="npz"):
        save_sim_scene(scene, tmp_path / "x.bin")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        load_sim_scene(tmp_path / "bad.npz")


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-6.0, 6.0), min_size=2, max_size=2),
    st.floats(-math.pi, math.pi),
    st.floats(-math.pi, math.pi),
    st.lists(st.floats(0.2, 3.0), min_size=4, max_size=4),
)
def test_bounds_prefilter_never_hides_an_overlap(offset, yaw_a, yaw_b, half):
    """The world builder skips the exact footprint test for boxes whose axis-aligned bounds do not
    touch; that must never skip a pair that overlaps."""
    from evgrid_sim.world import _aabbs, _overlap, _touch

    a = pack_boxes(
        np.zeros(1),
        np.zeros(1),
        np.array([yaw_a]),
        np.array([half[0]]),
        np.array([half[1]]),
        np.zeros(1),
        np.ones(1),
    )
    b = pack_boxes(
        np.array([offset[0]]),
        np.array([offset[1]]),
        np.array([yaw_b]),
        np.array([half[2]]),
        np.array([half[3]]),
        np.zeros(1),
        np.ones(1),
    )
    if _overlap(a, b)[0]:
        assert _touch(_aabbs(a), _aabbs(b))[0]
