"""A recording as a scene: frames made of lidar sweeps, the radar sweeps since the last one and
the ego poses, read lazily as the rig file says."""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.data.bag.decoding import (
    compensate,
    lidar_points,
    radar_cloud_points,
    radar_scan_points,
)
from evgrid.data.bag.errors import BagError
from evgrid.data.bag.reading import Recording
from evgrid.data.bag.rig import RadarTopic, RecordingRig, load_rig
from evgrid.data.bag.transforms import TransformBuffer
from evgrid.data.frame import LIDAR_CHANNEL, Frame, LidarSweep, RadarSweep
from evgrid.geometry import SE3
from evgrid.ros import CloudError

__all__ = ["BagScene", "load_bag"]

logger = logging.getLogger(__name__)

#: Skips of one reason logged one by one before they are only counted.
_LOG_FIRST = 5
#: A lidar stamp this far (s) ahead of the recording's clock, beyond the lead its stamps
#: usually have, is not a time the sweep can have been taken at.
_FUTURE_S = 10.0


@dataclass
class _PoseTrack:
    tf: TransformBuffer
    world: str
    base: str

    def ego(self, t_us: int) -> SE3 | None:
        return self.tf.lookup(self.world, self.base, t_us)


#: Message types of sensor topics that a rig might have meant to read.
_SENSOR_TYPES = ("sensor_msgs/msg/PointCloud2", "radar_msgs/msg/RadarScan")


def _pose_samples(topic: str, msg: Any, rig: RecordingRig) -> Iterator[tuple]:
    """The transforms of one pose message, each as the arguments of
    :meth:`TransformBuffer.add`: ``(parent, child, t_us, translation, q_xyzw, static)``."""
    from evgrid.ros import stamp_to_us

    if topic == rig.odometry_topic:
        p = msg.pose.pose
        yield (
            msg.header.frame_id,
            msg.child_frame_id,
            stamp_to_us(msg.header.stamp),
            (p.position.x, p.position.y, p.position.z),
            (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w),
            False,
        )
        return
    for tr in msg.transforms:
        tt, q = tr.transform.translation, tr.transform.rotation
        yield (
            tr.header.frame_id,
            tr.child_frame_id,
            stamp_to_us(tr.header.stamp),
            (tt.x, tt.y, tt.z),
            (q.x, q.y, q.z, q.w),
            topic == rig.tf_static_topic,
        )


