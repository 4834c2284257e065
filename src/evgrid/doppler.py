"""The Doppler cue of the dynamic score: radar detections that move (docs/equations.md).

Every source fills the radar columns ``vx_comp, vy_comp`` with the ego-motion compensated
Doppler velocity (nuScenes stores it; the simulator and the bag decoder compensate the raw
radial speed with the odometry), so a detection's own speed is the length of that vector. The
newest sweep of each radar gives the detections faster than ``doppler_mps``; their positions in
the map frame go to :meth:`evgrid.fusion.MapSet.update`, which adds to the score of the map
cells within ``doppler_radius_m`` of any of them ``doppler_mass`` times the share of its ISM's
evidence that is not free now (the disc says something moves near; the ISM rules out the cells
it sees free, such as the road around a moving car).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from evgrid.data.frame import RadarSweep, radar_column
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.grid import EvidentialMap

__all__ = ["moving_detections", "disc_cells", "not_free_now", "add_to_layer"]

_X, _VX, _VY = (radar_column(c) for c in ("x", "vx_comp", "vy_comp"))


def moving_detections(sweeps: Sequence[RadarSweep], to_map: SE3, min_speed: float) -> np.ndarray:
    """``(k, 3)`` float64: map-frame position (m) and speed (m/s) of the detections of ``sweeps``
    whose ego-motion compensated Doppler speed ``|(vx_comp, vy_comp)|`` exceeds ``min_speed``;
    ``to_map`` takes the global frame to the map frame. Each sweep moves with its own ego pose
    and extrinsics; detections with a non-finite position or velocity are skipped."""
    parts = []
    for s in sweeps:
        p = s.points
        if not len(p):
            continue
        speed = np.hypot(p[:, _VX].astype(np.float64), p[:, _VY].astype(np.float64))
        xyz = p[:, _X : _X + 3].astype(np.float64)
        fast = (speed > min_speed) & np.isfinite(xyz).all(axis=1)  # NaN speeds compare False
        if fast.any():
            xy = (to_map @ s.ego_pose @ s.sensor_to_ego).apply(xyz[fast])[:, :2]
            parts.append(np.column_stack([xy, speed[fast]]))
    return np.concatenate(parts) if parts else np.zeros((0, 3), np.float64)


@numba.njit(cache=True)
def _stamp(x, y, res, radius, r_lo, c_lo, mask):
    # mask[R - r_lo, C - c_lo] = True for every map cell (R, C) whose centre (-(R + 0.5) res,
    # -(C + 0.5) res) lies within ``radius`` of a point, or that holds one
    k = int(np.ceil(radius / res)) + 1
    h, w = mask.shape
    for p in range(len(x)):
        r0 = int(np.floor(-x[p] / res))
        c0 = int(np.floor(-y[p] / res))
        for r in range(max(r0 - k, r_lo), min(r0 + k + 1, r_lo + h)):
            dx = -(r + 0.5) * res - x[p]
            for c in range(max(c0 - k, c_lo), min(c0 + k + 1, c_lo + w)):
                dy = -(c + 0.5) * res - y[p]
                if dx * dx + dy * dy <= radius * radius or (r == r0 and c == c0):
                    mask[r - r_lo, c - c_lo] = True


@numba.njit(cache=True)
def _marked(mask, r_lo, c_lo):
    # np.nonzero(mask) + (r_lo, c_lo), row-major, without numpy's generic path (the mask spans
    # the discs' box, most of it empty)
    n = 0
    for r in range(mask.shape[0]):
        for c in range(mask.shape[1]):
            n += mask[r, c]
    rows = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    k = 0
    for r in range(mask.shape[0]):
        for c in range(mask.shape[1]):
            if mask[r, c]:
                rows[k] = r + r_lo
                cols[k] = c + c_lo
                k += 1
    return rows, cols


def disc_cells(
    grid: GridSpec, pose: SE2, xy: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Map cells ``(rows, cols)`` (each once, in row-major order) whose centre lies within
    ``radius_m`` of a point of ``xy`` (``(k, 2)`` map frame, m), or that hold one; points outside
    the local grid at ego ``pose`` are ignored (no map cell there is updated at this step)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    local = pose.inverse().apply(xy)
    xy = xy[(np.abs(local) < grid.half_extent).all(axis=1)]
    if not len(xy):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    res = grid.resolution
    rows, cols = grid.map_xy_to_cell(xy[:, 0], xy[:, 1])
    k = int(np.ceil(radius_m / res)) + 1
    # each cell once: marked on a mask over the discs' box (cheaper than sorting the cells)
    r_lo, c_lo = int(rows.min()) - k, int(cols.min()) - k
    mask = np.zeros((int(rows.max()) + k + 1 - r_lo, int(cols.max()) + k + 1 - c_lo), np.bool_)
    _stamp(xy[:, 0].copy(), xy[:, 1].copy(), res, float(radius_m), r_lo, c_lo, mask)
    return _marked(mask, r_lo, c_lo)


@numba.njit(cache=True)
def _not_free(rows, cols, ism, res, n, x0, y0, c, s, out):
    # out[k]: 1 - m_f / (m_f + m_o) of the ISM cell nearest to map cell k's centre (see
    # not_free_now); (x0, y0, c, s): the ego pose's position and the cos and sin of its yaw
    for k in range(len(rows)):
        dx = -(rows[k] + 0.5) * res - x0
        dy = -(cols[k] + 0.5) * res - y0
        r = int(np.rint(n / 2.0 - 0.5 - (c * dx + s * dy) / res))
        q = int(np.rint(n / 2.0 - 0.5 - (-s * dx + c * dy) / res))
        w = 1.0
        if r >= 0 and r < n and q >= 0 and q < n:
            f, o = np.float64(ism[r, q, 0]), np.float64(ism[r, q, 1])
            # invalid cells (NaN, negative) say nothing, as the update rules take them
            if f > 0.0 and o >= 0.0 and np.isfinite(f) and np.isfinite(o):
                w = o / (o + f)
        out[k] = w


@numba.njit(cache=True)
def _add_cells(layer, rows, cols, values, r0, c0):
    # layer[rows - r0, cols - c0] += values where inside the tile
    ts0, ts1 = layer.shape
    for k in range(len(rows)):
        r, q = rows[k] - r0, cols[k] - c0
        if r >= 0 and r < ts0 and q >= 0 and q < ts1:
            layer[r, q] += values[k]


def not_free_now(
    grid: GridSpec, pose: SE2, rows: np.ndarray, cols: np.ndarray, ism: np.ndarray
) -> np.ndarray:
    """Per map cell, ``1 - m_f / (m_f + m_o)`` of the local ISM grid ``ism`` (``(n, n, 3)``, ego
    frame at ego ``pose``) in the local cell nearest to the map cell's centre: 0 where the ISM
    says only free now, 1 where it says only occupied or nothing (vacuous, or outside the local
    grid: the ISM cannot rule a mover out there)."""
    out = np.empty(len(rows), np.float32)
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    _not_free(rows, cols, ism, grid.resolution, grid.n_cells, pose.x, pose.y, c, s, out)
    return out


def add_to_layer(m: EvidentialMap, rows: np.ndarray, cols: np.ndarray, value: np.ndarray) -> None:
    """Add ``value`` (a float per cell) to the dynamic score of map cells ``(rows, cols)`` (in
    row-major order, as :func:`disc_cells` gives them) of ``m`` where a tile is stored (a cell of
    no tile was never updated: it has no score)."""
    if not len(rows):
        return
    ts = m.tile_cells
    for a in range(int(rows.min()) // ts, int(rows.max()) // ts + 1):
        # the cells are in row-major order: those of tile row a are one slice
        i, j = np.searchsorted(rows, (a * ts, (a + 1) * ts))
        for b in range(int(cols.min()) // ts, int(cols.max()) // ts + 1):
            layer = m.dynamic_tiles.get((a, b))
            if layer is not None and j > i:
                _add_cells(layer, rows[i:j], cols[i:j], value[i:j], a * ts, b * ts)
