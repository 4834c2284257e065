"""Ray IRM (paper sec. V-B): cone geometry, barriers, moving sensors, a dense reference, bad
input."""

from __future__ import annotations

import logging
import math
import re

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid.data import RadarBuffer
from evgrid.data.frame import RADAR_COLUMNS, Frame, LidarSweep, RadarSweep
from evgrid.geometry import SE3, GridSpec
from evgrid.ism import IsmResult, RayIrmParams, ray_irm, ray_irm_with_stats, ray_irm_xy
from evgrid_sim.synthetic import street_radar_sweeps

GRID = GridSpec()
RES = GRID.resolution
WIDE = GridSpec(768, 60.0)  # same 0.078125 m cells, room for a 28 m cone
FREE = np.array([0.3, 0.0, 0.7], dtype=np.float32)
OCC = np.array([0.0, 0.5, 0.5], dtype=np.float32)
VAC = np.array([0.0, 0.0, 1.0], dtype=np.float32)
HALF = math.radians(1.0)  # half the 2-degree opening


def is_mass(m: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.all(m == ref, axis=-1)


def corners_polar(grid: GridSpec, apex: tuple[float, float], axis_deg: float = 0.0):
    """Per cell: (min, max) range (m) and (min, max) angle (rad, from ``axis_deg``) over its 4
    corners."""
    n, res = grid.n_cells, grid.resolution
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x0, y0 = grid.cell_to_xy(r, c)
    rho, ang = [], []
    for dx in (-0.5, 0.5):
        for dy in (-0.5, 0.5):
            px, py = x0 + dx * res - apex[0], y0 + dy * res - apex[1]
            rho.append(np.hypot(px, py))
            ang.append(np.angle(np.exp(1j * (np.arctan2(py, px) - math.radians(axis_deg)))))
    rho, ang = np.stack(rho), np.stack(ang)
    return rho.min(0), rho.max(0), ang.min(0), ang.max(0)


def inside(polar, r0: float, r1: float, a0_deg: float, a1_deg: float) -> np.ndarray:
    """Cells lying wholly inside range [r0, r1] m and angle [a0, a1] degrees."""
    rmin, rmax, amin, amax = polar
    return (
        (rmin >= r0)
        & (rmax <= r1)
        & (amin >= math.radians(a0_deg))
        & (amax <= math.radians(a1_deg))
    )


def touching(polar, r0: float, r1: float, a0_deg: float, a1_deg: float) -> np.ndarray:
    """Cells whose corner hull overlaps range [r0, r1] and angle [a0, a1] (a superset of the cells
    touched)."""
    rmin, rmax, amin, amax = polar
    return (
        (rmax >= r0)
        & (rmin <= r1)
        & (amax >= math.radians(a0_deg))
        & (amin <= math.radians(a1_deg))
    )


# --- cone geometry -------------------------------------------------------------------------------


@pytest.mark.parametrize("rng_m", [5.0, 25.0])
def test_cone_width_is_2_degrees_within_one_cell(rng_m):
    m = ray_irm_xy(np.array([[28.03, 0.0]]), np.array([0.0, 0.0]), grid=WIDE).masses
    x, _ = WIDE.cell_to_xy(np.arange(WIDE.n_cells), np.zeros(WIDE.n_cells))
    row = int(np.argmin(np.abs(x - rng_m)))
    cols = np.flatnonzero(m[row, :, 0] > 0)
    expected = 2 * x[row] * math.tan(HALF) / RES  # cells
    assert abs((len(cols) - 1) - expected) <= 1.0  # distance between the outer cell centres
    assert np.array_equal(cols, np.arange(cols[0], cols[-1] + 1))  # one run, no gaps
    assert is_mass(m[row, cols], FREE).all()


def test_cone_has_no_gaps_at_any_range_and_stays_inside_its_sector():
    # An oblique cone 26 m long: every cell wholly inside the sector (before the cap) is free,
    # and no free cell lies outside it.
    ang = 37.0
    det = 26.0 * np.array([math.cos(math.radians(ang)), math.sin(math.radians(ang))])
    apex = (-9.0, -7.0)
    m = ray_irm_xy((np.array(apex) + det)[None], np.array(apex), grid=WIDE).masses
    polar = corners_polar(WIDE, apex, ang)
    must = inside(polar, 0.0, 26.0 - RES, -1.0, 1.0)
    assert must.sum() > 1000  # of the sector's ~1900 cells
    assert is_mass(m[must], FREE).all()
    free = m[..., 0] > 0
    assert not (free & ~touching(polar, 0.0, 26.0, -1.0, 1.0)).any()
    # the oblique width at 20 m: the angular spread of the free cells' centres, within sqrt(2) cells
    rmin, rmax, amin, amax = polar
    ring = free & (rmin > 19.9) & (rmax < 20.2)
    r, c = np.nonzero(ring)
    cx, cy = WIDE.cell_to_xy(r, c)
    a = np.arctan2(cy - apex[1], cx - apex[0])
    width_cells = (a.max() - a.min()) * 20.05 / RES
    assert abs(width_cells - 2 * 20.05 * math.tan(HALF) / RES) <= math.sqrt(2)


def test_near_cap_blocks_far_cone_behind_it_and_nowhere_else_same_sensor():
    # A at 8 m on the axis; B at 16 m, 1.07 degrees off it. B's rays from 0.07 to 1 degree meet
    # A's cap at 8 m; the rest of B reaches 16 m.
    det = np.array([[8.0, 0.0], [16.0, 0.3]])
    res = ray_irm_xy(det, np.array([0.0, 0.0]))
    m = res.masses
    b_lo, b_hi = (
        math.degrees(math.atan2(0.3, 16.0)) - 1.0,
        math.degrees(math.atan2(0.3, 16.0)) + 1.0,
    )
    polar = corners_polar(GRID, (0.0, 0.0))
    shadow = inside(polar, 8.0 + 2 * RES, 16.0, b_lo, 1.0)
    lit_far = inside(polar, 8.0 + 2 * RES, 16.0 - 2 * RES, 1.0, b_hi)
    before = inside(polar, 0.2, 8.0 - 2 * RES, -1.0, b_hi)
    assert shadow.sum() > 100 and lit_far.sum() > 100
    assert is_mass(m[shadow], VAC).all()
    assert is_mass(m[lit_far], FREE).all()
    assert is_mass(m[before], FREE).all()
    # nowhere else: free only inside the two cones, occupied only on the two detections
    assert not ((m[..., 0] > 0) & ~touching(polar, 0.0, 16.0, -1.0, b_hi)).any()
    occ = np.zeros(GRID.shape, bool)
    occ[GRID.xy_to_cell(det[:, 0], det[:, 1])] = True
    assert np.array_equal(m[..., 1] > 0, occ)
    assert is_mass(m[occ], OCC).all()


def test_cap_of_another_sensors_cone_blocks_too():
    # A is seen by a second sensor 1 m to the right; its cap at 8 m crosses B's cone for B's
    # rays below ~1 degree (hand-computed: the cap spans y in [-0.14, 0.14] m at x = 8 m).
    det = np.array([[8.0, 0.0], [16.0, 0.3]])
    org = np.array([[0.0, -1.0], [0.0, 0.0]])
    m = ray_irm_xy(det, org).masses
    polar = corners_polar(GRID, (0.0, 0.0))
    b_lo = math.degrees(math.atan2(0.3, 16.0)) - 1.0
    assert is_mass(m[inside(polar, 9.0, 15.5, b_lo + 0.1, 0.85)], VAC).all()
    lit = inside(polar, 9.0, 15.5, 1.15, b_lo + 2.0)
    assert lit.sum() > 20
    assert is_mass(m[lit], FREE).all()
    # without A, the same region of B is free
    alone = ray_irm_xy(det[1:], org[1:]).masses
    assert is_mass(alone[inside(polar, 9.0, 15.5, b_lo + 0.1, 0.85)], FREE).all()


def test_detection_beyond_the_grid_casts_to_the_edge():
    m = ray_irm_xy(np.array([[60.0, 0.03]]), np.array([0.0, 0.0])).masses
    assert not (m[..., 1] > 0).any()
    assert is_mass(m[0:250, 255:257], FREE).all()  # from the front edge (x = 20 m) to the sensor
    assert is_mass(m[300:, :], VAC).all()
    # absurd ranges are clamped, not overflowed: the same cone to the edge
    far = ray_irm_xy(
        np.array([[1e30, 0.03 * 1e30 / 60.0], [5.0, 1e250]]), np.array([0.0, 0.0])
    ).masses
    assert is_mass(far[0:250, 255:257], FREE).all() and not (far[..., 1] > 0).any()


def test_detection_in_another_sensors_cell_is_occupied_and_does_not_stop_that_sensor():
    # Cell (229, 229) has its centre at (2.0703, 2.0703) m. Sensor A, 1 m behind, sees a target
    # there (its cap, 3.5 cm long, stays inside that cell); sensor B sits in the same cell.
    ctr = (256 - 229.5) * RES
    det = np.array([[ctr, ctr], [16.0, ctr + 0.01]])
    org = np.array([[ctr - 1.0, ctr], [ctr + 0.01, ctr + 0.01]])
    m = ray_irm_xy(det, org).masses
    assert is_mass(m[229, 229], OCC)  # detections win over the free mark of B's cone
    polar = corners_polar(GRID, (ctr + 0.01, ctr + 0.01))
    lit = inside(polar, 0.2, 13.5, -0.9, 0.9)
    assert lit.sum() > 100
    assert is_mass(m[lit], FREE).all()


# --- sweeps, poses, buffer
# -------------------------------------------------------------------------


def radar_sweep(
    xy_sensor, sensor_to_ego: SE3, ego_pose: SE3, t: int, channel: str = "RADAR_FRONT"
) -> RadarSweep:
    xy = np.asarray(xy_sensor, dtype=np.float32).reshape(-1, 2)
    pts = np.zeros((len(xy), len(RADAR_COLUMNS)), dtype=np.float32)
    pts[:, :2] = xy
    return RadarSweep(pts, sensor_to_ego, ego_pose, t, channel)


FRONT = SE3.from_quaternion([1, 0, 0, 0], [3.5, 0.0, 0.5])


def yaw_pose(x: float, y: float, yaw_deg: float) -> SE3:
    h = math.radians(yaw_deg) / 2
    return SE3.from_quaternion([math.cos(h), 0, 0, math.sin(h)], [x, y, 0.0])


def test_sweeps_from_a_moving_sensor_cast_from_their_own_positions():
    # 0.8 s ago the ego was 6 m back: that sweep's sensor was at (-2.5, 0) in today's frame and
    # saw a target at (12, 3) in its own frame = (9.5, 3) today. Today's sweep, from (3.5, 0),
    # sees (6, -4) = (9.5, -4).
    old = radar_sweep([[12.0, 3.0]], FRONT, yaw_pose(-6.0, 0.0, 0.0), 0)
    new = radar_sweep([[6.0, -4.0]], FRONT, yaw_pose(0.0, 0.0, 0.0), 800_000)
    res = ray_irm_with_stats([new, old], SE3.identity())
    m = res.masses
    assert res.n_points == 2 and res.n_used == 2 and res.n_dropped == 0

    def at(x, y):
        r, c = GRID.xy_to_cell(np.array([x]), np.array([y]))
        return m[r[0], c[0]]

    assert is_mass(at(9.5, 3.0), OCC) and is_mass(at(9.5, -4.0), OCC)
    # along the old cone, from the old sensor position: (x, 3 (x + 2.5) / 12)
    for x in (-2.0, 0.0, 3.5, 6.5, 9.0):
        assert is_mass(at(x, 3.0 * (x + 2.5) / 12.0), FREE), x
    # where the cone would be if cast from today's sensor position: nothing
    assert is_mass(at(6.5, 1.5), VAC)
    for x in (4.0, 6.5, 9.0):
        assert is_mass(at(x, -4.0 * (x - 3.5) / 6.0), FREE), x


def test_rotated_and_translated_sweeps_are_moved_into_the_current_frame():
    # A left radar (yaw 90 deg), ego turning: global = ego o s2e o p; local = current^-1 o global.
    s2e = yaw_pose(2.4, 0.8, 90.0)
    pose_then = yaw_pose(10.0, 5.0, 30.0)
    pose_now = yaw_pose(12.0, 6.5, 40.0)
    p_sensor = np.array([[7.0, 1.0, 0.0]])
    sweep = radar_sweep(p_sensor[:, :2], s2e, pose_then, 0, "RADAR_FRONT_LEFT")
    m = ray_irm([sweep], pose_now)
    to_now = pose_now.inverse() @ pose_then @ s2e
    det = to_now.apply(p_sensor)[0, :2]
    apex = to_now.translation[:2]
    r, c = GRID.xy_to_cell(np.array([det[0]]), np.array([det[1]]))
    assert is_mass(m[r[0], c[0]], OCC)
    assert (m[..., 1] > 0).sum() == 1
    for f in (0.15, 0.5, 0.85):
        p = apex + f * (det - apex)
        r, c = GRID.xy_to_cell(np.array([p[0]]), np.array([p[1]]))
        assert is_mass(m[r[0], c[0]], FREE), f


def test_only_the_last_n_sweeps_per_channel_are_used():
    sweeps = [radar_sweep([[5.0 + k, 0.0]], FRONT, SE3.identity(), 1000 * k) for k in range(12)]
    sweeps.append(radar_sweep([[-5.0, 0.0]], FRONT, SE3.identity(), 0, "RADAR_BACK_LEFT"))
    res = ray_irm_with_stats(sweeps[::-1], SE3.identity())  # any order
    assert res.n_points == 11  # 10 front sweeps (x = 7..16 m) and the back one
    r, c = GRID.xy_to_cell(np.array([8.5, 9.5, 3.5 + 7.0]), np.array([0.0, 0.0, 0.0]))
    assert not (res.masses[r[:2], c[:2], 1] > 0).any()  # the two oldest: not detections
    assert res.masses[r[2], c[2], 1] > 0
    res3 = ray_irm_with_stats(sweeps, SE3.identity(), params=RayIrmParams(n_sweeps=3))
    assert res3.n_points == 4


def make_frame(k: int, sweeps: dict[str, tuple[RadarSweep, ...]]) -> Frame:
    lidar = LidarSweep(np.zeros((0, 5), np.float32), SE3.identity(), SE3.identity(), k)
    return Frame("scene", k, k, SE3.identity(), False, lidar, sweeps)


def test_radar_buffer_keeps_the_last_n_sweeps_per_channel():
    buf = RadarBuffer(n_sweeps=3)
    for k in range(5):
        front = radar_sweep([[5.0, 0.0]], FRONT, SE3.identity(), 10 * k)
        back = radar_sweep([[1.0, 0.0]], FRONT, SE3.identity(), 10 * k + 1, "RADAR_BACK_RIGHT")
        buf.update(
            make_frame(
                k,
                {"RADAR_FRONT": (front,), "RADAR_BACK_RIGHT": (back,)}
                if k % 2 == 0
                else {"RADAR_FRONT": (front,)},
            )
        )
    held = buf.sweeps()
    assert [s.timestamp for s in held if s.channel == "RADAR_FRONT"] == [20, 30, 40]
    assert [s.timestamp for s in held if s.channel == "RADAR_BACK_RIGHT"] == [1, 21, 41]
    assert len(buf) == 6 and list(buf) == held
    buf.push(held[-1])  # the same sweep again: ignored
    assert len(buf) == 6
    assert np.array_equal(ray_irm(buf, SE3.identity()), ray_irm(held, SE3.identity()))
    buf.clear()
    assert len(buf) == 0
    with pytest.raises(ValueError, match="n_sweeps"):
        RadarBuffer(0)
    with pytest.raises(TypeError):
        buf.update("not a frame")


# --- a dense numerical reference -----------------------------------------------------------------


def dense_reference(
    det_xy: np.ndarray, org_xy: np.ndarray, grid: GridSpec
) -> tuple[np.ndarray, np.ndarray]:
    """Ray IRM by brute force: caps sampled every 0.002 cells, cones as sub-rays 0.05 cells apart
    (at their far end) marched in 0.02-cell steps. Returns (free, occupied) masks."""
    n = grid.n_cells
    inv = 1 / grid.resolution
    duv = n / 2 - det_xy * inv
    ouv = n / 2 - org_xy * inv
    barrier = np.zeros((n, n), bool)
    cones = []
    for d, o in zip(duv, ouv):
        v = d - o
        r = float(np.hypot(*v))
        phi = math.atan2(v[1], v[0])
        cones.append((o, r, phi))
        b = np.linspace(-HALF, HALF, max(int(2 * HALF * r / 0.002), 2))
        p = o[None] + r * np.stack([np.cos(phi + b), np.sin(phi + b)], 1)
        c = np.floor(p).astype(int)
        ok = ((c >= 0) & (c < n)).all(1)
        barrier[c[ok, 0], c[ok, 1]] = True
    free = np.zeros((n, n), bool)
    for o, r, phi in cones:
        b = np.linspace(-HALF, HALF, max(int(2 * HALF * r / 0.05), 2))
        t = np.arange(0, r, 0.02)
        p = (
            o[None, None]
            + t[None, :, None] * np.stack([np.cos(phi + b), np.sin(phi + b)], 1)[:, None, :]
        )
        c = np.floor(p).astype(int)
        ins = ((c >= 0) & (c < n)).all(-1)
        cc = np.clip(c, 0, n - 1)
        own = np.floor(o).astype(int)
        bar = (
            barrier[cc[..., 0], cc[..., 1]] & ins & ~((c[..., 0] == own[0]) & (c[..., 1] == own[1]))
        )
        first = np.where(bar.any(1), bar.argmax(1), len(t))
        valid = (np.arange(len(t))[None] < first[:, None]) & ins
        free[c[valid][:, 0], c[valid][:, 1]] = True
    occ = np.zeros((n, n), bool)
    dc = np.floor(duv).astype(int)
    ok = ((dc >= 0) & (dc < n)).all(1)
    occ[dc[ok, 0], dc[ok, 1]] = True
    return free & ~occ, occ


@pytest.mark.parametrize("seed", [0, 1])
def test_agrees_with_dense_subray_reference(seed):
    grid = GridSpec(256, 20.0)
    rng = np.random.default_rng(seed)
    det, org = [], []
    for o in rng.uniform(-3, 3, (3, 2)):
        for _ in range(6):
            a, r = rng.uniform(-np.pi, np.pi), rng.uniform(1, 14)
            det.append(o + r * np.array([np.cos(a), np.sin(a)]))
            org.append(o)
    det, org = np.array(det), np.array(org)
    m = ray_irm_xy(det, org, grid=grid).masses
    free_ref, occ_ref = dense_reference(det, org, grid)
    free = m[..., 0] > 0
    assert np.array_equal(m[..., 1] > 0, occ_ref)
    assert free_ref.sum() > 2000
    assert not (free_ref & ~free).any()  # the exact cones cover every cell the sub-rays reach
    # ...and only a few more: cells whose corner a cone grazes between two sub-rays
    assert (free & ~free_ref).sum() <= 0.005 * free_ref.sum()


# --- bad input ---------------------------------------------------------------------------------


def test_nan_and_inf_detections_are_dropped_counted_and_logged_once(caplog):
    good = radar_sweep([[10.0, 1.0], [7.0, -2.0]], FRONT, SE3.identity(), 0)
    pts = np.concatenate([good.points, good.points, good.points[:1]])
    pts[2, 0], pts[3, 1], pts[4, 2] = np.nan, np.inf, -np.inf
    bad = RadarSweep(pts, FRONT, SE3.identity(), 0, "RADAR_FRONT")
    with caplog.at_level(logging.WARNING, logger="evgrid.ism.radar"):
        res = ray_irm_with_stats([bad], SE3.identity())
    assert isinstance(res, IsmResult)
    assert (res.n_points, res.n_dropped, res.n_used) == (5, 3, 2)
    assert np.array_equal(res.masses, ray_irm([good], SE3.identity()))
    msgs = [r for r in caplog.records if r.name == "evgrid.ism.radar"]
    assert len(msgs) == 1 and "3" in msgs[0].getMessage()
    res_xy = ray_irm_xy(np.array([[5.0, 0.0], [np.nan, 1.0]]), np.zeros(2))
    assert (res_xy.n_dropped, res_xy.n_used) == (1, 1)


def test_empty_input_is_vacuous():
    for sweeps in ([], [radar_sweep(np.zeros((0, 2)), FRONT, SE3.identity(), 0)]):
        res = ray_irm_with_stats(sweeps, SE3.identity())
        assert is_mass(res.masses, VAC).all() and res.n_points == 0
    assert is_mass(ray_irm_xy(np.zeros((0, 2)), np.zeros(2)).masses, VAC).all()


@pytest.mark.parametrize("shape", [(4, 3), (4,), (2, 4, 2)])
def test_bad_shape_raises_valueerror_naming_it(shape):
    with pytest.raises(ValueError, match=re.escape(str(shape))):
        ray_irm_xy(np.zeros(shape), np.zeros(2))


def test_bad_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match=re.escape("(3, 2)")):
        ray_irm_xy(np.zeros((4, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"\(n, 12\)"):
        RadarSweep(np.zeros((4, 5), np.float32), FRONT, SE3.identity(), 0, "RADAR_FRONT")
    with pytest.raises(TypeError, match="RadarSweep"):
        ray_irm([np.zeros((3, 12))], SE3.identity())
    with pytest.raises(TypeError, match="ego_pose"):
        ray_irm([], np.eye(4))
    with pytest.raises(ValueError, match="threads"):
        ray_irm([], SE3.identity(), threads=-1)
    with pytest.raises(ValueError, match="out must be"):
        ray_irm([], SE3.identity(), out=np.zeros((10, 10, 3), np.float32))
    for kw in (
        {"n_sweeps": 0},
        {"opening_angle_deg": 0.0},
        {"opening_angle_deg": 180.0},
        {"m_free": -0.1},
    ):
        with pytest.raises(ValueError, match="RayIrmParams"):
            RayIrmParams(**kw)


# --- realistic input: simplex, threads, parameters
# ---------------------------------------------------


def test_realistic_sweeps_masses_on_simplex_and_threads_agree():
    sweeps, now = street_radar_sweeps(seed=2)
    assert len(sweeps) == 50 and sum(len(s.points) for s in sweeps) == 5000
    before = numba.get_num_threads()
    res = ray_irm_with_stats(sweeps, now)
    m = res.masses
    assert m.dtype == np.float32 and m.shape == (512, 512, 3)
    assert np.allclose(m.sum(-1), 1.0, atol=1e-6) and (m >= 0).all() and (m <= 1).all()
    kinds = {tuple(v) for v in np.unique(m.reshape(-1, 3), axis=0)}
    assert kinds == {tuple(FREE), tuple(OCC), tuple(VAC)}
    out = np.empty_like(m)
    assert ray_irm(sweeps, now, threads=2, out=out) is out
    assert np.array_equal(out, m)
    assert numba.get_num_threads() == before


def test_masses_and_opening_are_parameters():
    p = RayIrmParams(opening_angle_deg=10.0, m_free=0.2, m_occupied=0.7)
    m = ray_irm_xy(np.array([[10.0, 0.03]]), np.zeros(2), params=p).masses
    r, c = GRID.xy_to_cell(np.array([10.0]), np.array([0.03]))
    assert np.allclose(m[r[0], c[0]], [0.0, 0.7, 0.3])
    row = GRID.xy_to_cell(np.array([8.0]), np.array([0.0]))[0][0]
    cols = np.flatnonzero(m[row, :, 0] > 0)
    assert abs((len(cols) - 1) - 2 * 7.96 * math.tan(math.radians(5)) / RES) <= 1.0
    assert np.allclose(m[row, cols], [0.2, 0.0, 0.8])


@pytest.mark.parametrize("opening", [60.0, 150.0])
def test_wide_cones_spanning_several_octants(opening):
    # cones wider than an octant take the general (trigonometric) split; check the sector
    apex, axis = (0.3, -0.2), 100.0
    det = np.array(apex) + 9.0 * np.array(
        [math.cos(math.radians(axis)), math.sin(math.radians(axis))]
    )
    m = ray_irm_xy(det[None], np.array(apex), params=RayIrmParams(opening_angle_deg=opening)).masses
    polar = corners_polar(GRID, apex, axis)
    half = opening / 2
    must = inside(polar, 0.0, 9.0 - RES, -half, half)
    assert must.sum() > 0.8 * math.radians(opening) * 81 / 2 / RES**2
    assert is_mass(m[must], FREE).all()
    assert not ((m[..., 0] > 0) & ~touching(polar, 0.0, 9.0, -half, half)).any()


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-12, 12), st.floats(-12, 12)), min_size=1, max_size=12),
    st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=1, max_size=3),
)
def test_property_simplex_detections_and_free_inside_cones(dets, orgs):
    grid = GridSpec(128, 20.0)
    det = np.array(dets)
    org = np.array([orgs[i % len(orgs)] for i in range(len(dets))])
    m = ray_irm_xy(det, org, grid=grid).masses
    assert np.allclose(m.sum(-1), 1.0, atol=1e-6) and (m >= 0).all()
    r, c = grid.xy_to_cell(det[:, 0], det[:, 1])
    ok = grid.contains_cell(r, c)
    occ = np.zeros(grid.shape, bool)
    occ[r[ok], c[ok]] = True
    assert np.array_equal(m[..., 1] > 0, occ)
    # every free cell is touched by some cone
    reach = np.zeros(grid.shape, bool)
    for d, o in zip(det, org):
        v = d - o
        rng_m = float(np.hypot(*v))
        polar = corners_polar(grid, tuple(o), math.degrees(math.atan2(v[1], v[0])))
        rmin = polar[0]
        reach |= touching(polar, 0.0, rng_m, -1.0, 1.0) | (
            rmin <= grid.resolution
        )  # (the apex's own cell)
    assert not ((m[..., 0] > 0) & ~reach).any()


def test_radar_buffer_skips_and_counts_duplicate_and_late_sweeps_of_any_channel():
    buf = RadarBuffer(n_sweeps=2)
    kept = [
        buf.push(radar_sweep([[5.0, 0.0]], FRONT, SE3.identity(), t, "corner_fl"))
        for t in (10, 20, 15, 20, 30)
    ]
    assert kept == [True, True, False, False, True]
    assert (buf.n_out_of_order, buf.n_duplicate) == (1, 1)
    assert [x.timestamp for x in buf.sweeps()] == [20, 30]
    assert [x.timestamp for x in buf.sweeps(1)] == [30]
    buf.push(radar_sweep([[5.0, 0.0]], FRONT, SE3.identity(), 5, "RADAR_FRONT"))
    assert buf.channels == ("RADAR_FRONT", "corner_fl")  # nuScenes' names first, then by name
