"""Scenes from robot recordings: ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and plain MCAP files.

A *rig file* (YAML, see docs/ros.md and docs/rig_example.yaml) says which topics hold the lidar
and the radars, which frames are the world and the vehicle, how point-cloud fields are named and
which lidar sweeps are keyframes. :func:`load_bag` turns the recording into a scene of
:class:`~evgrid.data.frame.Frame` like every other source:

* one frame per lidar message (``sensor_msgs/PointCloud2``), at its header stamp;
* the radar sweeps (``sensor_msgs/PointCloud2`` with named fields, or ``radar_msgs/RadarScan``)
  whose stamps fall in ``(previous frame, this frame]``, oldest first;
* ego poses (base frame in the world frame) from ``/tf`` or a ``nav_msgs/Odometry`` topic,
  interpolated at each sweep's own stamp (linear in translation, spherical in rotation);
* extrinsics (sensor frame in the base frame) from ``/tf_static`` or the rig file.

Recordings are read twice: once for the poses (small messages), once, lazily, for the sweeps.
A truncated recording is read up to where it breaks; the scene's ``stopped`` says where, and a
warning is logged.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.data.frame import (
    LIDAR_CHANNEL,
    LIDAR_COLUMNS,
    RADAR_COLUMNS,
    Frame,
    LidarSweep,
    RadarSweep,
)
from evgrid.geometry import SE3

__all__ = [
    "BagError",
    "RigError",
    "RigConfig",
    "LidarTopic",
    "RadarTopic",
    "load_rig",
    "load_bag",
    "BagScene",
    "TransformBuffer",
    "bag_kind",
]

logger = logging.getLogger(__name__)


class BagError(ValueError):
    """A recording that cannot be mapped as the rig file describes it (missing topic, frame or field)."""


class RigError(ValueError):
    """A rig file that is not valid."""


#: Radar columns a cloud must provide (or that the rig must map): position and cross-section.
RADAR_REQUIRED = ("x", "y", "z", "rcs")
#: Values of the ARS 408 validity columns when a radar does not report them: stationary,
#: unambiguous, valid, false-alarm probability < 25 % (what the ISMs would accept anyway).
RADAR_DEFAULTS = {"dyn_prop": 1.0, "ambig_state": 3.0, "invalid_state": 0.0, "pdh0": 1.0}
_RADIAL = "radial_velocity"


# --- the rig file -------------------------------------------------------------------------------


def _fields(d: Any, allowed: tuple[str, ...], where: str) -> dict[str, str]:
    if d is None:
        return {}
    if not isinstance(d, Mapping):
        raise RigError(f"{where}: 'fields' must map column names to field names, got {d!r}")
    bad = [k for k in d if k not in allowed]
    if bad:
        raise RigError(f"{where}: unknown column(s) {bad} in 'fields'; columns are {list(allowed)}")
    for k, v in d.items():
        if not isinstance(v, str) or not v:
            raise RigError(f"{where}: fields.{k} must be a field name, got {v!r}")
    return dict(d)


@dataclass(frozen=True)
class LidarTopic:
    """The lidar: its topic, optionally its frame (else the header's) and field names per column."""

    topic: str
    frame: str | None = None
    fields: Mapping[str, str] = field(default_factory=dict)

    def field_name(self, column: str) -> str:
        return self.fields.get(column, column)


@dataclass(frozen=True)
class RadarTopic:
    """One radar: its topic, the channel name its sweeps get, optionally its frame and field names."""

    topic: str
    channel: str
    frame: str | None = None
    fields: Mapping[str, str] = field(default_factory=dict)
    compensated: bool = (
        True  # False: raw Doppler, compensated here with the ego motion of the poses
    )

    def field_name(self, column: str) -> str:
        return self.fields.get(column, column)


@dataclass(frozen=True)
class RigConfig:
    """What the recording's topics and frames mean (see docs/ros.md)."""

    lidar: LidarTopic
    radars: tuple[RadarTopic, ...] = ()
    world_frame: str = "odom"
    base_frame: str = "base_link"
    odometry_topic: str | None = None  # None: ego poses from tf_topic
    tf_topic: str = "/tf"
    tf_static_topic: str = "/tf_static"
    extrinsics: Mapping[str, SE3] = field(
        default_factory=dict
    )  # frame -> sensor_to_ego, beats /tf_static
    keyframe_every: int | None = 10  # every N-th lidar frame from the first ...
    keyframe_rate_hz: float | None = (
        None  # ... or the first frame at or after each tick of this rate
    )
    sync_tolerance_s: float = 0.5  # how late (in bag time) a radar sweep may arrive after its frame
    max_pose_gap_s: float = (
        0.1  # how far beyond the pose track a sweep may lie and still get a pose
    )
    scene: str | None = None  # scene name; default: the recording's file name

    def __post_init__(self) -> None:
        if (self.keyframe_every is None) == (self.keyframe_rate_hz is None):
            raise RigError("rig: give exactly one of keyframes.every and keyframes.rate_hz")
        if self.keyframe_every is not None and (
            not isinstance(self.keyframe_every, int) or self.keyframe_every < 1
        ):
            raise RigError(
                f"rig: keyframes.every must be an integer >= 1, got {self.keyframe_every!r}"
            )
        if self.keyframe_rate_hz is not None and not (
            self.keyframe_rate_hz > 0 and math.isfinite(self.keyframe_rate_hz)
        ):
            raise RigError(
                f"rig: keyframes.rate_hz must be positive, got {self.keyframe_rate_hz!r}"
            )
        for name in ("sync_tolerance_s", "max_pose_gap_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0 and math.isfinite(v)):
                raise RigError(f"rig: {name} must be a non-negative number of seconds, got {v!r}")
        channels = [r.channel for r in self.radars]
        dup = sorted({c for c in channels if channels.count(c) > 1})
        if dup:
            raise RigError(f"rig: radar channel(s) {dup} named twice")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "rig") -> RigConfig:
        """From the parsed YAML; raises :class:`RigError` naming the bad key."""
        if not isinstance(d, Mapping):
            raise RigError(f"{where}: must be a mapping, got {type(d).__name__}")
        known = {
            "scene",
            "world_frame",
            "base_frame",
            "poses",
            "lidar",
            "radars",
            "keyframes",
            "extrinsics",
            "sync_tolerance_s",
            "max_pose_gap_s",
        }
        bad = sorted(set(d) - known)
        if bad:
            raise RigError(f"{where}: unknown key(s) {bad}; keys are {sorted(known)}")
        lid = d.get("lidar")
        if not isinstance(lid, Mapping) or not isinstance(lid.get("topic"), str):
            raise RigError(f"{where}: 'lidar' must give at least a 'topic'")
        lidar = LidarTopic(
            lid["topic"],
            lid.get("frame"),
            _fields(lid.get("fields"), LIDAR_COLUMNS, f"{where} lidar"),
        )
        radars = []
        for i, r in enumerate(d.get("radars") or ()):
            w = f"{where} radars[{i}]"
            if not isinstance(r, Mapping) or not isinstance(r.get("topic"), str):
                raise RigError(f"{w}: each radar needs a 'topic'")
            ch = r.get("channel") or r["topic"].strip("/").replace("/", "_").upper()
            comp = r.get("compensated", True)
            if not isinstance(comp, bool):
                raise RigError(f"{w}: compensated must be true or false, got {comp!r}")
            radars.append(
                RadarTopic(
                    r["topic"],
                    str(ch),
                    r.get("frame"),
                    _fields(r.get("fields"), RADAR_COLUMNS + (_RADIAL,), w),
                    comp,
                )
            )
        poses = d.get("poses") or {}
        if not isinstance(poses, Mapping):
            raise RigError(f"{where}: 'poses' must be a mapping")
        source = poses.get("source", "tf")
        if source not in ("tf", "odometry"):
            raise RigError(f"{where}: poses.source must be 'tf' or 'odometry', got {source!r}")
        if source == "odometry" and not isinstance(poses.get("topic"), str):
            raise RigError(f"{where}: poses.source 'odometry' needs poses.topic")
        kf = d.get("keyframes") or {"every": 10}
        if not isinstance(kf, Mapping):
            raise RigError(f"{where}: 'keyframes' must be a mapping with 'every' or 'rate_hz'")
        ext = {}
        for frame, e in (d.get("extrinsics") or {}).items():
            ext[str(frame)] = _extrinsic(e, f"{where} extrinsics.{frame}")
        return cls(
            lidar=lidar,
            radars=tuple(radars),
            world_frame=str(d.get("world_frame", "odom")),
            base_frame=str(d.get("base_frame", "base_link")),
            odometry_topic=poses.get("topic") if source == "odometry" else None,
            tf_topic=str(poses.get("tf_topic", "/tf")),
            tf_static_topic=str(poses.get("tf_static_topic", "/tf_static")),
            extrinsics=ext,
            keyframe_every=kf.get("every"),
            keyframe_rate_hz=kf.get("rate_hz"),
            sync_tolerance_s=d.get("sync_tolerance_s", 0.5),
            max_pose_gap_s=d.get("max_pose_gap_s", 0.1),
            scene=d.get("scene"),
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data that :meth:`from_dict` reads back (extrinsics as translation + quaternion)."""
        from evgrid.geometry import matrix_to_quaternion

        out: dict[str, Any] = {
            "world_frame": self.world_frame,
            "base_frame": self.base_frame,
            "poses": (
                {"source": "odometry", "topic": self.odometry_topic}
                if self.odometry_topic
                else {
                    "source": "tf",
                    "tf_topic": self.tf_topic,
                    "tf_static_topic": self.tf_static_topic,
                }
            ),
            "lidar": {
                "topic": self.lidar.topic,
                **({"frame": self.lidar.frame} if self.lidar.frame else {}),
                **({"fields": dict(self.lidar.fields)} if self.lidar.fields else {}),
            },
            "radars": [
                {
                    "topic": r.topic,
                    "channel": r.channel,
                    **({"frame": r.frame} if r.frame else {}),
                    **({"fields": dict(r.fields)} if r.fields else {}),
                    **({} if r.compensated else {"compensated": False}),
                }
                for r in self.radars
            ],
            "keyframes": {"every": self.keyframe_every}
            if self.keyframe_every
            else {"rate_hz": self.keyframe_rate_hz},
            "sync_tolerance_s": self.sync_tolerance_s,
            "max_pose_gap_s": self.max_pose_gap_s,
        }
        if self.scene:
            out["scene"] = self.scene
        if self.extrinsics:
            out["extrinsics"] = {
                k: {
                    "translation": [float(v) for v in p.translation],
                    "rotation_wxyz": [float(v) for v in matrix_to_quaternion(p.rotation)],
                }
                for k, p in self.extrinsics.items()
            }
        return out


def _extrinsic(e: Any, where: str) -> SE3:
    if not isinstance(e, Mapping) or "translation" not in e:
        raise RigError(f"{where}: give 'translation' [x, y, z] and 'yaw_deg' or 'rotation_wxyz'")
    t = e["translation"]
    if not (isinstance(t, (list, tuple)) and len(t) == 3):
        raise RigError(f"{where}: translation must be [x, y, z] in metres, got {t!r}")
    try:
        if "rotation_wxyz" in e:
            return SE3.from_quaternion(e["rotation_wxyz"], t)
        yaw = math.radians(float(e.get("yaw_deg", 0.0)))
        c, s = math.cos(yaw), math.sin(yaw)
        return SE3(
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(t, dtype=np.float64)
        )
    except (TypeError, ValueError) as err:
        raise RigError(f"{where}: {err}") from None


def load_rig(path: str | Path) -> RigConfig:
    """Read a rig file (YAML); raises :class:`RigError` (or FileNotFoundError) naming the problem."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no rig file at {path}")
    try:
        import yaml
    except ImportError:
        raise ImportError("reading a rig file needs PyYAML (pip install 'evgrid[ros]')") from None
    try:
        d = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RigError(f"{path}: not valid YAML: {str(e).splitlines()[0]}") from None
    return RigConfig.from_dict(d, str(path))


# --- reading recordings ---------------------------------------------------------------------------


def bag_kind(path: str | Path) -> str:
    """``ros1`` (a ``.bag`` file), ``ros2-sqlite3`` / ``ros2-mcap`` (a rosbag2 folder) or ``mcap`` (a file)."""
    p = Path(path)
    if p.is_dir():
        meta = p / "metadata.yaml"
        if not meta.is_file():
            raise BagError(f"{p} is a folder without metadata.yaml: not a ROS 2 bag")
        text = meta.read_text()
        if "storage_identifier: mcap" in text:
            return "ros2-mcap"
        return "ros2-sqlite3"
    if not p.is_file():
        raise FileNotFoundError(f"no recording at {p}")
    if p.suffix == ".bag":
        return "ros1"
    if p.suffix == ".mcap":
        return "mcap"
    if p.suffix == ".db3":
        return "ros2-sqlite3"
    raise BagError(
        f"{p}: unknown recording type (expected a .bag or .mcap file or a ROS 2 bag folder)"
    )


class _Recording:
    """Messages of some topics, in bag order, deserialised; notes where a damaged file stopped."""

    def __init__(self, path: str | Path):
        from evgrid.ros import require

        require("rosbags")
        self.path = Path(path)
        self.kind = bag_kind(self.path)
        self.topics: dict[str, str] = {}  # topic -> message type, as far as read
        self.stopped: str | None = None

    def _mcap_files(self) -> list[Path]:
        if self.kind == "mcap":
            return [self.path]
        files = sorted(self.path.glob("*.mcap"))
        if not files:
            raise BagError(f"{self.path}: ROS 2 bag with MCAP storage but no .mcap file in it")
        return files

    def messages(
        self, topics: set[str], count_only: set[str] = frozenset()
    ) -> Iterator[tuple[str, int, Any]]:
        """(topic, bag time ns, message) for ``topics``; ``count_only`` topics yield ``None`` messages."""
        self.stopped = None
        if self.kind in ("mcap", "ros2-mcap"):
            for f in self._mcap_files():
                yield from self._mcap_messages(f, topics, count_only)
                if self.stopped:
                    return
        else:
            yield from self._rosbags_messages(topics, count_only)

    def _mcap_messages(
        self, path: Path, topics: set[str], count_only: set[str]
    ) -> Iterator[tuple[str, int, Any]]:
        from evgrid.ros import new_typestore, require

        require("mcap")
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader
        from rosbags.typesys import get_types_from_msg

        store = new_typestore(2)  # the file's own definitions are added to it
        schemas: dict[int, Schema] = {}
        channels: dict[int, tuple[str, str]] = {}
        last_t = None
        with open(path, "rb") as fh:
            reader = StreamReader(fh, validate_crcs=False)
            try:
                for rec in reader.records:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        sch = schemas.get(rec.schema_id)
                        name = sch.name if sch else ""
                        if (
                            sch is not None
                            and name not in store.fielddefs
                            and sch.encoding == "ros2msg"
                        ):
                            store.register(get_types_from_msg(sch.data.decode(), name))
                        channels[rec.id] = (rec.topic, name)
                        self.topics[rec.topic] = name
                    elif isinstance(rec, Message):
                        topic, typ = channels.get(rec.channel_id, ("", ""))
                        last_t = rec.log_time
                        if topic in count_only:
                            yield topic, rec.log_time, None
                        elif topic in topics:
                            yield topic, rec.log_time, store.deserialize_cdr(rec.data, typ)
            except Exception as e:  # noqa: BLE001 - any damage ends the readable part
                self.stopped = (
                    f"{path} is damaged or truncated at byte {fh.tell()}"
                    f"{f' after bag time {last_t} ns' if last_t is not None else ''}: "
                    f"{type(e).__name__} {e}".rstrip()
                )

    def _rosbags_messages(
        self, topics: set[str], count_only: set[str]
    ) -> Iterator[tuple[str, int, Any]]:
        from rosbags.highlevel import AnyReader

        from evgrid.ros import typestore

        paths = [self.path.parent if self.path.suffix == ".db3" else self.path]
        try:
            reader = AnyReader(paths, default_typestore=typestore(2 if self.kind != "ros1" else 1))
            reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags raises several types for damaged files
            if (
                self.kind == "ros1"
            ):  # a bag whose recording was cut has no index: read it record by record
                yield from self._ros1_scan(topics, count_only)
                return
            raise BagError(
                f"{self.path}: cannot read the recording: {type(e).__name__} {e}"
            ) from None
        last_t = None
        try:
            self.topics.update({c.topic: c.msgtype for c in reader.connections})
            conns = [c for c in reader.connections if c.topic in topics | set(count_only)]
            for conn, t, raw in reader.messages(connections=conns):
                last_t = t
                if conn.topic in count_only:
                    yield conn.topic, t, None
                else:
                    yield conn.topic, t, reader.deserialize(raw, conn.msgtype)
        except Exception as e:  # noqa: BLE001 - any damage ends the readable part
            self.stopped = f"{self.path} is damaged or truncated after bag time {last_t} ns: {type(e).__name__} {e}"
        finally:
            reader.close()

    def _ros1_scan(self, topics: set[str], count_only: set[str]) -> Iterator[tuple[str, int, Any]]:
        """Messages of a ROS 1 bag (format 2.0) read record by record, without its index."""
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        from rosbags.typesys.msg import normalize_msgtype

        store = get_typestore(Stores.EMPTY)
        conns: dict[int, tuple[str, str]] = {}
        last_t = None
        with open(self.path, "rb") as fh:
            if fh.readline() != b"#ROSBAG V2.0\n":
                raise BagError(f"{self.path} is not a ROS 1 bag (format 2.0)")
            try:
                for op, hdr, data in _ros1_records(fh):
                    for op2, hdr2, data2 in (
                        _ros1_chunk(hdr, data) if op == 0x05 else [(op, hdr, data)]
                    ):
                        if op2 == 0x07:  # connection: topic, type and message definition
                            ch = _ros1_header(data2)
                            typ = normalize_msgtype(ch["type"].decode())
                            if typ not in store.fielddefs:
                                store.register(
                                    get_types_from_msg(ch["message_definition"].decode(), typ)
                                )
                            topic = hdr2["topic"].decode()
                            conns[int.from_bytes(hdr2["conn"], "little")] = (topic, typ)
                            self.topics[topic] = typ
                        elif op2 == 0x02:  # message data
                            topic, typ = conns[int.from_bytes(hdr2["conn"], "little")]
                            sec, nsec = (
                                int.from_bytes(hdr2["time"][:4], "little"),
                                int.from_bytes(hdr2["time"][4:], "little"),
                            )
                            last_t = sec * 1_000_000_000 + nsec
                            if topic in count_only:
                                yield topic, last_t, None
                            elif topic in topics:
                                yield topic, last_t, store.deserialize_ros1(data2, typ)
            except Exception as e:  # noqa: BLE001 - any damage ends the readable part
                self.stopped = (
                    f"{self.path} is damaged or truncated at byte {fh.tell()}"
                    f"{f' after bag time {last_t} ns' if last_t is not None else ''}: "
                    f"{type(e).__name__} {e}".rstrip()
                )


def _ros1_header(buf: bytes) -> dict[str, bytes]:
    """Fields ``name=value`` of a ROS 1 record header (each prefixed by its uint32 length)."""
    out, i = {}, 0
    while i < len(buf):
        n = int.from_bytes(buf[i : i + 4], "little")
        name, _, value = buf[i + 4 : i + 4 + n].partition(b"=")
        out[name.decode()] = value
        i += 4 + n
    return out


def _ros1_records(fh: Any) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
    """(op code, header fields, data) of each record of a ROS 1 bag stream; EOFError when one is cut short."""
    while True:
        raw = fh.read(4)
        if not raw:
            return
        parts = []
        for k in range(2):
            if len(raw) < 4:
                raise EOFError("record length cut short")
            n = int.from_bytes(raw, "little")
            body = fh.read(n)
            if len(body) < n:
                raise EOFError("record cut short")
            parts.append(body)
            raw = fh.read(4) if k == 0 else b""
        hdr = _ros1_header(parts[0])
        yield hdr["op"][0], hdr, parts[1]


def _ros1_chunk(
    hdr: dict[str, bytes], data: bytes
) -> Iterator[tuple[int, dict[str, bytes], bytes]]:
    import io

    comp = hdr.get("compression", b"none").decode()
    if comp == "bz2":
        import bz2

        data = bz2.decompress(data)
    elif comp == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(data)
    elif comp != "none":
        raise BagError(f"unknown ROS 1 chunk compression {comp!r}")
    return _ros1_records(io.BytesIO(data))


# --- transforms -------------------------------------------------------------------------------------


class TransformBuffer:
    """The tf tree over time: per child frame its parent and samples; static edges apart.

    :meth:`lookup` gives the pose of a frame in an ancestor frame at a time, interpolating
    every dynamic edge on the way (and returning a stored sample itself when the time is one).
    """

    def __init__(self, max_gap_us: int = 100_000):
        self.max_gap_us = max_gap_us
        self._dyn: dict[str, tuple[str, list[int], list[tuple]]] = {}
        self._static: dict[str, tuple[str, SE3]] = {}
        self._arrays: dict[str, tuple[str, np.ndarray, np.ndarray, np.ndarray]] = {}

    def add(
        self,
        parent: str,
        child: str,
        t_us: int,
        translation: tuple,
        q_xyzw: tuple,
        static: bool = False,
    ) -> None:
        """One transform: the pose of ``child`` in ``parent``."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if static:
            from evgrid.ros import transform_to_se3

            self._static[child] = (parent, transform_to_se3(translation, q_xyzw))
            return
        p, ts, vals = self._dyn.setdefault(child, (parent, [], []))
        ts.append(int(t_us))
        vals.append((*translation, *q_xyzw))
        self._arrays.pop(child, None)

    def frames(self) -> set[str]:
        """Every frame named as a child or a parent."""
        out = set(self._dyn) | set(self._static)
        out |= {p for p, *_ in self._dyn.values()} | {p for p, _ in self._static.values()}
        return out

    def _edge(self, child: str) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
        a = self._arrays.get(child)
        if a is None:
            parent, ts, vals = self._dyn[child]
            t = np.asarray(ts, dtype=np.int64)
            v = np.asarray(vals, dtype=np.float64)
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
            a = self._arrays[child] = (parent, t, v[:, :3], v[:, 3:])
        return a

    def parent(self, child: str) -> str | None:
        """The parent frame of ``child`` (dynamic edges first), or None for a root."""
        child = child.lstrip("/")
        if child in self._dyn:
            return self._dyn[child][0]
        if child in self._static:
            return self._static[child][0]
        return None

    def _sample(self, child: str, t_us: int) -> SE3 | None:
        from evgrid.ros import transform_to_se3

        _, ts, trans, quat = self._edge(child)
        i = int(np.searchsorted(ts, t_us))
        if i < len(ts) and ts[i] == t_us:
            return transform_to_se3(trans[i], quat[i])
        if i == 0:
            return transform_to_se3(trans[0], quat[0]) if ts[0] - t_us <= self.max_gap_us else None
        if i == len(ts):
            return (
                transform_to_se3(trans[-1], quat[-1]) if t_us - ts[-1] <= self.max_gap_us else None
            )
        f = (t_us - ts[i - 1]) / (ts[i] - ts[i - 1])
        tr = (1 - f) * trans[i - 1] + f * trans[i]
        return transform_to_se3(tr, _slerp(quat[i - 1], quat[i], f))

    def span(self, target: str, source: str) -> tuple[int, int] | None:
        """Times (us) over which every dynamic transform from ``source`` up to ``target`` has samples."""
        lo, hi = -(2**62), 2**62
        frame, seen = source.lstrip("/"), set()
        while frame != target.lstrip("/"):
            if frame in seen:
                return None
            seen.add(frame)
            if frame in self._dyn:
                parent, ts, _, _ = self._edge(frame)
                lo, hi = max(lo, int(ts[0])), min(hi, int(ts[-1]))
            elif frame in self._static:
                parent = self._static[frame][0]
            else:
                return None
            frame = parent
        return lo, hi

    def lookup(self, target: str, source: str, t_us: int) -> SE3 | None:
        """Pose of ``source`` in ``target`` at ``t_us`` (None: no chain, or the time is off the track)."""
        target, frame = target.lstrip("/"), source.lstrip("/")
        pose: SE3 | None = None
        seen = set()
        while frame != target:
            if frame in seen:
                return None
            seen.add(frame)
            if frame in self._dyn:
                parent = self._dyn[frame][0]
                step = self._sample(frame, t_us)
                if step is None:
                    return None
            elif frame in self._static:
                parent, step = self._static[frame]
            else:
                return None
            pose = step if pose is None else step @ pose
            frame = parent
        return pose if pose is not None else SE3.identity()


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (x, y, z, w); yaw-only pairs stay yaw-only."""
    if q0[0] == q0[1] == q1[0] == q1[1] == 0.0:  # planar: interpolate the yaw itself
        y0, y1 = 2 * math.atan2(q0[2], q0[3]), 2 * math.atan2(q1[2], q1[3])
        y = y0 + f * math.remainder(y1 - y0, 2 * math.pi)
        return np.array([0.0, 0.0, math.sin(y / 2), math.cos(y / 2)])
    a = q0 / np.linalg.norm(q0)
    b = q1 / np.linalg.norm(q1)
    d = float(a @ b)
    if d < 0:
        b, d = -b, -d
    if d > 0.9995:
        q = a + f * (b - a)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - f) * th) * a + math.sin(f * th) * b) / math.sin(th)


