"""Ev-Net's inference runtimes (evgrid.ism.runtime): the trunk they run, ONNX Runtime and the torch
fallback."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest
import torch

import evgrid
from evgrid.ism import runtime as rt
from evgrid.ism.evnet import EvNet, EvNetConfig


def _model(pool=4, depth=3):
    torch.manual_seed(1)
    net = EvNet(EvNetConfig(in_channels=6, width=4, pool=pool, depth=depth)).eval()
    for m in net.modules():  # non-trivial batch-norm statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    return net


def _input(rng, n=128, pool=4):
    x = np.zeros((1, 6, n, n), np.float32)
    hit = rng.random((n, n)) < 0.05
    x[0, :5, hit] = rng.normal(0, 1, (hit.sum(), 5)).astype(np.float32)
    return x, torch.nn.functional.max_pool2d(torch.from_numpy(x), pool).numpy()


def test_trunk_then_upsample_is_the_whole_network():
    net = _model()
    x, pooled = _input(np.random.default_rng(0))
    with torch.inference_mode():
        whole = net(torch.from_numpy(x))[0].numpy()
        trunk = rt.evnet_trunk(net)(torch.from_numpy(pooled))
        up = torch.nn.functional.interpolate(
            trunk, size=(128, 128), mode="bilinear", align_corners=False
        )[0].numpy()
    np.testing.assert_array_equal(up, whole)
    out = rt.TorchRuntime(net)(pooled)
    assert out.shape == (2, 32, 32) and out.dtype == np.float32
    np.testing.assert_allclose(out, trunk[0].numpy(), rtol=1e-5, atol=1e-6)


def test_onnxruntime_matches_torch():
    if not rt.ort_available():
        pytest.skip("onnxruntime is not installed (pip install 'evgrid[fast]')")
    net = _model()
    _, pooled = _input(np.random.default_rng(1))
    ort = rt.make_runtime(net, (6, 32, 32), "onnxruntime", threads=1)
    ref = rt.make_runtime(net, (6, 32, 32), "torch")
    assert (ort.name, ref.name) == ("onnxruntime", "torch")
    a, b = ort(pooled), ref(pooled)
    assert a.shape == b.shape == (2, 32, 32)
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    assert rt.make_runtime(net, (6, 32, 32), "auto").name == "onnxruntime"


def test_auto_falls_back_to_torch_and_says_so_once(monkeypatch, caplog):
    monkeypatch.setattr(rt, "ort_available", lambda: False)
    monkeypatch.setattr(rt, "_warned_fallback", False)
    net = _model(depth=2)
    with caplog.at_level(logging.INFO, logger="evgrid.ism.runtime"):
        assert rt.make_runtime(net, (6, 32, 32), "auto").name == "torch"
        assert rt.make_runtime(net, (6, 32, 32), "auto").name == "torch"
    hint = evgrid.install_hint("fast")
    assert sum(hint in r.getMessage() for r in caplog.records) == 1
    with pytest.raises(ImportError, match=re.escape(hint)):
        rt.make_runtime(net, (6, 32, 32), "onnxruntime")
    with pytest.raises(ValueError, match="runtime must be one of"):
        rt.make_runtime(net, (6, 32, 32), "tensorrt")
