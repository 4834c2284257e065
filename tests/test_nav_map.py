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
