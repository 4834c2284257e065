"""The ray casting inverse lidar model, "ray ILM" (paper sec. V-A; docs/decisions.md#ray-ilm).

From one lidar sweep to a local mass grid ``(n, n, 3)`` [m_f, m_o, m_u] on a
:class:`~evgrid.geometry.GridSpec`:

1. points go from the sensor frame into the ego frame (``sensor_to_ego``); points whose ego
   height z is below ``z_min_m`` (0.3 m) or above ``z_max_m`` (3.0 m) are dropped; the
   nuScenes ego frame has z = 0 on the ground, so z is the height above ground;
2. the rest are projected onto the ground plane (z dropped) and discretised into the grid:
   their cells are *detection cells*;
3. rays every ``angular_resolution_deg`` (0.2 degrees) leave the lidar's position (the
   sensor origin in the ego frame, projected to the ground) and walk cell by cell (exact
   Amanatides-Woo traversal: every cell the ray's segment passes through) until the first
   detection cell or ``max_range_m`` (15 m) or the grid's edge;
4. detection cells get [0, m_o, 1 - m_o] with m_o = 0.5, cells crossed by a ray
   [m_f, 0, 1 - m_f] with m_f = 0.05, all others the vacuous [0, 0, 1].

Decisions the paper leaves open (documented here once):

* every detection cell in the grid is occupied, including those beyond ``max_range_m``: the
  paper marks "detection positions"; the 15 m only bounds the rays;
* a ray stops at the first detection cell *after* the cell holding the lidar itself, so a
  return in that cell cannot blank the whole grid. Returns from the vehicle's body in other
  cells do stop the rays through them; ``min_range_m`` (not in the paper, 0 by default)
  ignores returns that close to the lidar;
* a point within ``NO_RETURN_RANGE_M`` (1 mm) of the sensor is no return (organised clouds
  mark a beam without one as (0, 0, 0)): it is dropped and counted, like a NaN point;
* a sweep without a single finite return is no measurement: the grid stays vacuous. A sweep
  whose returns are all filtered out by height (say, only ground hits) still casts
  every ray to 15 m: the sensor saw no obstacle there;
* rays are at angles ``k * step`` in the grid's frame, ``step = 360 / round(360 /
  angular_resolution_deg)`` degrees so that they divide the circle evenly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numba
import numpy as np

from evgrid.data.frame import LIDAR_COLUMNS, NO_RETURN_RANGE_M, LidarSweep
from evgrid.geometry import SE3, GridSpec
from evgrid.ism._common import (
    FREE,
    OCCUPIED,
    IsmResult,
    as_points,
    check_ism_args,
    label_scratch,
    labels_to_masses,
    log_dropped,
    numba_threads,
    point_xyz,
)
from evgrid.validation import check_mass, check_number

__all__ = ["RayIlmParams", "ray_ilm", "ray_ilm_with_stats"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RayIlmParams:
    """Parameters of the ray ILM; the defaults are the paper's (sec. V-A). Lengths in metres."""

    z_min_m: float = 0.3
    z_max_m: float = 3.0
    max_range_m: float = 15.0
    angular_resolution_deg: float = 0.2
    m_free: float = 0.05
    m_occupied: float = 0.5
    #: Returns closer than this (horizontally) to the lidar are ignored, e.g. hits on the
    #: vehicle's own body, which would otherwise stop every ray through their cells. Not in
    #: the paper, so 0 (keep all) by default.
    min_range_m: float = 0.0

    def __post_init__(self) -> None:
        check_number(self, "z_min_m")
        check_number(self, "z_max_m", min=self.z_min_m, min_open=True)
        check_number(self, "max_range_m", min=0.0, min_open=True)
        check_number(self, "angular_resolution_deg", min=0.0, max=360.0, min_open=True)
        check_mass(self, "m_free")
        check_mass(self, "m_occupied")
        check_number(self, "min_range_m", min=0.0)

    @property
    def n_rays(self) -> int:
        """Number of rays over the full circle."""
        return max(1, int(round(360.0 / self.angular_resolution_deg)))


_DEFAULT_GRID = GridSpec()
_DEFAULT_PARAMS = RayIlmParams()


