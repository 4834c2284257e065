"""evgrid live and evgrid replay (evgrid.live): live frames are a recording's frames, the bytes
evgrid publishes are ROS 2's, and a recording replayed over DDS into the live node maps as the
recording itself.

The DDS tests run on the loopback interface only (CYCLONEDDS_URI from
:func:`evgrid.live.dds.loopback_config`, no multicast) on a ROS_DOMAIN_ID drawn in 100-200 for
this session, each bounded in time.
"""

from __future__ import annotations

import logging
import os
import random
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap")

from evgrid.data.bag import load_bag  # noqa: E402
from evgrid.data.bag.reading import Recording  # noqa: E402
from evgrid.data.bag_writer import write_bag  # noqa: E402
from evgrid.live.node import map_cells_for, merge_frames  # noqa: E402
from evgrid.live.source import LiveFrames, sweep_topics  # noqa: E402
from evgrid_sim import SimConfig, simulate_scene  # noqa: E402
from tests.test_bag import assert_same_frames  # noqa: E402

DOMAIN = random.Random().randrange(100, 200)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A simulated 1 s drive as a ROS 2 bag (MCAP) and its rig."""
    frames = list(simulate_scene(7, SimConfig(duration_s=1.0)))
    bag, rig = write_bag(frames, tmp_path_factory.mktemp("live") / "drive", storage="mcap")
    return bag, rig


def _live_frames(bag, rig, step_s=0.01):
    """The frames LiveFrames makes of a recording's messages fed in bag order."""
    from evgrid.data.bag import load_rig

    rig = load_rig(rig)
    live = LiveFrames(rig)
    out, now = [], 0.0
    for topic, _, msg in Recording(bag).messages(set(sweep_topics(rig))):
        now += step_s
        live.feed(topic, msg, now)
        out += live.poll(now)
    return out + live.poll(now + 10.0), live


def test_live_frames_are_the_recordings_frames(drive):
    bag, rig = drive
    got, live = _live_frames(bag, rig)
    assert_same_frames(list(load_bag(bag, rig)), got)
    assert not any(v for k, v in live.counts.items())


def test_a_lidar_sweep_waits_for_its_pose_then_gives_up_counted(drive, caplog):
    from evgrid.data.bag import load_rig

    bag, rig = drive
    rig = load_rig(rig)
    live = LiveFrames(rig, pose_wait_s=1.0)
    msgs = list(Recording(bag).messages(set(sweep_topics(rig))))
    static = [m for m in msgs if m[0] == rig.tf_static_topic]
    lidar = [m for m in msgs if m[0] == rig.lidar.topic]
    for topic, _, msg in static + lidar[:1]:  # no /tf at all
        live.feed(topic, msg, 0.0)
    assert live.poll(0.5) == []  # waiting for the pose
    with caplog.at_level(logging.WARNING):
        assert live.poll(1.5) == []  # given up: no pose, counted and named
    assert live.counts["frames_no_pose"] == 1
    assert "no ego pose" in caplog.text


def test_waiting_sweeps_are_bounded_and_the_oldest_dropped_counted(drive):
    from evgrid.data.bag import load_rig

    bag, rig = drive
    rig = load_rig(rig)
    live = LiveFrames(rig, max_waiting=3)
    lidar = [m for m in Recording(bag).messages({rig.lidar.topic})]
    for topic, _, msg in lidar[:5]:
        live.feed(topic, msg, 0.0)
    assert len(live._rd["lidar_q"]) == 3
    assert live.counts["lidar_sweeps_dropped_waiting"] == 2


def test_merged_frames_keep_the_radar_sweeps_and_count_the_lidar_sweeps(drive):
    bag, rig = drive
    frames = list(load_bag(bag, rig))[:3]
    m = merge_frames(frames)
    assert m.timestamp == frames[-1].timestamp and m.lidar is frames[-1].lidar
    assert m.lidar_skipped == 2
    for ch in m.radar:
        assert [s.timestamp for s in m.radar[ch]] == [
            s.timestamp for f in frames for s in f.radar.get(ch, ())
        ]


