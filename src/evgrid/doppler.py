"""The Doppler cue of the dynamic score: radar detections that move (docs/equations.md).

Every source fills the radar columns ``vx_comp, vy_comp`` with the ego-motion compensated
Doppler velocity (nuScenes stores it; the simulator and the bag decoder compensate the raw
radial speed with the odometry), so a detection's own speed is the length of that vector. The
newest sweep of each radar gives the detections faster than ``doppler_mps``; their positions and
the radar's in the map frame go to :meth:`evgrid.fusion.MapSet.update`, which adds to the score
of the map cells of a disc of ``doppler_radius_m`` behind each of them (the detection is the
object's surface that faces the radar; the disc touches it from behind) ``doppler_mass`` times
the share of its ISM's evidence that is not free now (the ISM rules out the cells it sees free).
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

from evgrid.data.frame import RadarSweep, radar_column
from evgrid.geometry import SE2, SE3, GridSpec

__all__ = ["moving_detections", "disc_centres", "disc_runs"]

_X, _VX, _VY = (radar_column(c) for c in ("x", "vx_comp", "vy_comp"))


def moving_detections(sweeps: Sequence[RadarSweep], to_map: SE3, min_speed: float) -> np.ndarray:
    """``(k, 5)`` float64: map-frame position (m), speed (m/s) and the radar's map-frame position
    (m) of the detections of ``sweeps`` whose ego-motion compensated Doppler speed ``|(vx_comp,
    vy_comp)|`` exceeds ``min_speed``; ``to_map`` takes the global frame to the map frame. Each
    sweep moves with its own ego pose and extrinsics; detections with a non-finite position or
    velocity are skipped."""
    parts = []
    for s in sweeps:
        p = s.points
        if not len(p):
            continue
        speed = np.hypot(p[:, _VX].astype(np.float64), p[:, _VY].astype(np.float64))
        xyz = p[:, _X : _X + 3].astype(np.float64)
        fast = (speed > min_speed) & np.isfinite(xyz).all(axis=1)  # NaN speeds compare False
        if fast.any():
            to = to_map @ s.ego_pose @ s.sensor_to_ego
            xy = to.apply(xyz[fast])[:, :2]
            radar = np.broadcast_to(to.translation[:2], xy.shape)  # the sensor's origin
            parts.append(np.column_stack([xy, speed[fast], radar]))
    return np.concatenate(parts) if parts else np.zeros((0, 5), np.float64)


def disc_centres(moving: np.ndarray, radius_m: float) -> np.ndarray:
    """``(k, 2)``: the centres of the Doppler cue's discs of ``moving`` (``(k, 5)``, as
    :func:`moving_detections` gives): ``radius_m`` behind each detection on the radar's line of
    sight through it, so that the disc touches the detection from behind (a detection is the
    near surface of its object; the object extends away from the radar). A detection at the
    radar's own position keeps its disc centred on it."""
    xy, radar = moving[:, :2], moving[:, 3:5]
    d = xy - radar
    n = np.hypot(d[:, 0], d[:, 1])[:, None]
    return xy + np.divide(radius_m * d, n, out=np.zeros_like(d), where=n > 0.0)


@numba.njit(cache=True)
def _runs(x, y, res, radius, r0, c0, h, w):
    # Window row i's cells in the discs: columns [runs[k, 0], runs[k, 1]) for k in
    # [ptr[i], ptr[i + 1]), disjoint and sorted. Map cell (R, C) is window cell (R - r0, C - c0)
    # and is in a disc when its centre (-(R + 0.5) res, -(C + 0.5) res) lies within ``radius`` of
    # a point, or when it holds one; in a row that set is one interval per point.
    k = int(np.ceil(radius / res)) + 1
    seg = np.empty((len(x) * (2 * k + 1), 3), np.int64)
    n = 0
    for p in range(len(x)):
        rp = int(np.floor(-x[p] / res))
        cp = int(np.floor(-y[p] / res))
        for r in range(max(rp - k, r0), min(rp + k + 1, r0 + h)):
            dx = -(r + 0.5) * res - x[p]
            lo, hi = c0 + w, c0 - 1
            for c in range(max(cp - k, c0), min(cp + k + 1, c0 + w)):
                dy = -(c + 0.5) * res - y[p]
                if dx * dx + dy * dy <= radius * radius or (r == rp and c == cp):
                    lo = min(lo, c)
                    hi = max(hi, c)
            if hi >= lo:
                seg[n, 0] = r - r0
                seg[n, 1] = lo - c0
                seg[n, 2] = hi + 1 - c0
                n += 1
    order = np.argsort(seg[:n, 0] * (w + 1) + seg[:n, 1])
    ptr = np.zeros(h + 1, np.int64)
    runs = np.empty((n, 2), np.int64)
    m = 0
    for q in range(n):
        i, lo, hi = seg[order[q], 0], seg[order[q], 1], seg[order[q], 2]
        if m > 0 and seg[order[q - 1], 0] == i and lo <= runs[m - 1, 1]:
            runs[m - 1, 1] = max(runs[m - 1, 1], hi)  # overlaps or touches the row's last run
        else:
            runs[m, 0] = lo
            runs[m, 1] = hi
            m += 1
            ptr[i + 1] = m
    for i in range(h):  # rows without a run start where the one before ends
        ptr[i + 1] = max(ptr[i + 1], ptr[i])
    return ptr, runs[:m]


def disc_runs(
    grid: GridSpec, pose: SE2, box: tuple[int, int, int, int], xy: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The map cells of window ``box`` ``(r0, c0, h, w)`` whose centre lies within ``radius_m``
    of a point of ``xy`` (``(k, 2)`` map frame, m), or that hold one, as runs per window row:
    ``ptr`` ``(h + 1,)`` and ``runs`` ``(n, 2)``, row i's cells are columns ``[runs[k, 0],
    runs[k, 1])`` for k in ``[ptr[i], ptr[i + 1])`` (disjoint, sorted; each cell once however
    many discs hold it). Points outside the local grid at ego ``pose`` are ignored (no map cell
    there is updated at this step)."""
    r0, c0, h, w = box
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    local = pose.inverse().apply(xy)
    xy = xy[(np.abs(local) < grid.half_extent).all(axis=1)]
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    return _runs(x, y, grid.resolution, float(radius_m), r0, c0, h, w)
