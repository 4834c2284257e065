"""Hostile masses and point arrays: what is not a mass never enters a map or the algebra.

Each test here failed before masses were checked where they enter (issue 12): a NaN ISM cell
reset informed map cells to vacuous, negative masses were stored in 4 of the 6 maps,
``mass.dempster(good, [2, 0, -1])`` returned negative masses, and a (4, n) point array was read
as 4 points.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.fusion import MAP_NAMES, RULES, FusionParams, MapSet
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import EvidentialMap, MapWindow, Warper
from evgrid.ism import ray_ilm
from evgrid.ism.radar import ray_irm_xy
from tests.oracle import TwoPassMaps
from tests.strategies import random_masses

GRID = GridSpec(32, 4.0)
N = GRID.n_cells
P = FusionParams(m_u_min=0.3, alpha=10.0)
ISMS = ("ray_ilm", "ray_irm", "deep_irm")
# Not masses: NaN, inf, a negative mass, a sum above or below 1, and the issue's [2, 0, -1].
BAD = [
    [np.nan, 0.0, 1.0],
    [0.2, np.inf, 0.0],
    [0.5, -np.inf, 0.5],
    [2.0, 0.0, -1.0],
    [-0.25, 0.75, 0.5],
    [0.5, 0.5, 0.5],
    [0.1, 0.1, 0.1],
    [0.0, 0.0, 1.5],
]


def _local(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: random_masses(rng, GRID.shape) for k in ISMS}


def _dense(ms: MapSet, name: str) -> np.ndarray:
    # at the identity pose the local grid lies on map cells R = r - n/2 (docs/conventions.md)
    return ms[name].read(-N // 2, -N // 2, N, N)[0]


def _informed_mapset() -> MapSet:
    ms = MapSet(GRID, P)
    ms.update(SE2(), _local(1))
    return ms


def test_nan_ism_cells_leave_informed_map_cells_untouched_and_are_counted():
    ms = _informed_mapset()
    before = {n: _dense(ms, n) for n in MAP_NAMES}
    isms = _local(2)
    for a in isms.values():
        a[4:10, 5:9] = np.nan  # 24 cells
    ms.update(SE2(), isms)
    for name in MAP_NAMES:
        after = _dense(ms, name)
        # bit for bit where the ISM held NaN (they used to be reset to vacuous), updated elsewhere
        np.testing.assert_array_equal(
            after[4:10, 5:9].view(np.uint32), before[name][4:10, 5:9].view(np.uint32)
        )
        assert not np.array_equal(after[12:], before[name][12:])
        mass.validate(after)
    assert ms.n_rejected == {k: 24 for k in ISMS}


@pytest.mark.parametrize("bad", BAD, ids=[str(b) for b in BAD])
def test_invalid_ism_cells_are_never_stored_in_any_of_the_six_maps(bad):
    ms = _informed_mapset()
    before = {n: _dense(ms, n) for n in MAP_NAMES}
    isms = _local(3)
    for a in isms.values():
        a[::3, ::2] = bad
    ms.update(SE2(), isms)
    for name in MAP_NAMES:
        after = _dense(ms, name)
        mass.validate(after, name)
        np.testing.assert_array_equal(after[::3, ::2], before[name][::3, ::2])
    assert ms.n_rejected == {k: len(range(0, N, 3)) * len(range(0, N, 2)) for k in ISMS}


def test_invalid_local_cells_do_not_leak_into_neighbours_through_the_warp():
    # A negative cell among vacuous ones: the bilinear warp would blend it into valid-looking
    # masses ([2w, 0, 1 - 2w] for weights w < 1/2); it carries no information instead.
    ms = MapSet(GRID, P, names=("ray_ilm",))
    local = mass.vacuous(GRID.shape)
    local[10:20, 10:20] = [2.0, 0.0, -1.0]
    ms.update(SE2(0.37 * GRID.resolution, 0.61 * GRID.resolution, 0.3), {"ray_ilm": local})
    m, cov, _, _ = ms["ray_ilm"].to_dense()
    np.testing.assert_array_equal(m[cov], np.tile(mass.VACUOUS, (int(cov.sum()), 1)))
    assert ms.n_rejected == {"ray_ilm": 100}
    assert local[10, 10, 0] == 2.0  # the caller's grid is not modified


def test_warper_takes_cells_that_are_not_masses_as_vacuous_counts_and_logs_them_once(caplog):
    # the warp on its own (truth grids, the m_u_min sweep's windows) checks like the map update
    warper = Warper(GRID, "deep_irm")
    local = random_masses(np.random.default_rng(5), GRID.shape)
    local[3, 4] = [np.nan, 0.0, 1.0]
    local[20, 7] = [-0.25, 0.75, 0.5]
    with caplog.at_level("WARNING", logger="evgrid.grid"):
        window = warper.warp(local, SE2())
        warper.warp(local, SE2())
    assert warper.n_rejected == 4
    assert len(caplog.records) == 1 and "deep_irm: 2 cell(s)" in caplog.records[0].getMessage()
    # at the identity pose local cell (r, c) lies on map cell (r - n/2, c - n/2)
    r, c = -window.r0 - N // 2, -window.c0 - N // 2
    got = window.masses[r : r + N, c : c + N]
    np.testing.assert_array_equal(got[3, 4], mass.VACUOUS)
    np.testing.assert_array_equal(got[20, 7], mass.VACUOUS)
    keep = np.ones(GRID.shape, bool)
    keep[3, 4] = keep[20, 7] = False
    np.testing.assert_array_equal(got[keep], local[keep])
    mass.validate(window.masses)


@pytest.mark.parametrize("name", MAP_NAMES)
def test_each_update_rule_rejects_invalid_cells_and_returns_their_count(name):
    rule = RULES[name]
    rng = np.random.default_rng(4)
    m = random_masses(rng, (len(BAD), 4))
    old = m.copy()
    isms = [random_masses(rng, (len(BAD), 4)) for _ in rule.isms]
    for a in isms:
        a[:, 1] = BAD  # one invalid cell a row, in every ISM the rule reads
    n = rule.update(m, *isms, P)
    np.testing.assert_array_equal(m[:, 1], old[:, 1])
    mass.validate(m)
    assert n == len(BAD) * len(rule.isms)


def test_apply_and_the_oracles_windows_count_rejected_window_cells():
    # Windows that did not come from a warper's check (the two-pass oracle of tests/oracle.py,
    # once MapSet.update_windows): each rule rejects their invalid cells and counts them.
    ism = mass.vacuous((4, 6))
    ism[1, 2] = [0.7, 0.0, 0.7]
    ism[2, 3] = [np.nan, np.nan, np.nan]
    window = MapWindow(5, -3, ism, np.ones((4, 6), bool))
    em = EvidentialMap(GRID, tile_cells=8)
    assert em.apply(window, RULES["ray_ilm"].update) == 2
    ms = TwoPassMaps(GRID, P)
    assert ms.update_windows({k: window for k in ISMS}) == {
        "ray_ilm": 2,
        "deep_acc": 2,
        "deep_replace": 2,
        "deep_disc": 2,
        "ray_irm": 2,
        "fused": 4,
    }
    assert ms.n_rejected_cells["fused"] == 4
    for name in MAP_NAMES:
        np.testing.assert_array_equal(ms[name].read(5, -3, 4, 6)[0], mass.vacuous((4, 6)))


_ANY_FLOAT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, 1.0, -0.0, 0.5, 1.0 + 2e-5, -1e-30]),
)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.lists(st.tuples(_ANY_FLOAT, _ANY_FLOAT, _ANY_FLOAT), min_size=12, max_size=12),
    st.sampled_from(MAP_NAMES),
)
def test_whatever_ism_is_applied_every_stored_cell_stays_a_valid_mass(seed, garbage, name):
    """Rejecting an invalid ISM cell is the same as the ISM saying nothing (vacuous) there."""
    rng = np.random.default_rng(seed)
    rule = RULES[name]
    m = random_masses(rng, (3, 4), p_edge=0.3)
    isms = [random_masses(rng, (3, 4), p_edge=0.3) for _ in rule.isms]
    isms[0][...] = np.array(garbage, np.float32).reshape(3, 4, 3)
    valid = np.array(
        [
            np.isfinite(c).all() and min(c) >= 0 and abs(sum(map(float, c)) - 1) <= 1e-5
            for c in isms[0].reshape(-1, 3)
        ]
    ).reshape(3, 4)
    ref, cleaned = m.copy(), [a.copy() for a in isms]
    cleaned[0][~valid] = mass.VACUOUS
    n = rule.update(m, *isms, P)
    rule.update(ref, *cleaned, P)
    np.testing.assert_array_equal(m.view(np.uint32), ref.view(np.uint32))
    mass.validate(m)
    assert n == int((~valid).sum())


# --- the public algebra ---------------------------------------------------------------------------

GOOD = np.array([0.2, 0.3, 0.5], np.float32)


def test_dempster_of_the_issue_raises_instead_of_returning_negative_masses():
    with pytest.raises(ValueError, match="m2: negative mass"):
        mass.dempster(GOOD, [2, 0, -1])


@pytest.mark.parametrize("bad", BAD, ids=[str(b) for b in BAD])
@pytest.mark.parametrize(
    "call, arg",
    [
        (lambda b: mass.dempster(GOOD, b), "m2"),
        (lambda b: mass.dempster(b, GOOD), "m1"),
        (lambda b: mass.yager(GOOD, b), "m2"),
        (lambda b: mass.conflict(b, GOOD), "m1"),
        (lambda b: mass.discount(b, 0.5), "m"),
        (lambda b: mass.limit_unknown(b, 0.3), "m"),
        (lambda b: mass.pignistic_occupied(b), "m"),
        (lambda b: mass.deep_discount_factor(GOOD, b, 0.3), "m_pred"),
        (lambda b: mass.deep_discount_factor(b, GOOD, 0.3), "m_map"),
    ],
    ids=[
        "dempster-m2",
        "dempster-m1",
        "yager",
        "conflict",
        "discount",
        "limit_unknown",
        "pignistic",
        "gamma-pred",
        "gamma-map",
    ],
)
def test_the_algebra_raises_naming_the_invalid_argument(call, arg, bad):
    grid = np.tile(GOOD, (5, 3, 1))
    grid[3, 1] = bad  # one bad cell in a grid
    with pytest.raises(ValueError, match=f"^{arg}: "):
        call(grid)


def test_nothing_is_written_to_out_when_an_argument_is_invalid():
    out = np.full((2, 3), 7.0, np.float32)
    with pytest.raises(ValueError, match="m1"):
        mass.dempster(np.array([GOOD, [0.5, 0.5, 0.5]]), GOOD, out=out)
    assert (out == 7.0).all()


@settings(max_examples=200, deadline=None)
@given(st.tuples(_ANY_FLOAT, _ANY_FLOAT, _ANY_FLOAT))
def test_dempster_accepts_exactly_the_masses(m):
    m32 = np.array(m, np.float32)
    valid = bool(
        np.isfinite(m32).all() and m32.min() >= 0 and abs(m32.astype(np.float64).sum() - 1) <= 1e-5
    )
    if valid:
        out = mass.dempster(GOOD, m32)
        mass.validate(out)
    else:
        with pytest.raises(ValueError, match="^m2: "):
            mass.dempster(GOOD, m32)


# --- point arrays in the devkit's (columns, n) layout ---------------------------------------------


@pytest.mark.parametrize("rows", [3, 4, 5])
def test_ray_ilm_refuses_transposed_point_arrays(rows):
    pts = np.random.default_rng(5).uniform(-5, 5, (200, rows)).astype(np.float32)
    ray_ilm(pts, grid=GRID)  # (n, rows) is fine
    with pytest.raises(ValueError, match="look transposed"):
        ray_ilm(pts.T, grid=GRID)  # was read as `rows` points of 200 coordinates


def test_ray_irm_xy_refuses_transposed_detections():
    det = np.random.default_rng(6).uniform(-1.5, 1.5, (50, 2))
    ray_irm_xy(det, np.zeros(2), grid=GRID)
    with pytest.raises(ValueError, match="look transposed"):
        ray_irm_xy(det.T, np.zeros(2), grid=GRID)


def test_sweeps_name_a_transposed_point_array():
    from evgrid.data.frame import LidarSweep
    from evgrid.geometry import SE3

    with pytest.raises(ValueError, match="transposed"):
        LidarSweep(np.zeros((5, 100), np.float32), SE3.identity(), SE3.identity(), 0)


# --- API edges, round 3 (issue 26) ---------------------------------------------------------------


@pytest.mark.parametrize(
    "pose", [SE2(1e30, 0.0, 0.0), SE2(0.0, -2e8, 1.0), SE2._unchecked(float("nan"), 0.0, 0.0)]
)
def test_map_update_refuses_a_pose_far_from_the_frame_naming_it(pose):
    # before: SE2(1e30, 0, 0) placed the grid at tile key -5e28 without an error
    ms = MapSet(GRID, P, ("ray_ilm",))
    with pytest.raises(ValueError, match=r"pose SE2\(x=.*finite and within 1e\+08 m"):
        ms.update(pose, {"ray_ilm": mass.vacuous(GRID.shape)})
    assert ms.n_updates == 0 and not ms["ray_ilm"].tiles


def test_map_update_takes_a_pose_in_a_utm_like_frame():
    # real fixed frames reach 1e7 m: a pose there maps, at its own tiles
    ms = MapSet(GRID, P, ("ray_ilm",))
    ism = mass.vacuous(GRID.shape)
    ism[10:20, 10:20] = [0.6, 0.1, 0.3]
    ms.update(SE2(5e7, -3e6, 0.3), {"ray_ilm": ism})
    r0, c0, _, _ = ms["ray_ilm"].covered_bounds()
    assert abs(r0 * GRID.resolution + 5e7) < 10 and abs(c0 * GRID.resolution - 3e6) < 10


def test_from_evidence_of_huge_evidence_is_a_mass():
    # before: [1e308, 1e308] gave [0, 0, 0] (S overflowed)
    np.testing.assert_array_equal(mass.from_evidence([1e308, 1e308]), [0.5, 0.5, 0.0])
    m = mass.from_evidence([[1e308, 1.0], [0.0, 1.7e308], [3.0, 1.0]])
    mass.validate(m)
    np.testing.assert_array_equal(m[0], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(m[2], np.float32([0.5, 1 / 6, 1 / 3]))


def test_map_set_arguments_of_the_wrong_kind_are_named():
    # before: MapSet(spec, {'m_u_min': 2.0}) raised an AttributeError
    with pytest.raises(TypeError, match=r"params must be a FusionParams.*dict"):
        MapSet(GRID, {"m_u_min": 2.0})
    with pytest.raises(TypeError, match="grid must be a GridSpec"):
        MapSet({"n_cells": 32})
    with pytest.raises(TypeError, match="names must be a tuple of map names"):
        MapSet(GRID, P, "fused")
    with pytest.raises(ValueError, match="repeat"):
        MapSet(GRID, P, ("fused", "fused"))


def test_grid_spec_from_dict_names_what_is_missing():
    # before: a bare KeyError
    with pytest.raises(ValueError, match=r"missing .*\['length_m'\]"):
        GridSpec.from_dict({"n_cells": 32})
    with pytest.raises(ValueError, match="length_m: expected float"):
        GridSpec.from_dict({"n_cells": 32, "length_m": "wide"})
    with pytest.raises(ValueError, match="expected an object"):
        GridSpec.from_dict([32, 4.0])
    assert GridSpec.from_dict(GRID.to_dict()) == GRID
