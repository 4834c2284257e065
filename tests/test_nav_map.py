"""The navigation map (issue 25): the lidar's evidence, with the radar and the prior filling
what the lidar has not seen; a cell the lidar saw occupied is never free
(docs/equations.md#the-navigation-map).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.classes import FREE, OCCUPIED
from evgrid.evaluate import classify
from evgrid.fusion import MAP_NAMES, RULES, FusionParams, MapSet, update_nav
from evgrid.geometry import SE2, GridSpec
from tests.strategies import random_masses


def cell(m) -> np.ndarray:
    return np.array(m, np.float32).reshape(1, 1, 3)


def nav_of(lidar, fused) -> np.ndarray:
    out = cell([0.0, 0.0, 1.0])
    assert update_nav(out, cell(lidar), cell(fused)) == 0
    return out[0, 0]


def test_lidar_occupied_dominant_ignores_the_fused_maps_free_mass():
    # L = [.1, .5, .4] (m_o > m_f), F = [.8, .1, .1]: F's free .8 counts as unknown, so
    # F' = [0, .1, .9]; Dempster: f = .1 * .9 = .09, o = .5 * .1 + .5 * .9 + .4 * .1 = .54,
    # u = .4 * .9 = .36, K = .1 * .1 = .01, divided by .99
    np.testing.assert_allclose(
        nav_of([0.1, 0.5, 0.4], [0.8, 0.1, 0.1]), np.array([0.09, 0.54, 0.36]) / 0.99, rtol=1e-6
    )


def test_lidar_free_dominant_ignores_the_fused_maps_occupied_mass():
    # L = [.3, 0, .7], F = [.2, .7, .1]: F' = [.2, 0, .8]; f = .3 * .2 + .3 * .8 + .7 * .2 = .44,
    # o = 0, u = .7 * .8 = .56, no conflict
    np.testing.assert_allclose(
        nav_of([0.3, 0.0, 0.7], [0.2, 0.7, 0.1]), [0.44, 0.0, 0.56], rtol=1e-6, atol=1e-7
    )


def test_where_the_lidar_saw_a_return_the_fused_map_adds_no_free_space():
    # L = [.3, .1, .6]: free-dominant, but the lidar saw a return here once (m_o > 0): F' holds
    # neither F's free mass nor its occupied mass, so nav is L
    np.testing.assert_allclose(nav_of([0.3, 0.1, 0.6], [0.8, 0.1, 0.1]), [0.3, 0.1, 0.6], rtol=1e-6)


def test_where_the_lidar_saw_nothing_nav_is_the_fused_map():
    np.testing.assert_allclose(nav_of([0.0, 0.0, 1.0], [0.6, 0.1, 0.3]), [0.6, 0.1, 0.3], rtol=1e-6)


def test_a_tie_in_the_lidar_evidence_takes_only_the_fused_maps_occupied_mass():
    # L = [.2, .2, .6], F = [.5, .3, .2]: F' = [0, .3, .7]; f = .2 * .7 = .14,
    # o = .2 * .3 + .2 * .7 + .6 * .3 = .38, u = .6 * .7 = .42, K = .2 * .3 = .06
    np.testing.assert_allclose(
        nav_of([0.2, 0.2, 0.6], [0.5, 0.3, 0.2]), np.array([0.14, 0.38, 0.42]) / 0.94, rtol=1e-6
    )


def test_nav_is_computed_when_asked_for_not_by_default():
    assert "nav" not in MAP_NAMES and "nav" in RULES
    assert RULES["nav"].isms == ("ray_ilm", "deep_irm", "ray_irm")
    grid = GridSpec(32, 4.0)
    ms = MapSet(grid, names=("nav",))
    assert tuple(ms.maps) == ("nav",) and ms.required_isms == ("ray_ilm", "ray_irm", "deep_irm")


def _isms(rng, grid):
    out = {}
    for k in ("ray_ilm", "ray_irm", "deep_irm"):
        m = random_masses(rng, grid.shape, p_edge=0.2)
        m[rng.random(grid.shape) < 0.3] = [0.0, 0.0, 1.0]
        out[k] = m
    return out


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    steps=st.integers(1, 6),
    m_u_min=st.floats(0.0, 0.9),
    tile_cells=st.sampled_from([8, 24, 256]),
)
def test_a_cell_the_lidar_saw_occupied_is_never_free_in_nav(seed, steps, m_u_min, tile_cells):
    """After any sequence of updates: where the lidar map's evidence is occupied-dominant
    (m_o > m_f), nav is not free; where the lidar map is free, nav is free (all its free space);
    and nav alone is the same map as nav beside the ray_ilm and fused maps."""
    grid = GridSpec(40, 4.0)
    rng = np.random.default_rng(seed)
    params = FusionParams(m_u_min=m_u_min)
    both = MapSet(grid, params, ("ray_ilm", "fused", "nav"), tile_cells)
    alone = MapSet(grid, params, ("nav",), tile_cells)
    for _ in range(steps):
        pose = SE2(*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi))
        isms = _isms(rng, grid)
        both.update(pose, isms)
        alone.update(pose, isms)
    lidar, cov, r0, c0 = both["ray_ilm"].to_dense()
    nav, nav_cov, r1, c1 = both["nav"].to_dense()
    assert (r0, c0) == (r1, c1)
    np.testing.assert_array_equal(cov, nav_cov)
    mass.validate(nav)
    occupied_dominant = cov & (lidar[..., 1] > lidar[..., 0])
    assert occupied_dominant.any()
    assert not (classify(nav)[occupied_dominant] == FREE).any()
    lidar_free = cov & (classify(lidar) == FREE)
    assert (classify(nav)[lidar_free] == FREE).all()
    assert (classify(nav)[cov & (classify(lidar) == OCCUPIED)] == OCCUPIED).all()
    np.testing.assert_array_equal(alone["nav"].to_dense()[0], nav)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), steps=st.integers(2, 6), show_lidar=st.booleans())
def test_with_the_gate_a_cell_the_lidar_map_calls_occupied_is_never_free_in_nav(
    seed, steps, show_lidar
):
    """With the dynamic score on, nav reads gated copies of its inputs (gate_nav): the gate may
    take a cell the (ungated) lidar map holds occupied-dominant to unknown, never to free; with
    the lidar map shown or kept hidden for nav alike."""
    from evgrid.fusion import DynamicParams

    grid = GridSpec(40, 4.0)
    rng = np.random.default_rng(seed)
    d = DynamicParams(decay=0.5, threshold=0.05)
    both = MapSet(grid, names=("ray_ilm", "fused", "nav"), dynamic=d)
    alone = MapSet(grid, names=("nav", "ray_ilm") if show_lidar else ("nav",), dynamic=d)
    plain = MapSet(grid, names=("ray_ilm",))  # the lidar map without any score or gate
    for _ in range(steps):
        pose = SE2(*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi))
        isms = _isms(rng, grid)
        for s in (both, alone, plain):
            s.update(pose, isms)
    lidar, cov, _, _ = plain["ray_ilm"].to_dense()
    nav = both["nav"].to_dense()[0]
    mass.validate(nav)
    occupied_dominant = cov & (lidar[..., 1] > lidar[..., 0])
    assert occupied_dominant.any()
    assert not (classify(nav)[occupied_dominant] == FREE).any()
    assert (nav[occupied_dominant][:, 0] == 0.0).all()
    np.testing.assert_array_equal(alone["nav"].to_dense()[0], nav)


def test_nav_holds_more_free_space_than_the_lidar_map():
    # the fused map fills cells the lidar did not see: not a copy of the lidar map
    grid = GridSpec(32, 4.0)
    ms = MapSet(grid, names=("ray_ilm", "nav"))
    lidar = mass.vacuous(grid.shape)
    lidar[:, :10] = [0.7, 0.0, 0.3]
    radar = mass.vacuous(grid.shape)
    radar[:, :20] = [0.6, 0.0, 0.4]
    ms.update(SE2(), {"ray_ilm": lidar, "ray_irm": radar, "deep_irm": mass.vacuous(grid.shape)})
    n_lidar = int((classify(ms["ray_ilm"].to_dense()[0]) == FREE).sum())
    n_nav = int((classify(ms["nav"].to_dense()[0]) == FREE).sum())
    assert n_lidar == 32 * 10 and n_nav == 32 * 20


def test_attached_nav_rows_read_their_own_sets_fused_map():
    # an extra map set with nav and another m_u_min: its nav reads its own (hidden) fused map
    grid = GridSpec(32, 4.0)
    rng = np.random.default_rng(7)
    host = MapSet(grid, FusionParams(m_u_min=0.3), ("ray_ilm", "fused"))
    extra = MapSet(grid, FusionParams(m_u_min=0.6), ("nav",))
    ref = MapSet(grid, FusionParams(m_u_min=0.6), ("nav",))
    host.attach(extra)
    for k in range(3):
        isms = _isms(rng, grid)
        host.update(SE2(0.3 * k, 0.1, 0.2 * k), isms)
        ref.update(SE2(0.3 * k, 0.1, 0.2 * k), isms)
    assert extra.n_updates == 3
    np.testing.assert_array_equal(extra["nav"].to_dense()[0], ref["nav"].to_dense()[0])
    with pytest.raises(ValueError, match="attached"):
        extra.update(SE2(), isms)


# --- the clearance: the fused map's free mass is kept off the lidar's returns ----------------


def _grid(value, shape=(5, 5)) -> np.ndarray:
    return np.broadcast_to(np.array(value, np.float32), (*shape, 3)).copy()


def _nav(lidar, fused, r, occupied_min=1.0) -> np.ndarray:
    out = np.empty_like(lidar)
    assert update_nav(out, lidar, fused, margin_cells=r, occupied_min=occupied_min) == 0
    return out


def test_no_fused_free_space_within_the_margin_of_a_lidar_return():
    # one lidar return at (2, 2) (L = [0, .5, .5], else vacuous), F = [.8, .1, .1] everywhere:
    # within 1 cell (the 3 x 3 square) F' = [0, .1, .9] (its free mass as unknown; L is not
    # free-dominant, so its occupied mass stays). At (2, 2): o = .5 .1 + .5 .9 + .5 .1 = .55,
    # u = .5 .9 = .45, no conflict; on the ring nav is F'; beyond, nav is F
    lidar = _grid([0.0, 0.0, 1.0])
    lidar[2, 2] = [0.0, 0.5, 0.5]
    fused = _grid([0.8, 0.1, 0.1])
    nav = _nav(lidar, fused, 1)
    near = np.zeros((5, 5), bool)
    near[1:4, 1:4] = True
    np.testing.assert_allclose(nav[2, 2], [0.0, 0.55, 0.45], rtol=1e-6)
    ring = near.copy()
    ring[2, 2] = False
    np.testing.assert_allclose(nav[ring], np.tile([0.0, 0.1, 0.9], (8, 1)), rtol=1e-6)
    np.testing.assert_allclose(nav[~near], np.tile([0.8, 0.1, 0.1], (16, 1)), rtol=1e-6)
    # margin 0: only the return's own cell
    assert (_nav(lidar, fused, 0)[ring][:, 0] > 0.7).all()


def test_fused_occupied_mass_above_occupied_min_blocks_the_fused_free_space_around_it():
    lidar = _grid([0.0, 0.0, 1.0])
    fused = _grid([0.8, 0.05, 0.15])
    fused[0, 0] = [0.2, 0.3, 0.5]  # a radar or prior obstacle
    nav = _nav(lidar, fused, 2, occupied_min=0.1)
    blocked = np.zeros((5, 5), bool)
    blocked[:3, :3] = True  # within 2 cells of (0, 0)
    assert (nav[blocked][:, 0] == 0).all() and (nav[~blocked][:, 0] > 0.7).all()
    # below occupied_min (.05 elsewhere) nothing is blocked; occupied_min 1 ignores F entirely
    assert (_nav(lidar, fused, 2, occupied_min=1.0)[..., 0] >= 0.2).all()


def test_the_maps_edges_are_vacuous_not_blocking():
    lidar = _grid([0.0, 0.0, 1.0], (3, 4))
    fused = _grid([0.6, 0.0, 0.4], (3, 4))
    np.testing.assert_allclose(_nav(lidar, fused, 3, occupied_min=0.1), fused, rtol=1e-6)


def _blocked(lidar, fused, r, occupied_min):
    """Brute force: the cells within r (square) of a lidar return or a fused obstacle."""
    # in float64 as the kernel compares: numpy 1.x would round the threshold to float32
    # (0.9999999999999999 to 1.0) against a float32 map
    hit = (lidar[..., 1] > 0) | (fused[..., 1].astype(np.float64) > occupied_min)
    h, w = hit.shape
    out = np.zeros_like(hit)
    for i, j in zip(*np.nonzero(hit)):
        out[max(0, i - r) : i + r + 1, max(0, j - r) : j + r + 1] = True
    return out


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    r=st.integers(0, 4),
    occupied_min=st.floats(0.01, 1.0),
)
def test_near_what_a_sensor_saw_navs_free_mass_never_exceeds_the_lidars(seed, r, occupied_min):
    """Where a cell is within the margin of a lidar return or a fused obstacle, nav's free mass
    is at most the lidar map's (F' holds no free mass: m_f = m_f(L) m_u(F') / (1 - K) <= m_f(L));
    elsewhere it is L (+)_D F' as at margin 0. nav is always a valid mass."""
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 12)), int(rng.integers(1, 12)))
    lidar = random_masses(rng, shape, p_edge=0.3)
    lidar[rng.random(shape) < 0.5] = [0.0, 0.0, 1.0]
    no_return = rng.random(shape) < 0.3  # many cells without a return
    lidar[no_return, 2] += lidar[no_return, 1]
    lidar[no_return, 1] = 0.0
    fused = random_masses(rng, shape, p_edge=0.3)
    nav = _nav(lidar, fused, r, occupied_min)
    mass.validate(nav)
    blocked = _blocked(lidar, fused, r, occupied_min)
    assert (nav[blocked][:, 0] <= lidar[blocked][:, 0] + 1e-6).all()
    clear = _nav(lidar, fused, 0, occupied_min=1.0)  # the same cells with nothing blocked...
    lone = ~blocked & (lidar[..., 1] == 0)  # ...equal where no cell is blocked
    np.testing.assert_allclose(nav[lone], clear[lone], rtol=1e-6, atol=1e-7)


