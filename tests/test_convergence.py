"""The paper's convergence claim, measured: perception field over time, and intervals over
scenes."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from evgrid import mass
from evgrid.evaluate import bootstrap_interval, iou_intervals, tile_confusions_vs_truth
from evgrid.geometry import GridSpec
from evgrid.grid import EvidentialMap, MapWindow
from evgrid.runs import convergence_at, convergence_table


def test_bootstrap_interval_hand_cases():
    assert bootstrap_interval([0.5, 0.5, 0.5]) == {"mean": 0.5, "lo": 0.5, "hi": 0.5, "n": 3}
    assert bootstrap_interval([0.3, math.nan, None]) == {"mean": 0.3, "lo": 0.3, "hi": 0.3, "n": 1}
    assert bootstrap_interval([])["n"] == 0
    ci = bootstrap_interval([0.0, 1.0] * 10)
    assert ci["mean"] == 0.5 and 0.25 < ci["lo"] < 0.5 < ci["hi"] < 0.75  # sd of the mean ~0.11
    # the same scenes, the same interval: the resampling is seeded
    assert bootstrap_interval([0.1, 0.4, 0.2, 0.9]) == bootstrap_interval([0.1, 0.4, 0.2, 0.9])


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=2, max_size=30))
def test_bootstrap_interval_holds_the_mean_within_the_values(v):
    ci = bootstrap_interval(v)
    assert (
        min(v) - 1e-12 <= ci["lo"] <= ci["mean"] + 1e-12
        and ci["mean"] - 1e-12 <= ci["hi"] <= max(v) + 1e-12
    )


def test_iou_intervals_per_map_and_class():
    scenes = [{"fused": {"free": 0.8, "occupied": None}}, {"fused": {"free": 0.6, "occupied": 0.2}}]
    ci = iou_intervals(scenes)
    assert ci["fused"]["free"]["n"] == 2 and abs(ci["fused"]["free"]["mean"] - 0.7) < 1e-12
    assert ci["fused"]["occupied"] == {"mean": 0.2, "lo": 0.2, "hi": 0.2, "n": 1}


def test_convergence_at_picks_the_first_keyframe_after_each_time():
    def kf(t_s, free):
        return {
            "timestamp": int(t_s * 1e6),
            "field": {"fused": {"free": free, "occupied": 0.1, "area_m2": 100 * free}},
        }

    kfs = [kf(0.0, 0.0), kf(0.5, 0.1), kf(1.0, 0.2), kf(1.5, 0.3), kf(2.5, 0.4)]
    c = convergence_at(kfs, (1.0, 2.0, 5.0))
    assert c["t_s"] == [1.0, 2.0, 5.0]
    assert c["maps"]["fused"]["free"] == [0.2, 0.4, None]
    assert c["maps"]["fused"]["area_m2"] == [20.0, 40.0, None]
    assert convergence_at([{"timestamp": 0}]) == {}


def test_convergence_table_shows_intervals_and_gaps():
    ci = bootstrap_interval([0.5, 0.7])
    conv = {
        "t_s": [1.0, 10.0],
        "maps": {
            "fused": {
                "free": [ci, bootstrap_interval([])],
                "occupied": [ci, ci],
                "area_m2": [bootstrap_interval([100.0]), ci],
            }
        },
    }
    table = convergence_table(conv)
    assert "free IoU 1 s" in table and "correct m² 10 s" in table
    row = table.strip().splitlines()[-1]
    assert row.startswith("| `fused` | 60.0 (") and "| n/a |" in row and "| 100 |" in row


def test_the_perception_field_counts_true_cells_the_reference_never_covered():
    grid = GridSpec(16, 2.0)
    truth, ref, deep = (EvidentialMap(grid, 8) for _ in range(3))
    free = mass.vacuous(grid.shape)
    free[...] = [1.0, 0.0, 0.0]
    win = MapWindow(0, 0, free, np.ones(grid.shape, bool))
    truth.apply(win, lambda c, m: np.copyto(c, m))
    deep.apply(win, lambda c, m: np.copyto(c, m))
    left = MapWindow(0, 0, free[:, :8].copy(), np.ones((16, 8), bool))
    ref.apply(left, lambda c, m: np.copyto(c, m))  # the lidar saw only the left half
    maps = {"ray_ilm": ref, "deep_disc": deep}
    right = (0, 1)  # the right tile column: true free, covered by the deep map only
    restricted = tile_confusions_vs_truth(maps, truth, "ray_ilm", right)
    everything = tile_confusions_vs_truth(maps, truth, None, right)
    assert restricted.sum() == 0
    assert (
        everything[1, 0, 0] == 64 and everything[0, 0, 0] == 0
    )  # deep_disc right, ray_ilm unknown
