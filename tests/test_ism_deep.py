"""Deep IRM: the radar input image and the Ev-Net wrapper (evgrid.ism.deep)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evgrid import mass
from evgrid.data.frame import RADAR_COLUMNS, RadarSweep
from evgrid.geometry import SE2, SE3, GridSpec
from evgrid.ism.deep import CHANNELS, DeepIrm, RadarImageParams, radar_image
from evgrid.ism.evnet import CheckpointError, EvNet, EvNetConfig, save_checkpoint

SPEC = GridSpec()


def sweep(points, t_us=0, ego=SE3.identity(), sensor=SE3.identity(), channel="RADAR_FRONT") -> RadarSweep:
    p = np.zeros((len(points), len(RADAR_COLUMNS)), np.float32)
    for k, d in enumerate(points):
        for name, v in d.items():
            p[k, RADAR_COLUMNS.index(name)] = v
    return RadarSweep(p, sensor, ego, t_us, channel)


def test_image_hand_computed():
    s1 = sweep([{"x": 10.0, "y": 0.01, "rcs": 10.0, "vx_comp": -2.0}], t_us=1_000_000)
    s0 = sweep([{"x": 10.0, "y": 0.01, "rcs": 0.0, "vx_comp": 0.0}], t_us=500_000)
    img = radar_image([s0, s1], SE3.identity(), SPEC)
    assert img.shape == (len(CHANNELS), 512, 512)
    r, c = 128, 255  # x = 10 m is 128 cells ahead of the centre line; y = +0.01 m is just left
    assert img[0, r, c] == pytest.approx(math.log(3.0))
    assert img[1, r, c] == pytest.approx(0.25)  # mean rcs 5 dBsm / 20
    assert img[2, r, c] == pytest.approx(-0.1)  # mean vx -1 m/s / 10
    assert img[4, r, c] == pytest.approx(1.0)  # newest detection is now
    assert np.count_nonzero(img[0]) == 1
    assert img[5, 255, 255] == pytest.approx(math.hypot(0.5, 0.5) * SPEC.resolution / 20.0)


def test_image_moves_old_sweeps_and_rotates_doppler():
    # the old sweep was taken 1 m behind the current pose, by a radar looking left
    left = SE3.from_se2(SE2(0.0, 0.0, math.pi / 2))
    old = sweep([{"x": 5.0, "vx_comp": 3.0}], t_us=0, ego=SE3.from_se2(SE2(-1.0, 0.0, 0.0)), sensor=left)
    img = radar_image([old], SE3.identity(), SPEC, now_us=500_000, params=RadarImageParams(horizon_s=1.0))
    # global (-1, 5) -> current ego (-1, 5): row floor(256 + 12.8) = 268, col floor(256 - 64) = 192
    assert img[0, 268, 192] > 0
    assert img[3, 268, 192] == pytest.approx(0.3)  # vx along the radar axis = +y in the ego frame
    assert img[2, 268, 192] == pytest.approx(0.0, abs=1e-7)
    assert img[4, 268, 192] == pytest.approx(0.5)


def test_image_drops_nan_and_handles_empty_and_outside():
    s = sweep([{"x": float("nan")}, {"x": 100.0}, {"x": 1.0, "y": 1.0}])
    img = radar_image([s], SE3.identity(), SPEC)
    assert np.isfinite(img).all() and np.count_nonzero(img[0]) == 1
    empty = radar_image([], SE3.identity(), SPEC)
    assert np.count_nonzero(empty[:5]) == 0


def _checkpoint(tmp_path, grid=SPEC):
    torch.manual_seed(0)
    net = EvNet(EvNetConfig(in_channels=len(CHANNELS), width=4, pool=4, depth=2))
    return save_checkpoint(net, tmp_path / "evnet.safetensors", extra={"grid": grid.to_dict()})


def test_deep_irm_predicts_masses_on_the_simplex(tmp_path):
    deep = DeepIrm(_checkpoint(tmp_path), SPEC)
    m = deep([sweep([{"x": 8.0, "y": 2.0, "rcs": 5.0}])], SE3.identity())
    assert m.shape == (512, 512, 3) and m.dtype == np.float32
    mass.validate(m)
    with pytest.raises(ValueError, match="input image"):
        deep.predict_image(np.zeros((3, 512, 512), np.float32))


def test_deep_irm_refuses_a_checkpoint_for_another_grid(tmp_path):
    with pytest.raises(CheckpointError, match="trained on grid"):
        DeepIrm(_checkpoint(tmp_path, GridSpec(256, 40.0)), SPEC)


def test_shipped_checkpoint_loads_and_predicts_masses():
    from evgrid.ism.deep import default_checkpoint
    from evgrid.ism.synthetic import street_radar_sweeps

    path = default_checkpoint()
    assert path.is_file() and path.stat().st_size < 5 * 2**20
    deep = DeepIrm()  # the shipped checkpoint is the default
    assert deep.info["grid"] == SPEC.to_dict() and deep.info["val_iou"]["free"] > 0.8
    sweeps, ego_pose = street_radar_sweeps()
    m = deep(sweeps, ego_pose)
    mass.validate(m)
    # it has learned something: free space around the vehicle, unknown far out
    near = m[240:272, 240:272]
    assert (near[..., 0] > near[..., 2]).mean() > 0.5
