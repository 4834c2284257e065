"""What the deep IRM's prior may not say (docs/equations.md#the-deep-irms-guards).

Ev-Net learns the shape of the streets it was trained on, and paints it where the radar saw
nothing: facades beside any road, obstacles on the road the vehicle has just driven. Two rules
move such occupied mass before the deep masses enter the deep maps (the other masses untouched,
so the masses stay a valid BBA):

* **radar support**: occupied mass is kept only within ``support_m`` of a radar detection of
  the deep IRM's input sweeps (an obstacle the prior calls must have been seen by a radar);
  elsewhere it goes to unknown (``m_u += m_o``, ``m_o = 0``);
* **the vehicle's path**: occupied mass within ``path_m`` of the vehicle's trail (the path
  since it came into the local grid, kept as cells of ``trail_step_m``) goes to free
  (``m_f += m_o``): the vehicle drove there. Not to unknown: a vacuous update changes none of
  the deep maps. The prior also paints the road ahead before the vehicle reaches it, which
  ``deep_replace`` (the more certain mass wins) and ``deep_disc`` (Yager's rule keeps what it
  has) would never take back, so the mapper clears the stretch driven at each update in the
  deep maps too (``driven_cells``, ``OccupancyMapper.clear_driven``).

Both are off with ``None``, which keeps the paper's deep IRM and the maps bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from evgrid.data.frame import RadarSweep
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.validation import check_number

__all__ = [
    "PriorGuardParams",
    "Trail",
    "keep_supported",
    "clear_path",
    "driven_cells",
    "detections_xy",
]

#: The cells of the radar-support mask are this many local cells a side (coarser than the grid:
#: the support radius is metres, a detection's position is uncertain by decimetres).
_SUPPORT_POOL = 4


@dataclass(frozen=True)
class PriorGuardParams:
    """The deep IRM's guards (docs/equations.md#the-deep-irms-guards); None turns one off."""

    #: occupied mass of the deep IRM kept only within this many metres of a radar detection of
    #: its input sweeps (none: kept everywhere, as in the paper); the default, below one
    #: support cell, keeps it only in the support cells the detections fall in
    #: (docs/decisions.md#radar-support-radius)
    support_m: float | None = 0.25
    #: occupied mass of the deep IRM within this many metres of the vehicle's trail goes to
    #: free (none: kept, as in the paper); 1 m: half the car's width and a margin
    path_m: float | None = 1.0
    #: the side of the trail's cells (metres): a point of the path lies within
    #: ``Trail.margin_m`` (0.24 m at 0.25) of a cell kept; at least 5 cm (the trail's memory
    #: grows as its inverse square), at most 2 m (the margin is added to ``path_m``)
    trail_step_m: float = 0.25

    def __post_init__(self) -> None:
        for name in ("support_m", "path_m"):
            if getattr(self, name) is not None:
                check_number(self, name, min=0.0, min_open=True)
        check_number(self, "trail_step_m", min=0.05, max=2.0)

    @property
    def off(self) -> bool:
        """Neither rule applies: the deep masses pass unchanged."""
        return self.support_m is None and self.path_m is None


def _move_occupied(masses: np.ndarray, where: np.ndarray, to: int) -> np.ndarray:
    """``masses`` with the occupied mass of the cells ``where`` moved to channel ``to`` (0
    free, 2 unknown), a copy."""
    out = masses.copy()
    occ = out[..., 1]
    out[..., to][where] += occ[where]
    occ[where] = 0.0
    return out


def _disc(radius_cells: float) -> tuple[np.ndarray, np.ndarray]:
    r = int(math.ceil(radius_cells))
    du, dv = np.mgrid[-r : r + 1, -r : r + 1]
    keep = du * du + dv * dv <= radius_cells * radius_cells
    return du[keep], dv[keep]


