"""The rig file: which topics of a recording hold the lidar and the radars, which frames are the
world and the vehicle, how point-cloud fields are named and which lidar sweeps are keyframes
(docs/ros.md, docs/rig_example.yaml)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.data.bag.errors import RigError
from evgrid.data.frame import LIDAR_COLUMNS, RADAR_COLUMNS
from evgrid.geometry import SE3

__all__ = ["RecordingRig", "LidarTopic", "RadarTopic", "load_rig", "RADIAL"]

#: The radar column name of a radial (Doppler) speed, which the rig may map like the others.
RADIAL = "radial_velocity"


#: A radar entry's ``type``: what a live graph publishes on its topic (recordings say it).
_RADAR_TYPES = {
    "PointCloud2": "sensor_msgs/msg/PointCloud2",
    "RadarScan": "radar_msgs/msg/RadarScan",
}

#: The keys of a rig file's top level.
_TOP_KEYS = (
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
)


def _keys(d: Any, known: tuple[str, ...], where: str, entry: str | None = None) -> None:
    """RigError naming the file, the entry and every key of ``d`` that is not ``known``."""
    what = f"{where} {entry}" if entry else where
    if not isinstance(d, Mapping):
        raise RigError(f"{what}: must be a mapping, got {type(d).__name__}")
    bad = sorted(str(k) for k in set(d) - set(known))
    if bad:
        raise RigError(f"{what}: unknown key(s) {bad}; keys are {sorted(known)}")


def _name(v: Any, where: str, key: str) -> str | None:
    if v is not None and not (isinstance(v, str) and v):
        raise RigError(f"{where}: {key} must be a frame name, got {v!r}")
    return v


def _topic(v: Any, where: str, key: str) -> str:
    if not (isinstance(v, str) and v):
        raise RigError(f"{where}: {key} must be a topic name (a string such as /lidar), got {v!r}")
    return v


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
    """One radar: its topic, the channel name its sweeps get, optionally its frame and field
    names."""

    topic: str
    channel: str
    frame: str | None = None
    fields: Mapping[str, str] = field(default_factory=dict)
    compensated: bool = (
        True  # False: raw Doppler, compensated here with the ego motion of the poses
    )
    #: the message type, for a live graph (a recording says it itself)
    msgtype: str = "sensor_msgs/msg/PointCloud2"

    def field_name(self, column: str) -> str:
        return self.fields.get(column, column)


@dataclass(frozen=True)
class RecordingRig:
    """What the recording's topics and frames mean (see docs/ros.md)."""

    lidar: LidarTopic
    radars: tuple[RadarTopic, ...] = ()
    world_frame: str = "odom"
    base_frame: str = "base_link"
    odometry_topic: str | None = None  # None: ego poses from tf_topic
    tf_topic: str = "/tf"
    tf_static_topic: str = "/tf_static"
    #: frame -> sensor_to_ego, beats /tf_static
    extrinsics: Mapping[str, SE3] = field(default_factory=dict)
    #: every N-th lidar frame, from frame ``keyframe_offset`` on ...
    keyframe_every: int | None = 10
    #: ... or the first frame at or after each tick of this rate, from ``keyframe_offset_s``
    #: after the first frame on
    keyframe_rate_hz: float | None = None
    keyframe_offset: int = 0
    keyframe_offset_s: float = 0.0
    #: how late (in bag time) a radar sweep may arrive after its frame
    sync_tolerance_s: float = 0.5
    #: how far beyond the pose track a sweep may lie and still get a pose
    max_pose_gap_s: float = 0.1
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
        if self.keyframe_every is None and self.keyframe_offset:
            raise RigError("rig: keyframes.offset (frames) goes with keyframes.every")
        if self.keyframe_rate_hz is None and self.keyframe_offset_s:
            raise RigError("rig: keyframes.offset_s (seconds) goes with keyframes.rate_hz")
        off = self.keyframe_offset
        if isinstance(off, bool) or not isinstance(off, int) or off < 0:
            raise RigError(f"rig: keyframes.offset must be an integer >= 0, got {off!r}")
        for name in ("sync_tolerance_s", "max_pose_gap_s", "keyframe_offset_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v >= 0 and math.isfinite(v)):
                raise RigError(f"rig: {name} must be a non-negative number of seconds, got {v!r}")
        channels = [r.channel for r in self.radars]
        dup = sorted({c for c in channels if channels.count(c) > 1})
        if dup:
            raise RigError(f"rig: radar channel(s) {dup} named twice")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "rig") -> RecordingRig:
        """From the parsed YAML; raises :class:`RigError` naming the file (``where``) and the
        bad key, at every level (a typo such as ``chanel:`` in a radar entry is an error, not a
        silently ignored line)."""
        _keys(d, _TOP_KEYS, where)
        lid = d.get("lidar")
        if not isinstance(lid, Mapping) or lid.get("topic") is None:
            raise RigError(f"{where}: 'lidar' must give at least a 'topic'")
        _topic(lid["topic"], where, "lidar.topic")
        _keys(lid, ("topic", "frame", "fields"), where, "lidar")
        lidar = LidarTopic(
            lid["topic"],
            _name(lid.get("frame"), where, "lidar.frame"),
            _fields(lid.get("fields"), LIDAR_COLUMNS, f"{where} lidar"),
        )
        radars = []
        entries = d.get("radars") or ()
        if not isinstance(entries, (list, tuple)):
            raise RigError(f"{where}: 'radars' must be a list of radar entries")
        for i, r in enumerate(entries):
            radars.append(_radar_topic(r, where, f"radars[{i}]", lidar.topic))
        poses, source = _pose_source(d, where)
        kf = _keyframes(d, where)
        ext = _extrinsics(d.get("extrinsics"), where)
        try:
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
                keyframe_offset=kf.get("offset", 0),
                keyframe_offset_s=kf.get("offset_s", 0.0),
                sync_tolerance_s=d.get("sync_tolerance_s", 0.5),
                max_pose_gap_s=d.get("max_pose_gap_s", 0.1),
                scene=d.get("scene"),
            )
        except RigError as e:  # name the file, not "rig"
            msg = str(e)
            raise RigError(
                f"{where}{msg[3:]}" if msg.startswith("rig:") else f"{where}: {msg}"
            ) from None

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
            "radars": [_radar_entry(r) for r in self.radars],
            "keyframes": (
                {"every": self.keyframe_every}
                | ({"offset": self.keyframe_offset} if self.keyframe_offset else {})
                if self.keyframe_every
                else {"rate_hz": self.keyframe_rate_hz}
                | ({"offset_s": self.keyframe_offset_s} if self.keyframe_offset_s else {})
            ),
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