class BagScene:
    """A recording as a :class:`~evgrid.data.frame.Scene`; frames are read lazily on iteration.

    ``stopped`` says where a damaged recording stopped being readable (None when whole);
    ``counts`` what was skipped on the last full iteration, each under its reason: pose samples
    that are not finite, frames without a pose, lidar messages whose stamp goes backwards,
    repeats one or lies far ahead of the recording's time, malformed clouds (layout or
    implausible coordinates), radar sweeps recorded after their frame was made, without a pose,
    or after the last lidar sweep. Each skip is logged with the topic, message index and stamp
    (the first few of each reason). Frame indices (and ``keyframes: every``) count the frames
    made. ``has_radar``: whether the rig names any radar (a rig without one is said at load).
    """

    def __init__(self, path: str | Path, rig: RecordingRig):
        self.path = Path(path)
        self.rig = rig
        self.name = rig.scene or self.path.stem
        self._rec = Recording(self.path)
        self.stopped: str | None = None
        self.counts: dict[str, int] = {}
        self._logged: dict[str, int] = {}
        self._pose_counts = {"pose_samples_not_finite": 0}
        self._scan_poses()

    @property
    def has_radar(self) -> bool:
        """Whether the rig names any radar topic."""
        return bool(self.rig.radars)

    def _skip(self, reason: str, counts: dict[str, int], msg: str, *args: Any) -> None:
        """Count a skip under its reason and log the first few of each reason."""
        counts[reason] = counts.get(reason, 0) + 1
        n = self._logged.get(reason, 0)
        if n < _LOG_FIRST:
            more = f" (further {reason} are counted, not logged)" if n == _LOG_FIRST - 1 else ""
            logger.warning(msg + "%s", *args, more)
        self._logged[reason] = n + 1

    def __repr__(self) -> str:
        return f"BagScene({self.name!r}, {self._rec.kind}, {self._n_lidar} lidar sweeps)"

    @property
    def kind(self) -> str:
        """The recording's format (see :func:`bag_kind`)."""
        return self._rec.kind

    def _pose_types(self) -> dict[str, str]:
        rig = self.rig
        out = (
            {rig.odometry_topic: "nav_msgs/msg/Odometry"}
            if rig.odometry_topic
            else {rig.tf_topic: "tf2_msgs/msg/TFMessage"}
        )
        out[rig.tf_static_topic] = "tf2_msgs/msg/TFMessage"
        return out

    def _scan_poses(self) -> None:
        rig = self.rig
        tf = TransformBuffer(int(round(rig.max_pose_gap_s * 1e6)))
        types = self._pose_types()
        count = {rig.lidar.topic} | {r.topic for r in rig.radars}
        self._n_lidar = 0
        index: dict[str, int] = {}
        for topic, _, msg in self._rec.messages(set(types), count - set(types)):
            k = index[topic] = index.get(topic, -1) + 1
            if topic == rig.lidar.topic:
                self._n_lidar += 1
            if msg is None:
                continue
            if self._rec.topics[topic] != types[topic]:
                raise BagError(
                    f"{self.path}: pose topic {topic} is {self._rec.topics[topic]}, not "
                    f"{types[topic]}"
                )
            for sample in _pose_samples(topic, msg, rig):
                if not tf.add(*sample):
                    self._skip_pose(f"{topic} message {k}", sample)
        self.stopped = self._rec.stopped
        if self.stopped:
            logger.warning("%s; mapping what was read before", self.stopped)
        self._check(tf)
        self._said_silent_radars(index)
        self._said_second_parents(tf, next(iter(types)))
        self._tf = tf
        self._poses = _PoseTrack(tf, rig.world_frame, rig.base_frame)
        self._extrinsics: dict[str, SE3] = {}

    def _said_silent_radars(self, index: dict[str, int]) -> None:
        """A radar topic of the rig that the recording holds no message of: the radar maps are
        made without that radar, which a user must hear of (issue 39); counted in
        ``radar_topics_silent``. A warning, not an error: the other sensors still map, and a
        radar that was off is a fact of the recording, not a wrong rig."""
        silent = [r.topic for r in self.rig.radars if r.topic not in index]
        self._pose_counts["radar_topics_silent"] = len(silent)
        for topic in silent:
            logger.warning(
                "%s: radar topic %s has no message; the radar maps are made without it",
                self.path,
                topic,
            )

    def _said_second_parents(self, tf: TransformBuffer, topic: str) -> None:
        """Pose samples of a second tf parent (kept apart by the buffer): counted in
        ``pose_samples_second_parent`` and logged naming the topic."""
        n = sum(sum(p.values()) for p in tf.second_parents.values())
        self._pose_counts["pose_samples_second_parent"] = n
        for child, parents in tf.second_parents.items():
            logger.warning(
                "%s %s: %d sample(s) give frame %r a second parent (%s)",
                self.path,
                topic,
                sum(parents.values()),
                child,
                ", ".join(parents),
            )

    def _skip_pose(self, where: str, sample: tuple) -> None:
        """A transform the buffer refused (not finite, or a quaternion without length): counted
        and logged; the frames around it take the pose interpolated from the samples on either
        side."""
        parent, child, t_us, translation, q_xyzw, _ = sample
        self._skip(
            "pose_samples_not_finite",
            self._pose_counts,
            "%s %s (stamp %d us): transform %s -> %s is not finite (%s); sample ignored, "
            "the frames around it take the pose interpolated from its neighbours",
            self.path,
            where,
            t_us,
            parent,
            child,
            [float(v) for v in (*translation, *q_xyzw)],
        )

    def _check(self, tf: TransformBuffer) -> None:
        rig, have = self.rig, self._rec.topics
        need = [rig.lidar.topic, *(r.topic for r in rig.radars)]
        need.append(rig.odometry_topic or rig.tf_topic)
        missing = [t for t in need if t not in have]
        if missing:
            raise BagError(
                f"{self.path}: topic(s) {missing} not in the recording; it has {sorted(have)}"
            )
        for r in rig.radars:
            typ = have[r.topic]
            if typ not in ("sensor_msgs/msg/PointCloud2", "radar_msgs/msg/RadarScan"):
                raise BagError(
                    f"{self.path}: radar topic {r.topic} is {typ}; evgrid reads "
                    "sensor_msgs/PointCloud2 or radar_msgs/RadarScan"
                )
        if have[rig.lidar.topic] != "sensor_msgs/msg/PointCloud2":
            raise BagError(
                f"{self.path}: lidar topic {rig.lidar.topic} is {have[rig.lidar.topic]}, "
                "not sensor_msgs/PointCloud2"
            )
        for topic, typ in self._pose_types().items():
            if topic in have and have[topic] != typ:
                raise BagError(f"{self.path}: pose topic {topic} is {have[topic]}, not {typ}")
        frames = tf.frames()
        missing = [f for f in (rig.world_frame, rig.base_frame) if f not in frames]
        if missing:
            src = rig.odometry_topic or rig.tf_topic
            raise BagError(
                f"{self.path}: frame(s) {missing} not in {src}; its frames are {sorted(frames)}"
            )
        used = set(need) | set(self._pose_types())
        unused = {t: typ for t, typ in sorted(have.items()) if t not in used}
        sensors = {t: typ for t, typ in unused.items() if typ in _SENSOR_TYPES}
        if unused:
            logger.warning(
                "%s: the rig file leaves %d topic(s) unused: %s",
                self.path,
                len(unused),
                ", ".join(f"{t} ({typ.split('/')[-1]})" for t, typ in unused.items()),
            )
        if not rig.radars:
            logger.warning(
                "%s: the rig names no radar: only the lidar is read, so there are no radar maps "
                "(ray_irm, deep_irm and the maps fused from them)%s",
                self.path,
                f"; the recording has sensor topics {sorted(sensors)}: name them under radars: "
                if sensors
                else "",
            )

    def _extrinsic(self, frame: str, where: str) -> SE3:
        frame = frame.lstrip("/")
        e = self._extrinsics.get(frame)
        if e is None:
            e = self.rig.extrinsics.get(frame)
            if e is None:
                # a sensor hangs off the base through static transforms only
                e = (
                    self._tf.lookup(self.rig.base_frame, frame, 0)
                    if self._static_chain(frame)
                    else None
                )
            if e is None:
                raise BagError(
                    f"{where}: no extrinsics for frame {frame!r}: not in "
                    f"{self.rig.tf_static_topic} below {self.rig.base_frame!r} nor under "
                    "extrinsics: in the rig file"
                )
            self._extrinsics[frame] = e
        return e

    def _static_chain(self, frame: str) -> bool:
        f, seen = frame, set()
        while f != self.rig.base_frame:
            if f in seen or f not in self._tf._static:
                return False
            seen.add(f)
            f = self._tf._static[f][0]
        return True

    def __len__(self) -> int:
        return self._n_lidar

    def _sensor_velocity(
        self, t_us: int, sensor_to_ego: SE3, dt_us: int = 50_000
    ) -> np.ndarray | None:
        """Velocity (m/s) of a sensor's origin in its own frame at ``t_us``: poses differenced
        over ``t_us +- dt_us`` (one-sided at the ends of the pose track)."""
        span = self._tf.span(self.rig.world_frame, self.rig.base_frame)
        if span is None:
            return None
        ta, tb = max(t_us - dt_us, span[0]), min(t_us + dt_us, span[1])
        a, b, now = self._poses.ego(ta), self._poses.ego(tb), self._poses.ego(t_us)
        if a is None or b is None or now is None or tb <= ta:
            return None
        pa, pb = (a @ sensor_to_ego).translation, (b @ sensor_to_ego).translation
        v_world = (pb - pa) / ((tb - ta) * 1e-6)
        return (now @ sensor_to_ego).rotation.T @ v_world

    def _is_keyframe(self, index: int, t_us: int, state: dict) -> bool:
        rig = self.rig
        if rig.keyframe_every is not None:
            return index % rig.keyframe_every == rig.keyframe_offset % rig.keyframe_every
        period = 1e6 / rig.keyframe_rate_hz
        nxt = state.get("next")
        if nxt is None and rig.keyframe_offset_s:  # the first tick that long after the first frame
            nxt = state["next"] = t_us + rig.keyframe_offset_s * 1e6
        if nxt is None or t_us >= nxt:
            base = t_us if nxt is None else nxt
            state["next"] = base + period * (math.floor((t_us - base) / period) + 1)
            return True
        return False

    @staticmethod
    def _lidar_stamp(
        t: int, bag_ns: int, last: int | None, queue: list, leads: deque[int]
    ) -> str | None:
        """Why a lidar message at stamp ``t`` (us) recorded at ``bag_ns`` cannot make a frame
        (a key of :data:`_STAMP_REASONS`), or None when it can."""
        if t == last or any(q[0] == t for q in queue):
            return "duplicate"
        if last is not None and t < last:
            return "backwards"
        if leads and t - bag_ns // 1000 - sorted(leads)[len(leads) // 2] > _FUTURE_S * 1e6:
            return "future"
        return None

    def _radar_sweep(
        self, msg: Any, r: RadarTopic, t: int, where: str, counts: dict[str, int]
    ) -> RadarSweep | None:
        """The sweep of one radar message, or None when it is skipped (malformed, no pose),
        counted under its reason."""
        try:
            pts = (
                radar_scan_points(msg)
                if hasattr(msg, "returns")
                else radar_cloud_points(msg, r, where)
            )
        except CloudError as e:
            self._skip("radar_messages_malformed", counts, "%s: %s; skipped", where, e)
            return None
        ego = self._poses.ego(t)
        if ego is None:
            counts["radar_sweeps_no_pose"] += 1
            return None
        s2e = self._extrinsic(r.frame or msg.header.frame_id, where)
        if not r.compensated:
            v = self._sensor_velocity(t, s2e)
            if v is None:
                counts["radar_sweeps_no_pose"] += 1
                return None
            compensate(pts, v)
        return RadarSweep(pts, s2e, ego, t, r.channel)

    def _emit(
        self,
        upto_ns: int | None,
        lidar_q: list[tuple[int, np.ndarray, str, int]],
        radar_q: list[RadarSweep],
        counts: dict[str, int],
        state: dict,
    ) -> Iterator[Frame]:
        """The frames of the queued lidar sweeps whose stamps are ``sync_tolerance_s`` before
        bag time ``upto_ns`` (all with None), each with the radar sweeps since the last frame and
        the count of lidar sweeps skipped before it (``Frame.lidar_skipped``)."""
        rig = self.rig
        tol_ns = int(rig.sync_tolerance_s * 1e9)
        while lidar_q and (upto_ns is None or lidar_q[0][0] * 1000 + tol_ns < upto_ns):
            t, pts, frame_id, skipped = lidar_q.pop(0)
            skipped += state["carry"]
            ego = self._poses.ego(t)
            if ego is None:
                state["carry"] = skipped + 1  # this sweep's gap too, at the next frame
                self._skip(
                    "frames_no_pose",
                    counts,
                    "%s: no ego pose at lidar stamp %d us (%s -> %s); frame skipped",
                    self.path,
                    t,
                    rig.world_frame,
                    rig.base_frame,
                )
                continue
            last = state["last_t"]
            mine = [s for s in radar_q if s.timestamp <= t and (last is None or s.timestamp > last)]
            radar_q[:] = [s for s in radar_q if s.timestamp > t]
            radar = {
                r.channel: tuple(
                    sorted((s for s in mine if s.channel == r.channel), key=lambda s: s.timestamp)
                )
                for r in rig.radars
            }
            i = state["index"]
            kf = self._is_keyframe(i, t, state["kf"])
            s2e = self._extrinsic(frame_id, f"{self.path} lidar {rig.lidar.topic}")
            lidar = LidarSweep(pts, s2e, ego, t, LIDAR_CHANNEL)
            state["index"] = i + 1
            state["last_t"] = t
            state["carry"] = 0
            yield Frame(
                scene=self.name,
                index=i,
                timestamp=t,
                ego_pose=ego,
                is_keyframe=kf,
                lidar=lidar,
                radar=radar,
                lidar_skipped=skipped,
            )

    def _reading(self) -> dict:
        """The state of one pass over the sweeps (:meth:`_message`, :meth:`_emit`)."""
        counts = dict.fromkeys(
            (
                "frames_no_pose",
                "lidar_sweeps_duplicate",
                "lidar_sweeps_backwards",
                "lidar_sweeps_future",
                "lidar_messages_malformed",
                "radar_sweeps_late",
                "radar_sweeps_no_pose",
                "radar_sweeps_after_end",
                "radar_messages_malformed",
            ),
            0,
        )
        counts.update(self._pose_counts)
        return {
            "lidar_q": [],  # (stamp us, points, frame id, sweeps skipped before it)
            "radar_q": [],  # RadarSweep
            "counts": counts,
            "leads": deque(maxlen=9),  # lidar stamp minus bag time (us), last accepted
            "index": {},  # messages read per topic
            # skipped: lidar messages skipped since the last one queued, whose gap that one
            # carries
            "state": {"index": 0, "last_t": None, "kf": {}, "skipped": 0, "carry": 0},
            "radar_by_topic": {r.topic: r for r in self.rig.radars},
        }

    def _message(self, topic: str, bag_t: int, msg: Any, rd: dict) -> None:
        """Take one sweep message of the pass ``rd``: a lidar sweep is queued for its frame, a
        radar sweep (with its pose) for the frames; what cannot be used is counted."""
        from evgrid.ros import stamp_to_us

        rig, state, counts = self.rig, rd["state"], rd["counts"]
        k = rd["index"][topic] = rd["index"].get(topic, -1) + 1
        t = stamp_to_us(msg.header.stamp)
        where = f"{self.path} {topic} message {k} (stamp {t} us)"
        if topic == rig.lidar.topic:
            reason = self._lidar_stamp(t, bag_t, state["last_t"], rd["lidar_q"], rd["leads"])
            if reason is not None:
                state["skipped"] += 1
                self._skip(
                    f"lidar_sweeps_{reason}",
                    counts,
                    "%s: %s; sweep skipped",
                    where,
                    _STAMP_REASONS[reason].format(
                        last=state["last_t"], lead=bag_t // 1000, future=_FUTURE_S
                    ),
                )
                return
            try:
                pts = lidar_points(msg, rig.lidar, where)
            except CloudError as e:
                state["skipped"] += 1
                self._skip("lidar_messages_malformed", counts, "%s: %s; skipped", where, e)
                return
            rd["leads"].append(t - bag_t // 1000)
            # recorded out of order within the tolerance: put it in its place
            bisect.insort(
                rd["lidar_q"],
                (t, pts, rig.lidar.frame or msg.header.frame_id, state["skipped"]),
                key=lambda q: q[0],
            )
            state["skipped"] = 0
        elif state["last_t"] is not None and t <= state["last_t"]:
            counts["radar_sweeps_late"] += 1
        else:
            sweep = self._radar_sweep(msg, rd["radar_by_topic"][topic], t, where, counts)
            if sweep is not None:
                rd["radar_q"].append(sweep)

    def __iter__(self) -> Iterator[Frame]:
        rig = self.rig
        rd = self._reading()
        args = (rd["lidar_q"], rd["radar_q"], rd["counts"], rd["state"])
        for topic, bag_t, msg in self._rec.messages({rig.lidar.topic, *rd["radar_by_topic"]}):
            self._message(topic, bag_t, msg, rd)
            yield from self._emit(bag_t, *args)
        yield from self._emit(None, *args)
        counts = rd["counts"]
        counts["radar_sweeps_after_end"] = len(rd["radar_q"])
        self.counts = counts
        self._logged = {}
        if self._rec.stopped:
            self.stopped = self._rec.stopped
            logger.warning("%s; the scene ends at frame %d", self.stopped, rd["state"]["index"])


#: Why a lidar message is skipped for its stamp (``{last}``: the last frame's stamp, us).
_STAMP_REASONS = {
    "duplicate": "stamp repeats one already read",
    "backwards": "stamp is before the last frame made (t = {last} us), beyond the sync tolerance",
    "future": "stamp lies more than {future:g} s ahead of the recording's clock ({lead} us), "
    "beyond the lead the sweeps before had",
}


def load_bag(path: str | Path, rig: RecordingRig | Mapping[str, Any] | str | Path) -> BagScene:
    """A recording (``.bag``, ``.mcap`` or a ROS 2 bag folder) as a scene, read as the rig (a
    file, its dict or a RecordingRig) says.

    Raises :class:`BagError` naming missing topics or frames (fields are checked as sweeps are
    read), :class:`RigError` for a bad rig file.
    """
    if isinstance(rig, Mapping):
        rig = RecordingRig.from_dict(rig)
    elif not isinstance(rig, RecordingRig):
        rig = load_rig(rig)
    return BagScene(path, rig)
