"""Maps as ROS 2 messages in an MCAP file, for Foxglove (or RViz through a bag player).

What the file holds (:class:`McapParams`; defaults in brackets, docs/ros.md says why):

* ``/evgrid/NAME/occupancy``: ``nav_msgs/OccupancyGrid`` of the maps in ``maps`` [the
  navigation map ``nav``, else ``fused``], a square of ``window_m`` metres [40] around the
  vehicle at ``rate_hz`` [None: at keyframes, 2 Hz in nuScenes]; and of every map in
  ``final_maps`` [all maps] whole at the end, stamped 1 us after the last update (coarser
  by a whole factor where a side has over ``final_max_side`` [16384] cells). Values
  (:func:`~evgrid.export.nav2.occupancy_values`) agree with the nav2 export's classes at its
  thresholds: ``trinary`` [0 free, 100 occupied, -1 unknown] or ``scale``;
* ``/evgrid/NAME/grid_map``: ``grid_map_msgs/GridMap`` with the mass layers of ``layers``
  (``m_free``, ``m_occupied``, ``m_unknown``) [none: float masses are about ten times the
  OccupancyGrid's size], and the layer ``dynamic`` [off]: the dynamic score of the maps that
  keep one (:class:`evgrid.fusion.DynamicParams`), NaN in every cell of a map that keeps
  none; grid_map's storage is evgrid's map grid as it is (index (0, 0) at the largest x and
  y, rows towards -x, columns towards -y, column-major data);
* ``/tf``: ``map_frame -> fixed_frame`` at every update [``map -> odom``], the map frame as a
  parent of the recording's fixed frame (:mod:`evgrid.export._place`), never a second parent
  of ``base_link``; ``/evgrid/ego_pose`` (``geometry_msgs/PoseStamped``, map frame) at every
  update and ``/evgrid/path`` (``nav_msgs/Path``) at the end;
* metadata record ``evgrid``: the frames, the first ego pose in the fixed frame, the
  parameters.

Chunks are compressed (``compression``: zstd [default], lz4 or none). The file is written
under a temporary name and renamed when complete (:mod:`evgrid.export._files`). Stamps are
the frames' timestamps.
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.export._files import AtomicFile, refuse_empty, target_path, write_error
from evgrid.export._place import MapPlacement, fixed_in_map
from evgrid.export.nav2 import (
    OCCUPANCY_VALUES,
    UNKNOWN,
    Nav2Thresholds,
    _class_value_bounds,
    map_to_occupancy,
    occupancy_values,
)
from evgrid.geometry import SE2, SE3
from evgrid.grid import EvidentialMap, coarse_step

log = logging.getLogger(__name__)

__all__ = [
    "McapExporter",
    "McapParams",
    "occupancy_grid_msg",
    "coarsen_values",
    "occupancy_grid_cdr",
    "grid_map_msg",
    "write_maps_mcap",
    "write_map_mcap",
    "LAYERS",
    "DYNAMIC_LAYER",
    "GRID_LAYERS",
    "DYNAMIC_STEP",
    "MapCells",
    "COMPRESSIONS",
]

#: The GridMap's mass layers; ``occupancy`` names the OccupancyGrid.
LAYERS = ("m_free", "m_occupied", "m_unknown")
#: The GridMap layer of the dynamic score (:class:`evgrid.fusion.DynamicParams`).
DYNAMIC_LAYER = "dynamic"
#: Every GridMap layer evgrid writes.
GRID_LAYERS = (*LAYERS, DYNAMIC_LAYER)
#: The dynamic layer's step: the score is written rounded to it, far finer than any threshold,
#: so that the decaying tails of the score (tiny, all different) compress (docs/ros.md).
DYNAMIC_STEP = 1 / 1024
#: MCAP chunk compressions the ``mcap`` writer supports.
COMPRESSIONS = ("zstd", "lz4", "none")


def _pose_msg(store: Any, x: float, y: float, yaw: float = 0.0) -> Any:
    t = store.types
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw)
        ),
    )


@dataclass(frozen=True)
class MapCells:
    """Map cells ``[r0:r0+h, c0:c0+w]`` read for a message: masses ``(h, w, 3)``, coverage
    ``(h, w)``, the dynamic score ``(h, w)`` (None: the map keeps none, or it was not asked
    for) and the cells' size in metres."""

    masses: np.ndarray
    covered: np.ndarray
    r0: int
    c0: int
    resolution: float
    dynamic: np.ndarray | None = None

    @classmethod
    def read(
        cls, m: EvidentialMap, box: tuple[int, int, int, int], dynamic: bool = False
    ) -> MapCells:
        """Read ``box`` ``(r0, c0, h, w)`` of ``m``, with its dynamic score if ``dynamic`` and the
        map keeps one."""
        masses, cov = m.read(*box)
        score = m.read_dynamic(*box) if dynamic and m.dynamic else None
        return cls(masses, cov, box[0], box[1], m.grid.resolution, score)

    def occupancy(self, th: Nav2Thresholds, values: str) -> np.ndarray:
        """The OccupancyGrid values of the cells (:func:`~evgrid.export.nav2.occupancy_values`)."""
        return occupancy_values(self.masses, self.covered, th, values)


