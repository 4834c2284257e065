"""Hostile recordings (issues 25 and 26): bad poses, malformed clouds, damaged nuScenes files, rig
files with typos. Each is a counted, logged skip naming where it is, or a one-line error naming
the file, record and key; nothing else of the scene is lost (docs/hostile-input.md)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil

import numpy as np
import pytest

from evgrid.config import PoseLimits
from evgrid.data import LIDAR_COLUMNS
from evgrid.data.frame import LidarSweep
from evgrid.geometry import SE2, SE3
from evgrid.preprocess import PoseGate
from evgrid_sim import SimConfig, simulate_scene


@pytest.fixture(scope="module")
def frames():
    return list(simulate_scene(3, SimConfig(duration_s=0.8)))


# --- the frame contract and the pose gate --------------------------------------------------------


def test_a_lidar_sweep_without_extrinsics_is_refused_at_construction(frames):
    pts = frames[0].lidar.points
    with pytest.raises(ValueError, match=r"LidarSweep.sensor_to_ego must be an SE3.*NoneType"):
        LidarSweep(pts, None, SE3.identity(), 0)
    with pytest.raises(ValueError, match=r"LidarSweep.ego_pose must be an SE3"):
        LidarSweep(pts, SE3.identity(), None, 0)
    with pytest.raises(ValueError, match=r"timestamp must be an integer"):
        LidarSweep(pts, SE3.identity(), SE3.identity(), 1.5)


def test_a_half_turn_within_one_frame_is_said_to_be_a_turn(frames, caplog):
    gate = PoseGate(PoseLimits())
    bad = 4
    turned = [
        dataclasses.replace(f, ego_pose=f.ego_pose @ SE3.from_se2(SE2(0.0, 0.0, math.pi)))
        if f.index == bad
        else f
        for f in frames[:8]
    ]
    with caplog.at_level(logging.WARNING, logger="evgrid.preprocess"):
        accepted = [gate.accept(f) for f in turned]
    assert accepted == [True] * bad + [False] + [True] * 3
    msg = [r.getMessage() for r in caplog.records if "frame skipped" in r.getMessage()]
    assert len(msg) == 1 and "turned 180 deg" in msg[0] and "jumped" not in msg[0]
    assert gate.jumps[0]["turn_deg"] == pytest.approx(180.0, abs=1.0)


# --- recordings ----------------------------------------------------------------------------------

rosbags = pytest.importorskip("rosbags")
pytest.importorskip("mcap")
pytest.importorskip("yaml")

from evgrid.data.bag import RigError, load_bag, load_rig  # noqa: E402
from evgrid.ros import (  # noqa: E402
    RecordingWriter,
    columns_to_cloud,
    tf_message,
    transform_msg,
    us_to_stamp,
)

LIDAR_ONLY = {"lidar": {"topic": "/lidar"}}


def _write(path, frames, cloud=None, pose=None, stamp=None, extra_topics=()):
    """A lidar-only recording of ``frames``: /tf_static, /tf at each sweep, /lidar clouds;
    ``cloud(k, msg)``, ``pose(k, transform)`` and ``stamp(k, t)`` may tamper with message k."""
    w = RecordingWriter(path, "plain-mcap")
    s = w.store
    f0 = frames[0]
    t0 = f0.timestamp
    w.write(
        "/tf_static",
        "tf2_msgs/msg/TFMessage",
        t0 * 1000,
        tf_message([transform_msg("base_link", "LIDAR_TOP", t0, f0.lidar.sensor_to_ego, s)], s),
    )
    for k, f in enumerate(frames):
        t = f.timestamp
        tr = transform_msg("odom", "base_link", t, f.ego_pose, s)
        if pose:
            tr = pose(k, tr)
        w.write("/tf", "tf2_msgs/msg/TFMessage", t * 1000, tf_message([tr], s))
        ts = stamp(k, t) if stamp else t
        sec, ns = us_to_stamp(ts)
        msg = columns_to_cloud(f.lidar.points, LIDAR_COLUMNS, sec, ns, "LIDAR_TOP", s)
        if cloud:
            msg = cloud(k, msg)
        w.write("/lidar", "sensor_msgs/msg/PointCloud2", t * 1000, msg)
        for topic in extra_topics:
            w.write(topic, "sensor_msgs/msg/PointCloud2", t * 1000, msg)
    w.close()
    return path


def test_a_nan_pose_in_tf_is_ignored_and_logged_not_the_scene_lost(frames, tmp_path, caplog):
    bad = 5

    def nan(k, tr):
        if k == bad:
            tr.transform.translation.x = float("nan")
        return tr

    path = _write(tmp_path / "nan.mcap", frames, pose=nan)
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(path, LIDAR_ONLY)
        got = list(scene)
    assert len(got) == len(frames)  # before: "SE3 rotation and translation must be finite"
    assert scene.counts["pose_samples_not_finite"] == 1
    text = caplog.text
    assert f"/tf message {bad} (stamp {frames[bad].timestamp} us)" in text and "nan" in text
    assert str(path) in text
    # the frame takes the pose interpolated from the samples either side
    a, b = frames[bad - 1].ego_pose.translation, frames[bad + 1].ego_pose.translation
    x = got[bad].ego_pose.translation[0]
    assert min(a[0], b[0]) <= x <= max(a[0], b[0])


def _short_step(msg):
    return dataclasses.replace(msg, point_step=msg.point_step - 8)


def _long_step(msg):
    return dataclasses.replace(msg, point_step=msg.point_step + 8, row_step=msg.row_step * 2)


def _field_beyond(msg):
    fields = list(msg.fields)
    fields[2] = dataclasses.replace(fields[2], offset=msg.point_step)
    return dataclasses.replace(msg, fields=fields)


def _short_data(msg):
    return dataclasses.replace(msg, data=msg.data[: len(msg.data) // 2])


@pytest.mark.parametrize(
    "tamper,says",
    [
        (_short_step, "lies beyond the point_step"),
        (_long_step, "fewer than the"),
        (_field_beyond, "field 'z' (4 bytes at offset 20) lies beyond"),
        (_short_data, "fewer than the"),
    ],
    ids=["point_step too small", "point_step too big", "field beyond", "data short"],
)
def test_a_malformed_cloud_is_skipped_and_named(frames, tmp_path, caplog, tamper, says):
    bad = 3
    path = _write(tmp_path / "bad.mcap", frames, cloud=lambda k, m: tamper(m) if k == bad else m)
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(path, LIDAR_ONLY)
        got = list(scene)
    # before: numpy's "dtype descriptor requires ... bytes", and the whole scene lost
    assert [f.timestamp for f in got] == [f.timestamp for f in frames if f.index != bad]
    assert scene.counts["lidar_messages_malformed"] == 1
    line = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(line) == 1
    assert f"/lidar message {bad} (stamp {frames[bad].timestamp} us)" in line[0]
    assert says in line[0] and "NumPy" not in line[0] and "\n" not in line[0]


def test_a_cloud_wrongly_flagged_big_endian_is_flagged(frames, tmp_path, caplog):
    bad = 2
    path = _write(
        tmp_path / "be.mcap",
        frames,
        cloud=lambda k, m: dataclasses.replace(m, is_bigendian=True) if k == bad else m,
    )
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(path, LIDAR_ONLY)
        got = list(scene)
    assert len(got) == len(frames) - 1 and scene.counts["lidar_messages_malformed"] == 1
    assert "flagged big-endian" in caplog.text and "is_bigendian is probably wrong" in caplog.text


def test_a_true_big_endian_cloud_reads_as_the_little_endian_one(frames, tmp_path):
    def swap(k, m):
        data = np.frombuffer(bytes(m.data), "<f4").astype(">f4").view(np.uint8)
        return dataclasses.replace(m, is_bigendian=True, data=data)

    a = list(load_bag(_write(tmp_path / "le.mcap", frames[:4]), LIDAR_ONLY))
    b = list(load_bag(_write(tmp_path / "be.mcap", frames[:4], cloud=swap), LIDAR_ONLY))
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x.lidar.points, y.lidar.points)


def test_dropped_lidar_stamps_are_logged_and_counted_under_their_reason(frames, tmp_path, caplog):
    # 14: before frames already made (beyond the 0.5 s sync tolerance); 4: a repeat of 3's
    # stamp; 6: a minute ahead of the recording's clock
    shift = {14: -650_000, 4: None, 6: 60_000_000}

    def stamp(k, t):
        if k not in shift:
            return t
        return frames[3].timestamp if shift[k] is None else t + shift[k]

    path = _write(tmp_path / "st.mcap", frames, stamp=stamp)
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(path, LIDAR_ONLY)
        got = list(scene)
    assert len(got) == len(frames) - 3
    c = scene.counts
    assert (c["lidar_sweeps_backwards"], c["lidar_sweeps_duplicate"], c["lidar_sweeps_future"]) == (
        1,
        1,
        1,
    )
    assert f"stamp {frames[14].timestamp - 650_000} us): stamp is before" in caplog.text
    assert f"stamp {frames[3].timestamp} us): stamp repeats" in caplog.text
    assert f"stamp {frames[6].timestamp + 60_000_000} us): stamp lies more than" in caplog.text


def _lidar_missing(frames) -> tuple[int, dict]:
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper

    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm",)))
    for f in frames:
        mapper.process(f)
    m = mapper.counts()
    return m["lidar_frames_missing"], m


def test_a_skipped_sweep_is_counted_once_under_its_reason_not_as_missing(frames, tmp_path):
    # message 10 never recorded (truly missing); of the rest, 4 repeats 3's stamp, 6 lies a
    # minute ahead, 13 lies before frames already made: skipped by the reader for their stamps
    kept = frames[:10] + frames[11:]
    shift = {13: -650_000, 4: None, 6: 60_000_000}

    def stamp(k, t):
        if k not in shift:
            return t
        return kept[3].timestamp if shift[k] is None else t + shift[k]

    scene = load_bag(_write(tmp_path / "gaps.mcap", kept, stamp=stamp), LIDAR_ONLY)
    got = list(scene)
    c = scene.counts
    assert (c["lidar_sweeps_backwards"], c["lidar_sweeps_duplicate"], c["lidar_sweeps_future"]) == (
        1,
        1,
        1,
    )
    assert sum(f.lidar_skipped for f in got) == 3
    missing, _ = _lidar_missing(got)
    assert missing == 1  # frame 10's gap alone; each skipped sweep is counted under its reason
    # a whole recording: nothing skipped, nothing missing
    assert _lidar_missing(list(load_bag(_write(tmp_path / "all.mcap", frames), LIDAR_ONLY)))[0] == 0


def test_a_frame_the_pose_gate_drops_is_not_also_a_missing_sweep(frames):
    turned = [
        dataclasses.replace(f, ego_pose=f.ego_pose @ SE3.from_se2(SE2(0.0, 0.0, math.pi)))
        if f.index == 6
        else f
        for f in frames
    ]
    missing, m = _lidar_missing(turned)
    jumps = {k: v for k, v in m.items() if "jump" in k}
    assert missing == 0 and sum(jumps.values()) == 1, jumps
    assert _lidar_missing(frames[:6] + frames[7:])[0] == 1  # a sweep that never came is missing


def test_unused_topics_and_a_rig_without_radar_are_said(frames, tmp_path, caplog):
    path = _write(tmp_path / "u.mcap", frames[:3], extra_topics=("/radar_front/points",))
    with caplog.at_level(logging.WARNING, logger="evgrid.data.bag"):
        scene = load_bag(path, LIDAR_ONLY)
    assert not scene.has_radar
    assert "leaves 1 topic(s) unused: /radar_front/points (PointCloud2)" in caplog.text
    assert "the rig names no radar" in caplog.text and "/radar_front/points" in caplog.text


def test_a_keyframe_offset_in_the_rig(frames, tmp_path):
    path = _write(tmp_path / "kf.mcap", frames)
    got = list(load_bag(path, {**LIDAR_ONLY, "keyframes": {"every": 4, "offset": 1}}))
    assert [f.index for f in got if f.is_keyframe] == [1, 5, 9, 13][: len(range(1, len(got), 4))]
    with pytest.raises(RigError, match="offset_s"):
        load_bag(path, {**LIDAR_ONLY, "keyframes": {"every": 4, "offset_s": 1.0}})


@pytest.mark.parametrize(
    "rig,key",
    [
        (
            {"radars": [{"topic": "/r", "chanel": "RADAR_FRONT"}]},
            "radars[0]: unknown key(s) ['chanel']",
        ),
        ({"lidar": {"topic": "/lidar", "topc": "x"}}, "lidar: unknown key(s) ['topc']"),
        ({"poses": {"source": "tf", "tf_topik": "/tf"}}, "poses: unknown key(s) ['tf_topik']"),
        ({"keyframes": {"evry": 5}}, "keyframes: unknown key(s) ['evry']"),
        (
            {"extrinsics": {"velodyne": {"translation": [0, 0, 1], "yaw": 90}}},
            "extrinsics.velodyne: unknown key(s) ['yaw']",
        ),
        ({"lidar_topic": "/lidar"}, "unknown key(s) ['lidar_topic']"),
        ({"keyframes": {"every": 0}}, "keyframes.every must be an integer >= 1"),
    ],
)
def test_rig_files_are_checked_at_every_level(tmp_path, rig, key):
    import yaml

    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"lidar": {"topic": "/lidar"}, **rig}))
    with pytest.raises(RigError) as e:
        load_rig(path)
    assert str(e.value).startswith(str(path)) and key in str(e.value)


# --- nuScenes ------------------------------------------------------------------------------------

pytest.importorskip("nuscenes")

from evgrid.data.nuscenes import NuScenesDataError, load_nuscenes  # noqa: E402
from evgrid.data.nuscenes_format import write_nuscenes  # noqa: E402

VERSION = "v1.0-sim"


@pytest.fixture(scope="module")
def nusc_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc") / "clean"
    sc = simulate_scene(3, SimConfig(duration_s=1.0))
    write_nuscenes([sc], root, VERSION, splits={"val": [sc.name]})
    return root


@pytest.fixture
def root(nusc_root, tmp_path):
    out = tmp_path / "nusc"
    shutil.copytree(nusc_root, out)
    return out


def _table(root, name):
    return json.loads((root / VERSION / f"{name}.json").read_text())


def _put(root, name, records):
    (root / VERSION / f"{name}.json").write_text(json.dumps(records))


def _lidar_records(root):
    return sorted(
        (r for r in _table(root, "sample_data") if "LIDAR_TOP" in r["filename"]),
        key=lambda r: r["timestamp"],
    )


@pytest.mark.parametrize("cut", ["empty", "half", "inside a point"])
def test_a_damaged_lidar_file_is_a_counted_skip_naming_it(root, caplog, cut):
    rec = _lidar_records(root)[4]
    f = root / rec["filename"]
    data = f.read_bytes()
    n = len(data) // 20
    f.write_bytes({"empty": b"", "half": data[: 20 * (n // 2)], "inside a point": data[:-7]}[cut])
    (scene,) = load_nuscenes(root, VERSION, split="val")
    with caplog.at_level(logging.WARNING, logger="evgrid.data.nuscenes"):
        got = list(scene)
    assert len(got) == len(scene) - 1 and 4 not in [g.index for g in got]
    assert scene.stats["frames_damaged"] == 1 and str(f) in caplog.text
    # the frame after it carries the skip, so the mapper counts its gap under frames_damaged
    assert [g.lidar_skipped for g in got if g.lidar_skipped] == [1] and got[4].index == 5
    with pytest.raises(NuScenesDataError, match=str(f)):
        scene.frame(4)


def test_a_table_cut_in_half_names_the_file(root):
    f = root / VERSION / "sample_data.json"
    text = f.read_text()
    f.write_text(text[: len(text) // 2])
    with pytest.raises(NuScenesDataError, match=r"sample_data.json: not valid JSON at line"):
        load_nuscenes(root, VERSION, split="val")


@pytest.mark.parametrize("key", ["ego_pose_token", "filename", "timestamp"])
def test_a_record_missing_a_key_names_file_token_and_key(root, key):
    recs = _table(root, "sample_data")
    del recs[7][key]
    _put(root, "sample_data", recs)
    with pytest.raises(NuScenesDataError) as e:
        load_nuscenes(root, VERSION, split="val")
    msg = str(e.value)
    assert "sample_data.json" in msg and recs[7]["token"] in msg and repr(key) in msg


def test_a_nan_ego_pose_skips_the_frame_naming_the_record(root, caplog):
    rec = _lidar_records(root)[6]
    poses = _table(root, "ego_pose")
    for p in poses:
        if p["token"] == rec["ego_pose_token"]:
            p["translation"][0] = float("nan")
    _put(root, "ego_pose", poses)
    (scene,) = load_nuscenes(root, VERSION, split="val")
    with caplog.at_level(logging.WARNING, logger="evgrid.data.nuscenes"):
        got = list(scene)
    assert len(got) == len(scene) - 1 and scene.stats["frames_damaged"] == 1
    assert "ego_pose.json" in caplog.text and rec["ego_pose_token"] in caplog.text


def test_a_scene_that_never_moves_is_dropped_with_its_reason(root, caplog):
    with caplog.at_level(logging.WARNING, logger="evgrid.data.nuscenes"):
        scenes = load_nuscenes(root, VERSION, split="val", min_travel_m=1e4)
    assert scenes == [] and list(scenes.dropped) == ["sim-000003"]
    assert "never gets 10000 m from its first pose" in scenes.dropped["sim-000003"]
    assert "'sim-000003' dropped" in caplog.text


def test_a_rig_without_radar_maps_no_radar_map(frames, tmp_path, caplog):
    # the deep IRM never runs on detections from no sensor: only the lidar's map is made
    from evgrid.runs import map_scene

    path = _write(tmp_path / "nr.mcap", frames[:6], extra_topics=("/radar_front/points",))
    with caplog.at_level(logging.WARNING, logger="evgrid.runs"):
        res = map_scene(load_bag(path, LIDAR_ONLY), None, deep=object())
    assert "mapping ray_ilm only" in caplog.text
    assert not res.metrics.get("vs_ray_ilm")  # no other map to compare with the lidar's
    assert res.metrics["counts"]["updates"] > 0