# --- kernels ------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _k_ilm_points(pts, se, eg, z_min, z_max, min_range, no_return, half, inv_res, labels):
    """Mark detection cells; returns (n_dropped, n_at_origin, n_used). ``se``: sensor->ego 3x4,
    ``eg``: ego->grid 2x4; points within ``no_return`` of the sensor are no returns."""
    n_r, n_c = labels.shape
    min_r2 = min_range * min_range
    no_return2 = no_return * no_return
    n_dropped = 0
    n_at_origin = 0
    n_used = 0
    for i in range(pts.shape[0]):
        finite, x, y, z = point_xyz(pts, i)
        if not finite:
            n_dropped += 1
            continue
        if x * x + y * y + z * z < no_return2:
            n_at_origin += 1
            continue
        ex = se[0, 0] * x + se[0, 1] * y + se[0, 2] * z + se[0, 3]
        ey = se[1, 0] * x + se[1, 1] * y + se[1, 2] * z + se[1, 3]
        ez = se[2, 0] * x + se[2, 1] * y + se[2, 2] * z + se[2, 3]
        # Paper sec. V-A: drop detections below 0.3 m and above 3.0 m (ego z = height above ground).
        if ez < z_min or ez > z_max:
            continue
        if min_r2 > 0.0:
            hx = ex - se[0, 3]
            hy = ey - se[1, 3]
            if hx * hx + hy * hy < min_r2:
                continue
        n_used += 1
        gx = eg[0, 0] * ex + eg[0, 1] * ey + eg[0, 2] * ez + eg[0, 3]
        gy = eg[1, 0] * ex + eg[1, 1] * ey + eg[1, 2] * ez + eg[1, 3]
        # geometry.GridSpec.xy_to_cell: row = floor(n/2 - x/res), col = floor(n/2 - y/res).
        fr = math.floor(half - gx * inv_res)
        fc = math.floor(half - gy * inv_res)
        if fr >= 0 and fr < n_r and fc >= 0 and fc < n_c:
            labels[int(fr), int(fc)] = OCCUPIED
    return n_dropped, n_at_origin, n_used


@numba.njit(cache=True, inline="always")
def _cast_ray(labels, u0, v0, du, dv, t_end):
    """Walk a ray from continuous cell coords (u0, v0) along unit (du, dv) for t_end cells.

    Cell (r, c) is the half-open square [r, r+1) x [c, c+1). Exact traversal (Amanatides &
    Woo 1987): visits every cell the segment passes through, in order, 4-connected. Marks
    them FREE until the first OCCUPIED cell, which stops the ray (not the ray's start cell).
    """
    n_r, n_c = labels.shape
    t0 = 0.0
    t1 = t_end
    # Clip the segment to the grid square [0, n_r] x [0, n_c] (slab method).
    if du != 0.0:
        ta = (0.0 - u0) / du
        tb = (n_r - u0) / du
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    elif u0 < 0.0 or u0 >= n_r:
        return
    if dv != 0.0:
        ta = (0.0 - v0) / dv
        tb = (n_c - v0) / dv
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    elif v0 < 0.0 or v0 >= n_c:
        return
    if t0 >= t1:
        return
    r = int(math.floor(u0 + du * t0))
    c = int(math.floor(v0 + dv * t0))
    r = min(max(r, 0), n_r - 1)
    c = min(max(c, 0), n_c - 1)
    first = t0 == 0.0  # the ray starts inside: its own cell never stops it
    inf = np.inf
    if du > 0.0:
        sr, tmr, tdr = 1, (r + 1.0 - u0) / du, 1.0 / du
    elif du < 0.0:
        sr, tmr, tdr = -1, (r - u0) / du, -1.0 / du
    else:
        sr, tmr, tdr = 0, inf, inf
    if dv > 0.0:
        sc, tmc, tdc = 1, (c + 1.0 - v0) / dv, 1.0 / dv
    elif dv < 0.0:
        sc, tmc, tdc = -1, (c - v0) / dv, -1.0 / dv
    else:
        sc, tmc, tdc = 0, inf, inf
    while True:
        if labels[r, c] == OCCUPIED:
            if not first:
                return
        else:
            labels[r, c] = FREE
        first = False
        if tmr < tmc:
            t = tmr
            r += sr
            tmr += tdr
        else:
            t = tmc
            c += sc
            tmc += tdc
        if t >= t1 or r < 0 or r >= n_r or c < 0 or c >= n_c:
            return


@numba.njit(cache=True)
def _k_ilm_rays(labels, u0, v0, n_rays, t_end):
    step = 2.0 * math.pi / n_rays
    for k in range(n_rays):
        th = k * step
        # Ego x (forward) is -u (rows grow backwards), ego y (left) is -v (geometry.py).
        _cast_ray(labels, u0, v0, -math.cos(th), -math.sin(th), t_end)


@numba.njit(cache=True, parallel=True)
def _k_ilm_rays_par(labels, u0, v0, n_rays, t_end):
    # Rays only ever write FREE over non-OCCUPIED cells, and OCCUPIED is written before any
    # ray starts, so concurrent rays race only on writing the same byte value: harmless.
    step = 2.0 * math.pi / n_rays
    for k in numba.prange(n_rays):
        th = k * step
        _cast_ray(labels, u0, v0, -math.cos(th), -math.sin(th), t_end)


# --- public API ---------------------------------------------------------------------------------