@dataclass(frozen=True)
class TiledCells:
    """Map cells ``box`` of ``map`` for an OccupancyGrid, read tile by tile when the values are
    made (one byte a cell in memory, never the masses of the whole box)."""

    map: EvidentialMap
    r0: int
    c0: int
    h: int
    w: int

    @property
    def resolution(self) -> float:
        return self.map.grid.resolution

    def occupancy(
        self, th: Nav2Thresholds, values: str, out: np.ndarray | None = None
    ) -> np.ndarray:
        """The OccupancyGrid values of the cells, into ``out`` (``(h, w)`` int8, any strides:
        a view of a message's buffer) when given."""
        m = self.map
        if out is None:
            out = np.empty((self.h, self.w), dtype=np.int8)
        out[...] = UNKNOWN  # where no tile is stored
        for key, tr, tc, wr, wc in m.pieces(self.r0, self.c0, self.h, self.w):
            t = m.tiles.get(key)
            if t is not None:
                cov = m.covered_tiles[key][tr, tc]
                out[wr, wc] = occupancy_values(t[tr, tc], cov, th, values)
        return out


def occupancy_grid_msg(
    cells: MapCells | TiledCells,
    t_us: int,
    frame_id: str,
    store: Any,
    th: Nav2Thresholds = Nav2Thresholds(),
    values: str = "trinary",
) -> Any:
    """``nav_msgs/OccupancyGrid`` of ``cells``; ``values`` as
    :func:`~evgrid.export.nav2.occupancy_values`."""
    val = cells.occupancy(th, values)
    return occupancy_grid_of(val, cells.r0, cells.c0, cells.resolution, t_us, frame_id, store)


def occupancy_grid_of(
    values: np.ndarray, r0: int, c0: int, resolution: float, t_us: int, frame_id: str, store: Any
) -> Any:
    """``nav_msgs/OccupancyGrid`` of OccupancyGrid values (int8) of the map cells
    ``[r0:, c0:]``, in ROS order (:func:`~evgrid.export.nav2.map_to_occupancy`)."""
    data, origin = map_to_occupancy(values, r0, c0, resolution)
    return _occupancy_grid(data.reshape(-1), data.shape, origin, resolution, t_us, frame_id, store)


def _occupancy_grid(
    data: np.ndarray,
    shape: tuple[int, int],
    origin: tuple[float, float],
    resolution: float,
    t_us: int,
    frame_id: str,
    store: Any,
) -> Any:
    """``nav_msgs/OccupancyGrid`` of ``shape`` (height, width) with ``data`` (ROS order, flat)."""
    from evgrid.ros import header, us_to_stamp

    sec, ns = us_to_stamp(t_us)
    t = store.types
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns),
        resolution=float(resolution),
        width=int(shape[1]),
        height=int(shape[0]),
        origin=_pose_msg(store, *origin),
    )
    return t["nav_msgs/msg/OccupancyGrid"](
        header=header(sec, ns, frame_id, store), info=info, data=data
    )


#: The OccupancyGrid message type.
_OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"


