"""`evgrid train` wired to training at scale: the cache built in parallel from the scene source,
fine-tuning from a checkpoint (recorded as the parent), a recording as training data, a run's
config.json that trains again, and the ranks of torchrun waiting for rank 0's cache."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("torch")

from evgrid.cli import app  # noqa: E402
from evgrid.cli.options import train_config_from_args  # noqa: E402
from evgrid.config import document, load_config  # noqa: E402
from evgrid.ism.deep import default_checkpoint  # noqa: E402
from evgrid.ism.evnet import load_checkpoint  # noqa: E402
from evgrid.train_run import TrainRunConfig, _build_caches, _wait_for_cache  # noqa: E402

runner = CliRunner()

#: A tiny run: two simulated training scenes and one validation scene of 1 s, one epoch.
TINY = [
    "--scenes", "2", "--val-scenes", "1", "--duration", "1.0", "--epochs", "1",
    "--width", "4", "--depth", "2", "--workers", "0", "--frame-stride", "5",
]  # fmt: skip


def _shards(cache: Path) -> dict[str, dict[str, bytes]]:
    """Every shard's arrays (as bytes) under a run's cache folder."""
    (key,) = [p for p in (cache).iterdir() if p.is_dir()]
    return {
        d.name: {p.name: p.read_bytes() for p in sorted(d.glob("*.npy"))}
        for d in sorted(key.iterdir())
        if d.is_dir()
    }


@pytest.fixture(scope="module")
def parallel_run(tmp_path_factory):
    """`evgrid train` with the cache built by two worker processes of the local engine."""
    out = tmp_path_factory.mktemp("parallel") / "run"
    r = runner.invoke(app, ["train", *TINY, "--cache-workers", "2", "--out", str(out)])
    assert r.exit_code == 0, r.output
    return out


def test_the_cli_builds_the_cache_in_parallel_as_serially_and_its_config_trains_again(
    parallel_run, tmp_path
):
    run = load_config(parallel_run / "config.json", None)
    assert isinstance(run, TrainRunConfig)
    assert run.train.cache_workers == 2 and run.train.engine == "local"
    assert run == train_config_from_args([*TINY, "--cache-workers", "2"])
    # the same run again from its config.json, its cache built serially
    again = tmp_path / "again"
    r = runner.invoke(
        app,
        [
            "train", "--config", str(parallel_run / "config.json"), "--cache-workers", "1",
            "--out", str(again),
        ],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    rerun = load_config(again / "config.json", None)
    assert rerun.train.cache_workers == 1 and rerun.source == run.source
    assert json.loads((again / "config.json").read_text())["train"]["cache_workers"] == 1
    serial, parallel = _shards(again / "cache"), _shards(parallel_run / "cache")
    assert sorted(serial) == ["sim-000000", "sim-000001", "sim-000004"]
    assert serial == parallel  # shard by shard, byte for byte
    assert (again / "best.safetensors").is_file()
    data = load_checkpoint(again / "best.safetensors").extra["data"]
    assert data["source"] == "sim" and data["train"] == run.source and data["val"] == run.val_source


def test_init_fine_tunes_a_checkpoint_and_records_it_as_the_parent(parallel_run, tmp_path):
    parent = parallel_run / "best.safetensors"
    out = tmp_path / "ft"
    args = ["--scenes", "1", "--val-scenes", "1", "--duration", "1.0", "--epochs", "1"]
    args += ["--workers", "0", "--frame-stride", "5", "--lr", "1e-4", "--init", str(parent)]
    r = runner.invoke(app, ["train", *args, "--out", str(out)])
    assert r.exit_code == 0, r.output
    run = load_config(out / "config.json", None)
    assert run.train.init == str(parent)
    assert run.train.model == load_checkpoint(parent).model.config  # the parent's, not default
    extra = load_checkpoint(out / "last.safetensors").extra
    assert extra["parent"]["path"] == str(parent)
    assert extra["parent"]["sha256"] == hashlib.sha256(parent.read_bytes()).hexdigest()
    assert extra["parent"]["data"]["source"] == "sim"  # what the parent was trained on
    assert extra["config"]["init"] == str(parent)


def test_init_names_the_shipped_checkpoint_and_refuses_another_architecture():
    run = train_config_from_args(["--init", "shipped", "--scenes", "1"])
    shipped = load_checkpoint(default_checkpoint())
    assert run.train.init == str(default_checkpoint())
    assert run.train.model == shipped.model.config
    r = runner.invoke(app, ["train", "--init", "shipped", "--width", "4", "--depth", "2"])
    assert r.exit_code == 1
    assert r.output.startswith("evgrid: error: --init") and "architecture" in r.output
    r = runner.invoke(app, ["train", "--init", "no-such.safetensors"])
    assert r.exit_code == 1 and "no-such.safetensors" in r.output


def test_engine_and_precision_are_checked_options():
    run = train_config_from_args(["--precision", "bf16", "--engine", "ray", "--scenes", "1"])
    assert run.train.precision == "bf16" and run.train.engine == "ray"
    for bad in (["--engine", "spark"], ["--precision", "fp8"], ["--cache-workers", "0"]):
        r = runner.invoke(app, ["train", *bad])
        assert r.exit_code == 1 and r.output.startswith("evgrid: error:"), r.output


def test_a_recording_is_a_training_source(tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    pytest.importorskip("yaml")
    from evgrid.data.bag_writer import write_bag
    from evgrid_sim import SimConfig, simulate_scene

    bags = {}
    for seed, name in ((3, "drive"), (4, "check")):
        frames = list(simulate_scene(seed, SimConfig(duration_s=2.5)))
        bags[name] = write_bag(frames, tmp_path / name, storage="mcap")
    # one rig file for both recordings, without the scene name write_bag puts in it: each
    # recording is then named by its file name
    rig = tmp_path / "car.rig.yaml"
    lines = bags["drive"][1].read_text().splitlines(keepends=True)
    rig.write_text("".join(x for x in lines if not x.startswith("scene:")))
    out = tmp_path / "run"
    args = ["--bag", str(bags["drive"][0]), "--val-bag", str(bags["check"][0]), "--rig", str(rig)]
    args += ["--epochs", "1", "--width", "4", "--depth", "2", "--workers", "0"]
    args += ["--frame-stride", "5", "--batch-size", "2"]
    r = runner.invoke(app, ["train", *args, "--out", str(out)])
    assert r.exit_code == 0, r.output
    run = load_config(out / "config.json", None)
    assert run.source["kind"] == "bag" and run.val_source["kind"] == "bag"
    data = load_checkpoint(out / "best.safetensors").extra["data"]
    assert data["source"] == "bag" and data["rig"] == str(rig)
    assert data["rig_text"] == rig.read_text()
    assert data["recordings"] == [str(bags["drive"][0])]
    assert data["val_recordings"] == [str(bags["check"][0])]
    (key,) = (out / "cache").iterdir()
    index = json.loads((key / "index.json").read_text())
    samples = {n: m["samples"] for n, m in index["shards"].items()}
    assert samples.keys() == {"drive", "check"} and min(samples.values()) > 0
    assert index["shards"]["check"]["irm"] and not index["shards"]["drive"]["irm"]
    # with the rig's scene name, both recordings are one scene: refused, never trained on the
    # validation recording
    args[args.index(str(rig))] = str(bags["drive"][1])
    r = runner.invoke(app, ["train", *args, "--out", str(tmp_path / "same")])
    assert r.exit_code == 1 and "both training and validation" in r.output
    assert "sim-000003" in r.output and "scene:" in r.output
    # a recording without its validation recording is one line naming what is missing
    r = runner.invoke(app, ["train", "--bag", str(bags["drive"][0]), "--rig", str(rig)])
    assert r.exit_code == 1 and "--val-bag" in r.output


def test_the_other_ranks_wait_for_rank_0s_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("MASTER_PORT", "29999")
    args = ["--scenes", "1", "--val-scenes", "1", "--duration", "0.6", "--frame-stride", "3"]
    run = train_config_from_args(args)
    cache = tmp_path / "cache"
    got: dict = {}

    def rank1() -> None:
        got["names"] = _wait_for_cache(run, cache, poll_s=0.05, timeout_s=120)

    waiter = threading.Thread(target=rank1)
    waiter.start()
    time.sleep(0.3)
    assert waiter.is_alive()  # nothing cached yet: rank 1 waits
    names = _build_caches(run, cache, None)
    waiter.join(timeout=30)
    assert got["names"] == names == {"train": ["sim-000000"], "val": ["sim-000004"]}
    # a marker of other scenes is not this run's: the wait goes on (here, to its time limit)
    other = train_config_from_args([*args, "--seed", "5"])
    with pytest.raises(TimeoutError, match="did not build"):
        _wait_for_cache(other, cache, poll_s=0.05, timeout_s=0.3)


def test_rank_0s_failure_ends_the_wait_of_this_launch_only(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("MASTER_PORT", "29998")
    run = train_config_from_args(["--scenes", "1", "--val-scenes", "1", "--duration", "0.6"])
    missing = {"kind": "sim_files", "folder": "/nonexistent", "split": None}
    bad = TrainRunConfig(train=run.train, source=missing, val_source=run.val_source)
    cache = tmp_path / "cache"
    with pytest.raises(FileNotFoundError):
        _build_caches(bad, cache, None)
    with pytest.raises(RuntimeError, match="rank 0 could not build the cache.*nonexistent"):
        _wait_for_cache(bad, cache, poll_s=0.05, timeout_s=5)
    monkeypatch.setenv("MASTER_PORT", "29997")  # a later launch: the old error is not its own
    with pytest.raises(TimeoutError):
        _wait_for_cache(bad, cache, poll_s=0.05, timeout_s=0.3)


def test_train_under_torchrun_caches_on_rank_0_before_the_process_group(tmp_path):
    """The documented multi-process command, two CPU processes (gloo), on an empty run folder:
    rank 0 builds the cache while rank 1 waits outside the process group."""
    torchrun = Path(sys.executable).parent / "torchrun"
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [str(torchrun), "--nproc_per_node=2", "--master_port=29519", "-m", "evgrid.cli"]
    cmd += ["train", *TINY, "--out", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (out / "best.safetensors").is_file()
    assert json.loads((out / "config.json").read_text()) == document(train_config_from_args(TINY))
    (key,) = (out / "cache").iterdir()
    marker = json.loads((key / "ready.json").read_text())
    assert marker["train"] == ["sim-000000", "sim-000001"] and marker["val"] == ["sim-000004"]
    assert np.load(key / "sim-000004" / "irm.npy").ndim == 3
