"""``evgrid replay``: a recording's topics published onto DDS at their recorded timing, as
``ros2 bag play`` does: the recorded CDR payloads under their ROS 2 topic and type names, with
the QoS a ROS 2 publisher of each topic uses, after waiting (bounded) for subscribers.

Stamps are moved to the present by default (``stamps="now"``: every stamp shifted by one offset,
whole microseconds, so the recording looks like a robot driving now); ``"recorded"`` keeps
them. ``/tf_static`` is published as tf2's static broadcaster does: one transient-local message
holding every static transform seen so far. With ``loop`` each pass after the first moves the
stamps on by the recording's length and the poses (``world -> base``, odometry) by the loop's
displacement (first ego pose to last), so time never runs backwards and the path continues.

ROS 1 bags are not played: their payloads are ROS 1 serialisations with ROS 1 headers (``seq``);
convert them first (``rosbags-convert --src drive.bag --dst drive``, rosbags' converter).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evgrid.data.bag.errors import BagError
from evgrid.data.bag.reading import bag_kind
from evgrid.data.bag.rig import RecordingRig
from evgrid.geometry import SE3
from evgrid.live.dds import TF_QOS, TF_STATIC_QOS, Graph, QosProfile
from evgrid.live.source import sweep_topics

__all__ = ["replay", "raw_messages", "ReplayReport"]

log = logging.getLogger(__name__)

#: What ``ros2 bag play`` offers when a recording says nothing: reliable, volatile.
PLAY_QOS = QosProfile(reliable=True, transient_local=False, depth=10)


def raw_messages(path: str | Path, topics: set[str]) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, bag time ns, CDR payload) of ``topics`` in a ROS 2 bag or an MCAP file,
    in bag order."""
    path = Path(path)
    kind = bag_kind(path)
    if kind == "ros1":
        raise BagError(
            f"{path}: a ROS 1 bag holds ROS 1 payloads; convert it to ROS 2 first "
            "(rosbags-convert --src drive.bag --dst drive) and replay the result"
        )
    if kind in ("mcap", "ros2-mcap"):
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        files = [path] if kind == "mcap" else sorted(path.glob("*.mcap"))
        for f in files:
            schemas: dict[int, str] = {}
            channels: dict[int, tuple[str, str]] = {}
            with open(f, "rb") as fh:
                for rec in StreamReader(fh, validate_crcs=False).records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec.name
                    elif isinstance(rec, Channel):
                        channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                    elif isinstance(rec, Message):
                        topic, typ = channels.get(rec.channel_id, ("", ""))
                        if topic in topics:
                            yield topic, typ, rec.log_time, bytes(rec.data)
        return
    from rosbags.highlevel import AnyReader

    from evgrid.ros import typestore

    db = path.parent if path.suffix == ".db3" else path
    with AnyReader([db], default_typestore=typestore(2)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, t, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t, bytes(raw)


@dataclass
class ReplayReport:
    messages: int
    passes: int
    seconds: float
    late_ms_max: float  # the latest a message went out after its time
    unmatched: list[str]  # topics no subscriber had matched when playing began

    def line(self) -> str:
        """What ``evgrid replay`` prints at the end."""
        return (
            f"evgrid replay: {self.messages} messages in {self.passes} pass(es), "
            f"{self.seconds:.1f} s; latest {self.late_ms_max:.0f} ms behind its time"
        )


def _shift_stamp(stamp: Any, offset_ns: int) -> None:
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) + offset_ns
    stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)


def _moved(msg: Any, topic: str, offset_ns: int, shift: SE3 | None, rig: RecordingRig) -> Any:
    """The message with its stamps moved by ``offset_ns`` and, with ``shift``, its ego poses
    (``world -> base`` transforms, odometry) moved by it (left-multiplied)."""
    from evgrid.ros import se3_to_transform, transform_to_se3

    if hasattr(msg, "transforms"):
        for tr in msg.transforms:
            _shift_stamp(tr.header.stamp, offset_ns)
            is_ego = (
                tr.header.frame_id.lstrip("/") == rig.world_frame
                and tr.child_frame_id.lstrip("/") == rig.base_frame
            )
            if shift is not None and is_ego and topic != rig.tf_static_topic:
                tt, q = tr.transform.translation, tr.transform.rotation
                p = shift @ transform_to_se3((tt.x, tt.y, tt.z), (q.x, q.y, q.z, q.w))
                (tt.x, tt.y, tt.z), (q.x, q.y, q.z, q.w) = se3_to_transform(p)
        return msg
    _shift_stamp(msg.header.stamp, offset_ns)
    if shift is not None and topic == rig.odometry_topic:
        pp = msg.pose.pose
        o = pp.orientation
        p = shift @ transform_to_se3(
            (pp.position.x, pp.position.y, pp.position.z), (o.x, o.y, o.z, o.w)
        )
        (pp.position.x, pp.position.y, pp.position.z), (o.x, o.y, o.z, o.w) = se3_to_transform(p)
    return msg


def _ego_track(path: Path, rig: RecordingRig) -> tuple[SE3, SE3, int, int]:
    """The first and last ego pose of a recording and their stamps (ns), for ``--loop``."""
    from evgrid.data.bag.scene import _pose_samples
    from evgrid.ros import transform_to_se3, typestore

    store, found = typestore(2), []
    topic = rig.odometry_topic or rig.tf_topic
    for t, typ, _, raw in raw_messages(path, {topic}):
        for parent, child, t_us, tr, q, _ in _pose_samples(t, store.deserialize_cdr(raw, typ), rig):
            if parent.lstrip("/") == rig.world_frame and child.lstrip("/") == rig.base_frame:
                found.append((t_us, tr, q))
    if len(found) < 2:
        raise BagError(f"{path}: --loop needs ego poses ({rig.world_frame} -> {rig.base_frame})")
    found.sort(key=lambda f: f[0])
    (t0, a, qa), (t1, b, qb) = found[0], found[-1]
    return transform_to_se3(a, qa), transform_to_se3(b, qb), t0 * 1000, t1 * 1000


