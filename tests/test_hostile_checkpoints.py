"""Hostile Ev-Net checkpoints: every problem is a CheckpointError naming the file, found before
allocating.

Before format 2 (issue 12) a flipped exponent bit loaded silently, int32 weights loaded and
predicted "free" everywhere, a 200-byte file whose metadata said width 4000 allocated 4.6 GB,
and bad metadata gave AttributeError or KeyError.
"""

from __future__ import annotations

import json
import logging
import resource
import struct
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import save, save_file

from evgrid.ism.deep import default_checkpoint
from evgrid.ism.evnet import (
    CheckpointError,
    EvNet,
    EvNetConfig,
    load_checkpoint,
    save_checkpoint,
    upgrade_checkpoint,
)

TINY = EvNetConfig(in_channels=3, width=4, pool=2, depth=2)


def _net() -> EvNet:
    torch.manual_seed(0)
    return EvNet(TINY).eval()


def _header(path: Path) -> tuple[dict, int]:
    buf = path.read_bytes()
    (n,) = struct.unpack("<Q", buf[:8])
    return json.loads(buf[8 : 8 + n]), 8 + n


def _v1_meta(config: dict | str = None) -> dict[str, str]:
    cfg = config if isinstance(config, str) else json.dumps(config or TINY.__dict__)
    return {"format": "evgrid-evnet", "version": "1", "config": cfg}


def _tensors() -> dict[str, torch.Tensor]:
    return {k: v.contiguous() for k, v in _net().state_dict().items()}


def test_a_flipped_exponent_bit_is_caught_by_the_checksum(tmp_path):
    path = save_checkpoint(_net(), tmp_path / "ok.safetensors")
    header, start = _header(path)
    name = next(k for k, e in header.items() if k.endswith("0.weight") and e["dtype"] == "F32")
    w = _net().state_dict()[name].reshape(-1)
    i = int(torch.nonzero((w.abs() < 1) & (w != 0))[0])  # |w| < 1: the flipped value stays finite
    buf = bytearray(path.read_bytes())
    buf[start + header[name]["data_offsets"][0] + 4 * i + 3] ^= (
        0x40  # an exponent bit (little-endian float32)
    )
    bad = tmp_path / "flipped.safetensors"
    bad.write_bytes(bytes(buf))
    with pytest.raises(CheckpointError, match=r"flipped\.safetensors.*checksum"):
        load_checkpoint(bad)


def test_int32_weights_are_refused(tmp_path):
    ints = {k: (v.to(torch.int32) if v.is_floating_point() else v) for k, v in _tensors().items()}
    save_file(ints, str(tmp_path / "int32.safetensors"), metadata=_v1_meta())
    with pytest.raises(CheckpointError, match=r"int32\.safetensors.*dtype I32, expected F32"):
        load_checkpoint(tmp_path / "int32.safetensors")


def test_an_oversized_architecture_fails_fast_without_allocating(tmp_path):
    path = tmp_path / "huge.safetensors"
    save_file(
        {"w": torch.zeros(1)},
        str(path),
        metadata=_v1_meta({"in_channels": 6, "width": 4000, "pool": 4, "depth": 4}),
    )
    assert path.stat().st_size < 300
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with pytest.raises(
        CheckpointError,
        match=r"huge\.safetensors.*'config\.width' must be an integer in \[1, 512\]",
    ):
        load_checkpoint(path)
    # within the per-field bounds, but far too many parameters together
    save_file(
        {"w": torch.zeros(1)},
        str(path),
        metadata=_v1_meta({"in_channels": 64, "width": 512, "pool": 4, "depth": 8}),
    )
    with pytest.raises(CheckpointError, match=r"huge\.safetensors.*parameters, more than"):
        load_checkpoint(path)
    assert time.perf_counter() - t0 < 5.0
    assert (
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000
    )  # kB: no GB-sized tensors


