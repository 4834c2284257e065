"""Mapping whole simulated scenes with the online mapper (evgrid.pipeline)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from evgrid import mass
from evgrid.data import SimConfig, simulate_scene
from evgrid.fusion import MAP_NAMES
from evgrid.geometry import GridSpec
from evgrid.ism import RayIlmParams, RayIrmParams, ray_ilm, ray_irm
from evgrid.ism.deep import CHANNELS, DeepIrm
from evgrid.learn.evnet import EvNet, EvNetConfig, save_checkpoint
from evgrid.pipeline import MapperConfig, OccupancyMapper, map_scene


@pytest.fixture(scope="module")
def scene():
    return simulate_scene(1, SimConfig(duration_s=3.0))


@pytest.fixture(scope="module")
def deep(tmp_path_factory):
    torch.manual_seed(0)
    net = EvNet(EvNetConfig(in_channels=len(CHANNELS), width=4, depth=2))
    path = save_checkpoint(net, tmp_path_factory.mktemp("ck") / "tiny.safetensors", extra={"grid": GridSpec().to_dict()})
    return DeepIrm(path)


def test_map_scene_writes_results(scene, deep, tmp_path):
    res = map_scene(scene, tmp_path, MapperConfig(), deep=deep, save_maps=True)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["frames"] == len(scene) == 60
    assert m["updates"] == 30  # every other lidar frame: 10 Hz
    assert m["keyframes"] == 6
    assert set(m["vs_ray_ilm"]) == set(MAP_NAMES) - {"ray_ilm"}
    assert set(m["vs_truth"]) == set(MAP_NAMES)
    for ious in m["vs_ray_ilm"].values():
        assert all(v is None or 0.0 <= v <= 1.0 for v in ious.values())
    assert len(m["convergence"]) == 6 and m["frames_per_second"] > 0
    for key in ("maps", "isms", "convergence", "gif", "config", "metrics", "map_fused"):
        assert key in res.files
    assert json.loads((tmp_path / "config.json").read_text())["update_every"] == 2
    # the geometric maps know the street: the ray ILM agrees with the truth on free space
    assert m["vs_truth"]["ray_ilm"]["free"] > 0.3
    assert m["vs_truth"]["ray_irm"]["free"] > 0.3


def test_online_mapper_frame_by_frame(scene, deep):
    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm", "ray_irm", "fused"), update_every=5), deep=deep)
    updated = [mapper.process(f) for f in scene]
    assert sum(updated) == 12  # every 5th frame, keyframes included
    for m in mapper.maps.maps.values():
        dense, cov, _, _ = m.to_dense()
        mass.validate(dense)
        assert cov.sum() > 512 * 512 * 0.9
    assert set(mapper.timing_summary()) >= {"ray_ilm", "ray_irm", "deep_irm_net", "warp", "fuse", "step_total"}
    with pytest.raises(TypeError):
        mapper.process("frame")


def test_maps_without_deep_irm_need_no_checkpoint(scene):
    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm", "ray_irm")))
    assert mapper.deep is None
    for f in list(scene)[:4]:
        mapper.process(f)
    assert mapper.n_updates == 2


def test_config_validation():
    with pytest.raises(ValueError, match="unknown map"):
        MapperConfig(maps=("octomap",))
    with pytest.raises(ValueError, match="update_every"):
        MapperConfig(update_every=0)


def test_m_u_min_choice_rule():
    from evgrid.pipeline import choose_m_u_min

    rows = [{"m_u_min": v, "mean_of_classes": {"deep_disc": d}} for v, d in ((0.1, 0.530), (0.3, 0.525), (0.4, 0.49), (0.6, 0.2))]
    assert choose_m_u_min(rows) == 0.3  # the highest within 0.01 of the best
    assert choose_m_u_min(rows, tolerance=0.0) == 0.1


def test_the_ism_parameters_of_the_config_are_the_ones_used(scene):
    lidar, radar = RayIlmParams(max_range_m=6.0, min_range_m=2.0), RayIrmParams(n_sweeps=3, m_free=0.2)
    mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm", "ray_irm"), lidar=lidar, radar=radar))
    frames = list(scene)[:5]
    for f in frames:
        mapper.process(f)
    assert mapper.last_frame is frames[-1]  # frame 4 was an update
    isms, pose = mapper.last_isms, frames[-1].ego_pose
    np.testing.assert_array_equal(isms["ray_ilm"], ray_ilm(frames[-1].lidar, params=lidar))
    assert not np.array_equal(isms["ray_ilm"], ray_ilm(frames[-1].lidar))
    assert mapper.buffer.n_sweeps == 10  # the deep IRM's image still needs its 10 sweeps
    sweeps = mapper.buffer.sweeps()
    np.testing.assert_array_equal(isms["ray_irm"], ray_irm(sweeps, pose, params=radar))
    assert not np.array_equal(isms["ray_irm"], ray_irm(sweeps, pose, params=RayIrmParams(m_free=0.2)))
    assert np.isclose(isms["ray_irm"][..., 0].max(), 0.2, atol=1e-6)
