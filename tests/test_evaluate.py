"""Cell classes, per-class IoU and the Table I report (evgrid.evaluate)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evgrid import mass
from evgrid.evaluate import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    classify,
    compare_maps,
    iou_per_class,
    markdown_table,
    mean_iou,
)
from evgrid.fusion import MapSet
from evgrid.geometry import SE2, GridSpec


def test_classify_largest_mass_ties_to_unknown():
    m = np.array(
        [
            [0.6, 0.3, 0.1],
            [0.1, 0.6, 0.3],
            [0.2, 0.2, 0.6],
            [0.4, 0.4, 0.2],
            [0.45, 0.1, 0.45],
            [0, 0, 1],
        ],
        np.float32,
    )
    assert classify(m).tolist() == [FREE, OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN]


def test_iou_hand_computed():
    pred = np.array([FREE, FREE, OCCUPIED, UNKNOWN, UNKNOWN])
    ref = np.array([FREE, OCCUPIED, OCCUPIED, UNKNOWN, FREE])
    got = iou_per_class(pred, ref)
    # free: inter {0}, union {0, 1, 4} -> 1/3; occupied: inter {2}, union {1, 2} -> 1/2; unknown:
    # {3} / {3, 4}
    assert got == {
        "free": pytest.approx(1 / 3),
        "occupied": pytest.approx(0.5),
        "unknown": pytest.approx(0.5),
    }
    mask = np.array([True, False, True, True, False])
    assert iou_per_class(pred, ref, mask) == {"free": 1.0, "occupied": 1.0, "unknown": 1.0}
    assert math.isnan(iou_per_class(np.array([FREE]), np.array([FREE]))["occupied"])


def test_compare_maps_uses_reference_coverage():
    grid = GridSpec(32, 4.0)
    ms = MapSet(grid, names=("ray_ilm", "ray_irm"))
    free = mass.vacuous(grid.shape)
    free[:, :16] = [0.9, 0.0, 0.1]
    occ = mass.vacuous(grid.shape)
    occ[:, :8] = [0.9, 0.0, 0.1]
    occ[:, 8:16] = [0.0, 0.9, 0.1]
    ms.update(SE2(), {"ray_ilm": free, "ray_irm": occ})
    res = compare_maps(ms.maps)
    # the reference has 32 x 16 free cells; ray_irm agrees on 32 x 8 of them
    assert res["ray_irm"]["free"] == pytest.approx(0.5)
    assert res["ray_irm"]["occupied"] == 0.0
    assert res["ray_irm"]["unknown"] == pytest.approx(1.0)
    with pytest.raises(KeyError):
        compare_maps(ms.maps, reference="fused")


def test_mean_iou_skips_undefined_and_table_lists_paper():
    per_scene = [
        {"fused": {"free": 0.5, "occupied": math.nan, "unknown": 0.2}},
        {"fused": {"free": 0.7, "occupied": 0.1, "unknown": 0.4}},
    ]
    m = mean_iou(per_scene)
    assert m["fused"] == {
        "free": pytest.approx(0.6),
        "occupied": pytest.approx(0.1),
        "unknown": pytest.approx(0.3),
    }
    table = markdown_table(m)
    assert "| `fused` | 60.00 | 10.00 | 30.00 | 76.88 | 5.44 | 45.69 |" in table


def test_free_fraction_near_path_hand_computed():
    from evgrid.grid import EvidentialMap, MapWindow
    from tests.helpers import free_fraction_near_path

    grid = GridSpec(16, 1.6)  # 0.1 m cells
    m = EvidentialMap(grid, 8)
    masses = mass.vacuous(grid.shape)
    masses[:, :8] = [0.9, 0.0, 0.1]  # the left half free, the right half unknown
    m.apply(MapWindow(0, 0, masses, np.ones(grid.shape, bool)), lambda c, w: np.copyto(c, w))
    # a path along the boundary between the halves: x in the map frame is -row, y is -col
    path = [(-(r + 0.5) * 0.1, -8.05 * 0.1, 0.0) for r in range(16)]
    assert (
        free_fraction_near_path(m, path, radius_m=0.05) == 0.0
    )  # only the path's own cells (column 8)
    # within 0.35 m: columns 5..11 of every row, 3 of them free on the left of column 8
    assert abs(free_fraction_near_path(m, path, radius_m=0.35) - 3 / 7) < 1e-9
