"""Maps as ROS 2 messages in an MCAP file, for Foxglove (or RViz through a bag player).

Per exported map update, for each map ``NAME``:

* ``/evgrid/NAME/occupancy``: ``nav_msgs/OccupancyGrid``, -1 where unknown (never observed or
  ``m_u > unknown_mass``), else ``round(100 P(occ))`` with ``P(occ) = m_o + m_u / 2``;
* ``/evgrid/NAME/grid_map``: ``grid_map_msgs/GridMap`` with layers ``m_free``, ``m_occupied``,
  ``m_unknown`` (grid_map's storage: index (0, 0) at the largest x and y, rows towards -x,
  columns towards -y, column-major data, which is evgrid's map grid as it is);

and ``/tf`` with the ego pose (``base_link`` in ``map``, the first ego pose's frame). Stamps
are the frames' timestamps.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.export.nav2 import UNKNOWN, Nav2Thresholds, classify, map_to_occupancy
from evgrid.geometry import SE2, SE3
from evgrid.grid import EvidentialMap

__all__ = ["McapExporter", "occupancy_grid_msg", "grid_map_msg", "LAYERS"]

LAYERS = ("m_free", "m_occupied", "m_unknown")


def _pose_msg(store: Any, x: float, y: float) -> Any:
    t = store.types
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )


def occupancy_grid_msg(
    masses: np.ndarray,
    covered: np.ndarray,
    r0: int,
    c0: int,
    resolution: float,
    t_us: int,
    frame_id: str,
    store: Any,
    th: Nav2Thresholds = Nav2Thresholds(),
) -> Any:
    """``nav_msgs/OccupancyGrid`` of map cells ``[r0:r0+h, c0:c0+w]`` (masses ``(h, w, 3)``)."""
    from evgrid.ros import header, us_to_stamp

    m = np.asarray(masses, dtype=np.float32)
    val = np.clip(np.rint(100.0 * (m[..., 1] + 0.5 * m[..., 2])), 0, 100).astype(np.int8)
    val[classify(m, covered, th) == UNKNOWN] = UNKNOWN
    data, (ox, oy) = map_to_occupancy(val, r0, c0, resolution)
    sec, ns = us_to_stamp(t_us)
    t = store.types
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns),
        resolution=float(resolution),
        width=int(data.shape[1]),
        height=int(data.shape[0]),
        origin=_pose_msg(store, ox, oy),
    )
    return t["nav_msgs/msg/OccupancyGrid"](
        header=header(sec, ns, frame_id, store), info=info, data=data.reshape(-1)
    )


def grid_map_msg(
    masses: np.ndarray, r0: int, c0: int, resolution: float, t_us: int, frame_id: str, store: Any
) -> Any:
    """``grid_map_msgs/GridMap`` (layers m_free, m_occupied, m_unknown) of map cells ``[r0:r0+h, c0:c0+w]``."""
    from evgrid.ros import header, us_to_stamp

    m = np.asarray(masses, dtype=np.float32)
    h, w = m.shape[:2]
    t = store.types
    dims = [
        t["std_msgs/msg/MultiArrayDimension"](label="column_index", size=w, stride=h * w),
        t["std_msgs/msg/MultiArrayDimension"](label="row_index", size=h, stride=h),
    ]
    layout = t["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    data = [
        t["std_msgs/msg/Float32MultiArray"](
            layout=layout, data=np.ascontiguousarray(m[..., k].ravel(order="F"))
        )
        for k in range(3)
    ]
    info = t["grid_map_msgs/msg/GridMapInfo"](
        resolution=float(resolution),
        length_x=h * resolution,
        length_y=w * resolution,
        pose=_pose_msg(store, -(r0 + h / 2) * resolution, -(c0 + w / 2) * resolution),
    )
    sec, ns = us_to_stamp(t_us)
    return t["grid_map_msgs/msg/GridMap"](
        header=header(sec, ns, frame_id, store),
        info=info,
        layers=list(LAYERS),
        basic_layers=[],
        data=data,
        outer_start_index=0,
        inner_start_index=0,
    )


class McapExporter:
    """Observer that writes the maps to an MCAP file as the mapper updates them; call :meth:`close` at the end.

    ``keyframes_only``: export at keyframes (2 Hz in nuScenes) rather than every update.
    ``window_m``: export a square of that many metres around the vehicle (constant cost per
    update) instead of the whole observed map. ``maps``: which maps (default all). The final
    maps are written whole at :meth:`close`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        maps: Sequence[str] | None = None,
        keyframes_only: bool = True,
        window_m: float | None = None,
        frame_id: str = "map",
        base_frame: str = "base_link",
        thresholds: Nav2Thresholds = Nav2Thresholds(),
    ):
        from evgrid.ros import RecordingWriter

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} exists; evgrid does not overwrite recordings")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = RecordingWriter(self.path, "plain-mcap")
        self.maps = tuple(maps) if maps else None
        self.keyframes_only = keyframes_only
        self.window_m = window_m
        self.frame_id = frame_id
        self.base_frame = base_frame
        self.thresholds = thresholds
        self.n_messages = 0
        self._last: tuple[int, dict[str, EvidentialMap]] | None = None

    def _write_maps(
        self, maps: dict[str, EvidentialMap], t_us: int, box: tuple[int, int, int, int] | None
    ) -> None:
        store = self.writer.store
        for name, m in maps.items():
            if self.maps is not None and name not in self.maps:
                continue
            r0, c0, h, w = box or m.covered_bounds()
            if h == 0:
                continue
            masses, cov = m.read(r0, c0, h, w)
            res = m.grid.resolution
            self.writer.write(
                f"/evgrid/{name}/occupancy",
                "nav_msgs/msg/OccupancyGrid",
                t_us * 1000,
                occupancy_grid_msg(
                    masses, cov, r0, c0, res, t_us, self.frame_id, store, self.thresholds
                ),
            )
            self.writer.write(
                f"/evgrid/{name}/grid_map",
                "grid_map_msgs/msg/GridMap",
                t_us * 1000,
                grid_map_msg(masses, r0, c0, res, t_us, self.frame_id, store),
            )
            self.n_messages += 2

    def on_update(self, update: Any) -> None:
        from evgrid.ros import tf_message, transform_msg

        t_us = update.frame.timestamp
        store = self.writer.store
        pose: SE2 = update.pose
        self.writer.write(
            "/tf",
            "tf2_msgs/msg/TFMessage",
            t_us * 1000,
            tf_message(
                [transform_msg(self.frame_id, self.base_frame, t_us, SE3.from_se2(pose), store)],
                store,
            ),
        )
        self.n_messages += 1
        self._last = (t_us, update.maps.maps)
        if self.keyframes_only and not update.frame.is_keyframe:
            return
        box = None
        if self.window_m is not None:
            any_map = next(iter(update.maps.maps.values()))
            n = int(math.ceil(self.window_m / any_map.grid.resolution))
            rc, cc = any_map.grid.map_xy_to_cell(pose.x, pose.y)
            box = (int(rc) - n // 2, int(cc) - n // 2, n, n)
        self._write_maps(update.maps.maps, t_us, box)

    def close(self) -> Path:
        """Write the final maps whole and finish the file; returns its path."""
        if self._last is not None:
            self._write_maps(self._last[1], self._last[0] + 1, None)
            self._last = None
        self.writer.close()
        return self.path


def write_map_mcap(
    m: EvidentialMap,
    path: str | os.PathLike,
    name: str | None = None,
    frame_id: str = "map",
    thresholds: Nav2Thresholds = Nav2Thresholds(),
) -> Path:
    """One saved map as an MCAP file (one OccupancyGrid and one GridMap, stamped 0)."""
    exp = McapExporter(path, frame_id=frame_id, thresholds=thresholds)
    exp._write_maps({name or str(m.metadata.get("rule", "map")): m}, 0, None)
    return exp.close()
