"""Frames from a live graph: the messages of a rig's topics, as they arrive, made into the same
:class:`~evgrid.data.frame.Frame` s as a recording of them (:class:`~evgrid.data.bag.BagScene`'s
own assembly: keyframes, radar sweeps per frame, interpolated poses, extrinsics, counts).

A recording knows every pose before its first sweep; live, a sweep waits until the pose track
reaches its stamp (a ``/tf`` sample at or after it), at most ``pose_wait_s``; a lidar sweep also
waits ``sync_wait_s`` for radar sweeps stamped before it that are still on their way. Queues are
bounded: what overflows is dropped and counted under its reason.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from evgrid.data.bag.errors import BagError
from evgrid.data.bag.rig import RecordingRig
from evgrid.data.bag.scene import BagScene, _pose_samples, _PoseTrack
from evgrid.data.bag.transforms import TransformBuffer
from evgrid.data.frame import Frame

__all__ = ["LiveFrames", "sweep_topics"]

log = logging.getLogger(__name__)

#: How long (s) the pose track is kept behind the newest frame made (raw Doppler needs +-50 ms).
_POSE_HISTORY_S = 2.0


def sweep_topics(rig: RecordingRig) -> dict[str, str]:
    """The rig's topics and the message type each is read as: lidar, radars, poses."""
    out = {rig.lidar.topic: "sensor_msgs/msg/PointCloud2"}
    out.update({r.topic: r.msgtype for r in rig.radars})
    if rig.odometry_topic:
        out[rig.odometry_topic] = "nav_msgs/msg/Odometry"
    else:
        out[rig.tf_topic] = "tf2_msgs/msg/TFMessage"
    out[rig.tf_static_topic] = "tf2_msgs/msg/TFMessage"
    return out


