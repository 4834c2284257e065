"""Scenes from robot recordings: ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and plain MCAP
files.

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

from evgrid.data.bag.decoding import RADAR_DEFAULTS, RADAR_REQUIRED
from evgrid.data.bag.errors import BagError, RigError
from evgrid.data.bag.reading import bag_kind
from evgrid.data.bag.rig import LidarTopic, RadarTopic, RecordingRig, load_rig
from evgrid.data.bag.scene import BagScene, load_bag
from evgrid.data.bag.transforms import TransformBuffer

__all__ = [
    "BagError",
    "RigError",
    "RecordingRig",
    "LidarTopic",
    "RadarTopic",
    "load_rig",
    "load_bag",
    "BagScene",
    "TransformBuffer",
    "bag_kind",
    "RADAR_REQUIRED",
    "RADAR_DEFAULTS",
]
