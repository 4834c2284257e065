"""Ev-Net in the polar frame (EvNetConfig.frame="polar"): the resampling, the network, its
checkpoints, its runtimes and the deep IRM on it; the Cartesian default unchanged."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from evgrid import mass
from evgrid.geometry import GridSpec
from evgrid.ism import runtime as rt
from evgrid.ism.deep import CHANNELS, DeepIrm, radar_image
from evgrid.ism.evnet import (
    CheckpointError,
    EvNet,
    EvNetConfig,
    _AzimuthConv,
    load_checkpoint,
    polar_sampling,
    save_checkpoint,
)

from .test_ism_deep import random_scene

POLAR = EvNetConfig(in_channels=6, width=4, pool=4, depth=3, frame="polar", range_bins=16,
                    azimuth_bins=64)  # fmt: skip


def _net(config=POLAR, seed=1):
    torch.manual_seed(seed)
    net = EvNet(config).eval()
    for m in net.modules():  # non-trivial batch-norm statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    return net


def _xy(h):
    """Ego x (ahead) and y (left) of a square image's pixel centres, in half edges."""
    g = (2 * torch.arange(h, dtype=torch.float32) + 1) / h - 1
    return -g[:, None].expand(h, h), -g[None, :].expand(h, h)


def _to_polar(img, to_polar):
    return F.max_pool2d(
        F.grid_sample(img, to_polar.expand(len(img), -1, -1, -1), align_corners=False), 2
    )


def _to_cartesian(e, to_cart):
    e = torch.cat([e[..., -1:], e, e[..., :1]], dim=-1)
    return F.grid_sample(
        e, to_cart.expand(len(e), -1, -1, -1), padding_mode="border", align_corners=False
    )


def test_polar_bins_lie_where_their_range_and_azimuth_say():
    h, nr, na = 64, 32, 128
    to_polar, _ = polar_sampling(h, h, nr, na)
    assert to_polar.shape == (1, 2 * nr, 2 * na, 2) and to_polar.dtype == torch.float32
    x, y = _xy(h)
    p = F.grid_sample(torch.stack([x, y])[None], to_polar, align_corners=False)[0]
    # sub-bin (i, j): range (i + .5) / (2 nr) of the half diagonal, azimuth from -180 deg
    i, j = 20, 3 * (2 * na) // 4  # azimuth +90 deg: to the left
    rho = (i + 0.5) / (2 * nr) * math.sqrt(2)
    phi = -math.pi + (j + 0.5) * 2 * math.pi / (2 * na)
    assert float(p[0, i, j]) == pytest.approx(rho * math.cos(phi), abs=1e-5)
    assert float(p[1, i, j]) == pytest.approx(rho * math.sin(phi), abs=1e-5)
    assert float(p[1, i, j]) > 0.3  # left is +y


def test_cartesian_to_polar_and_back_keeps_a_smooth_image():
    h = 128
    to_polar, to_cart = polar_sampling(h, h, 64, 256)
    x, y = _xy(h)
    img = (x + 0.5 * y)[None, None]
    # one sample a bin (no max-pool) for a smooth image: back to where it was within the disc
    p = F.grid_sample(img, to_polar, align_corners=False)
    p = F.avg_pool2d(p, 2)
    back = _to_cartesian(p, to_cart)
    inside = torch.sqrt(x**2 + y**2) < 0.9
    assert (back - img)[0, 0][inside].abs().max() < 0.02
    assert back.shape == img.shape


def test_every_pooled_cell_reaches_the_polar_image():
    # a single detection anywhere on the grid, corners included, shows in the polar input
    h = 32
    to_polar, _ = polar_sampling(h, h, 16, 64)
    deltas = torch.eye(h * h).view(h * h, 1, h, h)
    seen = _to_polar(deltas, to_polar).flatten(1).max(dim=1).values
    assert seen.min() > 0.25


def test_azimuth_wraps_around():
    # the convolution's padding is circular in azimuth: rolling the input rolls the output
    torch.manual_seed(0)
    conv = _AzimuthConv(3, 4, 3, padding=2, dilation=2, bias=False).eval()
    x = torch.randn(1, 3, 8, 32)
    with torch.no_grad():
        np.testing.assert_allclose(
            conv(torch.roll(x, 5, dims=-1)), torch.roll(conv(x), 5, dims=-1), atol=1e-6
        )
        y = conv(x)
        ref = F.conv2d(F.pad(x, (2, 2, 0, 0), mode="circular"), conv.weight, None, 1, (2, 0), 2)
    np.testing.assert_allclose(y, ref, atol=1e-6)
    assert y.shape == (1, 4, 8, 32)


