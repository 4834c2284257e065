"""The six update rules of the paper's Table I (evgrid.fusion)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.fusion import (
    MAP_NAMES,
    RULES,
    FusionParams,
    MapSet,
    update_deep_acc,
    update_deep_disc,
    update_deep_replace,
    update_fused,
    update_ray_ilm,
    update_ray_irm,
)
from evgrid.geometry import SE2, GridSpec
from evgrid.grid import Warper
from tests.oracle import TwoPassMaps
from tests.strategies import random_masses

P = FusionParams(m_u_min=0.4, alpha=10.0)


def cell(m) -> np.ndarray:
    return np.array(m, np.float32).reshape(1, 1, 3)


def test_the_six_rules_are_the_papers():
    assert MAP_NAMES == ("ray_ilm", "deep_acc", "deep_replace", "deep_disc", "ray_irm", "fused")
    # the table holds the six of Table I and the navigation map (issue 25), computed when asked
    assert tuple(RULES) == (*MAP_NAMES, "nav")
    assert RULES["fused"].isms == ("deep_irm", "ray_irm")
    assert MapSet(GridSpec(16, 2.0)).names == MAP_NAMES


@pytest.mark.parametrize("rule", [update_ray_ilm, update_deep_acc, update_ray_irm])
def test_dempster_rules_hand_computed(rule):
    m = cell([0.5, 0.2, 0.3])
    rule(m, cell([0.1, 0.6, 0.3]))
    np.testing.assert_allclose(m[0, 0], [0.23 / 0.68, 0.36 / 0.68, 0.09 / 0.68], rtol=1e-6)


def test_deep_replace_hand_computed():
    # prediction [.6, .2, .2] limited to m_u >= .4 is [.45, .15, .4]: replaces a cell with m_u .7
    m = cell([0.1, 0.2, 0.7])
    update_deep_replace(m, cell([0.6, 0.2, 0.2]), P)
    np.testing.assert_allclose(m[0, 0], [0.45, 0.15, 0.4], rtol=1e-6)
    # but not a cell already more certain than the limited prediction
    m = cell([0.65, 0.0, 0.35])
    update_deep_replace(m, cell([0.1, 0.8, 0.1]), P)
    np.testing.assert_array_equal(m[0, 0], np.float32([0.65, 0.0, 0.35]))


def test_deep_disc_hand_computed():
    # map [.3, 0, .7], prediction [.6, 0, .4] at m_u_min .4: gamma = 5/7 and m_u lands on .4
    m = cell([0.3, 0.0, 0.7])
    update_deep_disc(m, cell([0.6, 0.0, 0.4]), P)
    np.testing.assert_allclose(m[0, 0], [0.6, 0.0, 0.4], rtol=1e-6)
    # a vacuous map and a limited prediction: gamma = tanh(10 * .6), Yager of the discounted mass
    m = cell([0.0, 0.0, 1.0])
    update_deep_disc(m, cell([0.0, 0.9, 0.1]), P)  # limited to [0, .6, .4]
    g = math.tanh(6.0)
    np.testing.assert_allclose(m[0, 0], [0.0, 0.6 * g, 1 - 0.6 * g], rtol=1e-6)


def test_fused_is_deep_disc_then_dempster_with_ray_irm():
    rng = np.random.default_rng(0)
    m0, deep, irm = (random_masses(rng, (16, 16)) for _ in range(3))
    a = m0.copy()
    update_fused(a, deep, irm, P)
    b = m0.copy()
    update_deep_disc(b, deep, P)
    update_ray_irm(b, irm)
    np.testing.assert_allclose(a, b, atol=1e-6)


@pytest.mark.parametrize("name", MAP_NAMES)
def test_vacuous_isms_leave_the_map_bit_identical(name):
    m0 = random_masses(np.random.default_rng(1), (8, 8))
    m = m0.copy()
    rule = RULES[name]
    rule.update(m, *[mass.vacuous((8, 8)) for _ in rule.isms], P)
    assert m.tobytes() == m0.tobytes()


def test_rules_work_on_strided_views_of_a_larger_map():
    rng = np.random.default_rng(2)
    big = random_masses(rng, (20, 20))
    ism = random_masses(rng, (20, 20))
    ref = big.copy()
    view_ref = ref[3:11, 5:17].copy()
    update_deep_disc(view_ref, ism[3:11, 5:17], P)
    update_deep_disc(big[3:11, 5:17], ism[3:11, 5:17], P)
    np.testing.assert_array_equal(big[3:11, 5:17], view_ref)
    untouched = np.ones((20, 20), bool)
    untouched[3:11, 5:17] = False
    np.testing.assert_array_equal(big[untouched], ref[untouched])


@pytest.mark.parametrize("name", MAP_NAMES)
def test_spans_limit_each_row_to_its_columns(name):
    rng = np.random.default_rng(3)
    m0 = random_masses(rng, (3, 5), p_edge=0.0)
    isms = [random_masses(rng, (3, 5), p_edge=0.0) for _ in RULES[name].isms]
    whole = m0.copy()
    RULES[name].update(whole, *isms, P)
    # row 0: columns 1-2; row 1: none; row 2: an out-of-range span, clamped to the whole row
    spans = np.array([[1, 3], [4, 4], [-7, 99]], dtype=np.int64)
    part = m0.copy()
    RULES[name].update(part, *isms, P, spans)
    touched = np.zeros((3, 5), bool)
    touched[0, 1:3] = True
    touched[2, :] = True
    np.testing.assert_array_equal(part[touched], whole[touched])
    np.testing.assert_array_equal(part[~touched], m0[~touched])
    assert not np.array_equal(whole[~touched], m0[~touched])  # the rule would have changed them


def test_rules_reject_bad_spans():
    m = mass.vacuous((2, 3))
    with pytest.raises(ValueError, match=r"spans must be an int64 array of shape \(2, 2\)"):
        update_ray_ilm(m, m.copy(), spans=np.zeros((3, 2), np.int64))
    with pytest.raises(ValueError, match="spans"):
        update_deep_disc(m, m.copy(), spans=np.zeros((2, 2), np.float64))
    with pytest.raises(ValueError, match="spans"):
        update_fused(m, m.copy(), m.copy(), spans=[[0, 3], [0, 3]])


def test_rules_reject_bad_views():
    with pytest.raises(ValueError, match="float32"):
        update_ray_ilm(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="differs"):
        update_ray_ilm(mass.vacuous((2, 2)), mass.vacuous((2, 3)))
    with pytest.raises(ValueError, match="contiguous"):
        update_ray_ilm(mass.vacuous((4, 4))[:, ::2], mass.vacuous((4, 2)))


def test_params_validation():
    with pytest.raises(ValueError, match="m_u_min"):
        FusionParams(m_u_min=1.0)
    with pytest.raises(ValueError, match="alpha"):
        FusionParams(alpha=-1)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.9))
def test_any_chain_of_the_six_rules_keeps_the_simplex(seed, m_u_min):
    """Random chains, total conflict included (a fifth of ISM cells at simplex corners/edges)."""
    rng = np.random.default_rng(seed)
    params = FusionParams(m_u_min=m_u_min, alpha=float(rng.uniform(0, 50)))
    m = random_masses(rng, (8, 8), p_edge=0.2)
    for _ in range(60):
        rule = RULES[MAP_NAMES[rng.integers(len(MAP_NAMES))]]
        rule.update(m, *[random_masses(rng, (8, 8), p_edge=0.2) for _ in rule.isms], params)
        assert np.isfinite(m).all()
        assert m.min() >= 0.0 and m.max() <= 1.0
        assert np.abs(m.sum(-1, dtype=np.float64) - 1.0).max() <= 1e-5


def test_total_conflict_in_a_map_gives_vacuous():
    m = cell([1.0, 0.0, 0.0])
    update_ray_ilm(m, cell([0.0, 1.0, 0.0]))
    np.testing.assert_array_equal(m[0, 0], [0, 0, 1])


def test_mapset_updates_all_six_maps_and_validates():
    grid = GridSpec(64, 5.0)
    rng = np.random.default_rng(3)
    ms = MapSet(grid, P)
    isms = {k: random_masses(rng, grid.shape) for k in ("ray_ilm", "ray_irm", "deep_irm")}
    ms.update(SE2(0.3, 0.1, 0.2), isms)
    ms.update(SE2(0.6, 0.1, 0.25), isms)
    assert ms.n_updates == 2
    for name in MAP_NAMES:
        m, cov, _, _ = ms[name].to_dense()
        mass.validate(m)
        assert cov.sum() > 64 * 64 * 0.9
    # the fused map differs from both of its parts
    a, b, c = (ms[n].to_dense()[0] for n in ("fused", "deep_disc", "ray_irm"))
    assert not np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(ValueError, match="missing ISM"):
        ms.update(SE2(), {"ray_ilm": isms["ray_ilm"]})
    with pytest.raises(ValueError, match="unknown map"):
        MapSet(grid, names=("ray_ilm", "octomap"))
    assert MapSet(grid, names=("ray_ilm",)).required_isms == ("ray_ilm",)


def _maps_equal(a, b) -> None:
    for name in a.names:
        ma, ca, ra, cca = a[name].to_dense()
        mb, cb, rb, ccb = b[name].to_dense()
        assert (ra, cca) == (rb, ccb), name
        np.testing.assert_array_equal(ma, mb, err_msg=name)
        np.testing.assert_array_equal(ca, cb, err_msg=name)


@settings(max_examples=25, deadline=None)
@given(
    names=st.lists(st.sampled_from(tuple(RULES)), min_size=1, max_size=7, unique=True),
    poses=st.lists(
        st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-math.pi, math.pi)),
        min_size=1,
        max_size=3,
    ),
    tile_cells=st.sampled_from([8, 24, 256]),
    seed=st.integers(0, 2**16),
)
def test_one_pass_update_equals_warping_whole_windows_then_fusing(names, poses, tile_cells, seed):
    """MapSet.update samples each ISM inside the rules' loop: the same maps, bit for bit, as the
    oracle's two passes through whole warped windows (tests/oracle.py), at any pose, over any
    tiling, for any subset of maps (nav included), with sparse ISMs (skipped vacuous blocks) and
    invalid cells."""
    grid = GridSpec(40, 4.0)
    rng = np.random.default_rng(seed)
    one = MapSet(grid, P, tuple(names), tile_cells)
    two = TwoPassMaps(grid, P, tuple(names), tile_cells)
    for x, y, yaw in poses:
        isms = {}
        for k in ("ray_ilm", "ray_irm", "deep_irm"):
            m = random_masses(rng, grid.shape)
            if rng.random() < 0.5:  # a few informative 8 x 8 blocks
                m[~np.kron(rng.random((5, 5)) < 0.3, np.ones((8, 8), bool))] = [0, 0, 1]
            m[tuple(rng.integers(0, 40, (2, 3)))] = [np.nan, 0.0, 1.0]
            isms[k] = m
        pose = SE2(x, y, yaw)
        assert one.update(pose, isms) == {n: 0 for n in names}
        assert two.update(pose, isms) == {n: 0 for n in names}
    _maps_equal(one, two)
    assert one.n_rejected == two.n_rejected and all(v > 0 for v in one.n_rejected.values())
    assert one.n_updates == two.n_updates == len(poses)


def test_one_pass_update_rejects_bad_isms_naming_them():
    ms = MapSet(GridSpec(16, 2.0), P, ("fused",))
    good = np.zeros((16, 16, 3), np.float32)
    good[..., 2] = 1
    with pytest.raises(
        ValueError, match=r"deep_irm: the local grid must be .* shape \(16, 16, 3\)"
    ):
        ms.update(SE2(), {"deep_irm": good[:8], "ray_irm": good})
    with pytest.raises(ValueError, match="deep_irm: the local grid must be a numeric array"):
        ms.update(SE2(), {"deep_irm": good.astype(str), "ray_irm": good})


def test_attached_map_sets_are_rows_of_the_same_pass():
    """The m_u_min sweep's extra map sets: attached, each keeps its own m_u_min and gets the
    same maps, bit for bit, as updating it on its own."""
    grid = GridSpec(40, 4.0)
    rng = np.random.default_rng(11)
    host = MapSet(grid, P, ("ray_ilm", "fused"), 24)
    swept = ("deep_replace", "deep_disc", "fused")
    extras = [MapSet(grid, FusionParams(m_u_min=v), swept, 24) for v in (0.1, 0.6)]
    alone = [MapSet(grid, FusionParams(m_u_min=v), swept, 24) for v in (0.1, 0.6)]
    for e in extras:
        host.attach(e)
    for k in range(3):
        isms = {i: random_masses(rng, grid.shape) for i in ("ray_ilm", "ray_irm", "deep_irm")}
        pose = SE2(0.4 * k, -0.2 * k, 0.3 * k)
        assert host.update(pose, isms) == {"ray_ilm": 0, "fused": 0}
        for a in alone:
            a.update(pose, isms)
    for e, a in zip(extras, alone):
        _maps_equal(e, a)
        assert e.n_updates == 3
        assert e.n_rejected == {i: host.n_rejected[i] for i in e.required_isms}
    assert not np.array_equal(extras[0]["deep_disc"].to_dense()[0], host["fused"].to_dense()[0])
    with pytest.raises(ValueError, match="attached"):
        extras[0].update(SE2(), isms)
    with pytest.raises(ValueError, match="once"):
        host.attach(extras[0])
    with pytest.raises(ValueError, match=r"needs ISMs \['ray_irm'\]"):
        MapSet(grid, P, ("ray_ilm",)).attach(MapSet(grid, P, ("ray_irm",)))
    with pytest.raises(ValueError, match="grid"):
        host.attach(MapSet(GridSpec(32, 4.0), P, ("ray_ilm",)))


def test_windows_for_observers_are_the_warps_of_the_last_update():
    # MapUpdate.windows: the ISMs of the last update warped whole; no map is updated from them
    grid = GridSpec(32, 4.0)
    rng = np.random.default_rng(5)
    ms = MapSet(grid, P, ("ray_ilm", "fused"))
    isms = {i: random_masses(rng, grid.shape) for i in ("ray_ilm", "ray_irm", "deep_irm")}
    pose = SE2(0.7, -0.3, 0.4)
    ms.update(pose, isms)
    before = {n: ms[n].to_dense()[0].copy() for n in ms.names}
    windows = ms.windows(pose)
    assert set(windows) == {"ray_ilm", "ray_irm", "deep_irm"}
    for name, w in windows.items():
        ref = Warper(grid).warp(isms[name], pose)
        assert (w.r0, w.c0) == (ref.r0, ref.c0)
        np.testing.assert_array_equal(w.masses, ref.masses)
        np.testing.assert_array_equal(w.covered, ref.covered)
    for n in ms.names:
        np.testing.assert_array_equal(ms[n].to_dense()[0], before[n])


def test_clear_occupied_moves_occupied_mass_to_free_in_the_maps_named_only(tmp_path):
    from evgrid.store import TileStore

    grid = GridSpec(40, 4.0)
    rng = np.random.default_rng(5)
    host = MapSet(grid, P, ("deep_acc", "deep_replace", "ray_irm"), 24)
    extra = MapSet(grid, FusionParams(m_u_min=0.1), ("deep_replace",), 24)
    host.attach(extra)
    host.update(SE2(0.1, 0.2, 0.3), {i: random_masses(rng, grid.shape) for i in host.required_isms})
    host.attach_store(TileStore(tmp_path / "store"))
    maps = {n: host.maps[n] for n in host.names} | {"extra": extra.maps["deep_replace"]}
    before = {n: m.to_dense() for n, m in maps.items()}
    keys_before = {n: set(m.tiles) for n, m in maps.items()}
    host.page_out(1e3, 1e3, 1.0)  # every tile to the store: clearing brings them back
    _, _, r0, c0 = before["deep_acc"]
    r0, c0 = r0 - 3, c0 - 3
    # the mask covers every map's dense extent so that each can be sliced from it
    rows = max(mr - r0 + m.shape[0] for m, _, mr, _ in before.values())
    cols = max(mc - c0 + m.shape[1] for m, _, _, mc in before.values())
    mask = np.zeros((rows, cols), bool)
    mask[rows // 2 - 6 : rows // 2 + 4, cols // 2 - 30 : cols // 2 + 2] = True  # seen and not
    n = host.clear_occupied(r0, c0, mask, ("deep_acc", "deep_replace"))
    n_occ = 0
    for name, em in maps.items():
        m, cov, mr, mc = em.to_dense()
        m0, cov0, mr0, mc0 = before[name]
        assert (mr, mc) == (mr0, mc0) and set(em.tiles) == keys_before[name]  # no tile created
        np.testing.assert_array_equal(cov, cov0)
        if name == "ray_irm":  # not named: untouched
            np.testing.assert_array_equal(m, m0)
            continue
        sel = mask[mr - r0 : mr - r0 + m.shape[0], mc - c0 : mc - c0 + m.shape[1]]
        np.testing.assert_allclose(m[sel][:, 0], m0[sel][:, 0] + m0[sel][:, 1], rtol=1e-6)
        assert (m[sel][:, 1] == 0).all()
        np.testing.assert_array_equal(m[sel][:, 2], m0[sel][:, 2])
        np.testing.assert_array_equal(m[~sel], m0[~sel])
        mass.validate(m)
        n_occ += int((m0[sel][:, 1] > 0).sum())
    assert n == n_occ > 0
    with pytest.raises(ValueError, match="cannot change"):
        MapSet(grid, P, ("ray_ilm", "fused", "nav")).clear_occupied(0, 0, mask, ("fused",))
