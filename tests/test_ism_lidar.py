"""Ray ILM (paper sec. V-A): analytic worlds, an independent slow reference, bad input."""

from __future__ import annotations

import logging
import math
import re

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.data.frame import LidarSweep
from evgrid.geometry import SE3, GridSpec
from evgrid.ism import IsmResult, RayIlmParams, ray_ilm, ray_ilm_with_stats
from evgrid_sim.synthetic import cast_lidar

GRID = GridSpec()  # 512 cells over 40 m
RES = GRID.resolution
FREE = np.array([0.05, 0.0, 0.95], dtype=np.float32)
OCC = np.array([0.0, 0.5, 0.5], dtype=np.float32)
VAC = np.array([0.0, 0.0, 1.0], dtype=np.float32)

# A nuScenes-like roof lidar: 0.5 m ahead of the ego origin, 1.8 m up, x axis to the right.
LIDAR = SE3.from_quaternion([math.cos(-math.pi / 4), 0, 0, math.sin(-math.pi / 4)], [0.5, 0.0, 1.8])
SENSOR_XY = (0.5, 0.0)


def to_sensor(points_ego: np.ndarray, sensor_to_ego: SE3 = LIDAR) -> np.ndarray:
    """Ego-frame xyz -> (n, 5) float32 sensor-frame lidar points."""
    p = sensor_to_ego.inverse().apply(np.asarray(points_ego, dtype=np.float64))
    out = np.zeros((len(p), 5), dtype=np.float32)
    out[:, :3] = p
    return out


def cell_centres(grid: GridSpec = GRID) -> tuple[np.ndarray, np.ndarray]:
    r, c = np.meshgrid(np.arange(grid.n_cells), np.arange(grid.n_cells), indexing="ij")
    return grid.cell_to_xy(r, c)


