"""The dynamic score (issue 27): the conflict of the Dempster step split by direction and
accumulated with a decay (docs/equations.md#the-dynamic-score), and the maps unchanged by it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evgrid.config import MapperConfig
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
    # fourth: something leaves: m_o(map) m_f(ISM)
    m = cell("ray_ilm")
    _step(ms, n, ilm=(0.8, 0.0), irm=(0.0, 0.0))
    assert np.allclose(score("ray_ilm"), 0.5 * s_ilm + m[1] * 0.8, rtol=1e-6)


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
    from evgrid.config import MAP_OPTIONS, RunConfig, options_to_overrides, resolve_config

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
    from evgrid.data import SimConfig, simulate_scene
    from evgrid.mapper import OccupancyMapper
    from evgrid.observers import SceneScores, TruthTracker

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
    from evgrid.bench import _dynamic_cost

    rng = np.random.default_rng(0)
    grid = GridSpec(64, 8.0)
    a, b = (rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32) for _ in range(2))
    res = _dynamic_cost(grid, a, b, SE2(0.3, -0.2, 0.7), repeat=2)
    assert res["on"] > 0 and res["off"] > 0
    assert res["cost"] == pytest.approx(res["on"] - res["off"])