def test_map_cells_whole_map_up_to_the_limit_then_a_window_around_the_vehicle():
    from evgrid.grid import EvidentialMap, GridSpec

    m = EvidentialMap(GridSpec())
    for key in ((0, 0), (1, 0)):  # two tiles observed: 2 x 1 tiles of cells
        m.tile(key)[1][:] = True
    r0, c0, h, w = m.covered_bounds()
    assert map_cells_for(m, 0.0, 0.0, h * w, 5.0) == (r0, c0, h, w)
    res = m.grid.resolution
    x, y = -(r0 + h / 2) * res, -(c0 + w / 4) * res  # inside, off the middle
    rb, cb, hb, wb = map_cells_for(m, x, y, h * w - 1, 5.0)
    n = int(np.ceil(5.0 / res))
    assert (hb, wb) == (n, n)
    rc, cc = (int(v) for v in m.grid.map_xy_to_cell(x, y))
    assert rb <= rc < rb + hb and cb <= cc < cb + wb
    assert r0 <= rb and rb + hb <= r0 + h and c0 <= cb and cb + wb <= c0 + w


# --- on DDS -------------------------------------------------------------------------------------

cyclonedds = pytest.importorskip("cyclonedds", reason="the live extra (cyclonedds) is needed")


@pytest.fixture(autouse=False)
def loopback(monkeypatch):
    """DDS on this machine only, on this session's domain."""
    from evgrid.live.dds import loopback_config

    monkeypatch.setenv("CYCLONEDDS_URI", loopback_config())
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    return DOMAIN


def _to_idl(msg, msgtype):
    """A rosbags message as the cyclonedds binding's own IDL object (an independent CDR
    serializer)."""
    from rosbags.typesys.store import Nodetype

    from evgrid.live.dds import idl_type
    from evgrid.ros import typestore

    _, fields = typestore(2).fielddefs[msgtype]

    def conv(node, v):
        kind, spec = node
        if kind == Nodetype.BASE:
            return v.item() if hasattr(v, "item") else v
        if kind == Nodetype.NAME:
            return _to_idl(v, spec)
        return [conv(spec[0], x) for x in v]

    return idl_type(msgtype)(**{n: conv(node, getattr(msg, n)) for n, node in fields})


def _published_messages(drive):
    """One message of every type evgrid publishes (and replays), as evgrid builds them."""
    from evgrid.config import RunConfig
    from evgrid.data.bag import load_rig
    from evgrid.export.mcap import MapCells, _pose_msg, grid_map_msg, occupancy_grid_msg
    from evgrid.mapper import OccupancyMapper
    from evgrid.ros import header, typestore

    bag, rig = drive
    store = typestore(2)
    mapper = OccupancyMapper(replace(RunConfig().mapper, maps=("ray_ilm",)))
    for f in list(load_bag(bag, rig))[:2]:
        mapper.process(f)
    m = mapper.maps.maps["ray_ilm"]
    cells = MapCells.read(m, m.covered_bounds())
    ego = store.types["geometry_msgs/msg/PoseStamped"](
        header=header(3, 4, "odom", store), pose=_pose_msg(store, 1.5, -2.0, 0.3)
    )
    out = [
        ("nav_msgs/msg/OccupancyGrid", occupancy_grid_msg(cells, 3_000_004, "odom", store)),
        ("grid_map_msgs/msg/GridMap", grid_map_msg(cells, 3_000_004, "odom", store)),
        ("geometry_msgs/msg/PoseStamped", ego),
    ]
    seen = set()
    for topic, typ, _, raw in __import__("evgrid.live.replay").live.replay.raw_messages(
        bag, set(sweep_topics(load_rig(rig)))
    ):
        if typ not in seen:
            seen.add(typ)
            out.append((typ, store.deserialize_cdr(raw, typ)))
    return out


def test_every_published_type_serialises_as_rosbags_does(drive):
    """rosbags' CDR serializer (what evgrid writes) and the cyclonedds binding's own serializer
    of the DDS types evgrid declares give the same bytes for the same message."""
    from evgrid.ros import typestore

    store = typestore(2)
    msgs = _published_messages(drive)
    assert {t for t, _ in msgs} >= {
        "nav_msgs/msg/OccupancyGrid",
        "grid_map_msgs/msg/GridMap",
        "geometry_msgs/msg/PoseStamped",
        "sensor_msgs/msg/PointCloud2",
        "tf2_msgs/msg/TFMessage",
    }
    for typ, msg in msgs:
        ours = bytes(store.serialize_cdr(msg, typ))
        theirs = _to_idl(msg, typ).serialize()
        assert ours == theirs[: len(ours)] and not any(theirs[len(ours) :]), typ


