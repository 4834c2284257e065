"""Observers of the mapper: the true occupancy, IoU over time, and the GIF.

Each takes :class:`~evgrid.mapper.MapUpdate` objects and touches only the tiles an update
changed (or a window of fixed size around the vehicle), so its cost per frame does not grow
with how long the vehicle has driven.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from evgrid.classes import FREE, OCCUPIED
from evgrid.evaluate import (
    classify,
    detection_scores,
    dynamic_confusion,
    iou_from_confusion,
    tile_confusions_vs_map,
    tile_confusions_vs_truth,
    tile_keys,
)
from evgrid.geometry import GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper, tile_pieces
from evgrid.mapper import MapUpdate
from evgrid.store import Pager, TileLayer, TileStore, tile_distance_m

__all__ = [
    "TruthTracker",
    "TileScores",
    "SceneScores",
    "GifRecorder",
    "MoverTrail",
    "truth_masks",
]

_TRUTH_MASSES = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 1, 0]], dtype=np.float32
)  # free, static, dynamic


def _replace_where_informed(cell: np.ndarray, m: np.ndarray) -> None:
    """Truth map update: the latest observed truth wins where it says anything."""
    np.copyto(cell, m, where=(m[..., 2] < 1.0)[..., None])


def _window_box(w: MapWindow, margin: int = 0) -> tuple[int, int, int, int]:
    h, wd = w.shape
    return w.r0 - margin, w.c0 - margin, h + 2 * margin, wd + 2 * margin


class TruthTracker:
    """The true occupancy (simulator only) accumulated in the map frame, as a mass map.

    ``changed`` collects the tiles a truth update touched (with a one-cell margin: a cell's
    observability depends on its neighbours) until a consumer takes them.
    """

    def __init__(self, grid: GridSpec, tile_cells: int = 256):
        self.map = EvidentialMap(grid, tile_cells, {"rule": "truth"})
        self._warper: Warper | None = None  # made at the first frame with true occupancy
        self.changed: set[tuple[int, int]] = set()

    def on_update(self, update: MapUpdate) -> None:
        occ = update.frame.occupancy
        if occ is None:
            return
        if self._warper is None:
            self._warper = Warper(self.map.grid)
        window = self._warper.warp(_TRUTH_MASSES[np.clip(occ, 0, 2)], update.pose)
        self.map.apply(window, _replace_where_informed)
        self.changed |= tile_keys(self.map, *_window_box(window, 1))

    def page_out(self, store: TileStore, x: float, y: float, radius_m: float) -> int:
        """The truth map's tiles beyond ``radius_m`` of map point ``(x, y)`` to ``store``."""
        if self.map.pager is None:
            self.map.attach_store(store.group("truth"))
        return self.map.page_out(x, y, radius_m)


class TileScores:
    """Confusion counts of several maps, kept per tile and summed; only changed tiles are
    recounted."""

    def __init__(self, names: tuple[str, ...], count_tile: Callable[[tuple[int, int]], np.ndarray]):
        self.names = names
        self._count = count_tile
        self._per_tile: dict[tuple[int, int], np.ndarray] = {}
        self.total = np.zeros((len(names), 3, 3), dtype=np.int64)
        self.dirty: set[tuple[int, int]] = set()

    def refresh(self) -> None:
        """Recount the dirty tiles."""
        for key in self.dirty:
            new = self._count(key)
            old = self._per_tile.get(key)
            if old is not None:
                self.total -= old
            self.total += new
            self._per_tile[key] = new
        self.dirty.clear()

    def iou(self, skip: tuple[str, ...] = ()) -> dict[str, dict[str, float]]:
        """Per-map, per-class IoU of the current counts (after :meth:`refresh`)."""
        return {
            n: iou_from_confusion(self.total[i]) for i, n in enumerate(self.names) if n not in skip
        }