def _radar_topic(r: Any, where: str, w: str, lidar_topic: str) -> RadarTopic:
    """The radar entry ``w`` of a rig file: its topic (not the lidar's), channel, frame, fields,
    compensation and message type."""
    if not isinstance(r, Mapping) or r.get("topic") is None:
        raise RigError(f"{where} {w}: each radar needs a 'topic'")
    _topic(r["topic"], where, f"{w}.topic")
    if r["topic"] == lidar_topic:
        # one topic's clouds cannot be both: the entry would be ignored without a word
        raise RigError(
            f"{where} {w}: topic {r['topic']!r} is the lidar's topic too; a topic is the "
            "lidar or a radar, not both"
        )
    _keys(r, ("topic", "channel", "frame", "fields", "compensated", "type"), where, w)
    ch = r.get("channel") or r["topic"].strip("/").replace("/", "_").upper()
    comp = r.get("compensated", True)
    if not isinstance(comp, bool):
        raise RigError(f"{where} {w}: compensated must be true or false, got {comp!r}")
    typ = _RADAR_TYPES.get(r.get("type", "PointCloud2"))
    if typ is None:
        raise RigError(
            f"{where} {w}: type must be one of {sorted(_RADAR_TYPES)}, got {r.get('type')!r}"
        )
    return RadarTopic(
        r["topic"],
        str(ch),
        _name(r.get("frame"), where, f"{w}.frame"),
        _fields(r.get("fields"), RADAR_COLUMNS + (RADIAL,), f"{where} {w}"),
        comp,
        typ,
    )