def test_a_qos_mismatch_is_named(loopback):
    from evgrid.live.dds import SENSOR_QOS, TF_QOS, Graph

    problems = []
    graph = Graph(loopback, on_problem=problems.append)
    try:
        r = graph.reader("/tf", "tf2_msgs/msg/TFMessage", TF_QOS)  # reliable, as tf2 publishes
        w = graph.writer("/tf", "tf2_msgs/msg/TFMessage", SENSOR_QOS)  # a best-effort /tf
        end = time.monotonic() + 10
        while not problems and time.monotonic() < end:
            time.sleep(0.05)
        assert r.publishers() == 0 and w.subscribers() == 0  # nothing flows
    finally:
        graph.close()
    assert problems and "/tf" in problems[0] and "RELIABILITY" in problems[0]


def _rti_xml(domain: int, readers: dict, writers: dict) -> str:
    """An RTI Connector configuration: the DDS types of ROS 2 messages (from the type store's
    definitions: final, XCDR1), readers and writers of ``{dds topic: (ros type, qos xml)}``, on
    the loopback interface of ``domain``."""
    from rosbags.typesys.store import Nodetype

    from evgrid.live.dds import dds_type
    from evgrid.ros import typestore

    store, done, structs = typestore(2), set(), []
    base = {"bool": "boolean", "byte": "uint8", "char": "uint8"}

    def member(name, node):
        kind, spec = node
        extra = ""
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (kind, spec), n = spec
            extra = (
                f' arrayDimensions="{n}"'
                if node[0] == Nodetype.ARRAY
                else (f' sequenceMaxLength="{n or -1}"')
            )
        if kind == Nodetype.NAME:
            add(spec)
            ref = dds_type(spec)
            return f'<member name="{name}" type="nonBasic" nonBasicTypeName="{ref}"{extra}/>'
        t, bound = spec
        if t == "string":
            return f'<member name="{name}" type="string" stringMaxLength="{bound or -1}"{extra}/>'
        return f'<member name="{name}" type="{base.get(t, t)}"{extra}/>'

    def add(msgtype):
        if msgtype in done:
            return
        done.add(msgtype)
        members = [member(n, node) for n, node in store.fielddefs[msgtype][1]]
        pkg, kind, name = msgtype.split("/")
        structs.append(
            f'<module name="{pkg}"><module name="{kind}"><module name="dds_">'
            f'<struct name="{name}_" extensibility="final">{"".join(members)}</struct>'
            "</module></module></module>"
        )

    for typ, _ in (*readers.values(), *writers.values()):
        add(typ)
    pool = (
        "<property><value><element><name>dds.data_{0}.history.memory_manager.fast_pool."
        "pool_buffer_max_size</name><value>4096</value></element></value></property>"
    )
    reps = (
        "<representation><value><element>XCDR_DATA_REPRESENTATION</element></value>"
        "</representation>"
    )
    regs = "".join(
        f'<register_type name="{dds_type(t)}" type_ref="{dds_type(t)}"/>'
        for t in {t for t, _ in (*readers.values(), *writers.values())}
    )
    topics = "".join(
        f'<topic name="{n}" register_type_ref="{dds_type(t)}"/>'
        for n, (t, _) in {**readers, **writers}.items()
    )
    subs = "".join(
        f'<data_reader name="{n.replace("/", "_")}" topic_ref="{n}"><datareader_qos>{q}{reps}'
        f"{pool.format('reader')}</datareader_qos></data_reader>"
        for n, (_, q) in readers.items()
    )
    pubs = "".join(
        f'<data_writer name="{n.replace("/", "_")}" topic_ref="{n}"><datawriter_qos>{q}{reps}'
        f"{pool.format('writer')}</datawriter_qos></data_writer>"
        for n, (_, q) in writers.items()
    )
    return (
        f"<dds><types>{''.join(structs)}</types>"
        f'<domain_library name="D"><domain name="d" domain_id="{domain}">{regs}{topics}'
        "</domain></domain_library>"
        '<domain_participant_library name="P"><domain_participant name="p" domain_ref="D::d">'
        "<domain_participant_qos><transport_builtin><mask>UDPv4</mask></transport_builtin>"
        "<discovery><initial_peers><element>builtin.udpv4://127.0.0.1</element></initial_peers>"
        "<multicast_receive_addresses/></discovery><property><value><element>"
        "<name>dds.transport.UDPv4.builtin.parent.allow_interfaces</name><value>lo</value>"
        "</element></value></property></domain_participant_qos>"
        f'<subscriber name="s">{subs}</subscriber><publisher name="w">{pubs}</publisher>'
        "</domain_participant></domain_participant_library></dds>"
    )