def test_polar_net_gives_non_negative_evidence_at_input_resolution():
    net = _net()
    x = torch.zeros(2, 6, 128, 128)
    x[:, 0, 40:44, 60:90] = 1.0
    with torch.no_grad():
        e = net(x)
        trunk = net.trunk(F.max_pool2d(x, 4))
    assert e.shape == (2, 2, 128, 128) and (e >= 0).all()
    assert trunk.shape == (2, 2, 32, 32)
    mass.validate(mass.from_evidence(e.permute(0, 2, 3, 1).numpy()))
    # the whole network is the trunk upsampled, as in the Cartesian frame
    np.testing.assert_array_equal(
        F.interpolate(trunk, size=(128, 128), mode="bilinear", align_corners=False), e
    )
    # the polar net is not the Cartesian one with the same weights
    cart = EvNet(EvNetConfig(in_channels=6, width=4, pool=4, depth=3)).eval()
    cart.load_state_dict(net.state_dict())
    with torch.no_grad():
        assert not torch.allclose(cart(x), e)


def test_polar_checkpoint_round_trips(tmp_path):
    net = _net()
    path = save_checkpoint(net, tmp_path / "polar.safetensors", extra={"epoch": 1})
    back = load_checkpoint(path)
    assert back.model.config == POLAR and back.model.config.frame == "polar"
    x = torch.randn(1, 6, 128, 128)
    with torch.no_grad():
        assert torch.equal(net(x), back.model(x))
    with pytest.raises(CheckpointError, match="asked for"):
        load_checkpoint(path, EvNetConfig(in_channels=6, width=4, pool=4, depth=3))


def _metadata(path):
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        return f.metadata()


def test_cartesian_checkpoints_are_what_they_were(tmp_path):
    # a Cartesian checkpoint names the four fields it always had (older evgrid reads it), and
    # one without the frame loads Cartesian
    cfg = EvNetConfig(in_channels=6, width=4, pool=4, depth=3)
    path = save_checkpoint(_net(cfg), tmp_path / "cart.safetensors")
    assert json.loads(_metadata(path)["config"]) == {
        "in_channels": 6,
        "width": 4,
        "pool": 4,
        "depth": 3,
    }
    assert load_checkpoint(path).model.config.frame == "cartesian"
    polar = json.loads(_metadata(save_checkpoint(_net(), tmp_path / "p.safetensors"))["config"])
    assert (polar["frame"], polar["range_bins"], polar["azimuth_bins"]) == ("polar", 16, 64)


def test_a_checkpoint_naming_an_unknown_frame_is_refused(tmp_path):
    from safetensors.torch import save_file

    net = _net()
    cfg = json.loads(_metadata(save_checkpoint(net, tmp_path / "p.safetensors"))["config"])
    meta = {
        "format": "evgrid-evnet",
        "version": "1",
        "config": json.dumps({**cfg, "frame": "spherical"}),
    }
    tensors = {k: v.contiguous() for k, v in net.state_dict().items()}
    save_file(tensors, str(tmp_path / "bad.safetensors"), metadata=meta)
    with pytest.raises(CheckpointError, match=r"bad.safetensors.*config.frame.*spherical"):
        load_checkpoint(tmp_path / "bad.safetensors")
    with pytest.raises(ValueError, match="frame"):
        EvNetConfig(frame="spherical")


@pytest.mark.parametrize("runtime", ["torch", "onnxruntime"])
def test_polar_trunk_runs_on_each_runtime(runtime):
    if runtime == "onnxruntime" and not rt.ort_available():
        pytest.skip("onnxruntime is not installed (pip install 'evgrid[fast]')")
    net = _net()
    rng = np.random.default_rng(0)
    pooled = (rng.random((1, 6, 32, 32)) < 0.1).astype(np.float32) * rng.normal(
        0, 1, (1, 6, 32, 32)
    ).astype(np.float32)
    r = rt.make_runtime(net, (6, 32, 32), runtime, threads=1)
    assert r.name == runtime  # GridSample exports (opset 17): no fallback to torch
    with torch.no_grad():
        ref = net.trunk(torch.from_numpy(pooled))[0].numpy()
    np.testing.assert_allclose(r(pooled), ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("runtime", ["torch", "onnxruntime"])
def test_deep_irm_on_a_polar_checkpoint(tmp_path, runtime):
    if runtime == "onnxruntime" and not rt.ort_available():
        pytest.skip("onnxruntime is not installed (pip install 'evgrid[fast]')")
    grid = GridSpec()
    cfg = EvNetConfig(in_channels=len(CHANNELS), width=4, pool=4, depth=2, frame="polar")
    path = save_checkpoint(_net(cfg), tmp_path / "p.safetensors", {"grid": grid.to_dict()})
    deep = DeepIrm(path, grid, runtime=runtime)
    assert deep.model.config.frame == "polar"
    sweeps, ego = random_scene(np.random.default_rng(5))
    plain = deep.predict_image(radar_image(sweeps, ego, grid, 250_000, deep.params))
    fast = deep.predict(sweeps, ego, 250_000)
    assert fast.shape == (512, 512, 3)
    mass.validate(fast)
    assert np.abs(fast - plain).max() <= 2e-5
