"""ROS messages without ROS: type stores, point clouds, transforms and stamps
(the ``ros`` extra, :func:`evgrid.install_hint`).

Messages are (de)serialised by the pure-Python ``rosbags`` package. Its type stores know the
standard ROS 1 (Noetic) and ROS 2 (Humble) messages; the two packages we need beyond them,
``radar_msgs`` and ``grid_map_msgs``, are registered here from their ``.msg`` text.

Poses cross the ROS boundary as a translation and a quaternion. A planar rotation (the
simulator's, and most ground vehicles' odometry) is written as a yaw-only quaternion chosen
so that :func:`transform_to_se3` rebuilds the very same ``cos``/``sin`` matrix, so a scene
written to a bag and read back maps bit-identically.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.geometry import SE3, quaternion_to_matrix

__all__ = [
    "require",
    "typestore",
    "new_typestore",
    "POINTFIELD_DTYPES",
    "cloud_fields",
    "cloud_to_columns",
    "CloudError",
    "columns_to_cloud",
    "se3_to_transform",
    "transform_to_se3",
    "us_to_stamp",
    "stamp_to_us",
    "EXTRA_MSGS",
    "header",
    "RecordingWriter",
    "STORAGES",
    "transform_msg",
    "tf_message",
]

#: Message definitions registered on top of the standard type stores (ROS 2 spelling).
EXTRA_MSGS: dict[str, str] = {
    "radar_msgs/msg/RadarReturn": (
        "float32 range\nfloat32 azimuth\nfloat32 elevation\nfloat32 doppler_velocity\n"
        "float32 amplitude\n"
    ),
    "radar_msgs/msg/RadarScan": "std_msgs/Header header\nradar_msgs/RadarReturn[] returns\n",
    "grid_map_msgs/msg/GridMapInfo": (
        "float64 resolution\nfloat64 length_x\nfloat64 length_y\ngeometry_msgs/Pose pose\n"
    ),
    "grid_map_msgs/msg/GridMap": (
        "std_msgs/Header header\ngrid_map_msgs/GridMapInfo info\nstring[] layers\n"
        "string[] basic_layers\n"
        "std_msgs/Float32MultiArray[] data\nuint16 outer_start_index\nuint16 inner_start_index\n"
    ),
}


def require(module: str, extra: str = "ros") -> Any:
    """Import an optional dependency, or raise ImportError saying how to install it."""
    import importlib

    from evgrid.package import install_hint

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{module} is needed for this ({install_hint(extra)}): {e}") from None


@functools.lru_cache(maxsize=2)
def typestore(ros_version: int = 2) -> Any:
    """The rosbags type store of ROS 2 Humble (or ROS 1 Noetic) with radar_msgs and grid_map_msgs
    added.

    Shared by every caller: register nothing more on it (use :func:`new_typestore`).
    """
    return new_typestore(ros_version)


def new_typestore(ros_version: int = 2) -> Any:
    """A fresh type store as :func:`typestore`'s, for a reader that registers a recording's own
    definitions."""
    require("rosbags")
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros_version == 2 else Stores.ROS1_NOETIC)
    types: dict = {}
    extra = dict(EXTRA_MSGS)
    extra.setdefault(
        "tf2_msgs/msg/TFMessage", "geometry_msgs/TransformStamped[] transforms\n"
    )  # not in Noetic's store
    for name, text in extra.items():
        if name not in store.fielddefs:
            types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


# --- time -----------------------------------------------------------------------------------


def stamp_to_us(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` (sec, nanosec) -> integer microseconds (evgrid's
    timestamps)."""
    return int(stamp.sec) * 1_000_000 + int(stamp.nanosec) // 1000


def us_to_stamp(us: int) -> tuple[int, int]:
    """Integer microseconds -> (sec, nanosec)."""
    sec, rem = divmod(int(us), 1_000_000)
    return sec, rem * 1000


# --- point clouds ---------------------------------------------------------------------------

#: sensor_msgs/PointField datatype -> numpy type (little-endian; big-endian clouds are swapped).
POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    8: "f8",
}


def cloud_fields(msg: Any) -> tuple[str, ...]:
    """Names of the fields of a PointCloud2."""
    return tuple(f.name for f in msg.fields)


class CloudError(ValueError):
    """A ``sensor_msgs/PointCloud2`` whose layout contradicts itself (a field beyond the point,
    data shorter than its points): it cannot be decoded."""


