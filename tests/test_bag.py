"""Robot recordings in (evgrid.data.bag): a simulated scene written as a bag maps as the scene
itself."""

from __future__ import annotations

import logging
import math
import shutil

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap")
pytest.importorskip("yaml")

from evgrid.config import MapperConfig  # noqa: E402
from evgrid.data.bag import BagError, RecordingRig, RigError, TransformBuffer, load_bag, load_rig  # noqa: E402
from evgrid.data.bag_writer import write_bag, write_rig  # noqa: E402
from evgrid.data.frame import RADAR_COLUMNS  # noqa: E402
from evgrid.fusion import MAP_NAMES  # noqa: E402
from evgrid.geometry import SE2, SE3  # noqa: E402
from evgrid.mapper import OccupancyMapper  # noqa: E402
from evgrid.ros import (  # noqa: E402
    RecordingWriter,
    columns_to_cloud,
    se3_to_transform,
    tf_message,
    transform_msg,
    transform_to_se3,
)
from evgrid.sources import BagSource, source_from_dict, source_to_dict  # noqa: E402
from evgrid_sim import SimConfig, simulate_scene  # noqa: E402


@pytest.fixture(scope="module")
def frames():
    return list(simulate_scene(3, SimConfig(duration_s=0.8)))


@pytest.fixture(scope="module")
def mcap_bag(frames, tmp_path_factory):
    return write_bag(frames, tmp_path_factory.mktemp("bag") / "drive", storage="mcap")


def assert_same_frames(want, got):
    assert len(want) == len(got)
    for a, b in zip(want, got):
        assert (a.index, a.timestamp, a.is_keyframe) == (b.index, b.timestamp, b.is_keyframe)
        assert a.ego_pose == b.ego_pose and a.lidar.sensor_to_ego == b.lidar.sensor_to_ego
        assert np.array_equal(a.lidar.points, b.lidar.points)
        assert {k: len(v) for k, v in a.radar.items()} == {k: len(v) for k, v in b.radar.items()}
        for ch in a.radar:
            for x, y in zip(a.radar[ch], b.radar[ch]):
                assert (x.timestamp, x.channel) == (y.timestamp, y.channel)
                assert x.ego_pose == y.ego_pose and x.sensor_to_ego == y.sensor_to_ego
                assert np.array_equal(x.points, y.points)


def test_ros2_mcap_bag_maps_bit_identically_to_the_scene(frames, mcap_bag):
    bag, rig = mcap_bag
    source = source_from_dict(source_to_dict(BagSource(str(bag), str(rig))))
    assert source.names() == [frames[0].scene]
    scene = source.load(frames[0].scene)
    got = list(scene)
    assert scene.kind == "ros2-mcap" and scene.stopped is None and len(scene) == len(frames)
    assert_same_frames(frames, got)
    cfg = MapperConfig()  # all maps of Table I, the shipped Ev-Net included
    direct = OccupancyMapper(cfg)
    via_bag = OccupancyMapper(cfg, deep=direct.deep)  # one Ev-Net (the shipped weights) for both
    for a, b in zip(frames, got):
        assert direct.process(a) == via_bag.process(b)
    assert set(direct.maps.maps) == set(MAP_NAMES)
    for name, m in direct.maps.maps.items():
        other = via_bag.maps.maps[name]
        assert m.tiles.keys() == other.tiles.keys()
        for k in m.tiles:
            assert np.array_equal(m.tiles[k], other.tiles[k]), name
            assert np.array_equal(m.covered_tiles[k], other.covered_tiles[k]), name


@pytest.mark.parametrize(
    "storage,name", [("sqlite3", "drive"), ("ros1", "drive.bag"), ("plain-mcap", "drive.mcap")]
)
def test_other_storages_give_the_same_frames(frames, tmp_path, storage, name):
    bag, rig = write_bag(frames[:6], tmp_path / name, storage=storage)
    scene = load_bag(bag, rig)
    assert scene.kind == {"sqlite3": "ros2-sqlite3", "ros1": "ros1", "plain-mcap": "mcap"}[storage]
    assert_same_frames(frames[:6], list(scene))


def test_radar_scan_messages(frames, tmp_path):
    bag, rig = write_bag(frames[:4], tmp_path / "scan", radar_format="radarscan")
    got = list(load_bag(bag, rig))
    n = 0
    for a, b in zip(frames[:4], got):
        for ch in a.radar:
            for x, y in zip(a.radar[ch], b.radar[ch]):
                p, q = x.points.astype(np.float64), y.points.astype(np.float64)
                np.testing.assert_allclose(q[:, :3], p[:, :3], atol=1e-4)
                np.testing.assert_array_equal(q[:, 3], p[:, 3])  # amplitude read as RCS
                # only the Doppler speed survives: the velocity's component along the line of sight
                u = p[:, :2] / np.linalg.norm(p[:, :3], axis=1)[:, None]
                vr = (p[:, 6:8] * u).sum(1)
                np.testing.assert_allclose((q[:, 6:8] * u).sum(1), vr, atol=1e-4)
                n += len(p)
    assert n > 0


