"""Mass grids in the map frame: the SE(2) warp of a local grid, a tiled map that grows, persistence.

Indexing and frames are those of :mod:`evgrid.geometry`. A local ISM grid (``(n, n, 3)``,
ego-centred) taken at ego pose ``pose`` (an :class:`~evgrid.geometry.SE2` of the ego in the
map frame) is resampled onto the map cells its square covers, bilinearly (a convex
mix of masses is a mass), cells beyond the local grid counting as vacuous [0, 0, 1]
(docs/decisions.md#map-frame-and-warp). Only that window of the map is read or written, and
within it the update rules visit only the covered cells of each row (:attr:`MapWindow.spans`).

The map stores square tiles of ``tile_cells`` cells, created the first time a local grid
covers them, so memory grows with the area explored, not with the bounding box of the drive.
"""

from __future__ import annotations

import json
import logging
import math
import os
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evgrid.geometry import MAX_POSE_M, SE2, SE3, GridSpec
from evgrid.io import atomic_write
from evgrid.kernels import COARSE, coarse_blocks, count_invalid, load_padded, warp_rows
from evgrid.mass import vacuous
from evgrid.store import Pager, TileGroup, TileLayer, tile_distance_m

logger = logging.getLogger(__name__)

__all__ = [
    "MapWindow",
    "EvidentialMap",
    "MapFrame",
    "MAP_FRAME_KINDS",
    "Warper",
    "warp_to_map",
    "warp_window",
    "window_affine",
    "save_map",
    "load_map",
    "MapFileError",
    "tile_pieces",
    "coarse_step",
]


@dataclass(frozen=True, slots=True, eq=False)
class MapWindow:
    """A local grid resampled into the map: masses ``(h, w, 3)`` whose cell [0, 0] is map cell
    ``(r0, c0)``.

    ``covered[i, j]`` is True where the local grid contributes any mass to the cell. Covered
    cells of a row are contiguous: ``spans[i] = (lo, hi)`` (int64) gives them as columns
    ``lo:hi`` (``(0, 0)`` for none); cells outside hold vacuous mass. Without ``spans``
    (a window built by hand), every row with a covered cell counts as covered whole.
    """

    r0: int
    c0: int
    masses: np.ndarray
    covered: np.ndarray
    spans: np.ndarray | None = None

    def row_spans(self) -> np.ndarray:
        """``spans``; without them, whole rows ``(0, w)`` where a row has a covered cell."""
        if self.spans is not None:
            return self.spans
        h, w = self.shape
        out = np.zeros((h, 2), dtype=np.int64)
        out[self.covered.any(axis=1), 1] = w
        return out

    @property
    def shape(self) -> tuple[int, int]:
        """``(h, w)`` in cells."""
        return self.covered.shape  # type: ignore[return-value]


def _pose_affine(grid: GridSpec, pose: SE2) -> tuple[float, float, float, float]:
    """Map (R, C) -> local (u, v) coefficients: u = cu + cos a + sin b, v = cu - sin a + cos b."""
    res = grid.resolution
    return math.cos(pose.yaw), math.sin(pose.yaw), pose.x / res, pose.y / res


def window_affine(
    grid: GridSpec, pose: SE2, r0: int, c0: int
) -> tuple[float, float, float, float, float, float]:
    """``(u00, v00, du_di, du_dj, dv_di, dv_dj)``: window cell (i, j) (map cell (r0 + i, c0 + j))
    samples local (u, v)."""
    cs, sn, tx, ty = _pose_affine(grid, pose)
    cc = grid.n_cells / 2.0 - 0.5
    a0 = r0 + 0.5 + tx
    b0 = c0 + 0.5 + ty
    return cc + cs * a0 + sn * b0, cc - sn * a0 + cs * b0, cs, sn, -sn, cs


def warp_window(grid: GridSpec, pose: SE2) -> tuple[int, int, int, int]:
    """Map cells ``(r0, c0, h, w)`` that a local grid at ``pose`` can contribute to."""
    n = grid.n_cells
    c0 = n / 2.0 - 0.5
    cs, sn, tx, ty = _pose_affine(grid, pose)
    rows, cols = [], []
    for u in (-1.0, float(n)):
        for v in (-1.0, float(n)):
            a = cs * (u - c0) - sn * (v - c0)
            b = sn * (u - c0) + cs * (v - c0)
            rows.append(a - 0.5 - tx)
            cols.append(b - 0.5 - ty)
    r0 = math.floor(min(rows))
    c0_ = math.floor(min(cols))
    r1 = math.ceil(max(rows))
    c1 = math.ceil(max(cols))
    return r0, c0_, r1 - r0 + 1, c1 - c0_ + 1