def truth_masks(
    update: MapUpdate, warper: Warper
) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray] | None:
    """The truth of the dynamic score at this update, in its map window: ``(r0, c0, moving,
    observed, free)``, boolean ``(h, w)`` arrays whose [0, 0] is map cell (r0, c0). ``moving``:
    the cells the simulator's truth raster marks as moving objects (value 2) now; ``free``:
    those it marks free (0); ``observed``: the cells the current ray ILM or ray IRM says
    anything about (non-vacuous). None without a truth raster or without either ISM. ``warper``
    (any, reused) warps the truth."""
    occ = update.frame.occupancy
    windows = update.windows if occ is not None else {}
    isms = [windows[i] for i in ("ray_ilm", "ray_irm") if i in windows]
    if not isms:
        return None
    local = np.zeros((*occ.shape, 3), np.float32)
    local[..., 2] = 1.0
    local[occ == 2] = (0.0, 1.0, 0.0)
    local[occ == 0] = (1.0, 0.0, 0.0)
    truth = warper.warp(local, update.pose)
    # a map cell is moving (free) where most of its bilinear sample comes from moving (free)
    # cells
    moving = truth.covered & (truth.masses[..., 1] >= 0.5)
    free = truth.covered & (truth.masses[..., 0] >= 0.5)
    observed = np.zeros_like(moving)
    for w in isms:
        observed |= w.covered & (w.masses[..., 2] < 1.0)
    return truth.r0, truth.c0, moving, observed, free