# --- sweeps ---------------------------------------------------------------------------------------


def _lidar_points(msg: Any, lidar: LidarTopic, where: str) -> np.ndarray:
    from evgrid.ros import cloud_fields, cloud_to_columns

    have = set(cloud_fields(msg))
    names, fill = [], []
    for col in LIDAR_COLUMNS:
        name = lidar.field_name(col)
        if name in have:
            names.append(name)
        elif col in ("x", "y", "z") or col in lidar.fields:
            raise BagError(
                f"{where}: lidar field {name!r} (column {col}) not in the cloud; it has {sorted(have)}"
            )
        else:
            fill.append(col)  # intensity / ring: optional
    pts = cloud_to_columns(msg, names)
    if not fill:
        return pts
    out = np.zeros((len(pts), len(LIDAR_COLUMNS)), dtype=np.float32)
    cols = [c for c in LIDAR_COLUMNS if c not in fill]
    out[:, [LIDAR_COLUMNS.index(c) for c in cols]] = pts
    return out


def _radar_cloud_points(msg: Any, radar: RadarTopic, where: str) -> np.ndarray:
    from evgrid.ros import cloud_fields, cloud_to_columns

    have = set(cloud_fields(msg))
    out = np.zeros((int(msg.height) * int(msg.width), len(RADAR_COLUMNS)), dtype=np.float32)
    take = {c: radar.field_name(c) for c in RADAR_COLUMNS if radar.field_name(c) in have}
    for col in radar.fields:
        if col != _RADIAL and col not in take:
            raise BagError(
                f"{where}: radar field {radar.fields[col]!r} (column {col}) not in the cloud; it has {sorted(have)}"
            )
    missing = [radar.field_name(c) for c in RADAR_REQUIRED if c not in take]
    if missing:
        raise BagError(
            f"{where}: radar field(s) {missing} not in the cloud; it has {sorted(have)} (map them under fields:)"
        )
    if take:
        vals = cloud_to_columns(msg, list(take.values()))
        for i, col in enumerate(take):
            out[:, RADAR_COLUMNS.index(col)] = vals[:, i]
    if "vx_comp" not in take or "vy_comp" not in take:
        if (
            "vx" in take and "vy" in take
        ):  # a velocity vector (compensated below if the rig says it is raw)
            out[:, RADAR_COLUMNS.index("vx_comp")] = out[:, RADAR_COLUMNS.index("vx")]
            out[:, RADAR_COLUMNS.index("vy_comp")] = out[:, RADAR_COLUMNS.index("vy")]
        else:
            radial = radar.field_name(_RADIAL)
            if radial not in have:
                raise BagError(
                    f"{where}: radar needs velocity fields (vx_comp and vy_comp, or vx and vy) or a radial "
                    f"velocity field {radial!r}; the cloud has {sorted(have)}"
                )
            _set_radial(out, cloud_to_columns(msg, [radial])[:, 0])
    for raw, comp in (("vx", "vx_comp"), ("vy", "vy_comp")):
        if raw not in take:
            out[:, RADAR_COLUMNS.index(raw)] = out[:, RADAR_COLUMNS.index(comp)]
    for col, v in RADAR_DEFAULTS.items():
        if col not in take:
            out[:, RADAR_COLUMNS.index(col)] = v
    return out