def coarsen_values(fine: np.ndarray, step: int, th: Nav2Thresholds) -> np.ndarray:
    """OccupancyGrid values ``(n * step, m * step)`` made ``step`` times coarser: a coarse cell
    is occupied (its largest value) if any of its cells is, unknown if any is unknown, else
    free (its largest value). Conservative for a reader: an obstacle is never hidden, and no
    cell is called free that was not seen free."""
    n, m = fine.shape[0] // step, fine.shape[1] // step
    blocks = fine.reshape(n, step, m, step)
    top = blocks.max(axis=(1, 3))
    unseen = blocks.min(axis=(1, 3)) == UNKNOWN
    return np.where(unseen & (top < _class_value_bounds(th)[1]), np.int8(UNKNOWN), top)


def occupancy_grid_cdr(
    cells: TiledCells,
    t_us: int,
    frame_id: str,
    store: Any,
    th: Nav2Thresholds = Nav2Thresholds(),
    values: str = "trinary",
    step: int = 1,
) -> bytearray:
    """The CDR bytes of :func:`occupancy_grid_msg` of ``cells``, the same as
    ``store.serialize_cdr`` gives them, made in one buffer: the values are written tile by tile
    straight to their places in ROS order, so a whole map costs one byte a cell once (not the
    values, their ROS-order copy, the message and its serialised copies, each a byte a cell).

    ``step`` > 1: cells ``step`` times larger (:func:`coarsen_values`), the box extended to a
    whole number of them (unknown beyond it), made in bands of about a tile's rows.

    ``data`` is the message's last field and int8 (no alignment), so the bytes are those of
    the message with no data, its sequence length set, then the cells."""
    h, w = -(-cells.h // step), -(-cells.w // step)  # cells of the message
    r0, c0, res = cells.r0, cells.c0, cells.resolution
    origin = (-(r0 + h * step) * res, -(c0 + w * step) * res)  # map_to_occupancy's
    empty = _occupancy_grid(np.zeros(0, np.int8), (w, h), origin, res * step, t_us, frame_id, store)
    head = store.serialize_cdr(empty, _OCCUPANCY_GRID)
    buf = bytearray(len(head) + h * w)
    buf[: len(head)] = head
    # the CDR encapsulation header says the byte order: 0x0001 little-endian, 0x0000 big
    struct.pack_into("<I" if head[1] else ">I", buf, len(head) - 4, h * w)
    data = np.frombuffer(buf, np.int8, offset=len(head)).reshape(w, h)
    # data[j, i] is box cell (h - 1 - i, w - 1 - j) (map_to_occupancy): this view is in map order
    target = data.swapaxes(0, 1)[::-1, ::-1]
    if step == 1:
        cells.occupancy(th, values, out=target)
        return buf
    band = max(1, cells.map.tile_cells // step)  # rows of the message a band
    for i in range(0, h, band):
        n = min(band, h - i)
        fine = TiledCells(cells.map, r0 + i * step, c0, n * step, w * step)
        target[i : i + n] = coarsen_values(fine.occupancy(th, values), step, th)
    return buf


def grid_map_msg(
    cells: MapCells,
    t_us: int,
    frame_id: str,
    store: Any,
    layers: Sequence[str] = LAYERS,
) -> Any:
    """``grid_map_msgs/GridMap`` of ``cells`` with ``layers`` (of :data:`GRID_LAYERS`): the
    masses, and ``dynamic``, the score rounded to :data:`DYNAMIC_STEP` (NaN in every cell when
    ``cells`` has none)."""
    from evgrid.ros import header, us_to_stamp

    m = np.asarray(cells.masses, dtype=np.float32)
    h, w = m.shape[:2]
    res = cells.resolution
    t = store.types
    dims = [
        t["std_msgs/msg/MultiArrayDimension"](label="column_index", size=w, stride=h * w),
        t["std_msgs/msg/MultiArrayDimension"](label="row_index", size=h, stride=h),
    ]
    layout = t["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)

    def layer(k: str) -> np.ndarray:
        if k != DYNAMIC_LAYER:
            return m[..., LAYERS.index(k)]
        if cells.dynamic is None:
            return np.full((h, w), np.nan, dtype=np.float32)
        return (np.round(cells.dynamic / DYNAMIC_STEP) * DYNAMIC_STEP).astype(np.float32)

    data = [
        t["std_msgs/msg/Float32MultiArray"](
            layout=layout, data=np.ascontiguousarray(layer(k).ravel(order="F"))
        )
        for k in layers
    ]
    info = t["grid_map_msgs/msg/GridMapInfo"](
        resolution=float(res),
        length_x=h * res,
        length_y=w * res,
        pose=_pose_msg(store, -(cells.r0 + h / 2) * res, -(cells.c0 + w / 2) * res),
    )
    sec, ns = us_to_stamp(t_us)
    return t["grid_map_msgs/msg/GridMap"](
        header=header(sec, ns, frame_id, store),
        info=info,
        layers=list(layers),
        basic_layers=[],
        data=data,
        outer_start_index=0,
        inner_start_index=0,
    )


@dataclass(frozen=True)
class McapParams:
    """What the MCAP export holds (see the module's docstring; docs/ros.md gives the sizes).

    ``window_m``: side of the square around the vehicle written while mapping (0: none).
    ``rate_hz``: how often the window is written (None: at every keyframe). ``maps``: the
    windowed maps (None: the first of ``navigation`` the run has, else its first map).
    ``final_maps``: the maps written whole at the end (None: every map of the run; ``()``:
    none). ``final_max_side``: the most cells along a side of a final OccupancyGrid (0: no
    limit); a larger map is written coarser by the smallest whole factor that fits
    (:func:`evgrid.grid.coarse_step`). ``layers``:
    ``occupancy`` (OccupancyGrid) and any of :data:`GRID_LAYERS` (one GridMap with those
    layers: the masses, ``dynamic`` the dynamic score).
    ``occupancy_values``: ``trinary`` or ``scale`` (:func:`~evgrid.export.nav2.occupancy_values`).
    ``compression``: the chunks' (:data:`COMPRESSIONS`). ``map_frame``, ``fixed_frame``: the
    map frame and the recording's fixed frame (the rig's ``world_frame``; nuScenes: global).
    """

    window_m: float = 40.0
    rate_hz: float | None = None
    maps: tuple[str, ...] | None = None
    final_maps: tuple[str, ...] | None = None
    # 16384: the largest texture side of common GPUs, which RViz and browser viewers such as
    # Foxglove draw an OccupancyGrid in (RViz draws a larger one empty); it also bounds the
    # memory of writing a final map however long the drive (docs/store.md)
    final_max_side: int = 16384
    layers: tuple[str, ...] = ("occupancy",)
    occupancy_values: str = "trinary"
    compression: str = "zstd"
    navigation: tuple[str, ...] = ("nav", "fused", "ray_ilm")
    thresholds: Nav2Thresholds = field(default_factory=Nav2Thresholds)
    map_frame: str = "map"
    fixed_frame: str = "odom"

    def __post_init__(self) -> None:
        if not (isinstance(self.window_m, (int, float)) and math.isfinite(self.window_m)):
            raise ValueError(f"McapParams.window_m must be a finite number, got {self.window_m!r}")
        if self.window_m < 0:
            raise ValueError(f"McapParams.window_m must be >= 0 m, got {self.window_m!r}")
        if self.rate_hz is not None and not (
            isinstance(self.rate_hz, (int, float)) and 0 < self.rate_hz < math.inf
        ):
            raise ValueError(
                f"McapParams.rate_hz must be a positive number or None, got {self.rate_hz!r}"
            )
        for key in ("maps", "final_maps", "layers", "navigation"):
            v = getattr(self, key)
            if v is None and key in ("maps", "final_maps"):
                continue
            if isinstance(v, str) or not all(isinstance(n, str) and n for n in v):
                raise ValueError(f"McapParams.{key} must be a tuple of names, got {v!r}")
            object.__setattr__(self, key, tuple(v))
        bad = [k for k in self.layers if k != "occupancy" and k not in GRID_LAYERS]
        if bad or not self.layers:
            raise ValueError(
                f"McapParams.layers: {bad or 'none'}; choose from {('occupancy', *GRID_LAYERS)}"
            )
        if self.occupancy_values not in OCCUPANCY_VALUES:
            raise ValueError(
                f"McapParams.occupancy_values must be one of {OCCUPANCY_VALUES}, "
                f"got {self.occupancy_values!r}"
            )
        if self.compression not in COMPRESSIONS:
            raise ValueError(
                f"McapParams.compression must be one of {COMPRESSIONS}, got {self.compression!r}"
            )
        if not self.navigation:
            raise ValueError("McapParams.navigation must name at least one map")
        side = self.final_max_side
        if isinstance(side, bool) or not isinstance(side, int) or not (side == 0 or side >= 256):
            raise ValueError(
                "McapParams.final_max_side must be 0 (no limit) or a whole number of cells >= "
                f"256, got {side!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["thresholds"] = asdict(self.thresholds)
        return d


def _open_mcap(path: Path, compression: str, overwrite: bool) -> tuple[AtomicFile, Any]:
    from evgrid.ros import require

    require("mcap")
    from mcap.writer import CompressionType, Writer

    f = AtomicFile(path, overwrite)
    try:
        kind = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }[compression]
        w = Writer(f.file, compression=kind)
        w.start(profile="ros2", library="evgrid")
    except BaseException as e:
        f.abort()
        raise write_error(path, e) from e
    return f, w


class McapExporter:
    """Observer that writes the maps to an MCAP file while mapping; call :meth:`close` at the
    end (or :meth:`abort` when the run fails: nothing is left under ``path``).

    ``path`` is a ``.mcap`` file (the suffix is added when missing) or a folder (``maps.mcap``
    in it); an existing file is refused unless ``overwrite``. See :class:`McapParams`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        params: McapParams = McapParams(),
        overwrite: bool = False,
    ):
        from evgrid.ros import typestore

        self.params = params
        self.path = target_path(path, "maps", ".mcap")
        self.store = typestore(2)
        self._file, self._w = _open_mcap(self.path, params.compression, overwrite)
        self._channels: dict[str, int] = {}
        self.n_messages = 0
        self.placement: MapPlacement | None = None
        self._window_maps: tuple[str, ...] = ()
        self._next_us: float | None = None
        self._last: tuple[int, dict[str, EvidentialMap]] | None = None
        self._path: list[tuple[int, SE2]] = []

    # -- writing -----------------------------------------------------------------------------

    def _write(self, topic: str, msgtype: str, t_us: int, msg: Any) -> None:
        self._write_cdr(topic, msgtype, t_us, bytes(self.store.serialize_cdr(msg, msgtype)))

    def _write_cdr(self, topic: str, msgtype: str, t_us: int, data: bytes | bytearray) -> None:
        """Write a message serialised already (CDR bytes)."""
        c = self._channels.get(topic)
        if c is None:
            text, _ = self.store.generate_msgdef(msgtype, ros_version=2)
            sid = self._w.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
            c = self._channels[topic] = self._w.register_channel(
                topic=topic, message_encoding="cdr", schema_id=sid
            )
        t_ns = int(t_us) * 1000
        self._w.add_message(channel_id=c, log_time=t_ns, data=data, publish_time=t_ns)
        self.n_messages += 1

    def _guarded(self, fn, *args) -> Any:
        """Run a writing step; on any failure remove the temporary file and name ``path``."""
        if self._file.done:
            raise ValueError(f"{self.path}: the MCAP export is closed")
        try:
            return fn(*args)
        except BaseException as e:
            self._file.abort()
            raise write_error(self.path, e) from e

    def write_maps(
        self,
        maps: dict[str, EvidentialMap],
        t_us: int,
        box: tuple[int, int, int, int] | None = None,
    ) -> None:
        """Write ``maps`` (a window ``(r0, c0, h, w)`` of map cells, or each whole) at ``t_us``."""
        self._guarded(self._write_maps, maps, t_us, box)

    def _write_maps(
        self, maps: dict[str, EvidentialMap], t_us: int, box: tuple[int, int, int, int] | None
    ) -> None:
        p, frame = self.params, self.params.map_frame
        grid_layers = tuple(k for k in p.layers if k != "occupancy")
        for name, m in maps.items():
            b = box or m.covered_bounds()
            if b[2] == 0:
                continue
            # a whole map with no GridMap layer is read tile by tile
            whole = box is None and not grid_layers
            cells = (
                TiledCells(m, *b) if whole else MapCells.read(m, b, DYNAMIC_LAYER in grid_layers)
            )
            topic = f"/evgrid/{name}/occupancy"
            if "occupancy" in p.layers and whole:  # a byte a cell, once (the box can be large)
                th, values = p.thresholds, p.occupancy_values
                step = coarse_step(b[2], b[3], p.final_max_side)
                if step > 1:
                    log.info(
                        "MCAP export %s: the final map %r is %d x %d cells, more than "
                        "final_max_side=%d a side: written %dx coarser (%d x %d cells of %.3g m; "
                        "a cell occupied if any of its cells is, unknown if any is, else free); "
                        "full resolution: the nav2 export and --save-maps",
                        self.path, name, b[2], b[3], p.final_max_side, step,
                        -(-b[2] // step), -(-b[3] // step), m.grid.resolution * step,
                    )  # fmt: skip
                data = occupancy_grid_cdr(cells, t_us, frame, self.store, th, values, step)
                self._write_cdr(topic, _OCCUPANCY_GRID, t_us, data)
                del data  # before the next map's
            elif "occupancy" in p.layers:
                msg = occupancy_grid_msg(
                    cells, t_us, frame, self.store, p.thresholds, p.occupancy_values
                )
                self._write(topic, _OCCUPANCY_GRID, t_us, msg)
            if grid_layers:
                msg = grid_map_msg(cells, t_us, frame, self.store, grid_layers)
                self._write(f"/evgrid/{name}/grid_map", "grid_map_msgs/msg/GridMap", t_us, msg)

    # -- the observer ------------------------------------------------------------------------

    def _start(self, update: Any) -> None:
        p = self.params
        maps = update.maps.maps
        if p.maps is None:
            found = [n for n in p.navigation if n in maps] or list(maps)[:1]
            if found[0] not in p.navigation:
                log.info(
                    "MCAP export %s: no navigation map %s in this run; the window shows %s",
                    self.path,
                    list(p.navigation),
                    found[0],
                )
            self._window_maps = (found[0],)
        else:
            self._window_maps = p.maps
        missing = [n for n in (*self._window_maps, *(p.final_maps or ())) if n not in maps]
        if missing:
            raise ValueError(f"{self.path}: no map {missing} in this run; it has {sorted(maps)}")
        self.placement = MapPlacement.from_update(update, p.map_frame, p.fixed_frame)
        meta = {**self.placement.as_dict(), "params": repr(p.to_dict())}
        self._w.add_metadata("evgrid", {k: str(v) for k, v in meta.items()})

    def _on_update(self, update: Any) -> None:
        from evgrid.ros import header, tf_message, transform_msg, us_to_stamp

        if self.placement is None:
            self._start(update)
        p, store = self.params, self.store
        t_us = int(update.frame.timestamp)
        pose: SE2 = update.pose
        if p.map_frame != p.fixed_frame:  # maps built in the fixed frame itself need no link
            fixed = SE3.from_se2(fixed_in_map(update))
            tf = transform_msg(p.map_frame, p.fixed_frame, t_us, fixed, store)
            self._write("/tf", "tf2_msgs/msg/TFMessage", t_us, tf_message([tf], store))
        sec, ns = us_to_stamp(t_us)
        ego = store.types["geometry_msgs/msg/PoseStamped"](
            header=header(sec, ns, p.map_frame, store),
            pose=_pose_msg(store, pose.x, pose.y, pose.yaw),
        )
        self._write("/evgrid/ego_pose", "geometry_msgs/msg/PoseStamped", t_us, ego)
        self._path.append((t_us, pose))
        self._last = (t_us, update.maps.maps)
        if p.window_m <= 0 or not self._due(t_us, update.frame.is_keyframe):
            return
        maps = {n: update.maps.maps[n] for n in self._window_maps}
        any_map = next(iter(maps.values()))
        n = int(math.ceil(p.window_m / any_map.grid.resolution))
        rc, cc = any_map.grid.map_xy_to_cell(pose.x, pose.y)
        self._write_maps(maps, t_us, (int(rc) - n // 2, int(cc) - n // 2, n, n))

    def _due(self, t_us: int, keyframe: bool) -> bool:
        """Whether the window is written at ``t_us``: keyframes, or a fixed rate's ticks."""
        if self.params.rate_hz is None:
            return keyframe
        period = 1e6 / self.params.rate_hz
        if self._next_us is None:
            self._next_us = t_us + period
            return True
        if t_us < self._next_us:
            return False
        while self._next_us <= t_us:
            self._next_us += period
        return True

    def on_update(self, update: Any) -> None:
        self._guarded(self._on_update, update)

    def _close(self) -> None:
        from evgrid.ros import header, us_to_stamp

        p, store = self.params, self.store
        if self._last is not None:
            t_us, maps = self._last
            t_us += 1  # after the last window, so a player shows the whole maps at the end
            names = tuple(maps) if p.final_maps is None else p.final_maps
            self._write_maps({n: maps[n] for n in names}, t_us, None)
            sec, ns = us_to_stamp(t_us)
            poses = []
            for tp, pose in self._path:
                s, n = us_to_stamp(tp)
                poses.append(
                    store.types["geometry_msgs/msg/PoseStamped"](
                        header=header(s, n, p.map_frame, store),
                        pose=_pose_msg(store, pose.x, pose.y, pose.yaw),
                    )
                )
            path = store.types["nav_msgs/msg/Path"](
                header=header(sec, ns, p.map_frame, store), poses=poses
            )
            self._write("/evgrid/path", "nav_msgs/msg/Path", t_us, path)
            self._last = None
        self._w.finish()

    def close(self) -> Path:
        """Write the final maps and the path, finish the file and rename it onto ``path``."""
        self._guarded(self._close)
        return self._guarded(self._file.commit)

    def abort(self) -> None:
        """Drop the file being written (nothing is left under ``path``)."""
        self._file.abort()

    def __enter__(self) -> McapExporter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_maps_mcap(
    maps: dict[str, EvidentialMap],
    path: str | os.PathLike,
    params: McapParams = McapParams(),
    overwrite: bool = False,
    stamp_us: int = 0,
    placement: MapPlacement | None = None,
) -> Path:
    """Saved maps as one MCAP file: each whole, stamped ``stamp_us`` (``params.layers`` and
    values, frames ``params.map_frame`` and ``fixed_frame``), with the metadata record
    ``evgrid`` (the frames, ``placement`` when known, the stamp, each map's own metadata) and,
    for a map frame other than the fixed frame, its ``/tf`` link as a run writes it."""
    from evgrid.ros import tf_message, transform_msg

    refuse_empty(maps, path)
    exp = McapExporter(path, params, overwrite)
    with exp:
        p = params
        meta = {"map_frame": p.map_frame, "fixed_frame": p.fixed_frame}
        if placement is not None:
            meta.update(placement.as_dict())
            if p.map_frame != p.fixed_frame:
                fixed = SE3.from_se2(placement.fixed_in_map)
                tf = transform_msg(p.map_frame, p.fixed_frame, stamp_us, fixed, exp.store)
                exp._guarded(
                    exp._write,
                    "/tf",
                    "tf2_msgs/msg/TFMessage",
                    stamp_us,
                    tf_message([tf], exp.store),
                )
        meta["stamp_us"] = str(int(stamp_us))
        meta["params"] = repr(p.to_dict())
        meta.update({f"map {n}": json.dumps(m.metadata, default=str) for n, m in maps.items()})
        exp._guarded(exp._w.add_metadata, "evgrid", {k: str(v) for k, v in meta.items()})
        exp.write_maps(maps, stamp_us, None)
    return exp.path


def write_map_mcap(
    m: EvidentialMap,
    path: str | os.PathLike,
    name: str | None = None,
    params: McapParams = McapParams(),
    overwrite: bool = False,
    stamp_us: int = 0,
    placement: MapPlacement | None = None,
) -> Path:
    """One saved map as an MCAP file (topic ``/evgrid/NAME/...``, NAME default the map's rule;
    the rest as :func:`write_maps_mcap`)."""
    return write_maps_mcap(
        {name or str(m.metadata.get("rule", "map")): m},
        path,
        params,
        overwrite,
        stamp_us,
        placement,
    )