class MoverTrail:
    """The map cells a moving object covered at some keyframe so far (the simulator's truth),
    and the area movers leave behind: cells truly free now, covered by a moving object earlier
    in the scene, that a map calls occupied (docs/equations.md#the-area-movers-leave-behind)."""

    def __init__(self, grid: GridSpec, tile_cells: int = 256):
        self.grid = grid
        self.tile_cells = tile_cells
        self._tiles: dict[tuple[int, int], np.ndarray] = {}
        self.pager: Pager | None = None  # with a tile store (page_out)
        self.tiles = TileLayer(self._tiles, "trail", self)

    def _layer_has(self, name: str) -> bool:
        return True

    def add(self, r0: int, c0: int, moving: np.ndarray) -> None:
        """Mark the ``moving`` cells (boolean ``(h, w)``, [0, 0] at map cell (r0, c0))."""
        ts = self.tile_cells
        for key, tr, tc, wr, wc in tile_pieces(ts, r0, c0, *moving.shape):
            part = moving[wr, wc]
            if part.any():
                t = self._tiles.get(key)
                if t is None:
                    if self.pager is not None and key in self.pager.stored:
                        self.pager.page_in(key)
                    else:
                        self._tiles[key] = np.zeros((ts, ts), np.bool_)
                    t = self._tiles[key]
                t[tr, tc] |= part

    def page_out(self, store: TileStore, x: float, y: float, radius_m: float) -> int:
        """The trail's tiles beyond ``radius_m`` of map point ``(x, y)`` to ``store``."""
        if self.pager is None:
            ts = self.tile_cells
            expect = {"trail": ((ts, ts), np.dtype(np.bool_))}
            self.pager = Pager(store.group("trail"), {"trail": self._tiles}, expect=expect)
        ts, res = self.tile_cells, self.grid.resolution
        far = [k for k in self._tiles if tile_distance_m(k, ts, res, x, y) > radius_m]
        if far:
            self.pager.page_out(far)
        return len(far)

    def read(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        """Dense ``(h, w)`` boolean copy of cells ``[r0:r0+h, c0:c0+w]``."""
        out = np.zeros((h, w), np.bool_)
        for key, tr, tc, wr, wc in tile_pieces(self.tile_cells, r0, c0, h, w):
            t = self.tiles.get(key)
            if t is not None:
                out[wr, wc] = t[tr, tc]
        return out

    def left_behind(
        self, m: EvidentialMap, r0: int, c0: int, free: np.ndarray
    ) -> tuple[int, float]:
        """``(cells, m^2)`` of map ``m`` left behind: ``free`` now (boolean ``(h, w)``, [0, 0] at
        map cell (r0, c0)), covered by a mover before, and classified occupied."""
        h, w = free.shape
        trail = self.read(r0, c0, h, w) & free
        if not trail.any():
            return 0, 0.0
        masses, _ = m.read(r0, c0, h, w)
        n = int(np.count_nonzero(trail & (classify(masses) == OCCUPIED)))
        return n, n * self.grid.resolution**2


class SceneScores:
    """IoU of every map against ``ray_ilm`` and, where the simulator gives it, the truth; at every
    keyframe if asked.

    Scores are kept per tile: an update dirties the tiles its windows touched, and a keyframe
    recounts only those, so tracking convergence costs the same in the first and the tenth minute.
    """

    def __init__(
        self,
        maps: dict[str, EvidentialMap],
        truth: TruthTracker | None,
        track: bool = True,
        reference: str = "ray_ilm",
    ):
        self.maps = maps
        self.truth = truth
        self.track = track
        self.reference = reference if reference in maps else None
        names = self.names = tuple(maps)
        truth_ref = self.reference or names[0]
        self.vs_ref = (
            TileScores(names, partial(tile_confusions_vs_map, maps, self.reference))
            if self.reference
            else None
        )
        self.vs_truth = (
            TileScores(names, partial(tile_confusions_vs_truth, maps, truth.map, truth_ref))
            if truth is not None
            else None
        )
        # the same against every true cell, not only those the lidar covered: the perception field
        self.field = (
            TileScores(names, partial(tile_confusions_vs_truth, maps, truth.map, None))
            if truth is not None
            else None
        )
        res = next(iter(maps.values())).grid.resolution
        self._cell_m2 = res * res
        self.keyframes: list[dict[str, Any]] = []
        # the dynamic score against the moving objects, summed over keyframes: (tp, fp, fn)
        self._dynamic = {n: np.zeros(3, np.int64) for n in names if maps[n].dynamic}
        self._moving_warper: Warper | None = None
        # the area movers leave behind, per map: m^2 at each keyframe with a truth raster
        self._trail: MoverTrail | None = None
        self._left_behind: dict[str, list[float]] = {n: [] for n in names}

    def page_out(self, store: TileStore, x: float, y: float, radius_m: float) -> int:
        """The mover trail's tiles beyond ``radius_m`` of map point ``(x, y)`` to ``store``."""
        return 0 if self._trail is None else self._trail.page_out(store, x, y, radius_m)

    def on_update(self, update: MapUpdate) -> None:
        keys = tile_keys(next(iter(self.maps.values())), *update.box)
        if self.vs_ref is not None:
            self.vs_ref.dirty |= keys
        if self.vs_truth is not None:
            self.vs_truth.dirty |= keys | self.truth.changed
            self.field.dirty |= keys | self.truth.changed
            self.truth.changed = set()
        if not update.frame.is_keyframe:
            return
        rec: dict[str, Any] = {"index": update.frame.index, "timestamp": update.frame.timestamp}
        if update.frame.occupancy is not None:
            rec.update(self._score_dynamic(update))
        if self.track:
            if self.vs_ref is not None:
                self.vs_ref.refresh()
                rec["iou"] = self.vs_ref.iou(skip=(self.reference,))
            if self.vs_truth is not None and self.truth.map.tiles:
                self.vs_truth.refresh()
                rec["iou_truth"] = {
                    n: {c: v for c, v in d.items() if c != "unknown"}
                    for n, d in self.vs_truth.iou().items()
                }
                self.field.refresh()
                rec["field"] = self.perception_field()
        self.keyframes.append(rec)

    def _score_dynamic(self, update: MapUpdate) -> dict[str, Any]:
        """At this keyframe: ``dynamic``, per dynamic map, precision, recall and IoU of the cells
        called dynamic against the cells of moving objects (truth value 2) that the current ray
        ILM or ray IRM observed (non-vacuous), counts also summed for :meth:`final`; and
        ``left_behind_m2``, per map, the area movers left behind (:class:`MoverTrail`)."""
        grid = next(iter(self.maps.values())).grid
        if self._moving_warper is None:
            self._moving_warper = Warper(grid, "moving objects")
            self._trail = MoverTrail(grid, next(iter(self.maps.values())).tile_cells)
        found = truth_masks(update, self._moving_warper)
        if found is None:
            return {}
        r0, c0, moving, observed, free = found
        h, w_ = moving.shape
        threshold = update.maps.dynamic.threshold
        out: dict[str, Any] = {}
        for name, total in self._dynamic.items():
            score = self.maps[name].read_dynamic(r0, c0, h, w_)
            counts = dynamic_confusion(score, threshold, moving, observed)
            total += counts
            out.setdefault("dynamic", {})[name] = detection_scores(*counts)
        self._trail.add(r0, c0, moving)
        left = {n: self._trail.left_behind(m, r0, c0, free)[1] for n, m in self.maps.items()}
        for n, v in left.items():
            self._left_behind[n].append(v)
        out["left_behind_m2"] = left
        return out

    def perception_field(self) -> dict[str, dict[str, float]]:
        """Per map, against every true cell seen so far: free and occupied IoU, and the area (m^2)
        classified correctly as free or occupied (the paper claims the deep prior enlarges this
        perception field)."""
        out = {}
        for i, (n, d) in enumerate(self.field.iou().items()):
            c = self.field.total[i]
            out[n] = {
                "free": d["free"],
                "occupied": d["occupied"],
                "area_m2": float(c[FREE, FREE] + c[OCCUPIED, OCCUPIED]) * self._cell_m2,
            }
        return out

    def final(self) -> dict[str, Any]:
        """Per-class IoU at the end of the scene: ``vs_ray_ilm`` and, with truth, ``vs_truth``; and
        ``confusion_vs_ray_ilm``, per map the cell counts [reference class][map's class] (free,
        occupied, unknown), which say where a map loses IoU."""
        out: dict[str, Any] = {}
        if self.vs_ref is not None:
            self.vs_ref.refresh()
            out["vs_ray_ilm"] = self.vs_ref.iou(skip=(self.reference,))
            out["confusion_vs_ray_ilm"] = {
                n: self.vs_ref.total[i].tolist()
                for i, n in enumerate(self.names)
                if n != self.reference
            }
        if self.vs_truth is not None and self.truth.map.tiles:
            self.vs_truth.dirty |= self.truth.changed
            self.truth.changed = set()
            self.vs_truth.refresh()
            out["vs_truth"] = {
                n: {c: v for c, v in d.items() if c != "unknown"}
                for n, d in self.vs_truth.iou().items()
            }
        if any(self._left_behind.values()):
            # the mean over keyframes of the area movers left behind that each map calls occupied
            out["left_behind_m2"] = {
                n: float(np.mean(v)) for n, v in self._left_behind.items() if v
            }
        if any(t.any() for t in self._dynamic.values()):
            # the cells of every keyframe pooled: precision, recall, IoU and the counts
            out["dynamic"] = {
                n: {**detection_scores(*map(int, t)), **dict(zip(("tp", "fp", "fn"), map(int, t)))}
                for n, t in self._dynamic.items()
            }
        return out


class GifRecorder:
    """A GIF that follows the vehicle: every map in a fixed window around it, at each kept keyframe.

    Each frame reads ``window_m`` metres around the ego pose at one cell in ``step`` (a fixed
    cost); at most ``max_frames`` are kept, halving the rate (every 2nd, 4th, ... keyframe)
    whenever that many are held, so memory stays bounded on any drive.
    """

    def __init__(
        self,
        grid: GridSpec,
        window_m: float = 80.0,
        step: int = 8,
        max_frames: int = 240,
        cols: int = 3,
    ):
        self.grid = grid
        self.step = step
        self.cells = int(round(window_m / grid.resolution))
        self.max_frames = max_frames
        self.cols = cols
        self.frames: list[np.ndarray] = []
        self._stride = 1
        self._n_keyframes = 0
        self._t0_us: int | None = None

    def on_update(self, update: MapUpdate) -> None:
        if not update.frame.is_keyframe:
            return
        k = self._n_keyframes
        self._n_keyframes += 1
        if k % self._stride:
            return
        from evgrid.render import DYNAMIC_COLOUR, dynamic_label, label_panels, map_picture

        rc, cc = self.grid.map_xy_to_cell(update.pose.x, update.pose.y)
        r0, c0 = int(rc) - self.cells // 2, int(cc) - self.cells // 2
        # the cells called dynamic, on the maps that keep a score
        threshold = update.maps.dynamic.threshold if update.maps.dynamic_maps else None
        n = self.cells
        pics = [
            map_picture(m, r0, c0, n, n, self.step, threshold) for m in update.maps.maps.values()
        ]
        legend = [(dynamic_label(threshold), DYNAMIC_COLOUR)] if threshold is not None else []
        if self._t0_us is None:
            self._t0_us = update.frame.timestamp
        t_s = (update.frame.timestamp - self._t0_us) * 1e-6
        caption = f"t = {t_s:.1f} s   {self.cells * self.grid.resolution:g} m around the vehicle"
        self.frames.append(label_panels(pics, list(update.maps.maps), caption, self.cols, legend))
        if len(self.frames) >= self.max_frames:
            self.frames = self.frames[::2]
            self._stride *= 2
