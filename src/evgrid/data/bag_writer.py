"""Write a scene (the simulator's, or any iterable of frames) as a robot recording with its rig
file.

The recording holds what a real vehicle would log:

* ``/tf_static``: each sensor's frame (its channel name) in ``base_link``, once;
* ``/tf``: ``base_link`` in ``odom`` at every sweep's stamp (lidar and radar);
* ``/<channel>/points`` (lowercase channel): ``sensor_msgs/PointCloud2`` with every column of
  the frame contract as a float32 field (or, for radars, ``radar_msgs/RadarScan`` on request,
  which keeps only range, angles, Doppler speed and amplitude).

Bag times equal header stamps. The rig file written beside it reads the recording back into
the same frames: ``load_bag(path, rig)`` maps bit-identically to the scene itself when the
radars are point clouds.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from evgrid.data.bag import LidarTopic, RadarTopic, RecordingRig
from evgrid.data.frame import LIDAR_COLUMNS, RADAR_COLUMNS, Frame, LidarSweep, RadarSweep
from evgrid.io import atomic_write_text

__all__ = ["write_bag", "write_rig", "topic_of"]

WORLD_FRAME = "odom"
BASE_FRAME = "base_link"


def topic_of(channel: str) -> str:
    """The topic a channel's sweeps are written to (``RADAR_FRONT`` -> ``/radar_front/points``)."""
    return f"/{channel.lower()}/points"