def test_nav_params_are_checked_and_reach_the_map_set():
    from evgrid.config import MapperConfig
    from evgrid.nav import NavParams

    with pytest.raises(ValueError, match="margin_m"):
        NavParams(margin_m=-1.0)
    with pytest.raises(ValueError, match="occupied_min"):
        NavParams(occupied_min=0.0)
    assert NavParams(margin_m=0.5).margin_cells(0.1) == 5
    cfg = MapperConfig(nav=NavParams(margin_m=0.3))
    assert MapSet(cfg.grid, names=("nav",), nav=cfg.nav).nav.margin_m == 0.3
    with pytest.raises(TypeError, match="NavParams"):
        MapSet(GridSpec(32, 4.0), names=("nav",), nav=0.5)


def test_nav_is_computed_when_read_over_the_cells_the_updates_changed():
    # two updates, one read: the same map as reading after each update
    grid = GridSpec(32, 4.0)
    rng = np.random.default_rng(3)
    lazy = MapSet(grid, names=("nav",))
    eager = MapSet(grid, names=("nav",))
    for k in range(3):
        isms = _isms(rng, grid)
        for s in (lazy, eager):
            s.update(SE2(0.8 * k, -0.5 * k, 0.3 * k), isms)
        eager["nav"]
        assert eager._stale is None and lazy._stale is not None
    np.testing.assert_array_equal(lazy["nav"].to_dense()[0], eager["nav"].to_dense()[0])
    assert lazy._stale is None
    with pytest.raises(TypeError, match="update_nav"):
        RULES["nav"].update(np.zeros((1, 1, 3), np.float32), cell([0, 0, 1]), cell([0, 0, 1]))


