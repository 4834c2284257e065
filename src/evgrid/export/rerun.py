"""A rerun recording (``.rrd``) or live viewer of a mapping run: maps, current ISMs, trajectory
(the ``rerun`` extra: ``evgrid.install_hint("rerun")`` says how to install it).

Everything lives in one 3-D space in metres, the map frame (the recording's fixed frame, or
the first pose's with ``MapperConfig.frame = "first_pose"``; z up), so maps, ISMs and the
trajectory overlay:

* ``maps/NAME``: a square of ``window_m`` metres around the vehicle, a textured quad whose
  corners are the window's outer cell corners in the map frame (colours:
  :func:`evgrid.render.map_rgb`, free white, occupied black, unknown grey);
* ``maps/NAME/dynamic``: the cells called dynamic (score above
  :attr:`evgrid.fusion.DynamicParams.threshold`) of the window, points at the cells' centres in
  :data:`evgrid.render.DYNAMIC_COLOUR`, for the maps that keep a score (``final/NAME/dynamic``
  for the whole map at the end);
* ``ego``: the ego pose (a transform: translation in metres, yaw about z) at every update;
  ``ego/isms/NAME``: the local ISM grids of the update, quads in the ego frame below it;
* ``trajectory``: the ego positions (metres); ``final/NAME``: each whole map at :meth:`close`;
* ``info``: the map frame, the recording's fixed frame and the first ego pose in it.

Timelines ``time`` (the frames' timestamps) and ``update`` (the update's number); pictures at
keyframes unless asked for at every update.

A ``.rrd`` is streamed through rerun's binary stream into a temporary file beside the target
and renamed when complete (:mod:`evgrid.export._files`): a full disk names the file and leaves
no partial ``.rrd``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.export._files import AtomicFile, refuse_empty, target_path, write_error
from evgrid.export._place import MapPlacement
from evgrid.grid import EvidentialMap, coarse_step

__all__ = ["RerunParams", "RerunRecorder", "write_map_rrd", "quad_corners"]


def _rr() -> Any:
    from evgrid.ros import require

    return require("rerun", "rerun")


@dataclass(frozen=True)
class RerunParams:
    """What a rerun recording holds: ``window_m`` metres around the vehicle at every ``step``-th
    cell (cells read per map and picture: ``(window_m / res / step)^2``), ISMs at every
    ``step``-th cell, pictures at keyframes only unless ``keyframes_only`` is False (the
    trajectory is logged at every update), ``isms`` whether to log them, ``dynamic`` whether to
    log the cells called dynamic (a point per ``step`` x ``step`` block drawn dynamic, as in the
    figures: :func:`evgrid.render.called_dynamic`); ``map_frame`` and ``fixed_frame`` name the
    frames in ``info``."""

    window_m: float = 40.0
    step: int = 2
    keyframes_only: bool = True
    isms: bool = True
    dynamic: bool = True
    map_frame: str = "map"
    fixed_frame: str = "odom"

    def __post_init__(self) -> None:
        if not (isinstance(self.window_m, (int, float)) and 0 < self.window_m < math.inf):
            raise ValueError(
                f"RerunParams.window_m must be a positive number, got {self.window_m!r}"
            )
        if not isinstance(self.step, int) or self.step < 1:
            raise ValueError(f"RerunParams.step must be an integer >= 1, got {self.step!r}")


def quad_corners(r0: float, c0: float, h: int, w: int, resolution: float) -> np.ndarray:
    """The four outer corners ``(4, 3)`` in metres of grid cells ``[r0, r0+h) x [c0, c0+w)``
    (map or local grid: rows towards -x, columns towards -y, :mod:`evgrid.geometry`), in the
    order of the texture's corners (0, 0), (1, 0), (1, 1), (0, 1) (u along image columns, v
    along image rows): an image of those cells drawn on this quad lies on its cells."""
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    x = -(r0 + uv[:, 1] * h) * resolution
    y = -(c0 + uv[:, 0] * w) * resolution
    return np.stack([x, y, np.zeros(4)], axis=1)


def _quad(rr: Any, rgb: np.ndarray, corners: np.ndarray) -> Any:
    return rr.Mesh3D(
        vertex_positions=corners,
        triangle_indices=[[0, 1, 2], [0, 2, 3]],
        vertex_texcoords=[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
        albedo_texture=rgb,
    )


def _dynamic_points(
    rr: Any, m: EvidentialMap, box: tuple[int, int, int, int], step: int, threshold: float
) -> Any:
    """The blocks of ``step`` x ``step`` cells of ``box`` ``(r0, c0, h, w)`` drawn as dynamic
    (:func:`evgrid.render.called_dynamic`), as points in metres at the blocks' centres (none:
    an empty set, so that the last ones do not linger in the viewer)."""
    from evgrid.render import DYNAMIC_COLOUR, called_dynamic

    r0, c0, h, w = box
    i, j = np.nonzero(called_dynamic(m, r0, c0, h, w, step, threshold))
    res = m.grid.resolution
    xyz = np.stack(
        [-(r0 + (i + 0.5) * step) * res, -(c0 + (j + 0.5) * step) * res, np.full(len(i), 0.05)],
        axis=1,
    ).astype(np.float32)
    colour = np.rint(np.asarray(DYNAMIC_COLOUR) * 255).astype(np.uint8)
    return rr.Points3D(xyz, radii=0.5 * step * res, colors=colour)


def _whole_step(m: EvidentialMap, max_cells: int = 2048) -> int:
    """One cell in how many of a whole map's picture (at most ``max_cells`` a side)."""
    _, _, h, w = m.covered_bounds()
    return coarse_step(h, w, max_cells)