def _radar_scan(sweep: RadarSweep, store) -> object:
    """``radar_msgs/RadarScan`` of a sweep: spherical positions, the Doppler speed along the line of
    sight."""
    from evgrid.ros import header, us_to_stamp

    p = sweep.points.astype(np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = np.sqrt(x * x + y * y + z * z)
    az = np.arctan2(y, x)
    el = np.arctan2(z, np.hypot(x, y))
    with np.errstate(invalid="ignore", divide="ignore"):
        vr = np.where(r > 0, (p[:, 6] * x + p[:, 7] * y) / r, 0.0)
    ret = store.types["radar_msgs/msg/RadarReturn"]
    returns = [
        ret(
            range=float(a),
            azimuth=float(b),
            elevation=float(c),
            doppler_velocity=float(d),
            amplitude=float(e),
        )
        for a, b, c, d, e in zip(r, az, el, vr, p[:, 3])
    ]
    sec, ns = us_to_stamp(sweep.timestamp)
    return store.types["radar_msgs/msg/RadarScan"](
        header=header(sec, ns, sweep.channel, store), returns=returns
    )


class _RecordingStream:
    """Writes frames into an open recording, sweep by sweep in time order, with the
    transforms a real vehicle logs beside them."""

    def __init__(self, writer, radar_format: str) -> None:
        self.w = writer
        self.store = writer.store
        self.radar_format = radar_format
        self.static_channels: set[str] | None = None
        self.last_pose_t: int | None = None
        self.radar_channels: list[str] = []

    def _tf(self, topic: str, t: int, transforms: list) -> None:
        from evgrid.ros import tf_message

        self.w.write(topic, "tf2_msgs/msg/TFMessage", t * 1000, tf_message(transforms, self.store))

    def frame(self, f: Frame) -> None:
        """One frame's sweeps, lidar and radar, in stamp order (lidar first at equal stamps)."""
        from evgrid.ros import transform_msg

        sweeps = [(s.timestamp, 1, s) for s in f.radar_sweeps()] + [(f.lidar.timestamp, 0, f.lidar)]
        sweeps.sort(key=lambda x: (x[0], x[1]))
        if self.static_channels is None:
            t0 = sweeps[0][0]
            mounts = {f.lidar.channel: f.lidar.sensor_to_ego}
            # radars that are silent in the first frame get their mount when they first speak
            mounts.update({s.channel: s.sensor_to_ego for s in f.radar_sweeps()})
            transforms = [
                transform_msg(BASE_FRAME, ch, t0, p, self.store) for ch, p in mounts.items()
            ]
            self._tf("/tf_static", t0, transforms)
            self.static_channels = set(mounts)
        for t, _, s in sweeps:
            self.sweep(t, s)

    def sweep(self, t: int, s: LidarSweep | RadarSweep) -> None:
        """A sweep at stamp ``t`` (us), after its mount (once) and the ego pose (once a stamp)."""
        from evgrid.ros import columns_to_cloud, transform_msg, us_to_stamp

        store = self.store
        if s.channel not in self.static_channels:
            self._tf(
                "/tf_static", t, [transform_msg(BASE_FRAME, s.channel, t, s.sensor_to_ego, store)]
            )
            self.static_channels.add(s.channel)
        if t != self.last_pose_t:
            self._tf("/tf", t, [transform_msg(WORLD_FRAME, BASE_FRAME, t, s.ego_pose, store)])
            self.last_pose_t = t
        sec, ns = us_to_stamp(t)
        topic = topic_of(s.channel)
        if not isinstance(s, RadarSweep):
            cloud = columns_to_cloud(s.points, LIDAR_COLUMNS, sec, ns, s.channel, store)
            self.w.write(topic, "sensor_msgs/msg/PointCloud2", t * 1000, cloud)
            return
        if s.channel not in self.radar_channels:
            self.radar_channels.append(s.channel)
        if self.radar_format == "radarscan":
            self.w.write(topic, "radar_msgs/msg/RadarScan", t * 1000, _radar_scan(s, store))
        else:
            cloud = columns_to_cloud(s.points, RADAR_COLUMNS, sec, ns, s.channel, store)
            self.w.write(topic, "sensor_msgs/msg/PointCloud2", t * 1000, cloud)


def write_bag(
    frames: Iterable[Frame],
    path: str | Path,
    storage: str = "mcap",
    radar_format: str = "pointcloud2",
    rig_path: str | Path | None = None,
    scene_name: str | None = None,
) -> tuple[Path, Path]:
    """Write ``frames`` as a recording at ``path`` and its rig file; returns (recording, rig
    file).

    ``storage``: ``mcap`` or ``sqlite3`` (a ROS 2 bag folder), ``ros1`` (a ``.bag`` file) or
    ``plain-mcap`` (one ``.mcap`` file). ``radar_format``: ``pointcloud2`` or ``radarscan``
    (ROS 2 only). The rig file defaults to ``<path>.rig.yaml``; keyframes are declared as
    every N-th frame, N read off the frames' own keyframes.
    """
    from evgrid.ros import RecordingWriter

    path = Path(path)
    _check_recording(path, storage, radar_format)
    rig_path = Path(rig_path) if rig_path else path.with_name(path.name + ".rig.yaml")
    keyframes: list[int] = []
    lidar_channel = None
    name = scene_name
    with RecordingWriter(path, storage) as w:
        stream = _RecordingStream(w, radar_format)
        for f in frames:
            name = name or f.scene
            lidar_channel = f.lidar.channel
            if f.is_keyframe:
                keyframes.append(f.index)
            stream.frame(f)
    if lidar_channel is None:
        raise ValueError("write_bag got no frames")
    rig = RecordingRig(
        lidar=LidarTopic(topic_of(lidar_channel)),
        radars=tuple(RadarTopic(topic_of(ch), ch) for ch in stream.radar_channels),
        world_frame=WORLD_FRAME,
        base_frame=BASE_FRAME,
        keyframe_every=_keyframe_every(keyframes),
        scene=name,
    )
    write_rig(rig, rig_path)
    return path, rig_path


def _check_recording(path: Path, storage: str, radar_format: str) -> None:
    """A recording :func:`write_bag` can write: a known radar format that the storage carries,
    and no file at ``path``."""
    if radar_format not in ("pointcloud2", "radarscan"):
        raise ValueError(f"radar_format must be 'pointcloud2' or 'radarscan', got {radar_format!r}")
    if radar_format == "radarscan" and storage == "ros1":
        raise ValueError(
            "radar_msgs/RadarScan is a ROS 2 message; write ROS 1 bags with "
            "radar_format='pointcloud2'"
        )
    if path.exists():
        raise FileExistsError(f"{path} exists; evgrid does not overwrite recordings")


def _keyframe_every(indices: list[int]) -> int:
    """N such that the keyframes are frames 0, N, 2N, ...; 10 (nuScenes' 2 Hz of 20 Hz) when
    undecidable."""
    if len(indices) < 2:
        return 10
    steps = set(np.diff(indices).tolist())
    if indices[0] != 0 or len(steps) != 1:
        raise ValueError(
            f"keyframes {indices[:5]}... are not every N-th frame from frame 0; a rig file cannot "
            "say so"
        )
    return int(steps.pop())


def write_rig(rig: RecordingRig, path: str | Path) -> Path:
    """Write a rig file (YAML) that :func:`evgrid.data.bag.load_rig` reads back."""
    import yaml

    path = Path(path)
    atomic_write_text(
        path,
        "# evgrid rig file: what the recording's topics and frames mean (docs/ros.md)\n"
        + yaml.safe_dump(rig.to_dict(), sort_keys=False),
    )
    return path