_MAP_QOS_XML = (
    "<reliability><kind>RELIABLE_RELIABILITY_QOS</kind></reliability><durability><kind>"
    "TRANSIENT_LOCAL_DURABILITY_QOS</kind></durability><history><kind>KEEP_LAST_HISTORY_QOS</kind>"
    "<depth>1</depth></history>"
)
_SENSOR_QOS_XML = (
    "<reliability><kind>RELIABLE_RELIABILITY_QOS</kind></reliability><history><kind>"
    "KEEP_LAST_HISTORY_QOS</kind><depth>5</depth></history>"
)


def _rti():
    try:
        import rticonnextdds_connector as rti
    except ImportError as e:  # pkg_resources (setuptools) or the package itself
        pytest.skip(f"RTI Connector cannot be imported here: {e}")
    return rti


def _until(cond, seconds, step=None):
    end = time.monotonic() + seconds
    while not cond() and time.monotonic() < end:
        step() if step else time.sleep(0.05)
    return cond()


def test_a_replay_into_evgrid_live_maps_as_the_recording_and_a_late_rti_reader_gets_map(
    drive, loopback, tmp_path
):
    """evgrid replay -> DDS -> evgrid live gives the maps of the recording mapped offline, bit
    for bit when no frame was dropped; RTI Connext (another DDS) joining after the replay ended
    receives /map: the navigation map's classes on the nav2 export's grid."""
    from evgrid.config import RunConfig
    from evgrid.data.bag import load_rig
    from evgrid.export.nav2 import classify, map_to_occupancy
    from evgrid.live.node import LiveNode, LiveOptions
    from evgrid.live.replay import replay
    from evgrid.mapper import OccupancyMapper

    bag, rig_path = drive
    rig = load_rig(rig_path)
    run = RunConfig()
    cfg = replace(run.mapper, maps=("nav",))
    offline = OccupancyMapper(cfg)
    for f in load_bag(bag, rig):
        offline.process(f)

    lines: list[str] = []
    node = LiveNode(rig, cfg, run.outputs, tmp_path / "live", LiveOptions(), loopback, lines.append)
    node.start()
    assert any("ready" in line for line in lines)
    done = threading.Event()

    def play():
        try:
            replay(bag, rig, rate=0.25, wait_s=10, domain=loopback, say=lines.append)
        finally:
            done.set()

    threading.Thread(target=play, daemon=True).start()
    try:
        assert _until(done.is_set, 40, node.step), "the replay did not end"
        t_end = time.monotonic()
        _until(lambda: time.monotonic() - t_end > 2.0, 3, node.step)  # the last map goes out
        rti = _rti()
        cfg_xml = tmp_path / "rti.xml"
        cfg_xml.write_text(
            _rti_xml(loopback, {"rt/map": ("nav_msgs/msg/OccupancyGrid", _MAP_QOS_XML)}, {})
        )
        with rti.open_connector(config_name="P::p", url=str(cfg_xml)) as conn:
            reader = conn.get_input("s::rt_map")
            got = []

            def take():
                node.step(0.05)
                reader.take()
                got.extend(s.get_dictionary() for s in reader.samples.valid_data_iter)

            assert _until(lambda: bool(got), 15, take), "RTI received no /map"
    finally:
        report = node.close()
    if report["dropped"]:
        pytest.skip(f"frames were dropped at 0.25x on this machine ({report['dropped']})")
    assert report["updates"] == offline.n_updates
    for name, m in offline.maps.maps.items():
        live = node.mapper.maps.maps[name]
        assert live.covered_bounds() == m.covered_bounds()
        a, b = m.read(*m.covered_bounds()), live.read(*m.covered_bounds())
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]), name
    # /map: nav's classes on the nav2 export's grid (the whole map: it is small)
    msg = got[-1]
    m = offline.maps.maps["nav"]
    r0, c0, h, w = m.covered_bounds()
    masses, cov = m.read(r0, c0, h, w)
    want, (ox, oy) = map_to_occupancy(
        classify(masses, cov, run.outputs.nav2.thresholds), r0, c0, m.grid.resolution
    )
    assert msg["header"]["frame_id"] == rig.world_frame
    assert (msg["info"]["height"], msg["info"]["width"]) == want.shape
    assert msg["info"]["origin"]["position"]["x"] == ox
    assert msg["info"]["origin"]["position"]["y"] == oy
    assert np.array_equal(np.array(msg["data"]).astype(np.int8), want.reshape(-1))