class Warper:
    """Warps local grids into the map, reusing its buffers between calls.

    Fresh multi-megabyte arrays cost more in page faults than the warp itself; a pipeline
    keeps one ``Warper`` per ISM. :meth:`load` takes a local grid (checked, into a padded
    copy); :meth:`warp_loaded` resamples it at a pose, and :meth:`evgrid.fusion.MapSet.update`
    samples the loaded copies of several warpers directly. Each returned window is a view that
    the next call overwrites.

    Cells of a local grid that are not masses (NaN, inf, a negative mass, masses not summing to
    1) are taken as vacuous, logged the first time and counted in ``n_rejected``: a bilinear mix
    would otherwise blend them into their neighbours, where a negative mass can hide inside a
    valid-looking sum.
    """

    def __init__(self, grid: GridSpec, name: str = "local grid"):
        self.grid = grid
        self.name = name
        n = grid.n_cells
        self._side = side = int(math.ceil(n * math.sqrt(2.0))) + 4
        self._masses = np.empty(side * side * 3, dtype=np.float32)
        self._covered = np.empty(side * side, dtype=np.bool_)
        self._spans = np.zeros((side, 2), dtype=np.int64)
        self._src = vacuous(
            (n + 3, n + 3)
        )  # local grid + vacuous border (see evgrid.kernels.warp_rows)
        self._coarse = np.zeros(((n + 3 + COARSE - 1) // COARSE,) * 2, dtype=np.bool_)
        self.n_rejected = 0

    def __getstate__(self) -> dict:
        # a checkpoint (evgrid.checkpoint) leaves out the buffers: every update loads its
        # local grid before it warps, and each warp overwrites the output
        drop = ("_masses", "_covered", "_src", "_coarse")
        return {k: v for k, v in self.__dict__.items() if k not in drop}

    def __setstate__(self, state: dict) -> None:
        n_rejected = state.pop("n_rejected")
        self.__init__(state.pop("grid"), state.pop("name"))
        self.__dict__.update(state)
        self.n_rejected = n_rejected

    @property
    def source(self) -> np.ndarray:
        """The loaded local grid with its vacuous border, flat (row stride ``3 (n + 3)``)."""
        return self._src.reshape(-1)

    @property
    def coarse(self) -> np.ndarray:
        """Which 8 x 8 blocks of :attr:`source` hold a cell that is not vacuous."""
        return self._coarse

    def load(self, local: np.ndarray) -> int:
        """Take ``local`` ``(n, n, 3)`` for the next warps; returns how many of its cells were not
        masses."""
        n = self.grid.n_cells
        a = np.asarray(local)
        if a.shape != (n, n, 3) or not (
            np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
        ):
            raise ValueError(
                f"{self.name}: the local grid must be a numeric array of shape {(n, n, 3)}, "
                f"got {a.dtype} {a.shape}"
            )
        n_bad = int(load_padded(np.ascontiguousarray(a, dtype=np.float32), self._src))
        if n_bad:
            if self.n_rejected == 0:
                logger.warning(
                    "%s: %d cell(s) of the local grid are not masses (NaN, inf, negative or not "
                    "summing to 1); they are taken as vacuous and counted in n_rejected",
                    self.name,
                    n_bad,
                )
            self.n_rejected += n_bad
        coarse_blocks(self._src, self._coarse)
        return n_bad

    def warp_loaded(self, pose: SE2) -> MapWindow:
        """The grid of the last :meth:`load`, taken at ego ``pose`` (first-pose frame, m/rad),
        resampled into the map."""
        grid = self.grid
        n = grid.n_cells
        r0, c0, h, w = warp_window(grid, pose)
        # windows are packed at the buffers' start (row stride w) so each is one contiguous block
        spans = self._spans[:h]
        warp_rows(
            self.source,
            3 * (n + 3),
            self._coarse,
            n,
            *window_affine(grid, pose, r0, c0),
            self._masses,
            3 * w,
            self._covered,
            w,
            h,
            w,
            spans,
        )
        masses = self._masses[: h * w * 3].reshape(h, w, 3)
        covered = self._covered[: h * w].reshape(h, w)
        return MapWindow(r0, c0, masses, covered, spans)

    def warp(self, local: np.ndarray, pose: SE2) -> MapWindow:
        """Resample ``local`` ``(n, n, 3)`` taken at ego ``pose`` (first-pose frame, m/rad) into the
        map."""
        self.load(local)
        return self.warp_loaded(pose)


def warp_to_map(local: np.ndarray, pose: SE2, grid: GridSpec) -> MapWindow:
    """Resample a local mass grid ``(n, n, 3)`` taken at ego ``pose`` (first-pose frame, m/rad) into
    the map."""
    return Warper(grid).warp(local, pose)


def _covered_box(layers: dict[str, np.ndarray]) -> tuple[int, int, int, int] | tuple[()]:
    """``(first row, last row, first col, last col)`` of a tile's covered cells; () if none."""
    cov = layers["covered"]
    r = np.flatnonzero(cov.any(axis=1))
    if not len(r):
        return ()
    c = np.flatnonzero(cov.any(axis=0))
    return int(r[0]), int(r[-1]), int(c[0]), int(c[-1])


def coarse_step(h: int, w: int, max_side: int) -> int:
    """The smallest whole factor that brings ``h`` by ``w`` cells to at most ``max_side`` along
    each side (1: it fits, or ``max_side`` is 0, no limit): how many cells of a large map a
    picture or a coarse message takes as one."""
    if max_side <= 0:
        return 1
    return max(1, -(-max(h, w) // max_side))


def tile_pieces(
    tile_cells: int, r0: int, c0: int, h: int, w: int
) -> Iterator[tuple[tuple[int, int], slice, slice, slice, slice]]:
    """The tiles of ``tile_cells`` a side that map cells ``[r0:r0+h, c0:c0+w]`` meet: for each,
    (tile key, tile rows, tile cols, window rows, window cols), the slices of the same cells
    (:meth:`EvidentialMap.pieces`, and any other layer tiled the same way)."""
    ts = tile_cells
    for ti in range(r0 // ts, (r0 + h - 1) // ts + 1):
        ra, rb = max(r0, ti * ts), min(r0 + h, (ti + 1) * ts)
        for tj in range(c0 // ts, (c0 + w - 1) // ts + 1):
            ca, cb = max(c0, tj * ts), min(c0 + w, (tj + 1) * ts)
            yield (
                (ti, tj),
                slice(ra - ti * ts, rb - ti * ts),
                slice(ca - tj * ts, cb - tj * ts),
                slice(ra - r0, rb - r0),
                slice(ca - c0, cb - c0),
            )


class EvidentialMap:
    """A mass grid in the map frame, stored as tiles created where local grids reach.

    Cells never covered read as vacuous. ``metadata`` is free JSON-serialisable data that is
    saved with the map. With ``dynamic``, each tile also holds a float32 dynamic score per cell
    (:attr:`dynamic_tiles`, created with the tile at 0; see :class:`evgrid.fusion.DynamicParams`).
    """

    def __init__(
        self,
        grid: GridSpec | None = None,
        tile_cells: int = 256,
        metadata: dict[str, Any] | None = None,
        dynamic: bool = False,
        frame: MapFrame | None = None,
    ):
        self.grid = grid or GridSpec()
        if not isinstance(tile_cells, (int, np.integer)) or tile_cells < 8:
            raise ValueError(f"tile_cells must be an integer >= 8, got {tile_cells!r}")
        self.tile_cells = int(tile_cells)
        # the tiles in memory, per layer; with a store attached (attach_store) the layers'
        # mappings also reach the tiles paged out to it (evgrid.store, docs/store.md)
        self._tiles: dict[tuple[int, int], np.ndarray] = {}
        self._covered: dict[tuple[int, int], np.ndarray] = {}
        self._dynamic: dict[tuple[int, int], np.ndarray] = {}
        self.pager: Pager | None = None
        self.tiles = TileLayer(self._tiles, "masses", self)
        self.covered_tiles = TileLayer(self._covered, "covered", self)
        self.dynamic_tiles = TileLayer(self._dynamic, "dynamic", self)
        self.metadata: dict[str, Any] = dict(metadata or {})
        if frame is not None and not isinstance(frame, MapFrame):
            raise TypeError(f"frame must be a MapFrame or None, got {type(frame).__name__}")
        self.frame = frame  # where the cells lie in the recording (None: not known)
        self.dynamic = bool(dynamic)

    def __repr__(self) -> str:
        mib = self.nbytes / 2**20
        return (
            f"EvidentialMap({len(self.tiles)} tiles of {self.tile_cells} cells, "
            f"{len(self._tiles)} in memory, {mib:.1f} MiB)"
        )

    def _layer_has(self, name: str) -> bool:
        return name != "dynamic" or self.dynamic

    @property
    def nbytes(self) -> int:
        """Bytes held in memory by the tiles (those paged out to a store hold none)."""
        layers = (self._tiles, self._covered, self._dynamic)
        return sum(a.nbytes for layer in layers for a in layer.values())

    def tile(self, key: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The masses ``(ts, ts, 3)`` and coverage ``(ts, ts)`` of tile ``key`` (tile row, tile
        column), views to update in place; a tile paged out is brought back, one not yet stored
        is created vacuous."""
        t = self._tiles.get(key)
        if t is None:
            if self.pager is not None and key in self.pager.stored:
                self.pager.page_in(key)
                return self._tiles[key], self._covered[key]
            ts = self.tile_cells
            t = vacuous((ts, ts))
            self._tiles[key] = t
            self._covered[key] = np.zeros((ts, ts), dtype=np.bool_)
            if self.dynamic:
                self._dynamic[key] = np.zeros((ts, ts), dtype=np.float32)
        return t, self._covered[key]

    # --- the tile store (evgrid.store, docs/store.md) -------------------------------------------

    def attach_store(self, group: TileGroup, write_meta: bool = True, copy: str = "") -> None:
        """Page this map's tiles to ``group`` from now on (:meth:`page_out`); tiles the group
        already holds (a map reopened) become this map's stored tiles. ``copy``: this map is a
        copy of the group's map named so (nav's gated inputs: "gated"), kept in the map's tile
        files as its difference from it (evgrid.store.TileGroup); its tiles leave memory with
        the map's."""
        if self.pager is not None:
            raise ValueError(f"this map already pages to {self.pager.group.folder}")
        ts = self.tile_cells
        layers = {"masses": self._tiles, "covered": self._covered}
        expect = {
            "masses": ((ts, ts, 3), np.dtype(np.float32)),
            "covered": ((ts, ts), np.dtype(bool)),
        }
        if self.dynamic:
            layers["dynamic"] = self._dynamic
            expect["dynamic"] = ((ts, ts), np.dtype(np.float32))
        self.pager = Pager(group, layers, _covered_box, expect, member=copy)
        if write_meta and not copy:
            self.write_store_meta()

    def write_store_meta(self) -> None:
        """Write what the store's tiles belong to (grid, tiling, metadata, frame) into its group."""
        if self.pager is None:
            raise ValueError("this map has no store attached")
        self.pager.group.write_meta(_header(self, self.frame))

    def page_out(self, x: float, y: float, radius_m: float) -> int:
        """Move the tiles in memory whose nearest point lies farther than ``radius_m`` metres from
        map point ``(x, y)`` to the store; returns how many moved. Nothing changes in the map:
        a stored tile reads as before and is brought back when written."""
        if self.pager is None:
            raise ValueError("page_out needs a store: attach_store first")
        ts, res = self.tile_cells, self.grid.resolution
        far = [k for k in self._tiles if tile_distance_m(k, ts, res, x, y) > radius_m]
        if far:
            self.pager.page_out(far)
        return len(far)

    def flush(self) -> int:
        """Write every tile in memory to the store as well (they stay in memory): the store then
        holds the whole map as it is now. Returns the bytes written."""
        if self.pager is None:
            raise ValueError("flush needs a store: attach_store first")
        if not self.pager.member:
            self.write_store_meta()
        return self.pager.flush()

    def pieces(
        self, r0: int, c0: int, h: int, w: int
    ) -> Iterator[tuple[tuple[int, int], slice, slice, slice, slice]]:
        """The tiles that map cells ``[r0:r0+h, c0:c0+w]`` meet, stored or not: for each, (tile
        key, tile rows, tile cols, window rows, window cols), the slices of the same cells."""
        return tile_pieces(self.tile_cells, r0, c0, h, w)

    def apply(
        self,
        window: MapWindow,
        fn: Callable[..., int | None],
        *masses: np.ndarray,
        pass_spans: bool = False,
    ) -> int:
        """Call ``fn(map_view, *window_views)`` on every covered piece; ``fn`` updates ``map_view``
        in place.

        ``masses`` are ``(h, w, 3)`` arrays aligned with ``window`` (default: ``window.masses``).
        With ``pass_spans``, ``fn`` also gets ``spans=``: the window's covered columns per row of
        the piece (``(h', 2)`` int64, as the update rules of :mod:`evgrid.fusion` take them), so
        that it can skip the uncovered cells (which hold vacuous mass).

        Returns the sum of what ``fn`` returned (None counting 0): for the update rules, the
        number of invalid ISM cells they rejected, leaving those map cells untouched.
        """
        arrays = masses or (window.masses,)
        h, w = window.shape
        for a in arrays:
            if a.shape != (h, w, 3):
                raise ValueError(f"window arrays must have shape {(h, w, 3)}, got {a.shape}")
        spans = window.row_spans()
        n_rejected = 0
        for key, tr, tc, wr, wc in self.pieces(window.r0, window.c0, h, w):
            piece = np.clip(spans[wr] - wc.start, 0, wc.stop - wc.start)
            rows_on = np.flatnonzero(piece[:, 1] > piece[:, 0])
            if len(rows_on) == 0:
                continue
            # trim the piece to its rows with covered cells
            a, b = int(rows_on[0]), int(rows_on[-1]) + 1
            tr = slice(tr.start + a, tr.start + b)
            wr = slice(wr.start + a, wr.start + b)
            tile, tcov = self.tile(key)
            views = (arr[wr, wc] for arr in arrays)
            if pass_spans:
                n = fn(tile[tr, tc], *views, spans=piece[a:b])
            else:
                n = fn(tile[tr, tc], *views)
            n_rejected += int(n or 0)
            tcov[tr, tc] |= window.covered[wr, wc]
        return n_rejected

    def read(self, r0: int, c0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """Dense copy of map cells ``[r0:r0+h, c0:c0+w]``: masses ``(h, w, 3)``, coverage
        ``(h, w)``."""
        out = vacuous((h, w))
        cov = np.zeros((h, w), dtype=np.bool_)
        for key, tr, tc, wr, wc in self.pieces(r0, c0, h, w):
            t = self.tiles.get(key)
            if t is not None:
                out[wr, wc] = t[tr, tc]
                cov[wr, wc] = self.covered_tiles[key][tr, tc]
        return out, cov

    def read_dynamic(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        """Dense copy ``(h, w)`` float32 of the dynamic score of cells ``[r0:r0+h, c0:c0+w]``;
        0 where no tile is stored. Raises ValueError if the map keeps no dynamic layer."""
        if not self.dynamic:
            raise ValueError(
                f"map {self.metadata.get('rule', '?')!r} keeps no dynamic layer (dynamic off)"
            )
        out = np.zeros((h, w), dtype=np.float32)
        for key, tr, tc, wr, wc in self.pieces(r0, c0, h, w):
            d = self.dynamic_tiles.get(key)
            if d is not None:
                out[wr, wc] = d[tr, tc]
        return out

    def bounds(self) -> tuple[int, int, int, int]:
        """``(r0, c0, h, w)``: the smallest tile-aligned box holding every tile; zeros if none."""
        if not self.tiles:
            return (0, 0, 0, 0)
        ts = self.tile_cells
        ti = [k[0] for k in self.tiles]
        tj = [k[1] for k in self.tiles]
        return (
            min(ti) * ts,
            min(tj) * ts,
            (max(ti) - min(ti) + 1) * ts,
            (max(tj) - min(tj) + 1) * ts,
        )

    def covered_bounds(self) -> tuple[int, int, int, int]:
        """``(r0, c0, h, w)`` of the smallest box holding every covered cell; zeros when none is."""
        ts = self.tile_cells
        rows, cols = [], []
        boxes = [(k, _covered_box({"covered": c})) for k, c in self._covered.items()]
        if self.pager is not None:
            for k, box in self.pager.stored.items():
                if box is None:  # a tile of a reopened store: read once
                    box = self.pager.stored[k] = _covered_box(self.pager.peek(k))
                boxes.append((k, box))
        for (ti, tj), box in boxes:
            if box:
                rows += [ti * ts + box[0], ti * ts + box[1]]
                cols += [tj * ts + box[2], tj * ts + box[3]]
        if not rows:
            return (0, 0, 0, 0)
        return (
            int(min(rows)),
            int(min(cols)),
            int(max(rows) - min(rows) + 1),
            int(max(cols) - min(cols) + 1),
        )

    def to_dense(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        """The whole map as dense arrays: masses, coverage, and the map cell ``(r0, c0)`` of element
        [0, 0]."""
        r0, c0, h, w = self.bounds()
        m, cov = self.read(r0, c0, h, w)
        return m, cov, r0, c0


# --- persistence --------------------------------------------------------------------------------

_FORMAT = "evgrid-map"
#: 2: the header holds the map frame (``frame``); version 1 files load with ``frame`` None.
_FORMAT_VERSION = 2
_READS = (1, 2)

#: The frames a map can be built in (:attr:`evgrid.config.MapperConfig.frame`).
MAP_FRAME_KINDS: tuple[str, ...] = ("world", "first_pose")


@dataclass(frozen=True)
class MapFrame:
    """Where a map's cells lie in the recording, kept in its file.

    ``kind``: ``"world"``, the recording's fixed frame ``fixed_frame`` itself (axis-aligned,
    the map origin at its origin), or ``"first_pose"``, the planar frame of the first ego pose
    mapped. ``fixed_frame``: the fixed frame's name (odom, nuScenes ``global``, a rig's
    ``world_frame``; "" when not known). ``first_pose``: the first ego pose mapped, in the fixed
    frame (None when not known); with ``first_pose`` maps it puts the map back into the
    recording. ``stamp_us``: the time of the last update (the maps' stamp, us; None when not
    known).
    """

    kind: str = "world"
    fixed_frame: str = ""
    first_pose: SE3 | None = None
    stamp_us: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in MAP_FRAME_KINDS:
            raise ValueError(f"MapFrame.kind must be one of {MAP_FRAME_KINDS}, got {self.kind!r}")
        if not isinstance(self.fixed_frame, str):
            raise ValueError(f"MapFrame.fixed_frame must be a name, got {self.fixed_frame!r}")
        if self.first_pose is not None and not isinstance(self.first_pose, SE3):
            raise ValueError(
                f"MapFrame.first_pose must be an SE3 or None, got {type(self.first_pose).__name__}"
            )
        if self.stamp_us is not None and (
            isinstance(self.stamp_us, bool) or not isinstance(self.stamp_us, (int, np.integer))
        ):
            raise ValueError(f"MapFrame.stamp_us must be an integer or None, got {self.stamp_us!r}")

    @classmethod
    def of(cls, mapper: Any, fixed_frame: str = "") -> MapFrame:
        """The frame ``mapper`` (an :class:`~evgrid.mapper.OccupancyMapper`) builds its maps in."""
        stamp = getattr(mapper, "last_update_us", None)
        return cls(
            mapper.config.frame,
            fixed_frame,
            mapper.first_pose,
            None if stamp is None else int(stamp),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON values; the pose as its 4x4 matrix, rows (floats round-trip exactly)."""
        pose = None if self.first_pose is None else self.first_pose.matrix().tolist()
        return {
            "kind": self.kind,
            "fixed_frame": self.fixed_frame,
            "first_pose": pose,
            "stamp_us": None if self.stamp_us is None else int(self.stamp_us),
        }

    @classmethod
    def from_dict(cls, d: Any) -> MapFrame:
        """The inverse of :meth:`to_dict` (files without ``stamp_us`` too); ValueError (or
        TypeError) naming what is wrong."""
        if not isinstance(d, dict) or set(d) - {"kind", "fixed_frame", "first_pose", "stamp_us"}:
            raise ValueError(
                f"a map frame is {{kind, fixed_frame, first_pose, stamp_us}}, got {d!r}"
            )
        pose = d.get("first_pose")
        return cls(
            d.get("kind", "world"),
            d.get("fixed_frame", ""),
            None if pose is None else SE3.from_matrix(np.asarray(pose, dtype=np.float64)),
            d.get("stamp_us"),
        )


class MapFileError(ValueError):
    """A file that is not a complete evgrid map (truncated, foreign or of a newer format)."""


#: The largest header the loader reads (bytes): a real header is a few hundred.
_MAX_HEADER_BYTES = 1 << 20
_ARRAYS = ("header", "keys", "tiles", "covered")


def _check_extent(where: str, grid: GridSpec, ts: int, keys, covered_any) -> str | None:
    """Why tile ``keys`` cannot belong to a map of ``grid`` (None if they can).

    Every tile must lie within :data:`evgrid.geometry.MAX_POSE_M` (plus a local grid) of the
    origin, and the tiles holding covered cells must span at least one local grid
    (``n_cells`` a side): each update covers a whole local grid.
    """
    if len(keys) == 0:
        return None
    limit = (MAX_POSE_M + grid.length_m) / grid.resolution / ts + 1
    worst = int(np.abs(keys).max())
    if worst > limit:
        return (
            f"{where} 'keys': tile key {worst} lies beyond {MAX_POSE_M:g} m of the map origin "
            f"(at most {int(limit)} for {ts}-cell tiles of {grid.resolution:g} m)"
        )
    used = keys[np.asarray(covered_any, bool)]
    if len(used):
        h = (int(used[:, 0].max()) - int(used[:, 0].min()) + 1) * ts
        w = (int(used[:, 1].max()) - int(used[:, 1].min()) + 1) * ts
        if min(h, w) < grid.n_cells:
            return (
                f"{where} 'spec': n_cells {grid.n_cells} contradicts the tiles: their covered "
                f"cells span {h} x {w} cells, less than one local grid"
            )
    return None


def _header(m: EvidentialMap, frame: MapFrame | None) -> dict[str, Any]:
    """The header of a map file (and of a store's ``map.json``)."""
    return {
        "format": _FORMAT,
        "version": _FORMAT_VERSION,
        "spec": m.grid.to_dict(),
        "tile_cells": m.tile_cells,
        "metadata": m.metadata,
        "frame": None if frame is None else frame.to_dict(),
        "dynamic": m.dynamic,
    }


def _covered_any(m: EvidentialMap, key: tuple[int, int]) -> bool:
    """Whether tile ``key`` holds a covered cell (a stored tile from its summary)."""
    c = m._covered.get(key)
    if c is not None:
        return bool(c.any())
    box = m.pager.stored[key]
    if box is None:
        box = m.pager.stored[key] = _covered_box(m.pager.peek(key))
    return bool(box)


def _write_member(zf: zipfile.ZipFile, name: str, shape: tuple, dtype, blocks) -> None:
    """Member ``name.npy`` of an .npz, written block by block (the array is never whole in
    memory); readers see the .npy that ``np.savez_compressed`` writes."""
    f = zf.open(name + ".npy", "w", force_zip64=True)
    try:
        header = {
            "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
            "fortran_order": False,
            "shape": shape,
        }
        np.lib.format.write_array_header_1_0(f, header)
        for b in blocks:
            f.write(np.ascontiguousarray(b, dtype=dtype).tobytes())
        f.close()
    except BaseException:
        _quietly(f.close)  # into the file about to be removed; the error is the caller's
        raise


def _quietly(close: Callable[[], None]) -> None:
    """Close what a failed (or interrupted) save leaves open, ignoring its errors: the file is
    removed anyway, and the first error is the one to report."""
    try:
        close()
    except BaseException:
        pass


def _abandon_zip(zf: zipfile.ZipFile) -> None:
    """Close a zip that a failed save throws away, before its file is closed and removed.

    Left to ``ZipFile.__del__``, its close would run after the file is gone and Python would
    print ``Exception ignored in: ZipFile.__del__ ... seek of closed file`` after the clean
    Ctrl-C message. A Ctrl-C that lands inside ``zf.open`` leaves it marked as writing a member
    with no handle to close, so that mark is cleared first."""
    zf._writing = False  # no member is written any more
    _quietly(zf.close)
    zf.fp = None  # even when close failed: nothing writes to the file again


def save_map(m: EvidentialMap, path: str | os.PathLike, frame: MapFrame | None = None) -> Path:
    """Save a map losslessly (compressed ``.npz`` with its grid, metadata, map frame:
    ``frame``, else ``m.frame``, and its dynamic score where it keeps one), atomically.

    The tiles are written one at a time (those paged out to a store read from it): saving
    never holds the whole map in memory."""
    if not isinstance(m, EvidentialMap):
        raise TypeError(f"save_map needs an EvidentialMap, got {type(m).__name__}")
    if not isinstance(path, (str, os.PathLike)) or not str(path) or Path(path).name in ("", "."):
        raise ValueError(f"save_map: {path!r} names no file; give one such as 'fused.npz'")
    if Path(path).is_dir():
        raise IsADirectoryError(f"save_map: {path} is a folder; give a file name inside it")
    frame = getattr(m, "frame", None) if frame is None else frame
    if frame is not None and not isinstance(frame, MapFrame):
        raise TypeError(f"save_map: frame must be a MapFrame or None, got {type(frame).__name__}")
    keys = sorted(m.tiles)
    header = _header(m, frame)
    del header["dynamic"]  # the file says it by its 'dynamic' array
    ts = m.tile_cells
    karr = np.array(keys, dtype=np.int64).reshape(-1, 2)
    why = _check_extent("save_map: field", m.grid, ts, karr, [_covered_any(m, k) for k in keys])
    if why:
        raise ValueError(f"{why}; the map could not be loaded back")
    n = len(keys)

    def write(f) -> None:
        zf = zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED)
        try:
            hb = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
            _write_member(zf, "header", hb.shape, np.uint8, [hb])
            _write_member(zf, "keys", karr.shape, np.int64, [karr])
            _write_member(zf, "tiles", (n, ts, ts, 3), np.float32, (m.tiles[k] for k in keys))
            _write_member(zf, "covered", (n, ts, ts), np.bool_, (m.covered_tiles[k] for k in keys))
            if m.dynamic:  # an optional array: readers that do not know it load the masses alone
                _write_member(
                    zf, "dynamic", (n, ts, ts), np.float32, (m.dynamic_tiles[k] for k in keys)
                )
        except BaseException:  # Ctrl-C included: the temporary file goes, quietly
            _abandon_zip(zf)
            raise
        zf.close()

    return atomic_write(path, write)


def _declared(path: Path, zf: zipfile.ZipFile, name: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype that member ``name.npy`` declares, read from its header only."""
    info = zf.getinfo(name + ".npy")
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        shape, fortran, dtype = (
            np.lib.format.read_array_header_1_0(f)
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0(f)
        )
    nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    if fortran or dtype.hasobject or nbytes > info.file_size:
        raise MapFileError(
            f"{path}: array '{name}' declares {shape} {dtype} ({nbytes} bytes), more than the "
            f"{info.file_size} bytes stored, or an order evgrid does not write; the file is corrupt"
        )
    return tuple(shape), dtype


def open_store_map(folder: str | os.PathLike) -> EvidentialMap:
    """The map a tile store's group holds (``STORE/NAME``, :mod:`evgrid.store`), every tile left
    on disk and read when asked for: also the store of a run that was killed (its tiles as
    last paged out or checkpointed). StoreError naming the file when the store is of another
    version or damaged."""
    from evgrid.store import StoreError, TileStore, read_group_meta

    folder = Path(folder)
    doc = read_group_meta(folder)
    if not (folder.parent / "store.json").is_file():
        raise StoreError(
            f"{folder.parent / 'store.json'} is missing: {folder.parent} is not an evgrid "
            "tile store"
        )
    head = folder / "map.json"
    try:
        ts, spec, metadata, frame = _header_fields(head, doc.get("map"))
    except MapFileError as e:
        raise StoreError(str(e)) from e
    store = TileStore(folder.parent)
    m = EvidentialMap(spec, ts, metadata, dynamic=bool(doc["map"].get("dynamic")), frame=frame)
    m.attach_store(store.group(folder.name), write_meta=False)
    m._store = store  # kept alive with the map
    return m


def load_map(path: str | os.PathLike, lazy: bool = False) -> EvidentialMap:
    """Load a map written by :func:`save_map`, or open one in a tile store (a folder
    ``STORE/NAME``: :func:`open_store_map`).

    With ``lazy``, the file's tiles are checked and moved one at a time into a temporary tile
    store, and the map reads them from there when asked: the whole map is never in memory.

    Anything else raises :class:`MapFileError`, one line naming the file (and the field where
    one is at fault). Each array's declared shape is checked against the header before its
    data is read, and the tiles must hold valid masses: a corrupt file never yields a map with
    NaN or negative cells, and never makes the loader allocate what the file does not hold.
    """
    path = Path(path)
    if path.is_dir() and (path / "map.json").exists():
        return open_store_map(path)
    if not path.is_file():
        raise FileNotFoundError(f"no map file at {path}")
    if lazy:
        return _load_lazy(path)
    ts, spec, metadata, frame, shapes, keys = _checked_head(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            tiles, covered = z["tiles"], z["covered"]
            scores = z["dynamic"] if "dynamic" in shapes else None
    except Exception as e:  # noqa: BLE001 - whatever a corrupt file makes zipfile or numpy raise
        raise _corrupt(path, e) from e
    tiles = np.ascontiguousarray(tiles)
    _check_tile_values(path, tiles, scores)
    m = EvidentialMap(spec, ts, metadata, frame=frame, dynamic=scores is not None)
    for i, (k, t, c) in enumerate(zip(keys, tiles, covered)):
        key = (int(k[0]), int(k[1]))
        m.tiles[key] = np.ascontiguousarray(t)
        m.covered_tiles[key] = np.ascontiguousarray(c)
        if scores is not None:
            m.dynamic_tiles[key] = np.ascontiguousarray(scores[i])
    return m


def _corrupt(path: Path, e: BaseException) -> MapFileError:
    # zlib.error, BadZipFile, EOFError, tokenize.TokenError or SyntaxError from a garbled array
    # header, UnicodeDecodeError, JSONDecodeError, MemoryError ...
    why = " ".join(str(e).split())[:200]  # one line, whatever the library wrote
    return MapFileError(f"{path} is truncated or not an evgrid map: {type(e).__name__}: {why}")


def _check_tile_values(path: Path, tiles: np.ndarray, scores: np.ndarray | None) -> None:
    n_bad = int(count_invalid(tiles.reshape(-1), 0, 1, tiles.size // 3)) if tiles.size else 0
    if n_bad:
        raise MapFileError(
            f"{path}: {n_bad} cell(s) hold no valid mass (NaN, inf, negative, or not summing "
            "to 1); the file is corrupt"
        )
    if scores is not None and not (np.isfinite(scores) & (scores >= 0)).all():
        raise MapFileError(
            f"{path}: field 'dynamic': a dynamic score is negative, NaN or inf; the file is corrupt"
        )


def _check_array_shapes(path: Path, shapes: dict, ts: int, n_keys: int) -> None:
    """MapFileError unless every array's declared shape and dtype agree with the header's
    tile_cells ``ts`` and the ``n_keys`` keys."""
    want = {  # shape, dtype test, what it is
        "keys": ((n_keys, 2), lambda d: d.kind == "i", "integer tile keys"),
        "tiles": ((n_keys, ts, ts, 3), lambda d: d == np.float32, "float32 masses"),
        "covered": ((n_keys, ts, ts), lambda d: d == np.bool_, "bool coverage"),
        "dynamic": ((n_keys, ts, ts), lambda d: d == np.float32, "float32 scores"),
    }
    for name, (shape, ok, what) in want.items():
        if name not in shapes:
            continue
        got_shape, got_dtype = shapes[name]
        if got_shape != shape or not ok(got_dtype):
            raise MapFileError(
                f"{path} is inconsistent: array '{name}' is {got_shape} {got_dtype}; "
                f"the header's tile_cells {ts} and {n_keys} keys make it {shape} {what}"
            )


def _checked_head(path: Path):
    """``(tile_cells, grid, metadata, frame, declared shapes, keys)`` of a map file, every
    array's declared shape checked against the header and the keys checked; MapFileError if
    anything is wrong. Reads the header and the keys only."""
    with open(path, "rb") as f:
        if f.read(6) == b"\x93NUMPY":
            raise MapFileError(
                f"{path} is a single numpy array (.npy), not an evgrid map (an .npz of save_map)"
            )
    try:
        with zipfile.ZipFile(path) as zf:
            names = {n.removesuffix(".npy") for n in zf.namelist()}
            if not set(_ARRAYS) <= names:
                raise MapFileError(f"{path} is not an evgrid map (arrays {sorted(names)})")
            shapes = {n: _declared(path, zf, n) for n in (*_ARRAYS, "dynamic") if n in names}
            hshape, hdtype = shapes["header"]
            if len(hshape) != 1 or hdtype != np.uint8 or hshape[0] > _MAX_HEADER_BYTES:
                raise MapFileError(f"{path}: array 'header' is {hshape} {hdtype}, not JSON bytes")
            with zf.open("header.npy") as f:
                header = json.loads(np.lib.format.read_array(f, allow_pickle=False).tobytes())
            ts, spec, metadata, frame = _header_fields(path, header)
            n_keys = shapes["keys"][0][0] if len(shapes["keys"][0]) == 2 else -1
            _check_array_shapes(path, shapes, ts, n_keys)
            with zf.open("keys.npy") as f:
                keys = np.lib.format.read_array(f, allow_pickle=False)
            # each tile's covered cells, read tile by tile (for the extent check)
            used = np.zeros(n_keys, bool)
            with zf.open("covered.npy") as f:
                _skip_npy_header(f)
                for i in range(n_keys):
                    used[i] = _read_exact(f, ts * ts).any()
    except (MapFileError, FileNotFoundError):
        raise
    except Exception as e:  # noqa: BLE001 - whatever a corrupt file makes zipfile or numpy raise
        raise _corrupt(path, e) from e
    keys = np.asarray(keys, dtype=np.int64)
    dup = _first_duplicate(keys)
    if dup is not None:
        raise MapFileError(
            f"{path}: field 'keys': tile key {dup} appears more than once; the file is corrupt"
        )
    why = _check_extent(f"{path}: field", spec, ts, keys, used)
    if why:
        raise MapFileError(why)
    return ts, spec, metadata, frame, shapes, keys


def _skip_npy_header(f) -> None:
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        np.lib.format.read_array_header_1_0(f)
    else:
        np.lib.format.read_array_header_2_0(f)


def _read_exact(f, n: int) -> np.ndarray:
    b = f.read(n)
    if len(b) != n:
        raise EOFError(f"the array ends after {len(b)} of {n} bytes")
    return np.frombuffer(b, np.uint8)


def _load_lazy(path: Path) -> EvidentialMap:
    """:func:`load_map` with ``lazy``: the tiles checked and moved one at a time into a temporary
    tile store that the map reads from (kept while the map lives)."""
    from evgrid.store import TileStore

    ts, spec, metadata, frame, shapes, keys = _checked_head(path)
    dynamic = "dynamic" in shapes
    m = EvidentialMap(spec, ts, metadata, frame=frame, dynamic=dynamic)
    store = TileStore()
    m._store = store  # the temporary folder goes with the map
    m.attach_store(store.group("map"))
    layers = [("tiles", np.float32, (ts, ts, 3)), ("covered", np.bool_, (ts, ts))]
    if dynamic:
        layers.append(("dynamic", np.float32, (ts, ts)))
    try:
        with zipfile.ZipFile(path) as zf:
            files = [zf.open(n + ".npy") for n, _, _ in layers]
            try:
                for f in files:
                    _skip_npy_header(f)
                for k in keys:
                    got = []
                    for f, (_, dtype, shape) in zip(files, layers):
                        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
                        got.append(_read_exact(f, n).view(dtype).reshape(shape).copy())
                    _check_tile_values(path, got[0], got[2] if dynamic else None)
                    key = (int(k[0]), int(k[1]))
                    m._tiles[key], m._covered[key] = got[0], got[1]
                    if dynamic:
                        m._dynamic[key] = got[2]
                    m.pager.page_out([key])
            finally:
                for f in files:
                    f.close()
    except MapFileError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a corrupt file makes zipfile or numpy raise
        raise _corrupt(path, e) from e
    return m


def _header_fields(
    path: Path, header: Any
) -> tuple[int, GridSpec, dict[str, Any], MapFrame | None]:
    """``tile_cells``, the grid, the metadata and the map frame (None in version 1 files) of a
    map file's header; MapFileError if bad."""
    if not isinstance(header, dict) or header.get("format") != _FORMAT:
        fmt = header.get("format") if isinstance(header, dict) else None
        raise MapFileError(f"{path} is not an evgrid map (format {fmt!r})")
    version = header.get("version")
    if isinstance(version, bool) or version not in _READS:
        raise MapFileError(
            f"{path} has map format version {version!r}; "
            f"this evgrid reads {', '.join(map(str, _READS))}"
        )
    ts = header.get("tile_cells")
    if isinstance(ts, bool) or not isinstance(ts, int) or not 8 <= ts <= 4096:
        raise MapFileError(
            f"{path}: header field 'tile_cells' must be an integer in [8, 4096], got {ts!r}"
        )
    try:
        spec = GridSpec.from_dict(header["spec"])
        metadata = dict(header.get("metadata", {}))
    except (KeyError, TypeError, ValueError) as e:
        raise MapFileError(f"{path}: header field 'spec' or 'metadata' is invalid ({e})") from e
    frame = None
    if version >= 2 and header.get("frame") is not None:
        try:
            frame = MapFrame.from_dict(header["frame"])
        except (TypeError, ValueError) as e:
            why = " ".join(str(e).split())[:200]
            raise MapFileError(f"{path}: header field 'frame' is invalid ({why})") from e
    return ts, spec, metadata, frame


def _first_duplicate(keys: np.ndarray) -> tuple[int, int] | None:
    if len(keys) < 2:
        return None
    u, counts = np.unique(keys, axis=0, return_counts=True)
    return (int(u[counts > 1][0, 0]), int(u[counts > 1][0, 1])) if (counts > 1).any() else None