@lru_cache(maxsize=8)
def _disc_rows(radius_cells: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The disc of :func:`_disc` as one span of columns a row: offsets ``du``, ``lo``, ``hi``."""
    du, dv = _disc(radius_cells)
    rows = np.unique(du)
    return (
        rows,
        np.array([dv[du == r].min() for r in rows]),
        np.array([dv[du == r].max() for r in rows]),
    )


def _stamp(n: int, rows: np.ndarray, cols: np.ndarray, radius_cells: float) -> np.ndarray:
    """A boolean ``(n, n)`` mask of the cells within ``radius_cells`` of any of the cells given."""
    mask = np.zeros((n, n), bool)
    if len(rows) == 0:
        return mask
    # each disc as a span a row: +1 where a span starts, -1 past its end, summed along the row
    # over the bounding box (a trail of a hundred 1 m discs is 90,000 cells, 3,000 spans)
    du, lo, hi = _disc_rows(float(radius_cells))
    r = (rows[:, None] + du[None, :]).ravel()
    c0 = np.clip((cols[:, None] + lo[None, :]).ravel(), 0, n)
    c1 = np.clip((cols[:, None] + hi[None, :] + 1).ravel(), 0, n)
    ok = (r >= 0) & (r < n) & (c0 < c1)
    r, c0, c1 = r[ok], c0[ok], c1[ok]
    if len(r) == 0:
        return mask
    r_lo, c_lo = int(r.min()), int(c0.min())
    h, w = int(r.max()) - r_lo + 1, int(c1.max()) - c_lo + 1
    base = (r - r_lo) * w - c_lo
    edge = np.bincount(base + c0, minlength=h * w) - np.bincount(base + c1, minlength=h * w)
    inside = np.cumsum(edge.reshape(h, w), axis=1)[:, : w - 1] > 0
    mask[r_lo : r_lo + h, c_lo : c_lo + w - 1] = inside
    return mask


def detections_xy(sweeps: Sequence[RadarSweep], ego_pose: SE3) -> np.ndarray:
    """The finite detections of ``sweeps``, ``(k, 2)`` metres in the ego frame at ``ego_pose``."""
    to_ego = ego_pose.inverse()
    parts = [np.zeros((0, 2))]
    for s in sweeps:
        p = s.points[:, 0:3]
        p = p[np.isfinite(p).all(axis=1)]
        if len(p):
            parts.append((to_ego @ s.ego_pose @ s.sensor_to_ego).apply(p)[:, :2])
    return np.concatenate(parts)


def keep_supported(masses: np.ndarray, xy: np.ndarray, grid: GridSpec, radius_m: float):
    """Masses with the occupied mass farther than ``radius_m`` from every detection ``xy``
    (ego-frame metres) moved to unknown. Distances are measured between cells of
    ``_SUPPORT_POOL`` local cells a side, so the radius holds to within one such cell."""
    n, pool = grid.n_cells, _SUPPORT_POOL
    nc = -(-n // pool)
    rows, cols = grid.xy_to_cell(xy[:, 0], xy[:, 1])
    rows, cols = np.unique(np.stack([rows // pool, cols // pool]), axis=1)
    near = _stamp(nc, rows, cols, radius_m / (grid.resolution * pool))
    near = np.repeat(np.repeat(near, pool, axis=0), pool, axis=1)[:n, :n]
    return _move_occupied(masses, ~near, 2)


def clear_path(masses: np.ndarray, trail_xy: np.ndarray, grid: GridSpec, radius_m: float):
    """Masses with the occupied mass within ``radius_m`` of the trail points ``trail_xy``
    (ego-frame metres) moved to free."""
    rows, cols = grid.xy_to_cell(trail_xy[:, 0], trail_xy[:, 1])
    return _move_occupied(masses, _stamp(grid.n_cells, rows, cols, radius_m / grid.resolution), 0)


def driven_cells(
    grid: GridSpec, a: tuple[float, float], b: tuple[float, float], radius_m: float
) -> tuple[int, int, np.ndarray]:
    """The map cells whose centres lie within ``radius_m`` of the segment from map point ``a``
    to ``b`` (the stretch of path one update drove): ``(r0, c0, mask)``, ``mask[i, j]`` for map
    cell ``(r0 + i, c0 + j)``."""
    (ax, ay), (bx, by) = a, b
    rows, cols = grid.map_xy_to_cell(
        np.array([min(ax, bx) - radius_m, max(ax, bx) + radius_m]),
        np.array([min(ay, by) - radius_m, max(ay, by) + radius_m]),
    )
    r0, c0 = int(rows.min()), int(cols.min())
    rr, cc = np.indices((int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1))
    x, y = grid.map_cell_to_xy(rr + r0, cc + c0)
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t = np.clip(((x - ax) * dx + (y - ay) * dy) / L2, 0.0, 1.0) if L2 > 0 else 0.0
    d2 = (x - ax - t * dx) ** 2 + (y - ay - t * dy) ** 2
    return r0, c0, d2 <= radius_m * radius_m


class Trail:
    """The vehicle's path in the map frame, as the centres of the cells of a square grid of
    ``step_m`` that it crossed: the straight line between consecutive poses is sampled every
    ``step_m / 2`` and each sample marks its cell. Cells farther than ``reach_m`` from the
    vehicle are dropped. Every point of the path within reach lies within :attr:`margin_m` of a
    centre, whatever the speed; the memory is bounded by the area within ``reach_m``, however
    long the drive."""

    def __init__(self, step_m: float, reach_m: float):
        self.step_m, self.reach_m = float(step_m), float(reach_m)
        self._keys = np.zeros((0, 2), np.int64)
        self._last: np.ndarray | None = None
        #: the stretch the last :meth:`add` drove, ``(a, b)`` map-frame points (a jump: its last
        #: ``reach_m``; the first pose: ``a == b``)
        self.stretch: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def margin_m(self) -> float:
        """How far a point of the path may lie from the nearest centre: half a cell's diagonal
        and a quarter step (the samples' spacing is half a step)."""
        return self.step_m * (math.sqrt(0.5) + 0.25)

    @property
    def xy(self) -> np.ndarray:
        """The centres ``(k, 2)`` of the cells kept, in the map frame."""
        return (self._keys + 0.5) * self.step_m

    def add(self, pose: SE2) -> None:
        """Take the vehicle's pose in the map frame."""
        p = np.array([pose.x, pose.y])
        a = p if self._last is None else self._last
        d = float(np.hypot(*(p - a)))
        if d > self.reach_m:  # a jump (a gap in the poses): what lies beyond reach is dropped
            a, d = p + (a - p) * (self.reach_m / d), self.reach_m
        n = max(int(math.ceil(d / (0.5 * self.step_m))), 1)
        pts = a + (p - a) * (np.arange(n + 1)[:, None] / n)
        keys = np.floor(pts / self.step_m).astype(np.int64)
        keys = np.unique(np.concatenate([self._keys, keys]), axis=0)
        centres = (keys + 0.5) * self.step_m
        self._keys = keys[np.hypot(*(centres - p).T) <= self.reach_m]
        self._last, self.stretch = p, (a, p)

    def in_ego(self, pose: SE2) -> np.ndarray:
        """The trail's points ``(k, 2)`` in the ego frame at ``pose``."""
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        d = self.xy - np.array([pose.x, pose.y])
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