def _cloud_layout(msg: Any, fmt: dict[str, tuple[np.dtype, int]]) -> tuple[int, int, int, int]:
    """(point_step, height, width, row_step) of a cloud, checked against its fields and data;
    :class:`CloudError` saying what contradicts what."""
    step, height, width = int(msg.point_step), int(msg.height), int(msg.width)
    row = int(msg.row_step)
    if step <= 0:
        raise CloudError(f"point_step is {step} bytes")
    for name, (dt, off) in fmt.items():
        if off < 0 or off + dt.itemsize > step:
            raise CloudError(
                f"field {name!r} ({dt.itemsize} bytes at offset {off}) lies beyond the "
                f"point_step of {step} bytes"
            )
    size = len(msg.data)
    if height > 1 and row != width * step:  # padded rows
        if row < width * step:
            raise CloudError(
                f"row_step {row} is shorter than width {width} x point_step {step} bytes"
            )
        need = (height - 1) * row + width * step
    else:
        need = height * width * step
    if size < need:
        raise CloudError(
            f"data holds {size} bytes, fewer than the {need} of {height} x {width} points of "
            f"{step} bytes (point_step or width too large, or the data cut short)"
        )
    return step, height, width, row


def cloud_to_columns(msg: Any, names: Sequence[str]) -> np.ndarray:
    """The named fields of a ``sensor_msgs/PointCloud2`` as an ``(n, len(names))`` float32 array.

    Raises KeyError listing the names the cloud lacks, :class:`CloudError` for a cloud whose
    layout contradicts itself (checked before any byte is read, so no numpy text escapes).
    """
    by_name = {f.name: f for f in msg.fields}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise KeyError(f"fields {missing} not in the cloud (it has {sorted(by_name)})")
    order = ">" if msg.is_bigendian else "<"
    fmt = {}
    for n in names:
        f = by_name[n]
        if f.datatype not in POINTFIELD_DTYPES:
            raise CloudError(f"field {n!r} has unknown PointField datatype {f.datatype}")
        fmt[n] = (np.dtype(order + POINTFIELD_DTYPES[f.datatype]), int(f.offset))
    step, height, width, row = _cloud_layout(msg, fmt)
    dtype = np.dtype(
        {
            "names": list(fmt),
            "formats": [v[0] for v in fmt.values()],
            "offsets": [v[1] for v in fmt.values()],
            "itemsize": step,
        }
    )
    data = np.asarray(msg.data, dtype=np.uint8)
    if height > 1 and row != width * step:  # padded rows: drop each row's padding
        data = np.concatenate([data[i * row : i * row + width * step] for i in range(height)])
    n = height * width
    rec = data[: n * step].view(dtype)
    out = np.empty((n, len(names)), dtype=np.float32)
    for i, nm in enumerate(names):
        out[:, i] = rec[nm]
    return out