def test_evgrid_live_maps_a_pointcloud2_that_rti_publishes(drive, loopback, tmp_path):
    """A lidar cloud published by RTI Connext (poses on /tf and /tf_static from Cyclone) is
    decoded and mapped by evgrid live."""
    from evgrid.config import RunConfig
    from evgrid.data.bag import RecordingRig
    from evgrid.live.dds import TF_QOS, TF_STATIC_QOS, Graph
    from evgrid.live.node import LiveNode, LiveOptions
    from evgrid.live.replay import raw_messages
    from evgrid.ros import typestore

    rti = _rti()
    bag, _ = drive
    rig = RecordingRig.from_dict(
        {"lidar": {"topic": "/lidar_top/points"}, "world_frame": "odom", "keyframes": {"every": 1}}
    )
    run = RunConfig()
    node = LiveNode(
        rig, replace(run.mapper, maps=("ray_ilm",)), run.outputs, None, LiveOptions(), loopback,
        lambda line: None,
    )  # fmt: skip
    node.start()
    tf = Graph(loopback)
    cfg_xml = tmp_path / "rti.xml"
    cfg_xml.write_text(
        _rti_xml(
            loopback, {}, {"rt/lidar_top/points": ("sensor_msgs/msg/PointCloud2", _SENSOR_QOS_XML)}
        )
    )
    store = typestore(2)
    try:
        w = {
            "/tf": tf.writer("/tf", "tf2_msgs/msg/TFMessage", TF_QOS),
            "/tf_static": tf.writer("/tf_static", "tf2_msgs/msg/TFMessage", TF_STATIC_QOS),
        }
        with rti.open_connector(config_name="P::p", url=str(cfg_xml)) as conn:
            out = conn.get_output("w::rt_lidar_top_points")
            out.wait_for_subscriptions(10_000)
            sent = 0
            for topic, typ, _, raw in raw_messages(bag, {"/tf", "/tf_static", rig.lidar.topic}):
                if topic != rig.lidar.topic:
                    w[topic].write(raw)
                    continue
                if sent == 3:
                    break
                msg = store.deserialize_cdr(raw, typ)
                d = {
                    "header": {
                        "stamp": {"sec": msg.header.stamp.sec, "nanosec": msg.header.stamp.nanosec},
                        "frame_id": msg.header.frame_id,
                    },
                    "height": 1,
                    "width": 0,
                    "fields": [
                        {
                            "name": f.name,
                            "offset": f.offset,
                            "datatype": f.datatype,
                            "count": f.count,
                        }
                        for f in msg.fields
                    ],
                    "is_bigendian": False,
                    "point_step": msg.point_step,
                    "is_dense": True,
                }
                pts = np.asarray(msg.data).reshape(-1, msg.point_step)[::50]  # a thinned cloud
                d["width"], d["row_step"] = len(pts), pts.size
                d["data"] = pts.reshape(-1).tolist()
                time.sleep(0.1)  # its pose first
                out.instance.set_dictionary(d)
                out.write()
                sent += 1
            assert _until(lambda: node.mapper.n_updates >= 2, 20, lambda: node.step(0.05))
    finally:
        tf.close()
        report = node.close()
    assert report["lidar_sweeps"] >= 2
    assert node.mapper.maps.maps["ray_ilm"].covered_bounds()[2] > 0


