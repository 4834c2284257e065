"""The evidential algebra: hand-computed cases for each equation, and the paper's properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from tests.strategies import masses, random_masses

M1 = np.array([0.5, 0.2, 0.3], dtype=np.float32)
M2 = np.array([0.1, 0.6, 0.3], dtype=np.float32)


# --- hand-computed cases -------------------------------------------------------------------------


def test_conflict_hand_computed():
    # K = m_f1 m_o2 + m_o1 m_f2 = 0.5 * 0.6 + 0.2 * 0.1
    assert mass.conflict(M1, M2) == pytest.approx(0.32)


def test_dempster_hand_computed():
    # f = .5*.1 + .5*.3 + .3*.1 = .23; o = .2*.6 + .2*.3 + .3*.6 = .36; u = .09; 1 - K = .68
    np.testing.assert_allclose(
        mass.dempster(M1, M2), [0.23 / 0.68, 0.36 / 0.68, 0.09 / 0.68], rtol=1e-6
    )


def test_dempster_total_conflict_is_vacuous():
    out = mass.dempster(
        np.array([[1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 0], [1, 0, 0]], np.float32)
    )
    np.testing.assert_array_equal(out, [[0, 0, 1], [0, 0, 1]])


def test_yager_hand_computed():
    # same products as Dempster, unnormalised, with K = .32 added to u: .09 + .32
    np.testing.assert_allclose(mass.yager(M1, M2), [0.23, 0.36, 0.41], rtol=1e-6)


def test_yager_total_conflict_is_all_unknown():
    np.testing.assert_allclose(mass.yager([1, 0, 0], [0, 1, 0]), [0, 0, 1])


def test_discount_hand_computed():
    np.testing.assert_allclose(mass.discount([0.6, 0.2, 0.2], 0.5), [0.3, 0.1, 0.6], rtol=1e-6)


def test_discount_broadcasts_per_cell_gamma():
    m = np.array([[0.6, 0.2, 0.2], [0.6, 0.2, 0.2]], np.float32)
    np.testing.assert_allclose(
        mass.discount(m, np.array([0.0, 1.0])), [[0, 0, 1], [0.6, 0.2, 0.2]], rtol=1e-6
    )


def test_limit_unknown_hand_computed():
    # Delta = 0.4 - 0.2 = 0.2, alpha = 0.2 / 0.8 = 0.25: [0.6 * 0.75, 0.2 * 0.75, 0.4]
    np.testing.assert_allclose(
        mass.limit_unknown([0.6, 0.2, 0.2], 0.4), [0.45, 0.15, 0.4], rtol=1e-6
    )


def test_limit_unknown_leaves_cells_above_limit_and_vacuous_cells():
    np.testing.assert_array_equal(
        mass.limit_unknown([0.1, 0.2, 0.7], 0.4), np.float32([0.1, 0.2, 0.7])
    )
    np.testing.assert_array_equal(mass.limit_unknown([0.0, 0.0, 1.0], 0.4), [0, 0, 1])


def test_from_evidence_hand_computed():
    # S = 2 + 2 + 4 = 8
    np.testing.assert_allclose(mass.from_evidence([2.0, 4.0]), [0.25, 0.5, 0.25])
    np.testing.assert_allclose(mass.from_evidence([0.0, 0.0]), [0, 0, 1])


def test_pignistic_hand_computed():
    assert mass.pignistic_occupied([0.2, 0.3, 0.5]) == pytest.approx(0.55)


def test_deep_discount_factor_hand_computed():
    # vacuous map, prediction at the limit 0.5: tanh(10 * 0.5) < bound (1 - .5) / (1 * .5) = 1
    g = mass.deep_discount_factor([0, 0, 1], [0.5, 0, 0.5], m_u_min=0.5, alpha=10)
    assert g == pytest.approx(math.tanh(5.0), abs=1e-7)
    # map [.3, 0, .7], prediction [.6, 0, .4], m_u_min .4: bound (.7 - .4) / (.7 * .6 - 0) = 5/7 <
    # tanh(3)
    g = mass.deep_discount_factor([0.3, 0, 0.7], [0.6, 0, 0.4], m_u_min=0.4, alpha=10)
    assert g == pytest.approx(5 / 7, rel=1e-6)
    fused = mass.yager([0.3, 0, 0.7], mass.discount([0.6, 0, 0.4], g))
    np.testing.assert_allclose(fused, [0.6, 0.0, 0.4], rtol=1e-6)  # lands exactly on m_u_min
    # prediction more unknown than the map: no information gain, gamma = 0
    assert mass.deep_discount_factor([0.2, 0.3, 0.5], [0.5, 0, 0.5], 0.3) == 0.0


def test_deep_discount_exact_bound_where_papers_bound_fails():
    """The paper's bound (eq. (35)) holds K fixed and lets m_u fall below m_u_min; the exact one
    does not.

    docs/decisions.md#exact-gamma-bound
    """
    m_map = np.array([0.1, 0.4, 0.5])
    m_pred = np.array([0.3, 0.3, 0.4])
    m_u_min, alpha = 0.4, 30.0
    k0 = m_map[0] * m_pred[1] + m_map[1] * m_pred[0]  # 0.15
    paper = min((m_map[2] + k0 - m_u_min) / (m_map[2] * (1 - m_pred[2])), math.tanh(alpha * 0.1))
    assert mass.yager(m_map, mass.discount(m_pred, paper))[2] < m_u_min - 0.02  # 0.375
    g = mass.deep_discount_factor(m_map, m_pred, m_u_min, alpha)
    assert g == pytest.approx(0.1 / 0.15, rel=1e-6)
    assert mass.yager(m_map, mass.discount(m_pred, g))[2] == pytest.approx(m_u_min, abs=1e-6)


# --- validation ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros((4, 2), np.float32), "last axis"),
        (np.array([[np.nan, 0, 1]], np.float32), "NaN"),
        (np.array([[-0.1, 0.1, 1.0]], np.float32), "negative"),
        (np.array([[0.5, 0.5, 0.5]], np.float32), "sum"),
        (np.array([[0, 0, 1]], np.int32), "floating"),
        (np.array([[1.5, -0.25, -0.25]], np.float32), "negative"),
    ],
)
def test_validate_names_the_problem(bad, message):
    with pytest.raises(ValueError, match=message):
        mass.validate(bad)


def test_validate_accepts_masses():
    mass.validate(random_masses(np.random.default_rng(0), (8, 8)))


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="gamma"):
        mass.discount(M1, 1.5)
    with pytest.raises(ValueError, match="m_u_min"):
        mass.limit_unknown(M1, -0.1)
    with pytest.raises(ValueError, match="evidence"):
        mass.from_evidence([-1.0, 2.0])
    with pytest.raises(ValueError, match="length 2"):
        mass.from_evidence([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="length 3"):
        mass.dempster(np.zeros(2), M1)
    with pytest.raises(ValueError, match="out"):
        mass.dempster(M1, M2, out=np.zeros(3, np.float64))


def test_shapes_broadcast_and_out_is_used():
    grid = random_masses(np.random.default_rng(1), (5, 7))
    out = np.empty_like(grid)
    res = mass.dempster(grid, M2, out=out)
    assert res is out and res.shape == (5, 7, 3) and res.dtype == np.float32
    np.testing.assert_allclose(res[2, 3], mass.dempster(grid[2, 3], M2), rtol=1e-6)
    assert mass.deep_discount_factor(grid, grid, 0.3).shape == (5, 7)


def test_kernels_match_a_float64_numpy_reference():
    rng = np.random.default_rng(2)
    a = random_masses(rng, (64, 64)).astype(np.float64)
    b = random_masses(rng, (64, 64)).astype(np.float64)
    k = a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0]
    f = a[..., 0] * b[..., 0] + a[..., 0] * b[..., 2] + a[..., 2] * b[..., 0]
    o = a[..., 1] * b[..., 1] + a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1]
    u = a[..., 2] * b[..., 2]
    ok = 1 - k > 1e-6
    ref_d = np.stack([f, o, u], -1) / np.where(ok, 1 - k, 1)[..., None]
    np.testing.assert_allclose(mass.dempster(a, b)[ok], ref_d[ok], atol=2e-6)
    np.testing.assert_allclose(mass.yager(a, b), np.stack([f, o, u + k], -1), atol=2e-6)
    gain = np.tanh(10 * np.maximum(0, a[..., 2] - b[..., 2]))
    den = a[..., 2] * (1 - b[..., 2]) - k
    bound = np.where(den > 1e-12, (a[..., 2] - 0.3) / np.where(den > 1e-12, den, 1), np.inf)
    ref_g = np.clip(np.minimum(gain, bound), 0, 1)
    np.testing.assert_allclose(mass.deep_discount_factor(a, b, 0.3, 10.0), ref_g, atol=2e-6)


# --- properties (paper section III/IV) -----------------------------------------------------------


@given(masses(), masses())
def test_dempster_never_raises_unknown(m1, m2):
    """Paper IV-A: Dempster's fused unknown mass never exceeds either input's (total conflict
    aside)."""
    if 1.0 - float(mass.conflict(m1, m2)) < 1e-6:
        return  # undefined there; vacuous (docs/decisions.md#total-conflict)
    u = mass.dempster(m1, m2)[2]
    assert u <= min(m1[2], m2[2]) + 1e-6


@given(masses(), masses())
def test_dempster_is_commutative_and_on_simplex(m1, m2):
    a, b = mass.dempster(m1, m2), mass.dempster(m2, m1)
    np.testing.assert_allclose(a, b, atol=1e-6)
    mass.validate(a)


@given(masses(), masses())
def test_yager_adds_conflict_to_unknown(m1, m2):
    y = mass.yager(m1, m2)
    k = float(mass.conflict(m1, m2))
    assert y[2] == pytest.approx(m1[2] * m2[2] + k, abs=2e-6)
    mass.validate(y)


@given(masses())
def test_discount_by_one_is_identity_and_by_zero_vacuous(m):
    np.testing.assert_allclose(mass.discount(m, 1.0), m, atol=1e-7)
    np.testing.assert_array_equal(mass.discount(m, 0.0), [0, 0, 1])


@given(masses(), st.floats(0.0, 0.99))
def test_limit_unknown_reaches_limit_and_keeps_ratio(m, m_u_min):
    out = mass.limit_unknown(m, m_u_min)
    mass.validate(out)
    if m[0] + m[1] > 0:
        assert out[2] >= np.float32(m_u_min) - 1e-6
        # f : o is kept: f_out * o_in == o_out * f_in
        assert out[0] * m[1] == pytest.approx(out[1] * m[0], abs=1e-6)
    if m[2] >= m_u_min:
        np.testing.assert_allclose(out, m, atol=1e-7)


@given(st.floats(0, 1e4), st.floats(0, 1e4))
def test_from_evidence_and_pignistic_identities(e_f, e_o):
    m = mass.from_evidence([e_f, e_o])
    s = 2.0 + e_f + e_o
    mass.validate(m)
    # the pignistic probability equals the Dirichlet mean (e_o + 1) / S, and (1 - m_f + m_o) / 2
    p_o = float(mass.pignistic_occupied(m))
    assert p_o == pytest.approx((e_o + 1.0) / s, abs=1e-6)
    assert p_o == pytest.approx((1.0 - m[0] + m[1]) / 2.0, abs=1e-6)


@given(masses(), masses(), st.floats(0.0, 0.95), st.floats(0.0, 100.0))
def test_gamma_in_unit_interval_and_zero_without_gain(m_map, m_pred, m_u_min, alpha):
    g = float(mass.deep_discount_factor(m_map, m_pred, m_u_min, alpha))
    assert 0.0 <= g <= 1.0
    if m_pred[2] >= m_map[2]:
        # no information gain; inputs off the simplex by float32 rounding may show a hair of it
        assert g <= 1e-6


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.05, 0.9), st.floats(0.5, 50.0))
def test_deep_discount_invariant_over_1000_updates(seed, m_u_min, alpha):
    """Paper eq. (30), docs/decisions.md#exact-gamma-bound: m_u >= m_u_min stays true under any
    deep_disc updates."""
    from evgrid.fusion import FusionParams, update_deep_disc

    rng = np.random.default_rng(seed)
    cells = random_masses(rng, (1, 64), p_edge=0.05)
    cells = mass.limit_unknown(cells, m_u_min)  # start at or above the limit
    params = FusionParams(m_u_min=m_u_min, alpha=alpha)
    floor = np.float32(m_u_min)
    for _ in range(1000):
        update_deep_disc(cells, random_masses(rng, (1, 64), p_edge=0.2), params)
        assert cells[..., 2].min() >= floor
    mass.validate(cells)
