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
from collections.abc import Sequence

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
    keys = np.unique(np.stack([r[inside], c[inside]], 1), axis=0)
    return keys[:, 0], keys[:, 1]


def not_free_now(
    grid: GridSpec, pose: SE2, rows: np.ndarray, cols: np.ndarray, ism: np.ndarray
) -> np.ndarray:
    """Per map cell, ``1 - m_f / (m_f + m_o)`` of the local ISM grid ``ism`` (``(n, n, 3)``, ego
    frame at ego ``pose``) in the local cell nearest to the map cell's centre: 0 where the ISM
    says only free now, 1 where it says only occupied or nothing (vacuous, or outside the local
    grid: the ISM cannot rule a mover out there)."""
    res, n = grid.resolution, grid.n_cells
    centres = np.stack([-(rows + 0.5) * res, -(cols + 0.5) * res], 1)
    local = pose.inverse().apply(centres)
    r = np.rint(n / 2.0 - 0.5 - local[:, 0] / res).astype(np.int64)
    c = np.rint(n / 2.0 - 0.5 - local[:, 1] / res).astype(np.int64)
    inside = (r >= 0) & (r < n) & (c >= 0) & (c < n)
    out = np.ones(len(rows), np.float32)
    f = ism[r[inside], c[inside], 0].astype(np.float64)
    o = ism[r[inside], c[inside], 1].astype(np.float64)
    # invalid cells (NaN, negative) say nothing, as the update rules take them
    ok = np.isfinite(f) & np.isfinite(o) & (f > 0.0) & (o >= 0.0)
    out[inside] = np.where(ok, o / np.where(ok, o + f, 1.0), 1.0)
    return out


def add_to_layer(m: EvidentialMap, rows: np.ndarray, cols: np.ndarray, value: np.ndarray) -> None:
    """Add ``value`` (a float per cell) to the dynamic score of map cells ``(rows, cols)`` of
    ``m`` where a tile is stored (a cell of no tile was never updated: it has no score)."""
    if not len(rows):
        return
    ts = m.tile_cells
    ti, tj = rows // ts, cols // ts
    key = ti * (1 << 32) + tj
    order = np.argsort(key, kind="stable")
    key, ti, tj = key[order], ti[order], tj[order]
    r, c, v = rows[order] - ti * ts, cols[order] - tj * ts, value[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    for a, b in zip(starts, ends):
        layer = m.dynamic_tiles.get((int(ti[a]), int(tj[a])))
        if layer is not None:
            layer[r[a:b], c[a:b]] += v[a:b]