def _set_radial(out: np.ndarray, v_r: np.ndarray) -> None:
    """Velocity columns from a radial (Doppler) speed: the speed along the line of sight, as a vector."""
    x, y, z = (out[:, i].astype(np.float64) for i in range(3))
    r = np.sqrt(x * x + y * y + z * z)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(r > 0, x / r, 0.0)
        uy = np.where(r > 0, y / r, 0.0)
    out[:, RADAR_COLUMNS.index("vx_comp")] = v_r * ux
    out[:, RADAR_COLUMNS.index("vy_comp")] = v_r * uy


def _compensate(out: np.ndarray, v_sensor: np.ndarray) -> None:
    """Ego-motion compensation of raw Doppler velocities: add the sensor's own speed along each line of sight.

    A static target seen from a sensor moving at ``v_sensor`` (sensor frame, m/s) has the raw
    radial speed ``-v_sensor . u`` (u: unit vector to the target); adding ``(v_sensor . u) u``
    to the raw vector ``(vx, vy)`` leaves the target's own motion, as ``vx_comp, vy_comp``.
    """
    p = out[:, :3].astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(r[:, None] > 0, p / r[:, None], 0.0)
    along = u @ v_sensor
    out[:, RADAR_COLUMNS.index("vx_comp")] = out[:, RADAR_COLUMNS.index("vx")] + along * u[:, 0]
    out[:, RADAR_COLUMNS.index("vy_comp")] = out[:, RADAR_COLUMNS.index("vy")] + along * u[:, 1]


