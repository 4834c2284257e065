"""Irregular simulated towns: the warp that bends the streets, and what the towns hold
(diagonal avenues, open squares, parking lots, parks, roundabouts), with nothing overlapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid_sim import SimConfig, WorldConfig
from evgrid_sim import materials as M
from evgrid_sim.raycast import pack_boxes
from evgrid_sim.trajectory import Warp
from evgrid_sim.world import _aabbs, _ego_boxes, _overlap, _touch, generate_world, plan_drive

SEEDS = range(12)


def _cfg(duration: float = 8.0, env: str = "mixed", layout: str = "irregular") -> SimConfig:
    return SimConfig(duration_s=duration, world=WorldConfig(environment=env, layout=layout))


@pytest.fixture(scope="module")
def worlds():
    return {seed: generate_world(seed, _cfg()) for seed in SEEDS}


def _to_city(world, xy: np.ndarray) -> np.ndarray:
    """Global points -> the unwarped city frame the layout is recorded in."""
    c = world.city_to_global.inverse().apply(xy)
    ux, uy = world.layout.warp.inverse(c[:, 0], c[:, 1])
    return np.stack([ux, uy], 1)


def _to_global(world, xy: np.ndarray) -> np.ndarray:
    wx, wy = world.layout.warp.apply(xy[:, 0], xy[:, 1])
    return world.city_to_global.apply(np.stack([wx, wy], 1))


def _inside(boxes: np.ndarray, xy: np.ndarray, margin: float) -> np.ndarray:
    """Which points lie within ``margin`` of a box footprint?"""
    d = xy[:, None, :] - boxes[None, :, :2]
    u = np.abs(d[..., 0] * boxes[:, 2] + d[..., 1] * boxes[:, 3])
    v = np.abs(-d[..., 0] * boxes[:, 3] + d[..., 1] * boxes[:, 2])
    return ((u <= boxes[:, 4] + margin) & (v <= boxes[:, 5] + margin)).any(1)


def _shrunk(p: np.ndarray, by: float) -> np.ndarray:
    return pack_boxes(
        p[:, 0],
        p[:, 1],
        np.arctan2(p[:, 3], p[:, 2]),
        np.maximum(p[:, 4] - by, 0.02),
        np.maximum(p[:, 5] - by, 0.02),
        p[:, 6],
        p[:, 7],
    )


def _any_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    ia, ib = np.nonzero(_touch(_aabbs(a)[:, None, :], _aabbs(b)[None, :, :]))
    return bool(len(ia)) and bool(_overlap(a[ia], b[ib]).any())


# --- the warp ----------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_warp_never_folds_and_inverts(seed):
    w = Warp.draw(np.random.default_rng(seed))
    x, y = np.meshgrid(np.linspace(-3000, 3000, 61), np.linspace(-3000, 3000, 61))
    a, b = w.jacobian(x, y)
    assert (1.0 - a * b).min() > 0.9  # determinant: never folds, barely changes areas
    assert max(abs(w.ax * w.kx), abs(w.ay * w.ky)) <= Warp.MAX_SLOPE
    assert max(abs(w.ax), abs(w.ay)) <= 20.0
    ux, uy = w.inverse(*w.apply(x, y))
    np.testing.assert_allclose(ux, x, atol=1e-6)
    np.testing.assert_allclose(uy, y, atol=1e-6)


# --- the ego's drive ---------------------------------------------------------------------------
def test_streets_are_curved():
    """Between turns the grid town's heading is constant; the irregular town's keeps changing."""
    curved = straight = 0
    for seed in range(6):
        fracs = []
        for layout in ("irregular", "grid"):
            _, _, _, traj = plan_drive(seed, _cfg(20.0, layout=layout))
            s = traj.s_at(np.arange(0.0, 20.0, 0.1))
            k = np.abs(np.interp(s, traj.path_s, traj.path_kappa))
            fracs.append(
                float(((k > 1e-4) & (k < 0.02)).mean())
            )  # bending gently, not a turn at a corner
        curved += fracs[0] > 0.5
        straight += fracs[1] < 0.05  # only where the speed profile samples the end of a corner arc
    assert curved >= 5 and straight == 6


def test_warped_worlds_do_not_overlap(worlds):
    """The ego never drives into a static box, and movers overlap neither the ego, nor each
    other, nor static boxes (0.1 m tolerance), at times between the builder's samples."""
    for seed, (w, traj, _) in worlds.items():
        static = w.boxes[(w.boxes[:, 6] < 1.6) & (w.boxes[:, 7] > 0.2)]
        ts = np.arange(0.0, 8.0, 0.13)
        ego = _ego_boxes(traj, ts, margin=-0.1)
        assert not _any_overlap(ego, static), seed
        for k, t in enumerate(ts[::3]):
            boxes, _, _ = w.movers.state_at(float(t), traj)
            m = _shrunk(boxes, 0.1)
            assert not _any_overlap(m, ego[3 * k : 3 * k + 1]), (seed, t)
            ia, ib = np.nonzero(np.triu(_touch(_aabbs(m)[:, None, :], _aabbs(m)[None, :, :]), 1))
            assert not _overlap(m[ia], m[ib]).any(), (seed, t)
            low = w.boxes[(w.boxes[:, 6] < 1.0) & (w.boxes[:, 7] > 0.1)]
            assert not _any_overlap(m, _shrunk(low, 0.05)), (seed, t)