class LiveFrames(BagScene):
    """The frames of live messages: :meth:`feed` each decoded message with its arrival time,
    then :meth:`poll` for the frames that are complete (oldest first).

    ``counts`` holds the recording's skip counts plus the live ones:
    ``lidar_sweeps_dropped_waiting`` / ``radar_sweeps_dropped_waiting`` (a queue waiting for
    poses overflowed: the oldest went) and ``messages_malformed`` (not decodable).
    """

    def __init__(
        self,
        rig: RecordingRig,
        sync_wait_s: float = 0.05,
        pose_wait_s: float = 1.0,
        max_waiting: int = 20,
    ):
        # what BagScene.__init__ sets up from a recording, without one
        self.path = Path(rig.scene or "live")
        self.rig = rig
        self.name = rig.scene or "live"
        self.stopped = None
        self._logged: dict[str, int] = {}
        self._pose_counts = {"pose_samples_not_finite": 0}
        self._tf = TransformBuffer(int(round(rig.max_pose_gap_s * 1e6)))
        self._poses = _PoseTrack(self._tf, rig.world_frame, rig.base_frame)
        self._extrinsics = {}
        self._n_lidar = 0
        self._rd = self._reading()
        self.counts = self._rd["counts"]
        self.counts.update(
            lidar_sweeps_dropped_waiting=0, radar_sweeps_dropped_waiting=0, messages_malformed=0
        )
        self.sync_wait_s, self.pose_wait_s, self.max_waiting = sync_wait_s, pose_wait_s, max_waiting
        self._radar_waiting: list[tuple[int, float, str, int, Any]] = []  # stamp, arrival, ...
        self._lidar_arrival: dict[int, float] = {}  # lidar stamp (us) -> arrival (monotonic s)
        self._pose_topics = {rig.odometry_topic or rig.tf_topic, rig.tf_static_topic}
        self._radar_topics = {r.topic: r for r in rig.radars}

    def __len__(self) -> int:
        return self._n_lidar

    def __iter__(self) -> Iterator[Frame]:
        raise TypeError("live frames come from poll(), not from iterating the scene")

    def _pose_hi(self) -> int | None:
        span = self._tf.span(self.rig.world_frame, self.rig.base_frame)
        return None if span is None else span[1]

    def feed(self, topic: str, msg: Any, arrival: float | None = None) -> None:
        """One decoded message of a rig topic, arrived at ``arrival`` (``time.monotonic()``)."""
        from evgrid.ros import stamp_to_us

        arrival = time.monotonic() if arrival is None else arrival
        bag_ns = time.time_ns()  # a recording's bag time: when the message was received
        if topic in self._pose_topics:
            for sample in _pose_samples(topic, msg, self.rig):
                if not self._tf.add(*sample):
                    self._skip_pose(f"{topic} message", sample)
            return
        t = stamp_to_us(msg.header.stamp)
        if topic == self.rig.lidar.topic:
            self._n_lidar += 1
            self._message(topic, bag_ns, msg, self._rd)
            self._lidar_arrival[t] = arrival
            q = self._rd["lidar_q"]
            while len(q) > self.max_waiting:  # the oldest goes; the next frame carries its gap
                old = q.pop(0)
                self._lidar_arrival.pop(old[0], None)
                self._rd["state"]["carry"] += old[3] + 1
                self._drop("lidar_sweeps_dropped_waiting", topic, old[0])
        elif topic in self._radar_topics:
            self._radar_waiting.append((t, arrival, topic, bag_ns, msg))
            self._radar_waiting.sort(key=lambda w: w[0])
            while len(self._radar_waiting) > self.max_waiting:
                old = self._radar_waiting.pop(0)
                self._drop("radar_sweeps_dropped_waiting", old[2], old[0])

    def malformed(self, topic: str, error: str) -> None:
        """A message of ``topic`` that could not be decoded: counted and logged."""
        self._skip(
            "messages_malformed",
            self.counts,
            "%s: a message that cannot be decoded (%s); skipped",
            topic,
            error,
        )

    def _drop(self, reason: str, topic: str, t_us: int) -> None:
        self._skip(
            reason,
            self.counts,
            "%s: sweep at stamp %d us dropped: more than %d sweeps waiting for poses (%s -> %s)",
            topic,
            t_us,
            self.max_waiting,
            self.rig.world_frame,
            self.rig.base_frame,
        )

    def _radar_ready(self, t: int, arrival: float, topic: str, hi: int | None, now: float) -> bool:
        need = t if self._radar_topics[topic].compensated else t + 50_000  # Doppler: +-50 ms
        return (hi is not None and hi >= need) or now - arrival >= self.pose_wait_s

    def poll(self, now: float | None = None) -> list[Frame]:
        """The frames complete by ``now`` (``time.monotonic()``), oldest first."""
        now = time.monotonic() if now is None else now
        rd = self._rd
        hi = self._pose_hi()
        while self._radar_waiting and self._radar_ready(*self._radar_waiting[0][:3], hi, now):
            t, _, topic, bag_ns, msg = self._radar_waiting.pop(0)
            self._guard(lambda: self._message(topic, bag_ns, msg, rd), topic)
        out: list[Frame] = []
        q = rd["lidar_q"]
        tol_ns = int(self.rig.sync_tolerance_s * 1e9)
        while q:
            t = q[0][0]
            waited = now - self._lidar_arrival.get(t, now)
            radar_before = self._radar_waiting and self._radar_waiting[0][0] <= t
            ready = hi is not None and hi >= t and waited >= self.sync_wait_s and not radar_before
            if not (ready or waited >= self.pose_wait_s):
                break
            args = (rd["lidar_q"], rd["radar_q"], rd["counts"], rd["state"])
            # emits the queued sweeps stamped up to t: the head (stamps are unique)
            made = self._guard(lambda: list(self._emit(t * 1000 + tol_ns + 1, *args)), "lidar")
            self._lidar_arrival.pop(t, None)
            if made is None:  # no extrinsics: the sweep is gone, its gap carried
                q.pop(0) if q and q[0][0] == t else None
                rd["state"]["carry"] += 1
                continue
            out += made
        if rd["state"]["last_t"] is not None:
            self._tf.forget_before(rd["state"]["last_t"] - int(_POSE_HISTORY_S * 1e6))
        return out

    def _guard(self, fn: Any, topic: str) -> Any:
        """Run ``fn``; a missing transform (no extrinsics for a sensor frame) is logged and
        counted, and the node goes on."""
        try:
            return fn()
        except BagError as e:
            self._skip("sweeps_no_transform", self.counts, "%s: %s; sweep skipped", topic, e)
            return None