def test_cells_the_dynamic_score_calls_moving_block_like_a_return():
    from evgrid.nav import nav_dense

    lidar = _grid([0.0, 0.0, 1.0])
    fused = _grid([0.8, 0.1, 0.1])
    moving = np.zeros((5, 5), np.float32)
    moving[2, 2] = 0.5
    nav = nav_dense(lidar, fused, 1, 1.0, moving, moving_min=0.1)
    assert (nav[1:4, 1:4, 0] == 0).all() and nav[0, 0, 0] > 0.7
    # at the threshold or without a threshold nothing is blocked
    assert (nav_dense(lidar, fused, 1, 1.0, moving, moving_min=0.5)[..., 0] > 0.7).all()
    assert (nav_dense(lidar, fused, 1, 1.0, moving)[..., 0] > 0.7).all()
    with pytest.raises(ValueError, match="moving must have shape"):
        nav_dense(lidar, fused, 1, 1.0, moving[:2], moving_min=0.1)


def test_an_update_reaches_the_navigation_maps_margin_beyond_its_window():
    # observers recount the tiles an update can change: nav's reach past the window (0.5 m at
    # 0.125 m a cell: 4 cells), also through an attached set; none without nav
    grid = GridSpec(32, 4.0)
    assert MapSet(grid, names=("nav",)).reach == 4
    host = MapSet(grid, names=("ray_ilm", "fused"))
    assert host.reach == 0
    host.attach(MapSet(grid, names=("nav",)))
    assert host.reach == 4
