"""Training Ev-Net end to end on a tiny simulated set (evgrid.learn.train); kept well under a
minute."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.ism.evnet import EvNet, EvNetConfig, load_checkpoint
from evgrid.learn.train import RadarDataset, TrainConfig, build_cache, ilm_classes, train
from evgrid_sim import SimConfig, simulate_scene

CFG = TrainConfig(
    epochs=2,
    batch_size=2,
    workers=0,
    frame_stride=10,
    model=EvNetConfig(in_channels=6, width=4, depth=2),
)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("cache")
    scenes = [simulate_scene(s, SimConfig(duration_s=2.0)) for s in (0, 4)]
    names = build_cache(scenes, root, CFG, with_irm=True)
    return root, names


def test_ilm_classes_follow_design():
    m = np.array([[0.05, 0, 0.95], [0, 0.5, 0.5], [0, 0, 1], [0.05, 0.5, 0.45]], np.float32)
    assert ilm_classes(m).tolist() == [FREE, OCCUPIED, UNKNOWN, OCCUPIED]


def test_cache_and_dataset(cache):
    root, names = cache
    assert names == ["sim-000000", "sim-000004"]
    ds = RadarDataset(root, names, CFG.grid, with_irm=True)
    assert len(ds) == 8  # 40 frames a scene, every 10th
    x, t, irm = ds[0]
    assert x.shape == (6, 512, 512) and t.shape == (512, 512) and irm.shape == (512, 512)
    assert set(torch.unique(t).tolist()) == {FREE, OCCUPIED, UNKNOWN}
    assert x[0].sum() > 0  # radar detections are there
    # a cached scene is not rebuilt: its shard's files keep their time stamps
    before = (root / "sim-000000" / "target.npy").stat().st_mtime_ns
    build_cache([simulate_scene(0, SimConfig(duration_s=2.0))], root, CFG)
    assert (root / "sim-000000" / "target.npy").stat().st_mtime_ns == before
    with pytest.raises(FileNotFoundError, match="build_cache"):
        RadarDataset(root, ["sim-999"], CFG.grid)


def test_train_writes_logs_and_checkpoints_and_resumes(cache, tmp_path):
    root, names = cache
    res = train(CFG, root, names[:1], names[1:], tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [r["epoch"] for r in rows] == ["0", "1"]
    assert float(rows[1]["train_loss"]) < float(rows[0]["train_loss"]) * 1.5
    assert 0.0 <= res.ray_irm_baseline["free"] <= 1.0
    ck = load_checkpoint(tmp_path / "best.safetensors")
    assert ck.extra["grid"] == CFG.grid.to_dict() and "val_iou" in ck.extra
    assert ck.extra["radar_filter"] == CFG.radar_filter.to_dict()  # mapping with another one warns
    # resume adds one epoch from where the run stopped
    res2 = train(
        TrainConfig(**{**CFG.__dict__, "epochs": 3}),
        root,
        names[:1],
        names[1:],
        tmp_path,
        resume=True,
    )
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [r["epoch"] for r in rows] == ["0", "1", "2"]
    assert res2.seconds_per_epoch > 0


def test_metrics_csv_is_rewritten_atomically_each_epoch(tmp_path, monkeypatch):
    import os

    from evgrid.learn import train as train_mod

    path = tmp_path / "metrics.csv"
    for epoch in range(3):
        train_mod._write_metrics(path, epoch, {"epoch": epoch, "train_loss": 1.0 / (epoch + 1)})
    assert [r["epoch"] for r in csv.DictReader(open(path))] == ["0", "1", "2"]
    # a resumed run that logs epoch 1 again: the rows before it kept, the later ones replaced
    train_mod._write_metrics(path, 1, {"epoch": 1, "train_loss": 0.25})
    rows = list(csv.DictReader(open(path)))
    assert [(r["epoch"], r["train_loss"]) for r in rows] == [("0", "1.0"), ("1", "0.25")]
    before = path.read_bytes()

    def full_disk(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)  # the real writer fails before its rename
    with pytest.raises(OSError, match="metrics.csv"):
        train_mod._write_metrics(path, 2, {"epoch": 2})
    assert path.read_bytes() == before  # the old file, whole
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.csv"]  # no temporary left


def test_config_validation():
    with pytest.raises(ValueError, match="epochs"):
        TrainConfig(epochs=0)
    with pytest.raises(ValueError, match="input channels"):
        TrainConfig(model=EvNetConfig(in_channels=3))


def test_training_runs_under_torchrun_with_two_processes(cache, tmp_path):
    """DistributedDataParallel on CPU (gloo): the command documented for multi-GPU runs."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root, names = cache
    script = tmp_path / "ddp.py"
    script.write_text(
        "import sys\n"
        "from evgrid.ism.evnet import EvNetConfig\n"
        "from evgrid.learn.train import TrainConfig, train\n"
        "cfg = TrainConfig(epochs=1, batch_size=2, workers=0, frame_stride=10, threads=1,\n"
        "                  model=EvNetConfig(in_channels=6, width=4, depth=2))\n"
        f"train(cfg, {str(root)!r}, {names[:1]!r}, {names[1:]!r}, sys.argv[1])\n"
    )
    torchrun = Path(sys.executable).parent / "torchrun"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(
        [
            str(torchrun),
            "--nproc_per_node=2",
            "--master_port=29517",
            str(script),
            str(tmp_path / "run"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "run" / "best.safetensors").is_file()
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert len(rows) == 1  # rank 0 alone logs


def test_fine_tuning_starts_from_the_parent_and_records_it(cache, tmp_path):
    import hashlib
    import json

    from evgrid.config import from_dict
    from evgrid.learn.train import fine_tune_config

    root, names = cache
    parent_run = tmp_path / "parent"
    train(TrainConfig(**{**CFG.__dict__, "epochs": 1}), root, names[:1], names[1:], parent_run)
    parent = parent_run / "last.safetensors"
    # a config of another architecture takes the parent's
    wide = TrainConfig(**{**CFG.__dict__, "model": EvNetConfig(in_channels=6, width=8, depth=2)})
    with pytest.raises(ValueError, match="fine_tune_config"):
        train(TrainConfig(**{**wide.__dict__, "init": str(parent)}), root, names, names, tmp_path)
    cfg = fine_tune_config(TrainConfig(**{**wide.__dict__, "epochs": 1, "lr": 1e-9}), parent)
    assert cfg.model == CFG.model and cfg.init == str(parent)
    rig = {"lidar": "/lidar_top/points", "radars": ["/radar_front/points"]}
    child = tmp_path / "child"
    train(cfg, root, names[:1], names[1:], child, data={"source": "bag", "rig": rig})
    ck = load_checkpoint(child / "last.safetensors")
    assert ck.extra["parent"]["path"] == str(parent)
    assert ck.extra["parent"]["sha256"] == hashlib.sha256(parent.read_bytes()).hexdigest()
    assert ck.extra["data"]["rig"] == rig
    assert ck.extra["radar_filter"] == CFG.radar_filter.to_dict()
    # with a vanishing learning rate the child's weights are its parent's (the normalisation
    # statistics move with the data whatever the rate)
    before = dict(load_checkpoint(parent).model.named_parameters())
    after = dict(ck.model.named_parameters())
    assert all(torch.allclose(before[k], after[k], atol=1e-5) for k in before)
    fresh = dict(EvNet(CFG.model).named_parameters())
    assert not all(torch.allclose(before[k], fresh[k], atol=1e-5) for k in before)
    # the run's config.json reloads into the same TrainConfig
    saved = json.loads((child / "config.json").read_text())
    assert from_dict(TrainConfig, saved, "config.json") == cfg


def test_mixed_precision_is_off_on_the_cpu_and_chosen_on_cuda():
    from evgrid.learn.train import Precision

    cpu = Precision("bf16", torch.device("cpu"))
    assert cpu.name == "float32" and not cpu.scaler.is_enabled()
    with cpu.autocast():
        assert torch.ones(2, 2).matmul(torch.ones(2, 2)).dtype == torch.float32
    if torch.cuda.is_available():  # the GPU check (benchmarks/gpu_check.sh) runs this path
        cuda = torch.device("cuda")
        assert Precision("fp16", cuda).scaler.is_enabled()
        assert Precision("bf16", cuda).name == "bfloat16"
        assert Precision("fp32", cuda).name == "float32"
    with pytest.raises(ValueError, match="precision"):
        TrainConfig(precision="fp8")
    with pytest.raises(ValueError, match="engine"):
        TrainConfig(engine="spark")


def test_a_polar_net_trains_and_its_checkpoint_says_so(cache, tmp_path):
    from dataclasses import replace

    from evgrid.learn.train import saved_train_config

    root, names = cache
    polar = EvNetConfig(in_channels=6, width=4, depth=2, frame="polar", range_bins=32,
                        azimuth_bins=128)  # fmt: skip
    train(replace(CFG, epochs=1, model=polar), root, names[:1], names[1:], tmp_path)
    ck = load_checkpoint(tmp_path / "best.safetensors")
    assert ck.model.config == polar
    # the saved training config reads back with the frame (``--set train.model.frame=polar``)
    assert saved_train_config(ck.extra["config"], "best").model == polar
    assert saved_train_config({**CFG.to_dict(), "model": {"frame": "polar"}}, "x").model.frame == (
        "polar"
    )