def _radar_scan_points(msg: Any) -> np.ndarray:
    """``radar_msgs/RadarScan`` returns -> radar columns (amplitude taken as RCS in dBsm)."""
    ret = msg.returns
    out = np.zeros((len(ret), len(RADAR_COLUMNS)), dtype=np.float32)
    if not len(ret):
        return out
    a = np.array(
        [(r.range, r.azimuth, r.elevation, r.doppler_velocity, r.amplitude) for r in ret],
        dtype=np.float64,
    )
    ce = np.cos(a[:, 2])
    out[:, 0] = a[:, 0] * ce * np.cos(a[:, 1])
    out[:, 1] = a[:, 0] * ce * np.sin(a[:, 1])
    out[:, 2] = a[:, 0] * np.sin(a[:, 2])
    out[:, 3] = a[:, 4]
    _set_radial(out, a[:, 3])
    out[:, 4] = out[:, 6]
    out[:, 5] = out[:, 7]
    for col, v in RADAR_DEFAULTS.items():
        out[:, RADAR_COLUMNS.index(col)] = v
    return out


# --- the scene ------------------------------------------------------------------------------------


@dataclass
class _PoseTrack:
    tf: TransformBuffer
    world: str
    base: str

    def ego(self, t_us: int) -> SE3 | None:
        return self.tf.lookup(self.world, self.base, t_us)