def is_mass(m: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.all(m == ref, axis=-1)


def wall_points(x: float, y0: float, y1: float, step: float = 0.02) -> np.ndarray:
    y = np.arange(y0, y1, step)
    return np.concatenate(
        [np.stack([np.full_like(y, x), y, np.full_like(y, z)], 1) for z in (0.5, 1.0, 1.6, 2.4)]
    )


# --- analytic worlds
# -------------------------------------------------------------------------------


def test_wall_ahead_free_before_occupied_on_unknown_behind():
    # A wall 10 m ahead (x = 10.03 m, |y| <= 4 m), nothing else.
    m = ray_ilm(to_sensor(wall_points(10.03, -4.0, 4.0)), LIDAR)
    x, y = cell_centres()
    # hand-computed: row floor(256 - 10.03 / 0.078125) = 127, columns of y in [-4, 4) m: 205..307 (y
    # = -4 m -> 307.2)
    wall_cells = np.zeros(GRID.shape, bool)
    wall_cells[127, 205:308] = True
    assert np.array_equal(m[..., 1] > 0, wall_cells)  # the wall and nothing else is occupied
    assert is_mass(m[wall_cells], OCC).all()
    # in front of the wall, inside its shadow cone: free
    before = (x > SENSOR_XY[0] + 0.2) & (x < 10.03 - RES) & (np.abs(y) < 3.0 * (x - 0.5) / 9.5)
    assert before.sum() > 2000
    assert is_mass(m[before], FREE).all()
    # behind the wall, inside its shadow: unknown
    behind = (x > 10.03 + RES) & (x < 14.0) & (np.abs(y) < 3.5)
    assert is_mass(m[behind], VAC).all()
    # beside the wall, nothing stops the rays within 15 m
    side = (np.hypot(x - 0.5, y) < 14.8) & (np.abs(y) > 6.0)
    assert is_mass(m[side], FREE).all()


def test_rays_end_at_max_range():
    # Only ground returns (z = 0, filtered out): every ray runs its full 15 m.
    ang = np.linspace(0, 2 * np.pi, 500)
    ground = np.stack([10 * np.cos(ang), 10 * np.sin(ang), np.zeros_like(ang)], 1)
    res = ray_ilm_with_stats(to_sensor(ground), LIDAR)
    assert res.n_used == 0 and res.n_points == 500
    x, y = cell_centres()
    d = np.hypot(x - SENSOR_XY[0], y - SENSOR_XY[1])
    assert is_mass(res.masses[d < 15.0 - RES], FREE).all()
    assert is_mass(res.masses[d > 15.0 + RES], VAC).all()
    # the limit is a parameter
    m8 = ray_ilm(to_sensor(ground), LIDAR, params=RayIlmParams(max_range_m=8.0))
    assert is_mass(m8[d < 8.0 - RES], FREE).all()
    assert is_mass(m8[d > 8.0 + RES], VAC).all()


def test_height_filter_keeps_0_3_to_3_0_m_above_ground():
    z = np.array([0.25, 0.31, 1.5, 2.95, 3.05, 5.0])
    pts = np.stack([np.full(6, 6.03), np.linspace(-5, 5, 6) + 0.03, z], 1)
    res = ray_ilm_with_stats(to_sensor(pts), LIDAR)
    r, c = GRID.xy_to_cell(pts[:, 0], pts[:, 1])
    occ = res.masses[r, c, 1] > 0
    assert occ.tolist() == [False, True, True, True, False, False]
    assert res.n_used == 3
    wide = ray_ilm(to_sensor(pts), LIDAR, params=RayIlmParams(z_min_m=0.2, z_max_m=4.0))
    assert (wide[r, c, 1] > 0).tolist() == [True, True, True, True, True, False]


def test_detections_beyond_range_are_occupied_and_rays_clip_at_grid_edge():
    # A wall at 17 m (inside the 20 m grid, beyond the 15 m rays) and one far outside the grid.
    pts = np.concatenate([wall_points(17.03, -2.0, 2.0), wall_points(-60.0, -30, 30, step=0.5)])
    res = ray_ilm_with_stats(to_sensor(pts), LIDAR)
    x, y = cell_centres()
    assert (res.masses[..., 1] > 0).sum() > 0
    assert np.all(np.abs(x[res.masses[..., 1] > 0] - 17.03) < RES)
    # between 15 m and the wall: no free cell
    assert not (res.masses[(x > 15.6) & (x < 17.0) & (np.abs(y) < 1)][..., 0] > 0).any()
    # behind the ego the rays reach 15 m although the wall is at 60 m
    back = (x < 0.5 - 13.0) & (x > 0.5 - 14.8) & (np.abs(y) < 1)
    assert is_mass(res.masses[back], FREE).all()
    # points absurdly far away do not break the kernel
    far = ray_ilm(to_sensor(np.array([[1e7, 1e7, 1.0], [-1e30, 0, 1.0]])), LIDAR)
    assert not (far[..., 1] > 0).any()


def test_return_in_the_sensors_own_cell_does_not_blank_the_grid():
    # the lidar (0.5, 0) m is in cell (249, 256); so is a return at (0.51, -0.01) m
    pts = np.array([[0.51, -0.01, 1.0], [8.03, 0.03, 1.0]])
    m = ray_ilm(to_sensor(pts), LIDAR)
    r, c = GRID.xy_to_cell(pts[:, 0], pts[:, 1])
    assert (r[0], c[0]) == (249, 256)
    assert (m[r, c, 1] > 0).all()
    x, y = cell_centres()
    assert is_mass(m[(np.hypot(x - 0.5, y) < 14.8) & (x < -1.0)], FREE).all()


def test_min_range_ignores_returns_on_the_vehicle():
    # a return on the vehicle's own roof 0.8 m behind the lidar blocks the rays behind it...
    # (cell (259, 256), right behind the lidar's cell (249, 256); its shadow covers column 256)
    pts = np.array([[-0.3, -0.01, 1.6], [8.03, 0.03, 1.0]])
    behind = (slice(265, 420), 256)  # x from -4.5 m to -16.6 m
    m = ray_ilm(to_sensor(pts), LIDAR)
    assert is_mass(m[behind], VAC).all()
    # ...unless returns closer than min_range_m to the lidar are ignored
    res = ray_ilm_with_stats(to_sensor(pts), LIDAR, params=RayIlmParams(min_range_m=1.0))
    assert is_mass(res.masses[behind], FREE).all()
    assert res.n_used == 1


def test_reference_pose_moves_points_and_origin():
    pts = wall_points(10.03, -2.0, 2.0)
    p1 = SE3.from_quaternion([1, 0, 0, 0], [100.0, 50.0, 0.0])
    p2 = SE3.from_quaternion([1, 0, 0, 0], [103.125, 50.0, 0.0])  # 3.125 m = 40 cells further ahead
    sweep = LidarSweep(to_sensor(pts), LIDAR, p1, 0)
    own = ray_ilm(sweep)
    moved = ray_ilm(sweep, reference_pose=p2)
    r, c = np.nonzero(own[..., 1] > 0)
    r2, c2 = np.nonzero(moved[..., 1] > 0)
    assert np.array_equal(c, c2) and np.array_equal(r2, r + 40)
    with pytest.raises(ValueError, match="ego_pose"):
        ray_ilm(to_sensor(pts), LIDAR, reference_pose=p2)


def test_sweep_and_raw_arrays_agree():
    pts = to_sensor(wall_points(7.03, -3.0, 1.0))
    pose = SE3.from_quaternion([math.cos(0.2), 0, 0, math.sin(0.2)], [5.0, -3.0, 0.1])
    a = ray_ilm(LidarSweep(pts, LIDAR, pose, 0))
    b = ray_ilm(pts, LIDAR, pose)
    c = ray_ilm(pts[:, :3].astype(np.float64), LIDAR)
    assert np.array_equal(a, b) and np.array_equal(a, c)


# --- an independent slow reference on a realistic scan -------------------------------------------


def street_world() -> np.ndarray:
    """Boxes [x0, y0, z0, x1, y1, z1] (m) of a small street, in the global frame."""
    return np.array(
        [
            [-40, 9.0, 0, 40, 15, 10],  # facade left
            [-40, -15, 0, 3, -7.5, 8],  # facade right, with a gap
            [7, -15, 0, 40, -7.5, 8],
            [4.0, 3.0, 0, 8.5, 4.8, 1.6],  # parked car
            [-9.0, 3.2, 0, -4.5, 5.0, 1.5],
            [11.0, -1.2, 0, 15.0, 1.2, 3.2],  # van ahead
            [-3.0, -5.5, 0, -2.7, -5.2, 4.0],  # pole
            [2.0, -6.0, 0.0, 2.6, -5.4, 0.8],  # a low bin
        ],
        dtype=np.float64,
    )


def reference_ilm(
    points_ego: np.ndarray, origin_xy: tuple[float, float], grid: GridSpec, p: RayIlmParams
) -> np.ndarray:
    """Pure numpy ray ILM: exact segment/grid-line intersections per ray, no DDA. Labels 0/1/2."""
    n = grid.n_cells
    res = grid.resolution
    keep = (points_ego[:, 2] >= p.z_min_m) & (points_ego[:, 2] <= p.z_max_m)
    r, c = grid.xy_to_cell(points_ego[keep, 0], points_ego[keep, 1])
    inside = grid.contains_cell(r, c)
    labels = np.zeros((n, n), np.uint8)
    labels[r[inside], c[inside]] = 2
    # continuous coordinates with cell edges at integers: u = n/2 - x/res
    o = np.array([n / 2 - origin_xy[0] / res, n / 2 - origin_xy[1] / res])
    own = tuple(np.floor(o).astype(int))
    length = p.max_range_m / res
    for k in range(p.n_rays):
        th = 2 * np.pi * k / p.n_rays
        d = np.array([-np.cos(th), -np.sin(th)])
        end = o + length * d
        ts = [np.array([0.0, length])]
        for ax in range(2):
            if abs(d[ax]) < 1e-15:
                continue
            lo, hi = sorted((o[ax], end[ax]))
            lines = np.arange(np.ceil(lo), np.floor(hi) + 1)
            ts.append((lines - o[ax]) / d[ax])
        t = np.unique(np.concatenate(ts))
        t = t[(t >= 0) & (t <= length)]
        mid = o[None, :] + 0.5 * (t[1:] + t[:-1])[:, None] * d[None, :]
        cells = np.floor(mid).astype(int)
        ok = ((cells >= 0) & (cells < n)).all(1)
        # the segment leaves the grid for good at the first outside piece
        if not ok.all():
            cells = cells[: np.argmin(ok)] if ok[0] else cells[:0]
        for cr, cc in cells:
            if labels[cr, cc] == 2:
                if (cr, cc) != own:
                    break
            else:
                labels[cr, cc] = 1
    return labels


def test_agrees_with_slow_reference_on_realistic_scan():
    ego = SE3.from_quaternion([math.cos(0.15), 0, 0, math.sin(0.15)], [1.5, -0.7, 0.0])
    pts = cast_lidar(ego @ LIDAR, street_world(), seed=3)
    assert 30_000 < len(pts) < 36_000  # a 32-beam, ~1085-step sweep
    p = RayIlmParams()
    res = ray_ilm_with_stats(LidarSweep(pts, LIDAR, ego, 0), params=p)
    labels = np.select([res.masses[..., 1] > 0, res.masses[..., 0] > 0], [2, 1], 0)
    ref = reference_ilm(LIDAR.apply(pts[:, :3]), SENSOR_XY, GRID, p)
    assert np.array_equal(labels == 2, ref == 2)  # detections: same cells exactly
    assert (ref == 1).sum() > 30_000 and (ref == 2).sum() > 1_000
    agree = (labels == ref).mean()
    assert agree >= 0.98
    # in fact the two differ only where a ray grazes a cell corner
    assert (labels != ref).sum() < 50
    # ground hits are there and filtered
    assert res.n_used < 0.7 * res.n_points


# --- bad input ---------------------------------------------------------------------------------


def test_nan_and_inf_points_are_dropped_counted_and_logged_once(caplog):
    pts = to_sensor(wall_points(10.03, -1.0, 1.0))
    clean = ray_ilm(pts, LIDAR)
    bad = np.concatenate([pts, pts[:7]])
    bad[-7:-4, 0] = np.nan
    bad[-4:-2, 1] = np.inf
    bad[-2:, 2] = -np.inf
    with caplog.at_level(logging.WARNING, logger="evgrid.ism.lidar"):
        res = ray_ilm_with_stats(bad, LIDAR)
    assert isinstance(res, IsmResult)
    assert res.n_dropped == 7 and res.n_points == len(bad) and res.n_used == len(pts)
    assert np.array_equal(res.masses, clean)
    msgs = [r for r in caplog.records if r.name == "evgrid.ism.lidar"]
    assert len(msgs) == 1 and "7" in msgs[0].getMessage()


def test_empty_or_all_nan_sweep_is_vacuous():
    for pts in (np.zeros((0, 5), np.float32), np.full((10, 5), np.nan, np.float32)):
        res = ray_ilm_with_stats(LidarSweep(pts, LIDAR, SE3.identity(), 0))
        assert is_mass(res.masses, VAC).all()
        assert res.n_used == 0 and res.n_dropped == len(pts)


@pytest.mark.parametrize("shape", [(10,), (10, 2), (2, 10, 3), ()])
def test_bad_shape_raises_valueerror_naming_it(shape):
    with pytest.raises(ValueError, match=re.escape(str(shape))):
        ray_ilm(np.zeros(shape, np.float32), LIDAR)


def test_bad_arguments_raise_clear_errors():
    pts = to_sensor(wall_points(5.03, -1, 1))
    with pytest.raises(ValueError, match="not both"):
        ray_ilm(LidarSweep(pts, LIDAR, SE3.identity(), 0), LIDAR)
    with pytest.raises(ValueError, match="real numbers"):
        ray_ilm(np.array([["a", "b", "c"]]), LIDAR)
    with pytest.raises(ValueError, match="threads"):
        ray_ilm(pts, LIDAR, threads=0)
    with pytest.raises(ValueError, match="out must be"):
        ray_ilm(pts, LIDAR, out=np.zeros((512, 512, 3), np.float64))
    for kw in (
        {"z_min_m": 3.0, "z_max_m": 0.3},
        {"max_range_m": 0.0},
        {"m_free": 1.5},
        {"angular_resolution_deg": 0.0},
        {"m_occupied": float("nan")},
    ):
        with pytest.raises(ValueError, match="RayIlmParams"):
            RayIlmParams(**kw)


# --- output, threads, simplex
# ----------------------------------------------------------------------


def test_out_buffer_is_filled_and_returned():
    pts = to_sensor(wall_points(10.03, -4.0, 4.0))
    out = np.full((512, 512, 3), 7.0, np.float32)
    m = ray_ilm(pts, LIDAR, out=out)
    assert m is out
    assert np.array_equal(out, ray_ilm(pts, LIDAR))


def test_threads_give_the_same_grid_and_restore_numba_threads():
    ego = SE3.identity()
    pts = cast_lidar(ego @ LIDAR, street_world(), seed=1)
    before = numba.get_num_threads()
    one = ray_ilm(pts, LIDAR, threads=1)
    two = ray_ilm(pts, LIDAR, threads=2)
    many = ray_ilm(pts, LIDAR, threads=64)  # clamped to numba's pool
    assert np.array_equal(one, two) and np.array_equal(one, many)
    assert numba.get_num_threads() == before


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-30, 30), st.floats(-30, 30), st.floats(-1, 4)), min_size=0, max_size=60
    ),
    st.floats(-2, 2),
    st.floats(-2, 2),
)
def test_masses_on_simplex_and_detections_exact(points, sx, sy):
    grid = GridSpec(64, 10.0)
    s2e = SE3.from_quaternion([1, 0, 0, 0], [sx, sy, 1.5])
    pts = np.array(points, dtype=np.float32).reshape(-1, 3)
    m = ray_ilm(pts, s2e, grid=grid)
    assert m.dtype == np.float32 and m.shape == (64, 64, 3)
    assert (m >= 0).all() and (m <= 1).all()
    assert np.allclose(m.sum(-1), 1.0, atol=1e-6)
    e = s2e.apply(pts)
    keep = (e[:, 2] >= 0.3) & (e[:, 2] <= 3.0)
    keep &= (pts.astype(np.float64) ** 2).sum(axis=1) >= 1e-3**2  # else no return (1 mm)
    r, c = grid.xy_to_cell(e[keep, 0], e[keep, 1])
    inside = grid.contains_cell(r, c)
    expect = np.zeros((64, 64), bool)
    expect[r[inside], c[inside]] = True
    assert np.array_equal(m[..., 1] > 0, expect)
    if len(pts) == 0:
        assert (m[..., 2] == 1).all()
