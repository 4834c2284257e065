"""evgrid live and evgrid replay (evgrid.live): live frames are a recording's frames, the bytes
evgrid publishes are ROS 2's, and a recording replayed over DDS into the live node maps as the
recording itself.

The DDS tests run on the loopback interface only (CYCLONEDDS_URI from
:func:`evgrid.live.dds.loopback_config`, no multicast) on a ROS_DOMAIN_ID drawn in 100-200 for
this session, each bounded in time.
"""

from __future__ import annotations

import logging
import random

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap")

from evgrid.data import SimConfig, simulate_scene  # noqa: E402
from evgrid.data.bag import load_bag  # noqa: E402
from evgrid.data.bag.reading import Recording  # noqa: E402
from evgrid.data.bag_writer import write_bag  # noqa: E402
from evgrid.live.node import map_cells_for, merge_frames  # noqa: E402
from evgrid.live.source import LiveFrames, sweep_topics  # noqa: E402
from tests.test_bag import assert_same_frames  # noqa: E402

DOMAIN = random.Random().randrange(100, 200)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A simulated 2 s drive as a ROS 2 bag (MCAP) and its rig."""
    frames = list(simulate_scene(7, SimConfig(duration_s=2.0)))
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