# --- what the towns hold -----------------------------------------------------------------------
def test_a_diagonal_junction_has_more_than_four_arms(worlds):
    n_checked = 0
    for seed, (w, _, _) in worlds.items():
        for x, y, angle, hw, _ in w.layout.avenues:
            arms = [k * math.pi / 2 for k in range(4)] + [angle, angle + math.pi]
            gaps = np.diff(np.sort(np.mod(arms, 2 * math.pi)))
            assert gaps.min() > math.radians(20)
            near = w.boxes[(w.boxes[:, 6] < 3.0) & (w.boxes[:, 7] > 0.3)]
            for a in arms:
                r = np.arange(14.0, 42.0, 2.0)
                pts = _to_global(w, np.stack([x + r * math.cos(a), y + r * math.sin(a)], 1))
                assert not _inside(near, pts, 0.5).any(), (seed, math.degrees(a))
            n_checked += 1
    assert n_checked >= 2


def test_squares_lots_parks_roundabouts_appear(worlds):
    total = dict(avenues=0, squares=0, parking_lots=0, parks=0, roundabouts=0)
    for w, _, _ in worlds.values():
        for k, v in w.layout.counts().items():
            total[k] += v
        city = _to_city(w, w.boxes[:, :2])

        def in_rect(r, klass):
            x0, y0, x1, y1 = r
            sel = (city[:, 0] > x0) & (city[:, 0] < x1) & (city[:, 1] > y0) & (city[:, 1] < y1)
            return int((sel & np.isin(w.classes, klass)).sum())

        for r in w.layout.parking_lots:
            assert in_rect(r, [M.CAR, M.TRUCK]) >= 4
        for r in w.layout.squares:
            assert in_rect(r, [M.POLE]) >= 2 and in_rect(r, [M.BUILDING]) <= 1
        for r in w.layout.parks:
            assert in_rect(r, [M.CANOPY]) >= 3
        for x, y, rad in w.layout.roundabouts:
            d = np.hypot(city[:, 0] - x, city[:, 1] - y)
            assert (
                (d > rad - 0.5) & (d < rad + 0.5) & (w.classes == M.BARRIER)
            ).sum() >= 8  # the island's curb
            ring = (d > rad + 0.5) & (d < rad + 7.0) & (w.boxes[:, 7] > 0.3)
            assert not ring.any()  # the circulating carriageway is clear
    assert all(v >= 2 for v in total.values()), total


def test_grid_layout_is_the_plain_grid():
    w, _, _ = generate_world(2, _cfg(3.0, layout="grid"))
    assert w.layout is None and w.movers.warp is None
    yaw = np.mod(np.arctan2(w.boxes[:, 3], w.boxes[:, 2]) - w.city_to_global.yaw, math.pi / 2)
    b = w.classes == M.BUILDING
    assert np.minimum(yaw[b], math.pi / 2 - yaw[b]).max() < 0.2  # buildings face the grid


def test_bad_layout_is_named():
    with pytest.raises(ValueError, match="WorldConfig.layout"):
        WorldConfig(layout="spiral")


def test_warped_movers_move_as_their_velocity_says(worlds):
    """Positions, velocities and yaw of bent movers agree (radar Doppler uses the velocities)."""
    w, traj, _ = worlds[0]
    assert w.movers.warp is not None
    dt = 0.01
    b0, v0, yaw0 = w.movers.state_at(2.0, traj)
    b1, _, _ = w.movers.state_at(2.0 + dt, traj)
    moving = np.hypot(v0[:, 0], v0[:, 1]) > 1.0
    assert moving.sum() >= 5
    np.testing.assert_allclose((b1[moving, :2] - b0[moving, :2]) / dt, v0[moving], atol=0.02)
    heading = np.arctan2(v0[moving, 1], v0[moving, 0])
    np.testing.assert_allclose(np.cos(heading - yaw0[moving]), 1.0, atol=1e-6)