class BagScene:
    """A recording as a :class:`~evgrid.data.frame.Scene`; frames are read lazily on iteration.

    ``stopped`` says where a damaged recording stopped being readable (None when whole);
    ``counts`` what was skipped on the last full iteration (frames without a pose, lidar
    sweeps recorded too late or twice, radar sweeps recorded after their frame was made, without
    a pose, or after the last lidar sweep). Frame indices (and ``keyframes: every``) count the
    frames made.
    """

    def __init__(self, path: str | Path, rig: RigConfig):
        self.path = Path(path)
        self.rig = rig
        self.name = rig.scene or self.path.stem
        self._rec = _Recording(self.path)
        self.stopped: str | None = None
        self.counts: dict[str, int] = {}
        self._scan_poses()

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
        from evgrid.ros import stamp_to_us

        rig = self.rig
        tf = TransformBuffer(int(round(rig.max_pose_gap_s * 1e6)))
        types = self._pose_types()
        count = {rig.lidar.topic} | {r.topic for r in rig.radars}
        self._n_lidar = 0
        for topic, _, msg in self._rec.messages(set(types), count - set(types)):
            if topic == rig.lidar.topic:
                self._n_lidar += 1
            if msg is None:
                continue
            if self._rec.topics[topic] != types[topic]:
                raise BagError(
                    f"{self.path}: pose topic {topic} is {self._rec.topics[topic]}, not {types[topic]}"
                )
            if topic == rig.odometry_topic:
                p = msg.pose.pose
                tf.add(
                    msg.header.frame_id,
                    msg.child_frame_id,
                    stamp_to_us(msg.header.stamp),
                    (p.position.x, p.position.y, p.position.z),
                    (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w),
                )
            else:
                for tr in msg.transforms:
                    tt, q = tr.transform.translation, tr.transform.rotation
                    tf.add(
                        tr.header.frame_id,
                        tr.child_frame_id,
                        stamp_to_us(tr.header.stamp),
                        (tt.x, tt.y, tt.z),
                        (q.x, q.y, q.z, q.w),
                        static=topic == rig.tf_static_topic,
                    )
        self.stopped = self._rec.stopped
        if self.stopped:
            logger.warning("%s; mapping what was read before", self.stopped)
        self._check(tf)
        self._tf = tf
        self._poses = _PoseTrack(tf, rig.world_frame, rig.base_frame)
        self._extrinsics: dict[str, SE3] = {}

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
                    f"{self.path}: radar topic {r.topic} is {typ}; evgrid reads sensor_msgs/PointCloud2 "
                    "or radar_msgs/RadarScan"
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
                    f"{where}: no extrinsics for frame {frame!r}: not in {self.rig.tf_static_topic} "
                    f"below {self.rig.base_frame!r} nor under extrinsics: in the rig file"
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
        """Velocity (m/s) of a sensor's origin in its own frame at ``t_us``: poses differenced over ``t_us +- dt_us``
        (one-sided at the ends of the pose track)."""
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
            return index % rig.keyframe_every == 0
        period = 1e6 / rig.keyframe_rate_hz
        nxt = state.get("next")
        if nxt is None or t_us >= nxt:
            base = t_us if nxt is None else nxt
            state["next"] = base + period * (math.floor((t_us - base) / period) + 1)
            return True
        return False

    def __iter__(self) -> Iterator[Frame]:
        from evgrid.ros import stamp_to_us

        rig = self.rig
        radar_by_topic = {r.topic: r for r in rig.radars}
        tol_ns = int(rig.sync_tolerance_s * 1e9)
        lidar_q: list[tuple[int, np.ndarray, str]] = []
        radar_q: list[RadarSweep] = []
        counts = dict.fromkeys(
            (
                "frames_no_pose",
                "lidar_sweeps_late",
                "radar_sweeps_late",
                "radar_sweeps_no_pose",
                "radar_sweeps_after_end",
            ),
            0,
        )
        state: dict = {"index": 0, "last_t": None, "kf": {}}

        def emit(upto_ns: int | None) -> Iterator[Frame]:
            while lidar_q and (upto_ns is None or lidar_q[0][0] * 1000 + tol_ns < upto_ns):
                t, pts, frame_id = lidar_q.pop(0)
                ego = self._poses.ego(t)
                if ego is None:
                    counts["frames_no_pose"] += 1
                    logger.warning(
                        "%s: no ego pose at lidar stamp %d us (%s -> %s); frame skipped",
                        self.path,
                        t,
                        rig.world_frame,
                        rig.base_frame,
                    )
                    continue
                last = state["last_t"]
                mine = [
                    s for s in radar_q if s.timestamp <= t and (last is None or s.timestamp > last)
                ]
                radar_q[:] = [s for s in radar_q if s.timestamp > t]
                radar = {
                    r.channel: tuple(
                        sorted(
                            (s for s in mine if s.channel == r.channel), key=lambda s: s.timestamp
                        )
                    )
                    for r in rig.radars
                }
                i = state["index"]
                kf = self._is_keyframe(i, t, state["kf"])
                s2e = self._extrinsic(frame_id, f"{self.path} lidar {rig.lidar.topic}")
                lidar = LidarSweep(pts, s2e, ego, t, LIDAR_CHANNEL)
                state["index"] = i + 1
                state["last_t"] = t
                yield Frame(
                    scene=self.name,
                    index=i,
                    timestamp=t,
                    ego_pose=ego,
                    is_keyframe=kf,
                    lidar=lidar,
                    radar=radar,
                )

        topics = {rig.lidar.topic, *radar_by_topic}
        for topic, bag_t, msg in self._rec.messages(topics):
            where = f"{self.path} {topic}"
            t = stamp_to_us(msg.header.stamp)
            if topic == rig.lidar.topic:
                if (state["last_t"] is not None and t <= state["last_t"]) or any(
                    q[0] == t for q in lidar_q
                ):
                    counts["lidar_sweeps_late"] += (
                        1  # recorded after its frame was made, or a duplicate
                    )
                    continue
                # recorded out of order within the tolerance: put it in its place
                bisect.insort(
                    lidar_q,
                    (
                        t,
                        _lidar_points(msg, rig.lidar, where),
                        rig.lidar.frame or msg.header.frame_id,
                    ),
                    key=lambda q: q[0],
                )
            else:
                r = radar_by_topic[topic]
                if state["last_t"] is not None and t <= state["last_t"]:
                    counts["radar_sweeps_late"] += 1
                    continue
                pts = (
                    _radar_scan_points(msg)
                    if hasattr(msg, "returns")
                    else _radar_cloud_points(msg, r, where)
                )
                ego = self._poses.ego(t)
                if ego is None:
                    counts["radar_sweeps_no_pose"] += 1
                    continue
                s2e = self._extrinsic(r.frame or msg.header.frame_id, where)
                if not r.compensated:
                    v = self._sensor_velocity(t, s2e)
                    if v is None:
                        counts["radar_sweeps_no_pose"] += 1
                        continue
                    _compensate(pts, v)
                radar_q.append(RadarSweep(pts, s2e, ego, t, r.channel))
            yield from emit(bag_t)
        yield from emit(None)
        counts["radar_sweeps_after_end"] = len(radar_q)
        self.counts = counts
        if self._rec.stopped:
            self.stopped = self._rec.stopped
            logger.warning("%s; the scene ends at frame %d", self.stopped, state["index"])


def load_bag(path: str | Path, rig: RigConfig | Mapping[str, Any] | str | Path) -> BagScene:
    """A recording (``.bag``, ``.mcap`` or a ROS 2 bag folder) as a scene, read as the rig (a file, its dict or a RigConfig) says.

    Raises :class:`BagError` naming missing topics or frames (fields are checked as sweeps are
    read), :class:`RigError` for a bad rig file.
    """
    if isinstance(rig, Mapping):
        rig = RigConfig.from_dict(rig)
    elif not isinstance(rig, RigConfig):
        rig = load_rig(rig)
    return BagScene(path, rig)