@pytest.mark.parametrize(
    "meta, field",
    [
        ({}, "format"),
        ({"format": "evgrid-evnet"}, "version"),
        ({"format": "evgrid-evnet", "version": "7"}, "version"),
        ({"format": "evgrid-evnet", "version": "1"}, "config"),
        (_v1_meta("{not json"), "config"),
        (_v1_meta("[6, 12, 4, 4]"), "config"),
        (_v1_meta('{"in_channels": 3, "width": 4, "pool": 2, "depth": 2, "heads": 9}'), "config"),
        (_v1_meta('{"in_channels": 3, "width": -4, "pool": 2, "depth": 2}'), "config.width"),
        (_v1_meta('{"in_channels": 3, "width": 4.5, "pool": 2, "depth": 2}'), "config.width"),
        (
            _v1_meta('{"in_channels": true, "width": 4, "pool": 2, "depth": 2}'),
            "config.in_channels",
        ),
        ({**_v1_meta(), "extra": "{broken"}, "extra"),
        ({**_v1_meta(), "extra": "[1, 2]"}, "extra"),
        ({**_v1_meta(), "extra": '{"grid": "garbage"}'}, "extra.grid"),
        ({**_v1_meta(), "extra": '{"grid": {"n_cells": "x", "length_m": 40.0}}'}, "extra.grid"),
        ({**_v1_meta(), "version": "2"}, "tensors_sha256"),
    ],
)
def test_bad_metadata_is_a_checkpoint_error_naming_file_and_field(tmp_path, meta, field):
    path = tmp_path / "meta.safetensors"
    path.write_bytes(save(_tensors(), metadata=meta or None))
    with pytest.raises(CheckpointError, match=rf"meta\.safetensors.*'{field}'"):
        load_checkpoint(path)


def test_a_file_cut_anywhere_is_a_checkpoint_error(tmp_path):
    data = save_checkpoint(_net(), tmp_path / "ok.safetensors").read_bytes()
    _, start = _header(tmp_path / "ok.safetensors")
    for cut in (0, 5, 8, 100, start - 1, start, start + 7, len(data) - 1):
        path = tmp_path / f"cut{cut}.safetensors"
        path.write_bytes(data[:cut])
        with pytest.raises(CheckpointError, match=rf"cut{cut}\.safetensors"):
            load_checkpoint(path)


def test_format_1_loads_with_a_warning_and_upgrades_to_identical_weights(tmp_path, caplog):
    v1 = tmp_path / "v1.safetensors"
    save_file(_tensors(), str(v1), metadata={**_v1_meta(), "extra": '{"epoch": 4}'})
    with caplog.at_level(logging.WARNING, logger="evgrid.ism.evnet"):
        old = load_checkpoint(v1)
    assert old.version == 1 and "upgrade_checkpoint" in caplog.text
    v2 = upgrade_checkpoint(v1, tmp_path / "v2.safetensors")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="evgrid.ism.evnet"):
        new = load_checkpoint(v2)
    assert new.version == 2 and not caplog.text and new.extra == {"epoch": 4}
    assert "tensors_sha256" in _header(v2)[0]["__metadata__"]
    a, b = old.model.state_dict(), new.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    x = torch.rand(1, 3, 16, 16)
    with torch.no_grad():
        assert torch.equal(old.model(x), new.model(x))
    upgrade_checkpoint(v2, v2)  # in place, atomically
    assert load_checkpoint(v2).version == 2


def test_the_shipped_checkpoint_is_format_2():
    ck = load_checkpoint(default_checkpoint())
    assert ck.version == 2
    assert "tensors_sha256" in _header(default_checkpoint())[0]["__metadata__"]


@pytest.mark.parametrize("value", [1e30, -3e7])
def test_a_huge_weight_with_a_valid_checksum_is_refused(tmp_path, value):
    """Issue 26: a finite weight of 1e30, written with its checksum, must not load (it would
    overflow the activations and give NaN masses)."""
    from evgrid.ism.evnet import MAX_WEIGHT

    net = _net()
    name = next(k for k, v in net.state_dict().items() if k.endswith("weight"))
    with torch.no_grad():
        net.state_dict()[name].reshape(-1)[0] = value
    path = save_checkpoint(net, tmp_path / "huge.safetensors")
    with pytest.raises(CheckpointError, match=rf"huge\.safetensors: weight {name} holds .*bound"):
        load_checkpoint(path)
    # the bound is far above any weight a training writes: the shipped checkpoint loads
    shipped = load_checkpoint(default_checkpoint()).model.state_dict()
    assert max(float(v.abs().max()) for v in shipped.values() if v.is_floating_point()) < MAX_WEIGHT