def _recorded_topics(path: Path, topics: Mapping[str, str]) -> tuple[dict[str, str], int | None]:
    """Which of ``topics`` the recording has, with their types as recorded, and the first
    message's time."""
    found: dict[str, str] = {}
    first_ns = None
    for topic, typ, t, _ in raw_messages(path, set(topics)):
        found.setdefault(topic, typ)
        first_ns = t if first_ns is None else first_ns
        if len(found) == len(topics):
            break
    return found, first_ns


def replay(
    recording: str | Path,
    rig: RecordingRig,
    rate: float = 1.0,
    loop: bool = False,
    stamps: str = "now",
    wait_s: float = 5.0,
    domain: int | None = None,
    stop: Callable[[], bool] = lambda: False,
    say: Callable[[str], None] = print,
    passes: int | None = None,
) -> ReplayReport:
    """Publish ``recording``'s rig topics at their recorded timing (``rate`` times as fast),
    once or, with ``loop``, until ``stop()`` (or ``passes``)."""
    from evgrid.ros import typestore

    if not rate > 0 or not math.isfinite(rate):
        raise ValueError(f"--rate must be a positive number, got {rate!r}")
    if stamps not in ("now", "recorded"):
        raise ValueError(f"stamps must be 'now' or 'recorded', got {stamps!r}")
    path = Path(recording)
    topics = sweep_topics(rig)
    store = typestore(2)
    found, first_ns = _recorded_topics(path, topics)
    missing = [t for t in topics if t not in found and t != rig.tf_static_topic]
    if missing:
        raise BagError(f"{path}: rig topic(s) {missing} not in the recording")
    span = _ego_track(path, rig) if loop else None
    graph = Graph(domain)
    try:
        # sensors as ros2 bag play offers them (reliable): best-effort readers match too
        qos = {rig.tf_topic: TF_QOS, rig.tf_static_topic: TF_STATIC_QOS}
        writers = {t: graph.writer(t, typ, qos.get(t, PLAY_QOS)) for t, typ in found.items()}
        end = time.monotonic() + wait_s
        while time.monotonic() < end and not all(w.subscribers() for w in writers.values()):
            time.sleep(0.05)
        unmatched = sorted(t for t, w in writers.items() if not w.subscribers())
        if unmatched:
            say(f"evgrid replay: no subscriber after {wait_s:g} s on {', '.join(unmatched)}")
        return _play(
            path, rig, writers, store, rate, loop, stamps, span, stop, say, passes, first_ns,
            unmatched,
        )  # fmt: skip
    finally:
        time.sleep(0.5)  # reliable writers hand over their last samples
        graph.close()


#: The pause (ns of stamps) between two passes of ``--loop``: the vehicle stands at the end of
#: the loop for one 10 Hz period before the next pass starts where this one ended.
LOOP_GAP_NS = 100_000_000


def _play(
    path, rig, writers, store, rate, loop, stamps, span, stop, say, passes, first_ns, unmatched
):  # noqa: E501
    statics: dict[str, Any] = {}  # child frame -> its static transform, as tf2's broadcaster keeps
    t_start = time.monotonic()
    offset = (time.time_ns() - first_ns) // 1000 * 1000 if stamps == "now" else 0
    n, k, late = 0, 0, 0.0
    length_ns = 0  # of one pass, in stamps, with the gap
    shift = SE3.identity()
    while True:
        pass_offset = offset + k * length_ns
        t0 = t_start + k * length_ns / 1e9 / rate
        last_ns = first_ns
        for topic, typ, bag_ns, raw in raw_messages(path, set(writers)):
            if stop():
                return ReplayReport(n, k + 1, time.monotonic() - t_start, late, unmatched)
            due = t0 + (bag_ns - first_ns) / 1e9 / rate
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            else:
                late = max(late, -wait * 1e3)
            if pass_offset or k or topic == rig.tf_static_topic:
                msg = _moved(
                    store.deserialize_cdr(raw, typ), topic, pass_offset, shift if k else None, rig
                )
                if topic == rig.tf_static_topic:
                    for tr in msg.transforms:
                        statics[tr.child_frame_id] = tr
                    msg.transforms = list(statics.values())
                raw = bytes(store.serialize_cdr(msg, typ))
            writers[topic].write(raw)
            n += 1
            last_ns = max(last_ns, bag_ns)
        k += 1
        if not loop or stop() or (passes is not None and k >= passes):
            return ReplayReport(n, k, time.monotonic() - t_start, late, unmatched)
        first, last = span[0], span[1]
        length_ns = last_ns - first_ns + LOOP_GAP_NS
        shift = (last @ first.inverse()) @ shift
        say(f"evgrid replay: pass {k + 1}")


def replay_until_signal(*args: Any, **kwargs: Any) -> ReplayReport:
    """:func:`replay` that Ctrl-C or SIGTERM stop at the next message (the command's way)."""
    import signal
    import threading

    stop = threading.Event()
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, lambda *_: stop.set())
    try:
        return replay(*args, stop=stop.is_set, **kwargs)
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