def columns_to_cloud(
    points: np.ndarray,
    names: Sequence[str],
    sec: int,
    nanosec: int,
    frame_id: str,
    store: Any = None,
) -> Any:
    """A dense ``sensor_msgs/PointCloud2`` of float32 fields ``names`` from an ``(n, k)`` array."""
    store = store or typestore(2)
    t = store.types
    p = np.ascontiguousarray(points, dtype="<f4")
    if p.ndim != 2 or p.shape[1] != len(names):
        raise ValueError(f"points must have shape (n, {len(names)}), got {p.shape}")
    fields = [
        t["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
        for i, n in enumerate(names)
    ]
    return t["sensor_msgs/msg/PointCloud2"](
        header=header(sec, nanosec, frame_id, store),
        height=1,
        width=len(p),
        fields=fields,
        is_bigendian=False,
        point_step=4 * len(names),
        row_step=4 * len(names) * len(p),
        data=p.reshape(-1).view(np.uint8),
        is_dense=True,
    )


def header(sec: int, nanosec: int, frame_id: str, store: Any = None) -> Any:
    """A ``std_msgs/Header`` (with ``seq = 0`` in ROS 1)."""
    store = store or typestore(2)
    t = store.types
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    h = t["std_msgs/msg/Header"]
    if "seq" in h.__dataclass_fields__:
        return h(seq=0, stamp=stamp, frame_id=frame_id)
    return h(stamp=stamp, frame_id=frame_id)


# --- transforms -----------------------------------------------------------------------------


def _is_planar(r: np.ndarray) -> bool:
    return bool(
        r[2, 2] == 1.0 and r[0, 2] == 0.0 and r[1, 2] == 0.0 and r[2, 0] == 0.0 and r[2, 1] == 0.0
    )


def _yaw_of(qz: float, qw: float) -> float:
    return 2.0 * math.atan2(qz, qw)


def _planar_quaternion(c: float, s: float) -> tuple[float, float] | None:
    """(qz, qw) whose yaw 2 atan2(qz, qw) has exactly cos = c and sin = s; None if none is near."""
    y0 = math.atan2(s, c)
    yaws = [y0]
    lo = hi = y0
    for _ in range(8):  # the yaw that built the matrix is within a few ulps of atan2(s, c)
        lo, hi = math.nextafter(lo, -math.inf), math.nextafter(hi, math.inf)
        yaws += [lo, hi]
    for yaw in yaws:
        if math.cos(yaw) != c or math.sin(yaw) != s:
            continue
        qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
        for _ in range(16):  # nudge qz until the half-angle reads back as the same yaw
            y = _yaw_of(qz, qw)
            if y == yaw:
                return qz, qw
            qz = math.nextafter(qz, math.inf if (y < yaw) == (qw > 0) else -math.inf)
    return None


def se3_to_transform(
    pose: SE3,
) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """A pose as ROS ``(translation xyz, rotation xyzw)``; planar rotations read back exactly."""
    r = pose.rotation
    t = tuple(float(v) for v in pose.translation)
    if _is_planar(r) and r[0, 0] == r[1, 1] and r[0, 1] == -r[1, 0]:
        q = _planar_quaternion(float(r[0, 0]), float(r[1, 0]))
        if q is not None:
            return t, (0.0, 0.0, q[0], q[1])  # type: ignore[return-value]
    w, x, y, z = pose.quaternion()
    return t, (float(x), float(y), float(z), float(w))  # type: ignore[return-value]


def transform_to_se3(t: Sequence[float], q_xyzw: Sequence[float]) -> SE3:
    """ROS translation and quaternion (x, y, z, w) -> :class:`SE3`; yaw-only quaternions give the
    planar matrix."""
    x, y, z, w = (float(v) for v in q_xyzw)
    if x == 0.0 and y == 0.0 and (z != 0.0 or w != 0.0):
        yaw = _yaw_of(z, w)
        c, s = math.cos(yaw), math.sin(yaw)
        return SE3(
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(t, dtype=np.float64)
        )
    return SE3(quaternion_to_matrix([w, x, y, z]), np.asarray(t, dtype=np.float64))


# --- writing recordings -----------------------------------------------------------------------

#: Storage formats :class:`RecordingWriter` writes.
STORAGES = ("mcap", "sqlite3", "ros1", "plain-mcap")


class RecordingWriter:
    """Writes messages to a ROS 2 bag (``mcap`` or ``sqlite3`` storage), a ROS 1 bag or a plain
    MCAP file.

    ``write(topic, type, t_ns, msg)`` registers a topic on first use. Messages are built with
    :attr:`store` (ROS 1 types for ``ros1``, ROS 2 Humble otherwise).
    """

    def __init__(self, path: str | Path, storage: str = "mcap"):
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
        require("rosbags")
        self.path = Path(path)
        self.storage = storage
        self.store = typestore(1 if storage == "ros1" else 2)
        self._topics: dict[str, Any] = {}
        if storage == "plain-mcap":
            require("mcap")
            from mcap.writer import Writer

            self._fh = open(self.path, "wb")
            self._w = Writer(self._fh)
            self._w.start(profile="ros2", library="evgrid")
        elif storage == "ros1":
            from rosbags.rosbag1 import Writer as Writer1

            self._w = Writer1(self.path)
            self._w.open()
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self._w = Writer2(self.path, version=9, storage_plugin=plugin)
            self._w.open()

    def _topic(self, topic: str, msgtype: str) -> Any:
        c = self._topics.get(topic)
        if c is None:
            if self.storage == "plain-mcap":
                text, _ = self.store.generate_msgdef(msgtype, ros_version=2)
                sid = self._w.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
                c = self._w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
            else:
                c = self._w.add_connection(topic, msgtype, typestore=self.store)
            self._topics[topic] = c
        return c

    def write(self, topic: str, msgtype: str, t_ns: int, msg: Any) -> None:
        """Serialise and write one message at bag time ``t_ns``."""
        c = self._topic(topic, msgtype)
        if self.storage == "plain-mcap":
            data = bytes(self.store.serialize_cdr(msg, msgtype))
            self._w.add_message(channel_id=c, log_time=int(t_ns), data=data, publish_time=int(t_ns))
        elif self.storage == "ros1":
            self._w.write(c, int(t_ns), self.store.serialize_ros1(msg, msgtype))
        else:
            self._w.write(c, int(t_ns), self.store.serialize_cdr(msg, msgtype))

    def close(self) -> None:
        """Finish the file (index, summary, metadata)."""
        if self.storage == "plain-mcap":
            self._w.finish()
            self._fh.close()
        else:
            self._w.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def transform_msg(parent: str, child: str, t_us: int, pose: SE3, store: Any) -> Any:
    """A ``geometry_msgs/TransformStamped``: the pose of ``child`` in ``parent``."""
    ty = store.types
    (tx, tyy, tz), (qx, qy, qz, qw) = se3_to_transform(pose)
    sec, ns = us_to_stamp(t_us)
    return ty["geometry_msgs/msg/TransformStamped"](
        header=header(sec, ns, parent, store),
        child_frame_id=child,
        transform=ty["geometry_msgs/msg/Transform"](
            translation=ty["geometry_msgs/msg/Vector3"](x=tx, y=tyy, z=tz),
            rotation=ty["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )


def tf_message(transforms: Sequence[Any], store: Any) -> Any:
    """A ``tf2_msgs/TFMessage`` of some TransformStamped."""
    return store.types["tf2_msgs/msg/TFMessage"](transforms=list(transforms))