def _handmade(
    tmp_path,
    *,
    radar_fields=("x", "y", "z", "snr", "v_r"),
    storage="mcap",
    yaw_rate=0.5,
    compensated=True,
):
    """Odometry at 10 Hz driving along x at 2 m/s while turning at ``yaw_rate``; lidar and radar
    between samples."""
    path = tmp_path / "hand"
    w = RecordingWriter(path, storage)
    s = w.store
    for k in range(11):
        t = 1_000_000 + 100_000 * k
        pose = SE3.from_se2(SE2(0.2 * k, 0.0, 0.1 * yaw_rate * k))
        (tx, ty, tz), (qx, qy, qz, qw) = se3_to_transform(pose)
        odo = s.types["nav_msgs/msg/Odometry"](
            header=transform_msg("odom", "base_link", t, pose, s).header,
            child_frame_id="base_link",
            pose=s.types["geometry_msgs/msg/PoseWithCovariance"](
                pose=s.types["geometry_msgs/msg/Pose"](
                    position=s.types["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
                    orientation=s.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
                covariance=np.zeros(36),
            ),
            twist=s.types["geometry_msgs/msg/TwistWithCovariance"](
                twist=s.types["geometry_msgs/msg/Twist"](
                    linear=s.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=s.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                ),
                covariance=np.zeros(36),
            ),
        )
        w.write("/odom", "nav_msgs/msg/Odometry", t * 1000, odo)
    for k in range(4):
        t = 1_050_000 + 200_000 * k  # halfway between odometry samples
        sec, ns = divmod(t, 1_000_000)
        cloud = np.array([[10.0, 0.0, 0.0, 5.0, 1.0], [0.0, 5.0, 1.0, 7.0, 2.0]], np.float32)
        w.write(
            "/velodyne_points",
            "sensor_msgs/msg/PointCloud2",
            t * 1000,
            columns_to_cloud(
                cloud[:, :4], ("x", "y", "z", "intensity"), sec, ns * 1000, "velodyne", s
            ),
        )
        radar = np.array([[3.0, 4.0, 0.0, 12.0, -2.5]], np.float32)
        w.write(
            "/radar/points",
            "sensor_msgs/msg/PointCloud2",
            (t - 20_000) * 1000,
            columns_to_cloud(
                radar[:, : len(radar_fields)], radar_fields, sec, (ns - 20_000) * 1000, "radar", s
            ),
        )
    w.close()
    rig = RecordingRig.from_dict(
        {
            "world_frame": "odom",
            "base_frame": "base_link",
            "poses": {"source": "odometry", "topic": "/odom"},
            "lidar": {"topic": "/velodyne_points"},
            "radars": [
                {
                    "topic": "/radar/points",
                    "channel": "RADAR_FRONT",
                    "fields": {"rcs": "snr", "radial_velocity": "v_r"},
                    "compensated": compensated,
                }
            ],
            "extrinsics": {
                "velodyne": {"translation": [1.0, 0.0, 1.8], "yaw_deg": -90},
                "radar": {"translation": [3.5, 0.0, 0.5], "rotation_wxyz": [1, 0, 0, 0]},
            },
            "keyframes": {"rate_hz": 2.5},
        }
    )
    return path, rig


def test_odometry_interpolation_rig_extrinsics_and_field_names(tmp_path):
    path, rig = _handmade(tmp_path)
    got = list(load_bag(path, rig))
    assert [f.timestamp for f in got] == [1_050_000, 1_250_000, 1_450_000, 1_650_000]
    # halfway between samples k and k+1: x = 0.2 (k + 0.5), yaw = 0.05 (k + 0.5), k = 0, 2, 4, 6
    for f, k in zip(got, (0.5, 2.5, 4.5, 6.5)):
        assert f.ego_pose.translation == pytest.approx([0.2 * k, 0.0, 0.0], abs=1e-12)
        assert f.ego_pose.yaw == pytest.approx(0.05 * k, abs=1e-12)
    # keyframes at 2.5 Hz from the first frame: 1.05 s, then the first at or after 1.45 s
    assert [f.is_keyframe for f in got] == [True, False, True, False]
    f = got[0]
    assert f.lidar.sensor_to_ego.translation.tolist() == [1.0, 0.0, 1.8]
    assert f.lidar.sensor_to_ego.yaw == pytest.approx(-math.pi / 2)
    np.testing.assert_array_equal(f.lidar.points[:, 4], 0.0)  # no ring field: zeros
    (sweep,) = f.radar["RADAR_FRONT"]
    assert sweep.timestamp == 1_030_000
    assert sweep.ego_pose.translation[0] == pytest.approx(0.2 * 0.3, abs=1e-12)
    p = sweep.points[0]
    assert p[RADAR_COLUMNS.index("rcs")] == 12.0
    # the radial speed as a vector along the line of sight (3, 4, 0) / 5
    assert p[RADAR_COLUMNS.index("vx_comp")] == pytest.approx(-2.5 * 0.6)
    assert p[RADAR_COLUMNS.index("vy_comp")] == pytest.approx(-2.5 * 0.8)
    assert (
        p[RADAR_COLUMNS.index("invalid_state")] == 0.0
        and p[RADAR_COLUMNS.index("ambig_state")] == 3.0
    )


def test_raw_doppler_is_compensated_with_the_ego_motion(tmp_path):
    # driving straight along x at 2 m/s; the radar's target at (3, 4, 0) m is static, so its raw
    # radial speed is -2 m/s * 3/5 = -1.2 m/s (the handmade radar reports -2.5: 1.3 m/s its own)
    path, rig = _handmade(tmp_path, yaw_rate=0.0, compensated=False)
    assert load_rig(write_rig(rig, tmp_path / "rig.yaml")).radars[0].compensated is False
    (sweep,) = next(iter(load_bag(path, rig))).radar["RADAR_FRONT"]
    p = sweep.points[0]
    assert (p[RADAR_COLUMNS.index("vx")], p[RADAR_COLUMNS.index("vy")]) == pytest.approx(
        (-2.5 * 0.6, -2.5 * 0.8)
    )
    assert p[RADAR_COLUMNS.index("vx_comp")] == pytest.approx(-1.3 * 0.6, abs=1e-5)
    assert p[RADAR_COLUMNS.index("vy_comp")] == pytest.approx(-1.3 * 0.8, abs=1e-5)


def test_missing_topic_field_and_frame_are_named(mcap_bag, tmp_path):
    bag, rig_path = mcap_bag
    rig = load_rig(rig_path).to_dict()
    bad = dict(rig, lidar={"topic": "/nope/points"})
    with pytest.raises(BagError, match="/nope/points"):
        load_bag(bag, RecordingRig.from_dict(bad))
    bad = dict(rig, base_frame="chassis")
    with pytest.raises(BagError, match="chassis"):
        load_bag(bag, RecordingRig.from_dict(bad))
    bad = dict(rig, radars=[dict(rig["radars"][0], fields={"rcs": "snr"})])
    with pytest.raises(BagError, match="snr"):
        list(load_bag(bag, RecordingRig.from_dict(bad)))
    bad = dict(rig, lidar={"topic": rig["lidar"]["topic"], "frame": "velodyne"})
    with pytest.raises(BagError, match="velodyne"):
        list(load_bag(bag, RecordingRig.from_dict(bad)))
    bad = dict(rig, poses={"source": "odometry", "topic": "/lidar_top/points"})
    with pytest.raises(BagError, match="not nav_msgs/msg/Odometry"):
        load_bag(bag, bad)  # a rig may be given as its dict too
    path, hand = _handmade(tmp_path, radar_fields=("x", "y", "z", "snr"))
    with pytest.raises(BagError, match="v_r"):  # neither a velocity vector nor a radial speed
        list(load_bag(path, hand))


def test_rig_file_errors_and_round_trip(tmp_path):
    with pytest.raises(RigError, match="lidar"):
        RecordingRig.from_dict({"radars": []})
    with pytest.raises(RigError, match="colour"):
        RecordingRig.from_dict({"lidar": {"topic": "/l"}, "colour": 1})
    with pytest.raises(RigError, match="dopler"):
        RecordingRig.from_dict(
            {"lidar": {"topic": "/l"}, "radars": [{"topic": "/r", "fields": {"dopler": "v"}}]}
        )
    with pytest.raises(RigError, match="keyframes"):
        RecordingRig.from_dict({"lidar": {"topic": "/l"}, "keyframes": {"every": 0}})
    rig = RecordingRig.from_dict(
        {
            "lidar": {"topic": "/l", "fields": {"ring": "channel"}},
            "radars": [{"topic": "/radar/front"}],
            "extrinsics": {"l": {"translation": [1, 2, 3], "yaw_deg": 90}},
        }
    )
    assert rig.radars[0].channel == "RADAR_FRONT"
    back = load_rig(write_rig(rig, tmp_path / "rig.yaml"))
    assert back.to_dict() == rig.to_dict()
    np.testing.assert_allclose(
        back.extrinsics["l"].matrix(), rig.extrinsics["l"].matrix(), atol=1e-12
    )


@pytest.mark.parametrize("storage,suffix", [("plain-mcap", ".mcap"), ("ros1", ".bag")])
def test_truncated_recording_maps_what_is_readable(frames, tmp_path, caplog, storage, suffix):
    bag, rig = write_bag(frames, tmp_path / f"whole{suffix}", storage=storage)
    cut = tmp_path / f"cut{suffix}"
    data = bag.read_bytes()
    cut.write_bytes(
        data[: int(len(data) * 0.6)]
    )  # a ROS 1 bag loses its index, an MCAP file its summary
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(cut, rig)
        got = list(scene)
    assert scene.stopped is not None and cut.name in scene.stopped and "truncated" in scene.stopped
    assert any("truncated" in r.message for r in caplog.records)
    assert 0 < len(got) < len(frames)
    assert_same_frames(frames[: len(got)], got)


def test_transform_chain_and_exact_planar_quaternions():
    tf = TransformBuffer()
    tf.add(
        "map", "odom", 0, (10.0, 0.0, 0.0), (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))
    )
    tf.add(
        "map",
        "odom",
        1_000_000,
        (10.0, 0.0, 0.0),
        (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)),
    )
    tf.add("odom", "base_link", 0, (0.0, 0.0, 0.0), (0, 0, 0, 1))
    tf.add("odom", "base_link", 1_000_000, (2.0, 0.0, 0.0), (0, 0, 0, 1))
    tf.add("base_link", "lidar", 0, (1.0, 0.0, 2.0), (0, 0, 0, 1), static=True)
    # at 0.5 s the base is 1 m along odom's x, which map has turned by 90 degrees
    p = tf.lookup("map", "lidar", 500_000)
    np.testing.assert_allclose(p.translation, [10.0, 2.0, 2.0], atol=1e-12)
    assert p.yaw == pytest.approx(math.pi / 2)
    assert tf.lookup("map", "lidar", 2_000_000) is None  # beyond the track by more than max_gap
    assert tf.lookup("map", "nowhere", 0) is None
    rng = np.random.default_rng(0)
    for yaw in rng.uniform(-math.pi, math.pi, 500):
        pose = SE3.from_se2(SE2(1.0, -2.0, float(yaw)))
        assert transform_to_se3(*se3_to_transform(pose)) == pose  # bit-exact, not just close


