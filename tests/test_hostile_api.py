"""Hostile calls of the public API that earlier gave AttributeErrors deep inside (issue 26)."""

from __future__ import annotations

import numpy as np
import pytest

from evgrid.data.frame import RADAR_COLUMNS, RadarSweep
from evgrid.geometry import SE3
from evgrid.ism.deep import DeepIrm, radar_detections


@pytest.fixture(scope="module")
def deep():
    return DeepIrm()


def _sweep() -> RadarSweep:
    points = np.zeros((2, len(RADAR_COLUMNS)), np.float32)
    points[:, 0] = (10.0, 20.0)
    return RadarSweep(points, SE3.identity(), SE3.identity(), 1_000_000, "RADAR_FRONT")


def test_deep_irm_given_arrays_names_radar_sweeps(deep):
    with pytest.raises(TypeError, match="RadarSweep objects, got ndarray"):
        deep([np.zeros((2, len(RADAR_COLUMNS)), np.float32)], SE3.identity())


def test_deep_irm_given_one_sweep_says_wrap_it_in_a_list(deep):
    with pytest.raises(TypeError, match="wrap it in a list"):
        deep(_sweep(), SE3.identity())


def test_deep_irm_without_a_pose_names_ego_pose(deep):
    with pytest.raises(TypeError, match="ego_pose must be an SE3"):
        deep([_sweep()], None)
    with pytest.raises(TypeError, match="ego_pose must be an SE3"):
        radar_detections([_sweep()], None)


def test_deep_irm_on_valid_sweeps_still_maps(deep):
    m = deep([_sweep()], SE3.identity())
    assert m.shape == (*deep.grid.shape, 3) and np.allclose(m.sum(-1), 1.0, atol=1e-5)