def _whole(m: EvidentialMap, max_cells: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """A whole map as a picture (every ``step``-th cell) and its quad's corners.

    Sampled in bands of a tile's rows, so that the masses read at once (12 bytes a sampled
    cell, and map_rgb's float copies) are those of a band, not of the whole picture."""
    from evgrid.render import map_rgb, sample_map

    r0, c0, h, w = m.covered_bounds()
    step = _whole_step(m, max_cells)
    hh, ww = -(-h // step), -(-w // step)
    pic = np.empty((hh, ww, 3), np.uint8)
    band = max(1, m.tile_cells // step)  # picture rows a band
    for i in range(0, hh, band):
        rows = min(band * step, h - i * step)  # map rows from the band's first sampled one
        part = map_rgb(sample_map(m, r0 + i * step, c0, rows, w, step)[0])
        pic[i : i + part.shape[0]] = part
    # the sampled picture covers hh * step rows from r0 (the last sample's cell included)
    return pic, quad_corners(r0, c0, hh * step, ww * step, m.grid.resolution)


#: rerun's stream framing (rerun-sdk 0.23, the pinned version): each read of a binary stream
#: is a whole stream, a 12-byte header (``RRF2``, version, options) and messages ending with
#: an end-of-stream message (16 zero bytes).
_RRD_MAGIC, _RRD_HEADER, _RRD_END = b"RRF2", 12, bytes(16)


#: Points of the trajectory logged with each picture (the whole path is logged at the end).
_TRAJECTORY_POINTS = 500


class _RrdFile:
    """A rerun binary stream drained into an :class:`AtomicFile` as one ``.rrd`` stream.

    Each drain is a complete stream; the pieces are joined into one by keeping the first
    header and the last end-of-stream message only, so the file on disk grows as the run goes
    instead of the recording waiting in memory until the end.
    """

    def __init__(self, rec: Any, path: Path, overwrite: bool):
        self.file = AtomicFile(path, overwrite)
        self._header: bytes | None = None
        try:
            self.stream = rec.binary_stream()
        except BaseException as e:
            self.file.abort()
            raise write_error(path, e) from e

    def drain(self) -> None:
        data = self.stream.read(flush=True)
        if not data:
            return
        head = data[:_RRD_HEADER]
        if (
            not head.startswith(_RRD_MAGIC)
            or not data.endswith(_RRD_END)
            or (self._header is not None and head != self._header)
        ):
            raise ValueError(
                f"{self.file.path}: rerun's stream framing is not the one evgrid joins "
                "(rerun-sdk 0.23.1, pinned in the rerun extra)"
            )
        if self._header is None:
            self._header = head
            self.file.write(head)
        self.file.write(data[_RRD_HEADER : -len(_RRD_END)])

    def commit(self) -> Path:
        self.drain()
        self.file.write(_RRD_END)
        return self.file.commit()


class RerunRecorder:
    """Observer that logs each update to rerun: to ``path`` (``.rrd``, or a folder: ``maps.rrd``
    in it) or, with ``path=None``, a spawned viewer. An existing file is refused unless
    ``overwrite``; :meth:`abort` drops an unfinished file. See :class:`RerunParams`."""

    def __init__(
        self,
        path: str | os.PathLike | None = None,
        params: RerunParams = RerunParams(),
        overwrite: bool = False,
    ):
        rr = _rr()
        self.rr = rr
        self.params = params
        self.rec = rr.RecordingStream("evgrid")
        self.path = target_path(path, "maps", ".rrd") if path is not None else None
        self._out = _RrdFile(self.rec, self.path, overwrite) if self.path is not None else None
        if self._out is None:  # the viewer listens on loopback only (rerun's default: 0.0.0.0)
            rr.bindings.spawn(port=9876, memory_limit="75%", extra_args=["--bind", "127.0.0.1"])
            self.rec.connect_grpc("rerun+http://127.0.0.1:9876/proxy")
        self.rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.trajectory: list[tuple[float, float]] = []
        self._maps: dict[str, EvidentialMap] = {}
        self._mapset: Any = None  # the run's maps (its dynamic threshold: DynamicParams)
        self._n = 0
        self.placement: MapPlacement | None = None

    def _guarded(self, fn, *args) -> Any:
        if self._out is None:
            return fn(*args)
        if self._out.file.done:
            raise ValueError(f"{self.path}: the rerun recording is closed")
        try:
            return fn(*args)
        except BaseException as e:
            self._out.file.abort()
            raise write_error(self.path, e) from e

    def _on_update(self, update: Any) -> None:
        from evgrid.render import map_rgb, sample_map

        rr, rec, p = self.rr, self.rec, self.params
        if self.placement is None:
            self.placement = MapPlacement.from_update(update, p.map_frame, p.fixed_frame)
            text = "\n".join(f"* {k}: {v}" for k, v in self.placement.as_dict().items())
            rec.log("info", rr.TextDocument(text, media_type="text/markdown"), static=True)
        rec.set_time("time", timestamp=update.frame.timestamp * 1e-6)
        rec.set_time("update", sequence=self._n)
        self._n += 1
        pose = update.pose
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        self.trajectory.append((pose.x, pose.y))
        rec.log(
            "ego",
            # float32 arrays and a matrix: with numpy 1.x (the nuscenes extra's), rerun 0.23
            # drops lists and rotation objects (its asarray(copy=...) needs numpy 2)
            rr.Transform3D(
                translation=np.array([pose.x, pose.y, 0.0], np.float32),
                mat3x3=np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], np.float32),
            ),
        )
        rec.log("ego/position", rr.Points3D([[0.0, 0.0, 0.0]], radii=0.5, colors=[[230, 60, 30]]))
        self._maps = update.maps.maps
        self._mapset = update.maps
        if not (p.keyframes_only and not update.frame.is_keyframe):
            self._log_trajectory(_TRAJECTORY_POINTS)
            if p.isms:
                for name, ism in update.isms.items():
                    n = ism.shape[0]
                    pic = map_rgb(ism[:: p.step, :: p.step])
                    res = update.maps.grid.resolution
                    hh, ww = pic.shape[:2]
                    corners = quad_corners(-n / 2, -n / 2, hh * p.step, ww * p.step, res)
                    rec.log(f"ego/isms/{name}", _quad(rr, pic, corners))
            for name, m in update.maps.maps.items():
                n = int(round(p.window_m / m.grid.resolution))
                rc, cc = m.grid.map_xy_to_cell(pose.x, pose.y)
                r0, c0 = int(rc) - n // 2, int(cc) - n // 2
                pic = map_rgb(sample_map(m, r0, c0, n, n, p.step)[0])
                hh, ww = pic.shape[:2]
                corners = quad_corners(r0, c0, hh * p.step, ww * p.step, m.grid.resolution)
                rec.log(f"maps/{name}", _quad(rr, pic, corners))
                if p.dynamic and m.dynamic:
                    th = update.maps.dynamic.threshold
                    points = _dynamic_points(rr, m, (r0, c0, n, n), p.step, th)
                    rec.log(f"maps/{name}/dynamic", points)
            if self._out is not None:
                self._out.drain()  # with the pictures: the trajectory alone is small

    def on_update(self, update: Any) -> None:
        self._guarded(self._on_update, update)

    def _log_trajectory(self, max_points: int | None) -> None:
        """The path so far (at most ``max_points``, evenly spaced, the last one included), so
        that the pictures' updates cost the same on any drive instead of growing with it."""
        xy = np.asarray(self.trajectory, dtype=np.float64)
        if max_points is not None and len(xy) > max_points:
            xy = xy[np.unique(np.linspace(0, len(xy) - 1, max_points).astype(np.int64))]
        xyz = np.c_[xy, np.zeros(len(xy))].astype(np.float32)
        self.rec.log("trajectory", self.rr.LineStrips3D([xyz], colors=[[230, 60, 30]]))

    def _close(self) -> None:
        if self.trajectory:
            self._log_trajectory(None)  # the whole path, at the last update's time
        for name, m in self._maps.items():
            if m.covered_bounds()[2]:
                pic, corners = _whole(m)
                self.rec.log(f"final/{name}", _quad(self.rr, pic, corners), static=True)
                del pic
                if self.params.dynamic and m.dynamic:
                    th = self._mapset.dynamic.threshold
                    points = _dynamic_points(self.rr, m, m.covered_bounds(), _whole_step(m), th)
                    self.rec.log(f"final/{name}/dynamic", points, static=True)
                if self._out is not None:  # each map's picture to the file before the next's
                    self._out.drain()
        self.rec.flush()

    def close(self) -> Path | None:
        """Log the whole final maps and finish; returns the ``.rrd`` path (None for a viewer)."""
        self._guarded(self._close)
        if self._out is None:
            return None
        return self._guarded(self._out.commit)

    def abort(self) -> None:
        """Drop the file being written (nothing is left under ``path``)."""
        if self._out is not None:
            self._out.file.abort()


def write_map_rrd(
    m: EvidentialMap,
    path: str | os.PathLike,
    name: str | None = None,
    overwrite: bool = False,
    placement: MapPlacement | None = None,
) -> Path:
    """One saved map as a rerun recording (entity ``final/NAME``, a quad in metres; ``info``,
    as a run writes it, when the ``placement`` is known)."""
    refuse_empty({name or str(m.metadata.get("rule", "map")): m}, path)
    rr = _rr()
    rec = rr.RecordingStream("evgrid")
    out = _RrdFile(rec, target_path(path, "maps", ".rrd"), overwrite)
    try:
        rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if placement is not None:
            text = "\n".join(f"* {k}: {v}" for k, v in placement.as_dict().items())
            rec.log("info", rr.TextDocument(text, media_type="text/markdown"), static=True)
        pic, corners = _whole(m)
        rec.log(
            f"final/{name or m.metadata.get('rule', 'map')}", _quad(rr, pic, corners), static=True
        )
        rec.flush()
        return out.commit()
    except BaseException as e:
        out.file.abort()
        raise write_error(out.file.path, e) from e
