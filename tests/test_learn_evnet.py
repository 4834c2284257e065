"""Ev-Net: the loss on a hand-computed case, learning, and checkpoint files."""

from __future__ import annotations

import pytest
import torch

from evgrid import mass
from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.ism.evnet import CheckpointError, EvNet, EvNetConfig, load_checkpoint, save_checkpoint
from evgrid.learn.loss import evidential_loss

TINY = EvNetConfig(in_channels=3, width=4, pool=2, depth=2)


def test_loss_hand_computed():
    # e = [2, 4]: S = 8, p = [3/8, 5/8], m_u = 1/4
    e = torch.tensor([2.0, 4.0]).view(1, 2, 1, 1).expand(1, 2, 1, 3).contiguous()
    t = torch.tensor([[[FREE, OCCUPIED, UNKNOWN]]])
    # free: (1 - 3/8)^2 + (5/8)^2 + 2 * (3/8 * 5/8) / 9 = 50/64 + 30/576
    l_free = 50 / 64 + 30 / 576
    # occupied: (3/8)^2 + (1 - 5/8)^2 + the same variance term
    l_occ = 18 / 64 + 30 / 576
    l_unk = (1 - 0.25) ** 2
    assert float(evidential_loss(e, t)) == pytest.approx(l_free + l_occ + l_unk, rel=1e-6)


def test_loss_takes_per_class_expectations():
    # three free cells and one occupied: each class weighs the same whatever its cell count
    e = torch.zeros(1, 2, 1, 4)
    t = torch.tensor([[[FREE, FREE, FREE, OCCUPIED]]])
    # e = 0: p = [.5, .5], S = 2: per cell .25 + .25 + 2 * .25 / 3
    per_cell = 0.5 + 0.5 / 3
    assert float(evidential_loss(e, t)) == pytest.approx(2 * per_cell, rel=1e-6)
    valid = torch.tensor([[[True, True, True, False]]])
    assert float(evidential_loss(e, t, valid)) == pytest.approx(per_cell, rel=1e-6)


def test_loss_rejects_bad_shapes():
    with pytest.raises(ValueError, match="evidence"):
        evidential_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="target"):
        evidential_loss(torch.zeros(1, 2, 4, 4), torch.zeros(1, 4, 5, dtype=torch.long))


def test_output_is_non_negative_evidence_at_input_resolution():
    torch.manual_seed(0)
    net = EvNet(TINY).eval()
    e = net(torch.randn(2, 3, 32, 32))
    assert e.shape == (2, 2, 32, 32) and (e >= 0).all()
    m = mass.from_evidence(e.detach().permute(0, 2, 3, 1).numpy())
    mass.validate(m)


def test_a_few_optimiser_steps_lower_the_loss():
    torch.manual_seed(0)
    net = EvNet(TINY)
    x = torch.zeros(4, 3, 32, 32)
    x[:, 0, 8:24, 10] = 1.0  # a "detection" line
    t = torch.full((4, 32, 32), UNKNOWN)
    t[:, 8:24, 10] = OCCUPIED
    t[:, 8:24, 11:20] = FREE
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        opt.zero_grad()
        loss = evidential_loss(net(x), t)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.6 * losses[0]


def test_checkpoint_round_trip_gives_identical_outputs(tmp_path):
    torch.manual_seed(1)
    net = EvNet(TINY).eval()
    path = save_checkpoint(net, tmp_path / "ck" / "evnet.safetensors", extra={"epoch": 3})
    back = load_checkpoint(path)
    assert back.extra == {"epoch": 3} and back.model.config == TINY
    x = torch.randn(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(net(x), back.model(x))


def test_bad_checkpoints_raise_clear_errors(tmp_path):
    net = EvNet(TINY)
    path = save_checkpoint(net, tmp_path / "a.safetensors")
    data = path.read_bytes()
    (tmp_path / "cut.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="cut.safetensors"):
        load_checkpoint(tmp_path / "cut.safetensors")
    (tmp_path / "pickle.pt").write_bytes(b"\x80\x04\x95 not a safetensors file")
    with pytest.raises(CheckpointError, match="pickle.pt"):
        load_checkpoint(tmp_path / "pickle.pt")
    with pytest.raises(CheckpointError, match="asked for"):
        load_checkpoint(path, EvNetConfig(in_channels=3, width=8, pool=2, depth=2))
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(2)}, str(tmp_path / "foreign.safetensors"))
    with pytest.raises(CheckpointError, match="not an evgrid Ev-Net"):
        load_checkpoint(tmp_path / "foreign.safetensors")
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.safetensors")
    # weights of another shape under a valid header
    other = EvNet(EvNetConfig(in_channels=3, width=8, pool=2, depth=2))
    meta = {
        "format": "evgrid-evnet",
        "version": "1",
        "config": '{"in_channels": 3, "width": 4, "pool": 2, "depth": 2}',
    }
    save_file(
        {k: v.contiguous() for k, v in other.state_dict().items()},
        str(tmp_path / "shape.safetensors"),
        metadata=meta,
    )
    with pytest.raises(CheckpointError, match="shape"):
        load_checkpoint(tmp_path / "shape.safetensors")
    nan = {k: v.clone() for k, v in net.state_dict().items()}
    first = next(k for k, v in nan.items() if v.is_floating_point())
    nan[first].fill_(float("nan"))
    meta["config"] = '{"in_channels": 3, "width": 4, "pool": 2, "depth": 2}'
    save_file(
        {k: v.contiguous() for k, v in nan.items()},
        str(tmp_path / "nan.safetensors"),
        metadata=meta,
    )
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(tmp_path / "nan.safetensors")