def test_the_documented_rig_example_loads():
    from pathlib import Path

    rig = load_rig(Path(__file__).resolve().parents[1] / "docs" / "rig_example.yaml")
    assert [r.channel for r in rig.radars] == ["RADAR_FRONT", "RADAR_BACK"]
    assert rig.radars[0].fields == {"rcs": "snr", "radial_velocity": "v_r"}
    assert set(rig.extrinsics) == {"velodyne", "radar_front"} and rig.keyframe_every == 10


def test_lidar_recorded_out_of_order_is_put_in_place_and_duplicates_dropped(tmp_path):
    w = RecordingWriter(tmp_path / "x.mcap", "plain-mcap")
    s = w.store
    for k in range(10):
        t = 1_000_000 + 100_000 * k
        w.write(
            "/tf",
            "tf2_msgs/msg/TFMessage",
            t * 1000,
            tf_message([transform_msg("odom", "base_link", t, SE3.identity(), s)], s),
        )
    for k in (0, 2, 1, 3, 3):  # bag times 1 ms after the stamps, in this order
        t = 1_000_000 + 100_000 * k
        cloud = columns_to_cloud(
            np.full((2, 3), k, np.float32), "xyz", 1, k * 100_000_000, "base_link", s
        )
        w.write("/l", "sensor_msgs/msg/PointCloud2", t * 1000 + 1_000_000, cloud)
    w.close()
    scene = load_bag(tmp_path / "x.mcap", {"lidar": {"topic": "/l"}})
    got = list(scene)
    assert [f.timestamp for f in got] == [1_000_000, 1_100_000, 1_200_000, 1_300_000]
    assert [f.lidar.points[0, 0] for f in got] == [0, 1, 2, 3] and [f.index for f in got] == [
        0,
        1,
        2,
        3,
    ]
    # counted under its reason (was lidar_sweeps_late, which also held backwards stamps)
    assert scene.counts["lidar_sweeps_duplicate"] == 1
    assert scene.counts["lidar_sweeps_backwards"] == 0


def test_bag_errors_for_unreadable_paths(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_bag(tmp_path / "none.mcap", RecordingRig.from_dict({"lidar": {"topic": "/l"}}))
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(BagError, match="unknown recording"):
        load_bag(tmp_path / "x.txt", RecordingRig.from_dict({"lidar": {"topic": "/l"}}))
    shutil.rmtree(tmp_path)
