"""The dynamic score (issue 27): the conflict of the Dempster step split by direction and
accumulated with a decay (docs/equations.md#the-dynamic-score), and the maps unchanged by it."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from evgrid.classes import FREE
from evgrid.config import MapperConfig
from evgrid.evaluate import classify
from evgrid.fusion import DynamicParams, MapSet
from evgrid.geometry import SE2, GridSpec
from tests.test_golden_maps import GOLDEN, POSES, _digest, _isms, mapper_maps


def _uniform(n: int, f: float, o: float) -> np.ndarray:
    g = np.empty((n, n, 3), np.float32)
    g[...] = (f, o, 1.0 - f - o)
    return g


def _step(ms: MapSet, n: int, ilm, irm, deep=(0.0, 0.0)) -> None:
    ms.update(
        SE2(),
        {
            "ray_ilm": _uniform(n, *ilm),
            "ray_irm": _uniform(n, *irm),
            "deep_irm": _uniform(n, *deep),
        },
    )


def test_dynamic_score_split_and_decay_hand_computed():
    grid = GridSpec(16, 2.0)
    n = grid.n_cells
    names = ("ray_ilm", "ray_irm", "deep_disc", "fused")
    ms = MapSet(grid, names=names, dynamic=DynamicParams(decay=0.5, threshold=0.3))
    assert ms.dynamic_maps == ("ray_ilm", "ray_irm", "fused")
    assert not ms["deep_disc"].dynamic  # no Dempster step on an ISM: no score

    def score(name):
        # the score of the covered cells (all alike: the ISMs are uniform, the pose identity)
        m, cov, _, _ = ms[name].to_dense()
        assert cov.sum() == n * n
        return ms[name].read_dynamic(*ms[name].bounds())[cov]

    def cell(name):
        m, cov, _, _ = ms[name].to_dense()
        return m[cov][0].astype(np.float64)

    # first update: the maps are vacuous, so there is no conflict
    _step(ms, n, ilm=(0.6, 0.1), irm=(0.2, 0.1))
    for name in ms.dynamic_maps:
        assert score(name).max() == 0.0
    before = {k: cell(k) for k in names}
    np.testing.assert_allclose(before["ray_ilm"], [0.6, 0.1, 0.3], rtol=1e-6)
    # second: something arrives in every cell. K_arr = m_f(map) m_o(ISM), K_left = m_o(map)
    # m_f(ISM), from the map cell before the update
    _step(ms, n, ilm=(0.1, 0.7), irm=(0.05, 0.6), deep=(0.3, 0.2))
    f, o, _ = before["ray_ilm"]
    assert np.allclose(score("ray_ilm"), f * 0.7 + o * 0.1, rtol=1e-6)  # 0.42 + 0.01
    f, o, _ = before["ray_irm"]
    assert np.allclose(score("ray_irm"), f * 0.6 + o * 0.05, rtol=1e-6)
    # fused: its Dempster step is with the ray IRM; the map cell is the one before the update
    f, o, _ = before["fused"]
    s_fused = f * 0.6 + o * 0.05
    assert np.allclose(score("fused"), s_fused, rtol=1e-6)
    # third: vacuous ISMs add nothing and the score decays
    s_ilm = 0.5 * (0.6 * 0.7 + 0.1 * 0.1)
    _step(ms, n, ilm=(0.0, 0.0), irm=(0.0, 0.0))
    assert np.allclose(score("ray_ilm"), s_ilm, rtol=1e-6)
    assert np.allclose(score("fused"), 0.5 * s_fused, rtol=1e-6)
    # fourth: the ISM says free as much as occupied (not free now): both directions add
    m = cell("ray_ilm")
    _step(ms, n, ilm=(0.3, 0.3), irm=(0.0, 0.0))
    s_ilm = 0.5 * s_ilm + m[0] * 0.3 + m[1] * 0.3
    assert np.allclose(score("ray_ilm"), s_ilm, rtol=1e-6)
    # fifth: the ISM sees the cells free now: whatever moved there is gone, the score is 0
    _step(ms, n, ilm=(0.8, 0.0), irm=(0.0, 0.0))
    assert score("ray_ilm").max() == 0.0
    assert np.allclose(score("fused"), 0.5**3 * s_fused, rtol=1e-6)  # vacuous ray IRM: decays


def test_invalid_ism_cells_add_nothing_to_the_score():
    grid = GridSpec(16, 2.0)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=DynamicParams(decay=1.0))
    ms.update(SE2(), {"ray_ilm": _uniform(16, 0.9, 0.0)})
    bad = _uniform(16, 0.0, 0.9)
    bad[2, 3] = (np.nan, 0.5, 0.5)
    ms.update(SE2(), {"ray_ilm": bad})
    _, cov, _, _ = ms["ray_ilm"].to_dense()
    s = ms["ray_ilm"].read_dynamic(*ms["ray_ilm"].bounds())[cov]
    assert s.max() == pytest.approx(0.81, rel=1e-6)  # m_f(map) m_o(ISM) = 0.9 * 0.9
    assert (s == 0.0).sum() == 1


def test_score_off_keeps_no_layer_and_says_so():
    ms = MapSet(GridSpec(16, 2.0), names=("ray_ilm",))
    assert ms.dynamic_maps == () and not ms["ray_ilm"].dynamic
    with pytest.raises(ValueError, match="no dynamic layer"):
        ms["ray_ilm"].read_dynamic(0, 0, 4, 4)
    with pytest.raises(TypeError, match="DynamicParams"):
        MapSet(GridSpec(16, 2.0), dynamic={"enabled": True})


@pytest.mark.parametrize(
    "kwargs", [{"decay": 0.0}, {"decay": 1.5}, {"threshold": 0.0}, {"enabled": "yes"}]
)
def test_dynamic_params_are_checked(kwargs):
    with pytest.raises(ValueError):
        DynamicParams(**kwargs)


def test_the_score_changes_no_mass_golden_fusion_maps():
    # the reference maps of tests/test_golden_maps.py, with the dynamic score on
    grid = GridSpec(n_cells=128, length_m=19.2)
    maps = MapSet(grid, dynamic=DynamicParams())
    rng = np.random.default_rng(20261202)
    for pose in POSES:
        maps.update(pose, _isms(rng, grid.n_cells))
    digests = {name: _digest(maps[name]) for name in maps.names}
    assert digests == json.loads(GOLDEN.read_text())["fusion"]
    assert any(maps[n].read_dynamic(*maps[n].bounds()).max() > 0 for n in maps.dynamic_maps)


def test_golden_mapper_maps_with_the_score_off():
    # bit for bit the same maps with the score on (the default) and off, on this CPU; the
    # golden test compares them with 1f2fccd's across CPUs (tests/test_golden_maps.py)
    assert MapperConfig().dynamic.enabled
    on, off = mapper_maps(dynamic=True), mapper_maps(dynamic=False)
    assert sorted(on) == sorted(off)
    for key in on:
        np.testing.assert_array_equal(on[key], off[key], err_msg=key)


def test_dynamic_on_off_is_a_named_override():
    from evgrid.cli.options import MAP_OPTIONS, options_to_overrides
    from evgrid.config import RunConfig, resolve_config

    assert MAP_OPTIONS["dynamic"] == ("mapper.dynamic.enabled",)
    # a bool option: --dynamic=on|off, or --dynamic / --no-dynamic
    for args, on in (
        (["--dynamic=off"], False),
        (["--dynamic=on"], True),
        (["--no-dynamic"], False),
        (["--dynamic"], True),
    ):
        overrides, _ = options_to_overrides(args, MAP_OPTIONS, RunConfig)
        assert resolve_config(RunConfig, overrides=overrides).mapper.dynamic.enabled is on
    with pytest.raises(ValueError, match="dynamic"):
        resolve_config(RunConfig, overrides=[("mapper.dynamic.decay", "2")])


def test_dynamic_confusion_and_scores_hand_counted():
    from evgrid.evaluate import detection_scores, dynamic_confusion, dynamic_summary

    score = np.array([[0.9, 0.9, 0.1], [0.5, 0.0, 0.9]], np.float32)
    moving = np.array([[True, False, True], [True, False, False]])
    observed = np.array([[True, True, True], [True, True, False]])
    # called & observed: (0,0), (0,1), (1,0); truth & observed: (0,0), (0,2), (1,0)
    assert dynamic_confusion(score, 0.3, moving, observed) == (2, 1, 1)
    s = detection_scores(2, 1, 1)
    assert s == {"precision": 2 / 3, "recall": 2 / 3, "iou": 0.5}
    assert np.isnan(detection_scores(0, 0, 3)["precision"])
    with pytest.raises(ValueError, match="differ"):
        dynamic_confusion(score, 0.3, moving[:1], observed)
    out = dynamic_summary(
        [{"ray_ilm": {"precision": 0.5, "recall": 1.0, "iou": 0.5}}, {"ray_ilm": s}]
    )
    assert set(out["ray_ilm"]) == {"precision", "recall", "iou"}
    assert out["ray_ilm"]["precision"]["mean"] == pytest.approx((0.5 + 2 / 3) / 2)
    assert out["ray_ilm"]["recall"]["lo"] <= out["ray_ilm"]["recall"]["hi"]


def test_scene_scores_score_the_dynamic_layer_against_moving_objects():
    from evgrid.mapper import OccupancyMapper
    from evgrid.observers import SceneScores, TruthTracker
    from evgrid_sim import SimConfig, simulate_scene

    cfg = MapperConfig(maps=("ray_ilm", "ray_irm"))
    truth = TruthTracker(cfg.grid, cfg.tile_cells)
    mapper = OccupancyMapper(cfg, observers=(truth,))
    scores = SceneScores(mapper.maps.maps, truth, track=False)
    mapper.observers.append(scores)
    for frame in simulate_scene(3, SimConfig(duration_s=3.0)):
        mapper.process(frame)
    assert any("dynamic" in k for k in scores.keyframes)
    final = scores.final()["dynamic"]
    assert set(final) == {"ray_ilm", "ray_irm"}
    for d in final.values():
        assert d["tp"] + d["fn"] > 0  # the scene has moving objects the sensors saw
        assert d["iou"] == pytest.approx(d["tp"] / (d["tp"] + d["fp"] + d["fn"]))


def test_bench_times_the_score_on_and_off():
    from evgrid_lab.bench import _dynamic_cost

    rng = np.random.default_rng(0)
    grid = GridSpec(64, 8.0)
    a, b = (rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32) for _ in range(2))
    res = _dynamic_cost(grid, a, b, SE2(0.3, -0.2, 0.7), repeat=2)
    assert res["on"] > 0 and res["off"] > 0
    assert res["cost"] == pytest.approx(res["on"] - res["off"])


# --- the gate (docs/equations.md#the-gate) -----------------------------------------------------


def _cell(ms: MapSet, name: str) -> np.ndarray:
    m, cov, _, _ = ms[name].to_dense()
    return m[cov][0].astype(np.float64)


def test_gate_hand_computed():
    grid = GridSpec(16, 2.0)
    n = grid.n_cells
    names = ("ray_ilm", "ray_irm", "fused")
    d = DynamicParams(decay=0.5, threshold=0.1, gate_maps=True)
    gated, plain = (MapSet(grid, names=names, dynamic=x) for x in (d, replace(d, gate_maps=False)))
    for ms in (gated, plain):
        _step(ms, n, ilm=(0.0, 0.8), irm=(0.0, 0.8))  # something there: (0, 0.8, 0.2)
    # it leaves: K_left = 0.8 * 0.6 = 0.48 > 0.1, and the ISM says free (0.6 > 0)
    for ms in (gated, plain):
        _step(ms, n, ilm=(0.6, 0.0), irm=(0.6, 0.0))
    # gated: (0, 0.8, 0.2) -> (0, 0, 1) before eq. (5), then (+)_D (0.6, 0, 0.4) = the ISM
    for name in ("ray_ilm", "ray_irm"):
        np.testing.assert_allclose(_cell(gated, name), [0.6, 0.0, 0.4], atol=1e-6)
    # not gated: eq. (5) with K = 0.48: (0.2 * 0.6, 0.8 * 0.4, 0.2 * 0.4) / 0.52
    np.testing.assert_allclose(
        _cell(plain, "ray_ilm"), np.array([0.12, 0.32, 0.08]) / 0.52, rtol=1e-6
    )
    # fused: the gate before its steps (the deep IRM is vacuous here: only the ray IRM acts)
    np.testing.assert_allclose(_cell(gated, "fused"), [0.6, 0.0, 0.4], atol=1e-6)


def test_gate_keeps_what_the_ism_says_occupied_and_what_scores_low():
    grid = GridSpec(16, 2.0)
    n = grid.n_cells
    # the gate reads its own threshold, not the call's (threshold 0.01 calls the cell dynamic)
    d = DynamicParams(decay=0.5, threshold=0.01, gate_threshold=0.3, gate_maps=True)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=d)
    _step(ms, n, ilm=(0.0, 0.8), irm=(0.0, 0.0))
    # K_left = 0.8 * 0.3 = 0.24 <= 0.3: no gate, eq. (5) as without it
    _step(ms, n, ilm=(0.3, 0.0), irm=(0.0, 0.0))
    np.testing.assert_allclose(
        _cell(ms, "ray_ilm"), np.array([0.2 * 0.3, 0.8 * 0.7, 0.2 * 0.7]) / (1 - 0.24), rtol=1e-6
    )
    # an ISM that says occupied (0.5 > 0.2) is never gated, whatever the score
    ms = MapSet(grid, names=("ray_ilm",), dynamic=replace(d, gate_threshold=0.01))
    _step(ms, n, ilm=(0.0, 0.8), irm=(0.0, 0.0))
    _step(ms, n, ilm=(0.2, 0.5), irm=(0.0, 0.0))  # K_left = 0.16 > 0.01
    f1, o1, u1, f2, o2, u2 = 0.0, 0.8, 0.2, 0.2, 0.5, 0.3
    k = f1 * o2 + o1 * f2
    want = np.array([u1 * f2, o1 * o2 + o1 * u2 + u1 * o2, u1 * u2]) / (1 - k)
    np.testing.assert_allclose(_cell(ms, "ray_ilm"), want, rtol=1e-6)


def test_gate_is_off_for_the_papers_maps_by_default_golden():
    grid = GridSpec(n_cells=128, length_m=19.2)
    assert not DynamicParams().gate_maps
    maps = MapSet(grid, dynamic=DynamicParams(doppler_mass=0.7))
    rng = np.random.default_rng(20261202)
    for pose in POSES:
        # a Doppler cue too: it raises scores, never a mass
        near = [[pose.x + 2.0, pose.y, 5.0, pose.x, pose.y]]  # 2 m ahead, seen from the ego
        maps.update(pose, _isms(rng, grid.n_cells), np.array(near))
    assert {n: _digest(maps[n]) for n in maps.names} == json.loads(GOLDEN.read_text())["fusion"]
    gated = MapSet(grid, dynamic=DynamicParams(gate_maps=True))
    rng = np.random.default_rng(20261202)
    for pose in POSES:
        gated.update(pose, _isms(rng, grid.n_cells))
    changed = {n for n in gated.names if _digest(gated[n]) != _digest(maps[n])}
    assert changed == {"ray_ilm", "deep_acc", "ray_irm", "fused"}  # the maps with a score


# --- the Doppler cue (docs/equations.md#the-doppler-cue) --------------------------------------


def _disc_cells(grid, pose, box, xy, radius):
    from evgrid.doppler import disc_runs

    ptr, runs = disc_runs(grid, pose, box, xy, radius)
    assert ptr[0] == 0 and ptr[-1] == len(runs) and (np.diff(ptr) >= 0).all()
    cells = []
    for i in range(box[2]):
        row = runs[ptr[i] : ptr[i + 1]]
        assert (row[:, 1] > row[:, 0]).all() and (row[1:, 0] > row[:-1, 1]).all()  # disjoint
        cells += [(box[0] + i, box[1] + c) for a, b in row for c in range(a, b)]
    return cells


def _moving(centre, speed: float, radius: float) -> np.ndarray:
    """A ``(1, 5)`` moving detection whose disc of ``radius`` is centred on ``centre``: the
    detection ``radius`` before it, seen by a radar 10 m further along +x."""
    x, y = centre
    return np.array([[x + radius, y, speed, x + radius + 10.0, y]])


def test_doppler_discs_lie_behind_the_detection_hand_computed():
    from evgrid.doppler import disc_centres

    # the radar at the origin: a detection at (3, 4) m has its disc's centre 1 m further out
    moving = np.array([[3.0, 4.0, 5.0, 0.0, 0.0], [-2.0, 0.0, 5.0, 1.0, 0.0]])
    np.testing.assert_allclose(disc_centres(moving, 1.0), [[3.6, 4.8], [-3.0, 0.0]])
    # a detection on the radar itself: no line of sight, the disc stays on it
    np.testing.assert_array_equal(
        disc_centres(np.array([[1.0, 2.0, 5.0, 1.0, 2.0]]), 1.0), [[1, 2]]
    )
    # in a map update the detection's own cell is in its disc (on the near edge)
    grid = GridSpec(16, 2.0)  # 0.125 m cells
    res = grid.resolution
    d = DynamicParams(doppler_mps=0.5, doppler_mass=0.4, doppler_radius_m=2 * res)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=d)
    det = np.array([[-3.5 * res, -5.5 * res, 3.0, 5.0, -5.5 * res]])  # map cell (3, 5), radar at +x
    ms.update(SE2(), {"ray_ilm": _uniform(16, 0.0, 0.0)}, det)
    s = ms["ray_ilm"].read_dynamic(0, 0, 8, 8)
    # x decreases with the row: the disc of 2 cells round cell (5, 5), rows 3-7
    assert s[3, 5] == pytest.approx(0.4) and s[7, 5] == pytest.approx(0.4)
    assert s[2, 5] == 0.0 and (s[3:8, 5] > 0).all() and (s > 0).sum() == 13
    with pytest.raises(ValueError, match=r"moving must be \(k, 5\).*\(1, 3\)"):
        ms.update(SE2(), {"ray_ilm": _uniform(16, 0.0, 0.0)}, det[:, :3])
    with pytest.raises(ValueError, match=r"moving has 1 row\(s\) with NaN"):
        ms.update(SE2(), {"ray_ilm": _uniform(16, 0.0, 0.0)}, det * np.array([1, 1, np.nan, 1, 1]))


def test_doppler_discs_as_runs_hand_computed():
    grid = GridSpec(16, 2.0)  # 0.125 m cells
    res = grid.resolution
    box = (-8, -8, 16, 16)  # the window at the identity pose
    # the centre of map cell (3, 5): x = -(3 + 0.5) res, y = -(5 + 0.5) res
    xy = np.array([[-3.5 * res, -5.5 * res]])
    disc = {(a, b) for a in range(-2, 3) for b in range(-2, 3) if a * a + b * b <= 4}
    # centres within 2 cells: the cell, 4 at 1, 4 at sqrt(2), 4 at 2 (not (2, 1): sqrt(5) > 2)
    cells = _disc_cells(grid, SE2(), box, xy, 2 * res)
    assert len(cells) == 13 and {(r - 3, c - 5) for r, c in cells} == disc
    # two discs that overlap: each cell once, a row's runs merged
    two = np.array([[-3.5 * res, -5.5 * res], [-3.5 * res, -2.5 * res], [-3.5 * res, -5.5 * res]])
    cells = _disc_cells(grid, SE2(), box, two, 2 * res)
    assert sorted(cells) == sorted({(3 + a, 5 + b - d) for a, b in disc for d in (0, 3)})
    # a radius below half a cell: the cell that holds the point
    assert _disc_cells(grid, SE2(), box, xy, 0.1 * res) == [(3, 5)]
    # clipped to the window
    assert {c for _, c in _disc_cells(grid, SE2(), (-8, 4, 16, 3), xy, 2 * res)} == {4, 5, 6}
    # outside the local grid at the pose: ignored
    assert _disc_cells(grid, SE2(5.0, 0.0, 0.0), box, xy, 2 * res) == []


def test_doppler_cue_hand_computed():
    grid = GridSpec(16, 2.0)  # 0.125 m cells
    res = grid.resolution
    xy = np.array([[-3.5 * res, -5.5 * res]])  # the centre of map cell (3, 5)
    d = DynamicParams(decay=0.5, doppler_mps=0.5, doppler_mass=0.4, doppler_radius_m=2 * res)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=d)
    isms = {"ray_ilm": _uniform(16, 0.0, 0.0)}
    # at the identity pose local row r is map row r - 8 (the ego sits on the grid's centre)
    isms["ray_ilm"][8:12] = (0.6, 0.2, 0.2)  # map rows 0-3
    isms["ray_ilm"][13] = (0.0, 0.3, 0.7)  # map row 5
    slow = MapSet(grid, names=("ray_ilm",), dynamic=d)
    slow.update(SE2(), isms, _moving(xy[0], 0.4, 2 * res))  # not faster than doppler_mps: nothing
    assert slow["ray_ilm"].read_dynamic(*slow["ray_ilm"].bounds()).max() == 0.0
    ms.update(SE2(), isms, _moving(xy[0], 0.6, 2 * res))
    r0, c0, h, w = ms["ray_ilm"].bounds()
    s = ms["ray_ilm"].read_dynamic(r0, c0, h, w)
    assert (s > 0).sum() == 13
    # mass times 1 - m_f / (m_f + m_o) of the ISM now: 0.4 * 0.25 in rows 0-3, 0.4 in row 4
    # (vacuous: nothing rules a mover out) and row 5 (only occupied); no conflict at first
    assert s[3 - r0, 5 - c0] == pytest.approx(0.4 * 0.2 / 0.8)
    assert s[4 - r0, 5 - c0] == pytest.approx(0.4) and s[5 - r0, 5 - c0] == pytest.approx(0.4)
    two = np.concatenate([_moving(xy[0], 0.6, 2 * res), _moving(xy[0], 9.0, 2 * res)])
    ms.update(SE2(), isms, two)  # one disc: added once
    s = ms["ray_ilm"].read_dynamic(r0, c0, h, w)
    # row 3: the ISM sees it free (0.6 > 0.2): its score restarts from 0, then the cue's 0.1
    assert s[3 - r0, 5 - c0] == pytest.approx(0.1)
    # row 5: decay, no conflict (the map cell (0, 0.3, 0.7) meets the same ISM cell), the cue
    assert s[5 - r0, 5 - c0] == pytest.approx(0.5 * 0.4 + 0.4)


def test_doppler_cue_in_the_pass_reads_the_nearest_ism_cell_hand_computed():
    # the cue, added in the pass, reads the local ISM cell nearest to the map cell's centre,
    # not the bilinear sample that the Dempster step combines
    grid = GridSpec(16, 2.0)
    res = grid.resolution
    ism = _uniform(16, 0.0, 0.0)
    ism[8:12] = (0.6, 0.2, 0.2)  # map rows 0-3 at the identity pose
    ism[12:] = (0.0, 0.3, 0.7)  # map rows 4-7
    d = DynamicParams(decay=0.5, doppler_mps=0.5, doppler_mass=0.4, doppler_radius_m=2 * res)
    ms = MapSet(grid, names=("ray_ilm",), dynamic=d)
    pose = SE2(-0.3 * res, 0.0, 0.0)  # map row 4's centre is 0.3 cells from local row 11
    ms.update(pose, {"ray_ilm": ism}, _moving((-4.0 * res, -5.5 * res), 3.0, 2 * res))
    window = ms.windows(pose)["ray_ilm"]
    sample = window.masses[4 - window.r0, 5 - window.c0]
    assert sample == pytest.approx((0.3 * 0.6, 0.3 * 0.2 + 0.7 * 0.3, 0.3 * 0.2 + 0.7 * 0.7))
    s = ms["ray_ilm"].read_dynamic(0, 0, 8, 8)
    # the disc of 2 cells round the edge of cells (3, 5) and (4, 5): rows 2-5, columns 4-6
    assert (s > 0).sum() == 12 and (s[2:6, 4:7] > 0).all()
    # 0.4 (1 - m_f / (m_f + m_o)): 0.4 * 0.2 / 0.8 on rows 2-3, 0.4 on rows 4-5 (their nearest
    # ISM cell says only occupied; the sample would give 0.4 * 0.27 / 0.45)
    assert s[2, 5] == pytest.approx(0.1) and s[3, 5] == pytest.approx(0.1)
    assert s[4, 5] == pytest.approx(0.4) and s[5, 5] == pytest.approx(0.4)


def test_doppler_cue_reads_each_maps_own_ism_and_disc_set():
    # the pass finds a row's disc cells once and the not-free shares once per ISM, for all maps:
    # each map still reads its own Dempster step's ISM (fused: the ray IRM), and a set attached
    # with another radius its own discs (a first update: no conflict, the score is the cue)
    grid = GridSpec(16, 2.0)
    res = grid.resolution
    names = ("ray_ilm", "deep_acc", "ray_irm", "fused")
    d = DynamicParams(decay=0.5, doppler_mps=0.5, doppler_mass=0.4, doppler_radius_m=2 * res)
    ms = MapSet(grid, names=names, dynamic=d)
    small = MapSet(grid, names=("ray_irm",), dynamic=replace(d, doppler_radius_m=0.1 * res))
    ms.attach(small)
    isms = {
        "ray_ilm": _uniform(16, 0.6, 0.2),  # 1 - m_f / (m_f + m_o) = 0.25
        "ray_irm": _uniform(16, 0.2, 0.6),  # 0.75
        "deep_irm": _uniform(16, 0.0, 0.0),  # vacuous: 1
    }
    # map cell (3, 5), seen from its own position: each set's disc is centred on it
    ms.update(SE2(), isms, np.array([[-3.5 * res, -5.5 * res, 3.0, -3.5 * res, -5.5 * res]]))
    for name, share in zip(names, (0.25, 1.0, 0.75, 0.75)):
        s = ms[name].read_dynamic(0, 0, 8, 8)
        assert (s > 0).sum() == 13, name
        assert s[3, 5] == pytest.approx(0.4 * share) and s[1, 5] == pytest.approx(0.4 * share)
    s = small["ray_irm"].read_dynamic(0, 0, 8, 8)
    assert (s > 0).sum() == 1 and s[3, 5] == pytest.approx(0.4 * 0.75)


def test_doppler_cue_counts_for_the_next_updates_gate():
    # the cue is added after the gate: this update's gate does not see it, the next one does
    grid = GridSpec(16, 2.0)
    res = grid.resolution
    d = DynamicParams(
        decay=0.3, gate_threshold=0.5, gate_maps=True, doppler_mps=0.5, doppler_mass=1.0
    )
    cue, twin = (
        MapSet(grid, names=("ray_ilm",), dynamic=d),
        MapSet(grid, names=("ray_ilm",), dynamic=replace(d, doppler_mass=0.0)),
    )
    here = _moving((-3.5 * res, -5.5 * res), 3.0, d.doppler_radius_m)  # round map cell (3, 5)
    tie = _uniform(16, 0.4, 0.4)  # not occupied (the gate may act) nor free (the score stays)
    for ms in (cue, twin):
        ms.update(SE2(), {"ray_ilm": _uniform(16, 0.2, 0.6)}, None)  # occupied
        ms.update(SE2(), {"ray_ilm": tie}, here)
    # K = 0.2 * 0.4 + 0.6 * 0.4 = 0.32 < 0.5: not gated; then the cue adds 1.0 * 0.4 / 0.8
    s = cue["ray_ilm"].read_dynamic(3, 5, 1, 1)[0, 0]
    assert s == pytest.approx(0.32 + 0.5) and s > d.gate_threshold
    assert np.array_equal(cue["ray_ilm"].read(3, 5, 1, 1)[0], twin["ray_ilm"].read(3, 5, 1, 1)[0])
    for ms in (cue, twin):
        ms.update(SE2(), {"ray_ilm": tie}, None)
    # the map (0.2, 0.44, 0.04) / 0.68 meets the tie: K = 0.4 * 0.64 / 0.68; with the cue
    # 0.3 * 0.82 + K > 0.5 is gated (m_o to m_u first), without it 0.3 * 0.32 + K is not
    k = 0.4 * 0.64 / 0.68
    assert cue["ray_ilm"].read_dynamic(3, 5, 1, 1)[0, 0] == pytest.approx(0.3 * 0.82 + k)
    assert twin["ray_ilm"].read_dynamic(3, 5, 1, 1)[0, 0] == pytest.approx(0.3 * 0.32 + k)
    assert (
        cue["ray_ilm"].read(3, 5, 1, 1)[0][0, 0, 1] < twin["ray_ilm"].read(3, 5, 1, 1)[0][0, 0, 1]
    )


def test_doppler_cue_finds_the_simulators_movers():
    from evgrid.mapper import OccupancyMapper
    from evgrid_sim import SimConfig, simulate_scene

    cfg = MapperConfig(maps=("ray_ilm",), frame="first_pose")
    mapper = OccupancyMapper(cfg)
    near = total = 0
    for frame in simulate_scene(9, SimConfig(duration_s=5.0)):
        mapper.process(frame)
        if not frame.is_keyframe or frame.occupancy is None:
            continue
        mapper._doppler_seen.clear()  # the newest sweeps again, for this check
        xy = mapper.moving_detections()
        pose = mapper.pose_in_map(frame.ego_pose)
        local = pose.inverse().apply(xy[:, :2])
        r = np.floor(cfg.grid.n_cells / 2 - local[:, 0] / cfg.grid.resolution).astype(int)
        c = np.floor(cfg.grid.n_cells / 2 - local[:, 1] / cfg.grid.resolution).astype(int)
        inside = (r >= 0) & (r < cfg.grid.n_cells) & (c >= 0) & (c < cfg.grid.n_cells)
        movers = frame.occupancy == 2
        k = 12  # 1 m either way: the radar's position error and the object's extent
        for a, b in zip(r[inside], c[inside]):
            total += 1
            near += bool(movers[max(a - k, 0) : a + k + 1, max(b - k, 0) : b + k + 1].any())
    assert total > 0
    assert near / total > 0.5  # most moving detections are on moving objects (not clutter)


def test_doppler_cue_from_a_bag_radar_scan():
    from types import SimpleNamespace

    from evgrid.data.bag.decoding import compensate, radar_scan_points
    from evgrid.data.frame import RadarSweep
    from evgrid.doppler import moving_detections
    from evgrid.geometry import SE3

    # the sensor drives forward at 5 m/s: a static target dead ahead reads -5 m/s raw; a car
    # coming at us reads -8 m/s
    ret = [
        SimpleNamespace(range=10.0, azimuth=0.0, elevation=0.0, doppler_velocity=-5.0, amplitude=5),
        SimpleNamespace(range=12.0, azimuth=0.1, elevation=0.0, doppler_velocity=-8.0, amplitude=9),
    ]
    pts = radar_scan_points(SimpleNamespace(returns=ret))
    compensate(pts, np.array([5.0, 0.0, 0.0]))
    sweep = RadarSweep(pts, SE3.identity(), SE3.identity(), 0, "RADAR_FRONT")
    xy = moving_detections([sweep], SE3.identity(), 0.5)
    assert xy.shape == (1, 5)
    # its own radial speed: -8 m/s + the sensor's 5 m/s along the line of sight, 5 cos(0.1);
    # the radar at the origin
    want = [12.0 * np.cos(0.1), 12.0 * np.sin(0.1), 8.0 - 5.0 * np.cos(0.1), 0.0, 0.0]
    np.testing.assert_allclose(xy[0], want, rtol=1e-5, atol=1e-12)


# --- the area movers leave behind ---------------------------------------------------------------


def test_left_behind_hand_computed():
    from evgrid.observers import MoverTrail

    grid = GridSpec(16, 2.0)
    m = MapSet(grid, names=("ray_ilm",))["ray_ilm"]
    t, _ = m.tile((0, 0))
    t[:4, :4] = (0.1, 0.8, 0.1)  # occupied
    t[1, 1] = (0.8, 0.1, 0.1)  # free
    t[2, 2] = (0.3, 0.3, 0.4)  # unknown: a tie
    trail = MoverTrail(grid, m.tile_cells)
    moving = np.zeros((3, 3), bool)
    moving[0, :] = True  # cells (1, 1), (1, 2), (1, 3) at the first keyframe
    trail.add(1, 1, moving)
    moving = np.zeros((3, 3), bool)
    moving[1, 1] = True  # (2, 2) at the second
    trail.add(1, 1, moving)
    free = np.ones((4, 4), bool)
    free[1, 3] = False  # cell (1, 3) is not free now
    # left behind: (1, 2) only ((1, 1) is free in the map, (2, 2) unknown, (1, 3) not free now)
    n, area = trail.left_behind(m, 0, 0, free)
    assert n == 1 and area == pytest.approx(grid.resolution**2)


def test_dynamic_options_take_a_value_after_a_space():
    from evgrid.cli.options import MAP_OPTIONS, options_to_overrides
    from evgrid.config import RunConfig, resolve_config

    for args, on, gate in (
        (["--dynamic", "off"], False, False),
        (["--dynamic", "on", "--dynamic-gate", "on"], True, True),
        (["--dynamic", "--dynamic-gate"], True, True),
        (["--dynamic-gate", "off", "--no-dynamic"], False, False),
        (["--dynamic-gate=true", "--maps", "ray_ilm"], True, True),
    ):
        overrides, _ = options_to_overrides(args, MAP_OPTIONS, RunConfig)
        d = resolve_config(RunConfig, overrides=overrides).mapper.dynamic
        assert (d.enabled, d.gate_maps) == (on, gate), args


def test_nav_reads_gated_copies_of_its_inputs_by_default():
    from evgrid.nav import nav_dense

    grid = GridSpec(16, 2.0)
    n = grid.n_cells
    d = DynamicParams(decay=0.5, threshold=0.1)
    assert d.gate_nav and not d.gate_maps
    ms = MapSet(grid, names=("ray_ilm", "fused", "nav"), dynamic=d)
    alone = MapSet(grid, names=("nav",), dynamic=d)  # keeps the ungated lidar map hidden
    gated = MapSet(grid, names=("ray_ilm", "fused"), dynamic=replace(d, gate_maps=True))
    sets = (ms, alone, gated)
    for s in sets:
        _step(s, n, ilm=(0.0, 0.8), irm=(0.0, 0.8))
        _step(s, n, ilm=(0.6, 0.0), irm=(0.6, 0.0))  # the mover left: K_left = 0.48
    # Table I's maps are not gated (the ghost stays occupied); nav reads gated copies of them
    assert _cell(ms, "ray_ilm")[1] > 0.5
    np.testing.assert_allclose(_cell(gated, "ray_ilm"), [0.6, 0.0, 0.4], atol=1e-6)

    def want() -> np.ndarray:
        lidar, cov, _, _ = gated["ray_ilm"].to_dense()
        fused, _, _, _ = gated["fused"].to_dense()
        scores = np.maximum(
            gated["ray_ilm"].read_dynamic(*gated["ray_ilm"].bounds()),
            gated["fused"].read_dynamic(*gated["fused"].bounds()),
        )
        r, occupied_min = ms.nav.margin_cells(grid.resolution), ms.nav.occupied_min
        plain = ms["ray_ilm"].to_dense()[0]
        return nav_dense(lidar, fused, r, occupied_min, scores, 0.1, plain)[cov]

    cov = ms["nav"].to_dense()[1]
    np.testing.assert_allclose(ms["nav"].to_dense()[0][cov], want(), atol=1e-6)
    np.testing.assert_array_equal(alone["nav"].to_dense()[0], ms["nav"].to_dense()[0])
    # no ghost left in nav, and no free space where the ungated lidar map still says occupied:
    # the gate takes the cell to unknown
    np.testing.assert_allclose(ms["nav"].to_dense()[0][cov], [[0.0, 0.0, 1.0]] * cov.sum())
    # once the lidar map's own evidence is free-dominant (0.512 > 0.390), nav is free
    for s in sets:
        _step(s, n, ilm=(0.6, 0.0), irm=(0.6, 0.0))
    np.testing.assert_allclose(_cell(ms, "ray_ilm"), [0.512, 0.390, 0.098], atol=1e-3)
    np.testing.assert_allclose(ms["nav"].to_dense()[0][cov], want(), atol=1e-6)
    assert (classify(ms["nav"].to_dense()[0][cov]) == FREE).all()
    # --no-dynamic: nav reads the shown maps, as before the score existed
    plain = MapSet(grid, names=("ray_ilm", "fused", "nav"))
    assert plain._derived[0][1] is plain.maps["ray_ilm"] and plain._derived[0][3] is None
    assert ms._derived[0][1] is not ms.maps["ray_ilm"] and ms._derived[0][3] is ms.maps["ray_ilm"]


def test_summary_and_table_carry_the_moving_objects():
    from evgrid.runs import dynamic_table, summarize

    def scene(name, p, r, left):
        return {
            "scene": name,
            "frames": 10,
            "seconds": 1.0,
            "dynamic": {"ray_ilm": {"precision": p, "recall": r, "iou": p * r / (p + r - p * r)}},
            "left_behind_m2": {"ray_ilm": left, "deep_disc": 2 * left},
        }

    summary = summarize([scene("a", 0.4, 0.6, 1.0), scene("b", 0.2, 0.4, 3.0)])
    assert summary["dynamic"]["ray_ilm"]["precision"]["mean"] == pytest.approx(0.3)
    left = summary["left_behind_m2"]
    assert left["ray_ilm"]["mean"] == pytest.approx(2.0) and left["deep_disc"]["n"] == 2
    table = dynamic_table(summary)
    rows = {line.split(" | ")[0]: line for line in table.splitlines() if line.startswith("| `")}
    assert rows["| `ray_ilm`"].split(" | ")[1].startswith("30.0 (")  # precision, %, interval
    assert rows["| `ray_ilm`"].endswith("| 2.00 (1.00-3.00) |")
    assert rows["| `deep_disc`"].startswith("| `deep_disc` | - | - | - | 4.00")  # no score


def test_scene_scores_report_the_area_movers_leave_behind():
    from evgrid.mapper import OccupancyMapper
    from evgrid.observers import SceneScores, TruthTracker
    from evgrid_sim import SimConfig, simulate_scene

    cfg = MapperConfig(maps=("ray_ilm",))
    truth = TruthTracker(cfg.grid, cfg.tile_cells)
    mapper = OccupancyMapper(cfg, observers=(truth,))
    scores = SceneScores(mapper.maps.maps, truth, track=False)
    mapper.observers.append(scores)
    for frame in simulate_scene(9, SimConfig(duration_s=4.0)):
        mapper.process(frame)
    assert all("left_behind_m2" in k for k in scores.keyframes if "dynamic" in k)
    final = scores.final()
    area = [k["left_behind_m2"]["ray_ilm"] for k in scores.keyframes if "left_behind_m2" in k]
    assert final["left_behind_m2"]["ray_ilm"] == pytest.approx(np.mean(area))
