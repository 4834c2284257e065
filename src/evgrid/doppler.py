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

import functools
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


@functools.lru_cache(maxsize=8)
def _offsets(resolution: float, radius_m: float) -> np.ndarray:
    """Integer cell offsets (dr, dc) that a disc of ``radius_m`` around a point of a cell can
    reach (one cell of margin: the point lies anywhere in its cell)."""
    k = int(np.ceil(radius_m / resolution)) + 1
    dr, dc = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    return np.stack([dr.ravel(), dc.ravel()], 1).astype(np.int64)


def disc_cells(
    grid: GridSpec, pose: SE2, xy: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Map cells ``(rows, cols)`` (each once) whose centre lies within ``radius_m`` of a point of
    ``xy`` (``(k, 2)`` map frame, m), or that hold one; points outside the local grid at ego
    ``pose`` are ignored (no map cell there is updated at this step)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    local = pose.inverse().apply(xy)
    h = grid.half_extent
    xy = xy[(np.abs(local) < h).all(axis=1)]
    if not len(xy):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    res = grid.resolution
    rows, cols = grid.map_xy_to_cell(xy[:, 0], xy[:, 1])
    off = _offsets(res, radius_m)
    r = rows[:, None] + off[None, :, 0]
    c = cols[:, None] + off[None, :, 1]
    # map cell (R, C) has its centre at x = -(R + 0.5) res, y = -(C + 0.5) res
    dx = -(r + 0.5) * res - xy[:, 0:1]
    dy = -(c + 0.5) * res - xy[:, 1:2]
    inside = dx * dx + dy * dy <= radius_m * radius_m
    inside |= (off[:, 0] == 0) & (off[:, 1] == 0)  # the detection's own cell
    r, c = r[inside], c[inside]
    # each cell once: marked on a mask over the discs' box (cheaper than sorting the cells)
    r_lo, c_lo = int(r.min()), int(c.min())
    mask = np.zeros((int(r.max()) - r_lo + 1, int(c.max()) - c_lo + 1), np.bool_)
    mask[r - r_lo, c - c_lo] = True
    rr, cc = np.nonzero(mask)
    return rr + r_lo, cc + c_lo


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
    """Add ``value`` (a float per cell) to the dynamic score of map cells ``(rows, cols)`` of
    ``m`` where a tile is stored (a cell of no tile was never updated: it has no score)."""
    if not len(rows):
        return
    ts = m.tile_cells
    for a in range(int(rows.min()) // ts, int(rows.max()) // ts + 1):
        for b in range(int(cols.min()) // ts, int(cols.max()) // ts + 1):
            layer = m.dynamic_tiles.get((a, b))
            if layer is not None:
                _add_cells(layer, rows, cols, value, a * ts, b * ts)
