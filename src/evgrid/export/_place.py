"""Where an exported map lies in the recording's fixed frame (odom, nuScenes global, the rig's
``world_frame``).

Every map update carries the ego pose twice: ``update.frame.ego_pose``, the ego pose in the
fixed frame (SE(3)), and ``update.pose``, the planar ego pose in the map frame (SE(2)). The map
frame's pose of the fixed frame is therefore ``pose @ planar(ego_pose)^-1``: in tf's words the
transform ``map -> fixed``, which makes the map frame a parent of the fixed frame (REP 105's
``map -> odom -> base_link``) instead of a second parent of ``base_link``. Maps are planar, so
the transform is too (x, y, yaw; z = 0: the map's plane is the fixed frame's z = 0 plane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from evgrid.geometry import SE2, SE3

__all__ = ["FIRST_POSE_FRAME", "MapPlacement", "fixed_in_map", "saved_placement"]


#: The map frame's name when the maps are built in the first ego pose's frame (the default
#: ``map_frame`` of every export's parameters, REP 105's ``map``).
FIRST_POSE_FRAME = "map"


def fixed_in_map(update: Any) -> SE2:
    """The pose of the recording's fixed frame in the map frame, from what ``update`` carries."""
    return update.pose @ update.frame.ego_pose.to_se2().inverse()


@dataclass(frozen=True)
class MapPlacement:
    """The map frame placed in the fixed frame, from the first update of a run.

    ``first_pose``: the first ego pose in the fixed frame (what a user needs to put the map
    back into the recording); ``fixed_in_map``: the pose of the fixed frame in the map frame.
    """

    map_frame: str
    fixed_frame: str
    first_pose: SE3
    fixed_in_map: SE2

    @classmethod
    def from_update(cls, update: Any, map_frame: str, fixed_frame: str) -> MapPlacement:
        return cls(map_frame, fixed_frame, update.frame.ego_pose, fixed_in_map(update))

    def as_dict(self) -> dict[str, str]:
        """String key-values (MCAP metadata, YAML comments, rerun documents)."""
        t = self.first_pose.translation
        q = self.first_pose.quaternion()  # (w, x, y, z)
        f = self.fixed_in_map
        return {
            "map_frame": self.map_frame,
            "fixed_frame": self.fixed_frame,
            "first_pose_xyz": " ".join(repr(float(v)) for v in t),
            "first_pose_quaternion_wxyz": " ".join(repr(float(v)) for v in q),
            "first_pose_yaw_deg": repr(math.degrees(self.first_pose.yaw)),
            "fixed_in_map_xy_yaw_deg": f"{f.x!r} {f.y!r} {math.degrees(f.yaw)!r}",
        }

    def comments(self) -> list[str]:
        """YAML comment lines (without '#') saying where the map lies in the fixed frame."""
        d = self.as_dict()
        return [
            f"map frame '{self.map_frame}'; the recording's fixed frame '{self.fixed_frame}'",
            f"first ego pose in '{self.fixed_frame}': xyz {d['first_pose_xyz']}, quaternion "
            f"wxyz {d['first_pose_quaternion_wxyz']} (yaw {d['first_pose_yaw_deg']} deg)",
            f"'{self.fixed_frame}' in '{self.map_frame}': x y yaw_deg "
            f"{d['fixed_in_map_xy_yaw_deg']}",
        ]


def saved_placement(frame: Any) -> tuple[str, str, MapPlacement | None]:
    """``(map frame, fixed frame, placement)`` of a saved map from its
    :class:`~evgrid.grid.MapFrame` (``m.frame``), named as a run's exports name them: maps in
    the fixed frame (``world``) are in that frame; maps in the first pose's frame are in
    :data:`FIRST_POSE_FRAME`, a parent of the fixed frame. The placement is None when the file
    does not know the first pose; the names are the exports' defaults when it knows no frame."""
    if frame is None or not frame.fixed_frame:
        return FIRST_POSE_FRAME, "odom", None
    fixed = frame.fixed_frame
    own = fixed if frame.kind == "world" else FIRST_POSE_FRAME
    if frame.first_pose is None:
        return own, fixed, None
    # the first update's pose in the map frame is the origin (first_pose) or the ego pose in
    # the fixed frame itself (world): fixed_in_map as the run's first update gave it
    first = frame.first_pose.to_se2()
    in_map = first.inverse() if frame.kind == "first_pose" else SE2(0.0, 0.0, 0.0)
    return own, fixed, MapPlacement(own, fixed, frame.first_pose, in_map)