def _radar_entry(r: RadarTopic) -> dict[str, Any]:
    """A radar's entry in a rig file, as :func:`_radar_topic` reads it (defaults left out)."""
    return {
        "topic": r.topic,
        "channel": r.channel,
        **({"frame": r.frame} if r.frame else {}),
        **({"fields": dict(r.fields)} if r.fields else {}),
        **({} if r.compensated else {"compensated": False}),
        **(
            {"type": r.msgtype.split("/")[-1]} if r.msgtype != "sensor_msgs/msg/PointCloud2" else {}
        ),
    }


def _pose_source(d: Mapping[str, Any], where: str) -> tuple[Mapping[str, Any], str]:
    """A rig file's ``poses`` mapping and its source, ``tf`` or ``odometry``."""
    poses = d.get("poses") or {}
    if not isinstance(poses, Mapping):
        raise RigError(f"{where}: 'poses' must be a mapping")
    _keys(poses, ("source", "topic", "tf_topic", "tf_static_topic"), where, "poses")
    source = poses.get("source", "tf")
    if source not in ("tf", "odometry"):
        raise RigError(f"{where}: poses.source must be 'tf' or 'odometry', got {source!r}")
    if source == "odometry" and not isinstance(poses.get("topic"), str):
        raise RigError(f"{where}: poses.source 'odometry' needs poses.topic")
    if source == "tf" and "topic" in poses:
        raise RigError(f"{where}: poses.topic goes with source: odometry (tf uses tf_topic)")
    return poses, source


def _keyframes(d: Mapping[str, Any], where: str) -> Mapping[str, Any]:
    """A rig file's ``keyframes`` mapping (every tenth lidar sweep when absent)."""
    kf = d.get("keyframes") or {"every": 10}
    if not isinstance(kf, Mapping):
        raise RigError(f"{where}: 'keyframes' must be a mapping with 'every' or 'rate_hz'")
    _keys(kf, ("every", "rate_hz", "offset", "offset_s"), where, "keyframes")
    return kf


def _extrinsics(extrinsics: Any, where: str) -> dict[str, SE3]:
    """A rig file's ``extrinsics``: each frame name's pose."""
    ext = {}
    extrinsics = extrinsics or {}
    if not isinstance(extrinsics, Mapping):
        raise RigError(f"{where}: 'extrinsics' must map frame names to poses")
    for frame, e in extrinsics.items():
        ext[str(frame)] = _extrinsic(e, f"{where} extrinsics.{frame}")
    return ext


def _extrinsic(e: Any, where: str) -> SE3:
    if not isinstance(e, Mapping) or "translation" not in e:
        raise RigError(f"{where}: give 'translation' [x, y, z] and 'yaw_deg' or 'rotation_wxyz'")
    bad = sorted(set(e) - {"translation", "yaw_deg", "rotation_wxyz"})
    if bad:
        raise RigError(
            f"{where}: unknown key(s) {bad}; keys are ['rotation_wxyz', 'translation', 'yaw_deg']"
        )
    if "yaw_deg" in e and "rotation_wxyz" in e:
        raise RigError(f"{where}: give 'yaw_deg' or 'rotation_wxyz', not both")
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


def load_rig(path: str | Path) -> RecordingRig:
    """Read a rig file (YAML); raises :class:`RigError` (or FileNotFoundError) naming the
    problem."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no rig file at {path}")
    if path.is_dir():
        raise RigError(f"{path}: a folder, not a rig file")
    try:
        import yaml
    except ImportError:
        from evgrid import install_hint

        raise ImportError(f"reading a rig file needs PyYAML ({install_hint('ros')})") from None
    from evgrid.io import InputFileError, read_bounded

    try:
        d = yaml.safe_load(read_bounded(path, "rig"))  # at most 16 MiB (READ_LIMITS)
    except InputFileError as e:
        raise RigError(str(e)) from None
    except yaml.YAMLError as e:
        raise RigError(f"{path}: not valid YAML: {str(e).splitlines()[0]}") from None
    except RecursionError:
        raise RigError(f"{path}: nested deeper than the YAML reader goes; not a rig file") from None
    except ValueError as e:  # PyYAML's int() of an integer of more than 4300 digits
        raise RigError(f"{path}: a value YAML cannot read: {str(e).split(';')[0]}") from None
    return RecordingRig.from_dict(d, str(path))