def _resolve_inputs(
    sweep: LidarSweep | np.ndarray, sensor_to_ego: SE3 | None, ego_pose: SE3 | None
) -> tuple[np.ndarray, SE3, SE3 | None]:
    if isinstance(sweep, LidarSweep):
        if sensor_to_ego is not None or ego_pose is not None:
            raise ValueError(
                "ray_ilm: pass either a LidarSweep or raw points with sensor_to_ego/ego_pose, not "
                "both"
            )
        return sweep.points, sweep.sensor_to_ego, sweep.ego_pose
    pts = as_points(sweep, 3, "ray_ilm", max_cols=len(LIDAR_COLUMNS))
    if sensor_to_ego is None:
        sensor_to_ego = SE3.identity()
    elif not isinstance(sensor_to_ego, SE3):
        raise TypeError(
            f"ray_ilm: sensor_to_ego must be an SE3, got {type(sensor_to_ego).__name__}"
        )
    if ego_pose is not None and not isinstance(ego_pose, SE3):
        raise TypeError(f"ray_ilm: ego_pose must be an SE3, got {type(ego_pose).__name__}")
    return pts, sensor_to_ego, ego_pose


def ray_ilm_with_stats(
    sweep: LidarSweep | np.ndarray,
    sensor_to_ego: SE3 | None = None,
    ego_pose: SE3 | None = None,
    *,
    reference_pose: SE3 | None = None,
    grid: GridSpec = _DEFAULT_GRID,
    params: RayIlmParams = _DEFAULT_PARAMS,
    threads: int = 1,
    out: np.ndarray | None = None,
) -> IsmResult:
    """Ray ILM (paper sec. V-A) with point counts: masses ``(n, n, 3)`` float32 on ``grid``
    (metres).

    ``sweep`` is a :class:`~evgrid.data.frame.LidarSweep`, or raw points ``(n, >= 3)``
    (x, y, z in metres in the sensor frame, further columns ignored) with ``sensor_to_ego``
    (default identity: points already in the ego frame) and ``ego_pose`` (ego -> global at
    the sweep's time). The grid is the sweep's own ego frame, or, with ``reference_pose``
    (ego -> global), that pose's ego frame: points and the lidar origin are moved into it
    (heights are still taken in the sweep's ego frame). ``threads > 1`` runs the ray casting
    on that many numba threads. ``out``: a float32 ``(n, n, 3)`` array to write into.
    NaN/inf points are dropped, counted and logged once per call; points at the sensor origin
    (no returns) are dropped and counted (``n_at_origin``).
    """
    threads = check_ism_args("ray_ilm", grid, params, RayIlmParams, threads, out)
    pts, sensor_to_ego, ego_pose = _resolve_inputs(sweep, sensor_to_ego, ego_pose)

    se = np.ascontiguousarray(sensor_to_ego.matrix()[:3, :])
    if reference_pose is None:
        eg = np.ascontiguousarray(np.eye(4)[:2, :])
    else:
        if ego_pose is None:
            raise ValueError("ray_ilm: reference_pose needs the sweep's ego_pose")
        eg = np.ascontiguousarray((reference_pose.inverse() @ ego_pose).matrix()[:2, :])
    origin = eg[:, :3] @ se[:, 3] + eg[:, 3]  # lidar origin on the ground plane, grid frame (m)

    n = grid.n_cells
    inv_res = 1.0 / grid.resolution
    labels = label_scratch(grid, "ilm")
    n_dropped, n_at_origin, n_used = _k_ilm_points(
        pts,
        se,
        eg,
        float(params.z_min_m),
        float(params.z_max_m),
        float(params.min_range_m),
        NO_RETURN_RANGE_M,
        n / 2.0,
        inv_res,
        labels,
    )
    n_points = int(pts.shape[0])
    log_dropped(logger, "ray_ilm", int(n_dropped), n_points)
    if n_at_origin and n_points - n_dropped - n_at_origin == 0:
        # before: a sweep of (0, 0, 0) points painted a full free disc
        logger.warning(
            "ray_ilm: all %d finite point(s) lie within %g m of the sensor (no return): no "
            "measurement, the grid stays vacuous",
            int(n_at_origin),
            NO_RETURN_RANGE_M,
        )
    if n_points - n_dropped - n_at_origin > 0:  # no return at all: no measurement, vacuous
        # Continuous cell coordinates of the origin: u = n/2 - x/res puts cell edges at integers.
        u0 = n / 2.0 - origin[0] * inv_res
        v0 = n / 2.0 - origin[1] * inv_res
        t_end = params.max_range_m * inv_res
        if threads > 1:
            with numba_threads(threads):
                _k_ilm_rays_par(labels, u0, v0, params.n_rays, t_end)
        else:
            _k_ilm_rays(labels, u0, v0, params.n_rays, t_end)
    masses = labels_to_masses(labels, params.m_free, params.m_occupied, out, threads)
    return IsmResult(masses, n_points, int(n_dropped), int(n_used), int(n_at_origin))


def ray_ilm(sweep: LidarSweep | np.ndarray, *args, **kwargs) -> np.ndarray:
    """Ray ILM (paper sec. V-A): masses ``(n, n, 3)`` float32 [m_f, m_o, m_u] on ``grid``
    (metres); the parameters of :func:`ray_ilm_with_stats`, which also counts the points."""
    return ray_ilm_with_stats(sweep, *args, **kwargs).masses