def test_silence_and_malformed_messages_are_named_and_the_node_goes_on(loopback, caplog):
    from evgrid.config import RunConfig
    from evgrid.data.bag import RecordingRig
    from evgrid.live.dds import SENSOR_QOS, Graph
    from evgrid.live.node import LiveNode, LiveOptions
    from evgrid.ros import columns_to_cloud, typestore

    rig = RecordingRig.from_dict({"lidar": {"topic": "/points"}})
    run = RunConfig()
    opts = LiveOptions(silence_s=1.0)
    node = LiveNode(rig, replace(run.mapper, maps=("ray_ilm",)), run.outputs, None, opts, loopback)
    node.say = lambda line: None
    other = Graph(loopback)
    try:
        with caplog.at_level(logging.INFO):
            node.start()
            w = other.writer("/points", "sensor_msgs/msg/PointCloud2", SENSOR_QOS)
            _until(lambda: w.subscribers() > 0, 10)
            cloud = columns_to_cloud(np.ones((10, 3), np.float32), "xyz", 1, 0, "lidar")
            cloud.width = 1000  # ten points' data for a thousand
            w.write(typestore(2).serialize_cdr(cloud, "sensor_msgs/msg/PointCloud2"))
            counts = node.frames.counts
            assert _until(lambda: counts["lidar_messages_malformed"], 10, node.step)
            _until(lambda: "/tf: no message yet" in caplog.text, 5, node.step)
    finally:
        other.close()
        node.close()
    assert "/points message 0" in caplog.text and "fewer than the" in caplog.text
    assert "/tf: no message yet for 1." in caplog.text


def test_sigterm_saves_the_nav2_map_and_exits_0(drive, loopback, tmp_path):
    """evgrid live (the command) maps a replay, and SIGTERM saves nav2/map.pgm + map.yaml."""
    import signal
    import subprocess
    import sys

    from evgrid.data.bag import RecordingRig
    from evgrid.data.bag_writer import write_rig
    from evgrid.live.replay import replay

    bag, _ = drive
    rig = RecordingRig.from_dict(
        {"lidar": {"topic": "/lidar_top/points"}, "world_frame": "odom", "scene": "drive"}
    )
    rig_path = write_rig(rig, tmp_path / "rig.yaml")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "evgrid.cli", "live", "--rig", str(rig_path), "--out", str(out),
         "--maps", "ray_ilm", "--save-maps"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert "ready" in line, line + proc.stdout.read()
        replay(bag, rig, rate=0.5, wait_s=10, domain=loopback, say=lambda s: None)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=30)
    finally:
        proc.kill() if proc.poll() is None else None
    assert proc.returncode == 0, rest
    assert (out / "nav2" / "map.pgm").is_file() and (out / "nav2" / "map.yaml").is_file(), rest
    assert (out / "maps" / "ray_ilm.npz").is_file()
    assert "latency" in rest


def test_a_looped_pass_moves_stamps_on_and_starts_where_the_last_pass_ended(drive):
    """--loop: the second pass's first ego pose is the first pass's last, its stamps later."""
    from evgrid.data.bag import load_rig
    from evgrid.live.replay import _ego_track, _moved, raw_messages
    from evgrid.ros import stamp_to_us, transform_to_se3, typestore

    bag, rig_path = drive
    rig = load_rig(rig_path)
    first, last, t0, t1 = _ego_track(bag, rig)
    store = typestore(2)
    topic, typ, _, raw = next(raw_messages(bag, {rig.tf_topic}))
    msg = store.deserialize_cdr(raw, typ)
    before = stamp_to_us(msg.transforms[0].header.stamp)
    moved = _moved(msg, topic, 5_000_000_000, last @ first.inverse(), rig)
    tr = moved.transforms[0].transform
    pose = transform_to_se3(
        (tr.translation.x, tr.translation.y, tr.translation.z),
        (tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w),
    )
    assert stamp_to_us(moved.transforms[0].header.stamp) == before + 5_000_000
    assert np.allclose(pose.translation, last.translation, atol=1e-9)
    assert np.allclose(pose.rotation, last.rotation, atol=1e-12)
    # and replaying a ROS 1 bag says what it needs
    ros1 = Path(bag).parent / "x.bag"
    ros1.write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(Exception, match="rosbags-convert"):
        next(raw_messages(ros1, {"/tf"}))
