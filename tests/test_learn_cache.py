"""The training-sample cache at scale: shards built in parallel through evgrid.engine, an
index written by the driver, resume after an interruption, a failing scene named."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest

from evgrid.ism.evnet import EvNetConfig
from evgrid.learn.train import (
    CacheError,
    RadarDataset,
    TrainConfig,
    build_cache,
    cached_scenes,
    scene_shard,
)
from evgrid.sources import SimSource
from evgrid_sim import SimConfig, simulate_scene

CFG = TrainConfig(
    epochs=1,
    batch_size=2,
    workers=0,
    frame_stride=10,
    model=EvNetConfig(in_channels=6, width=4, depth=2),
)
SOURCE = SimSource((0, 4, 7), duration_s=1.0)


def _arrays(root, name):
    folder = root / name
    return {p.stem: np.load(p) for p in sorted(folder.glob("*.npy"))}


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    root = tmp_path_factory.mktemp("serial")
    names = build_cache(SOURCE, root, CFG, with_irm=True, workers=1)
    return root, names


def test_parallel_shards_equal_serial_ones_and_the_index_lists_them(serial, tmp_path):
    root, names = serial
    assert names == SOURCE.names()
    seen = []
    par = build_cache(
        SOURCE, tmp_path, CFG, with_irm=True, workers=2, progress=seen.append, engine="local"
    )
    assert par == names and sorted(seen) == sorted(names)
    for name in names:
        a, b = _arrays(root, name), _arrays(tmp_path, name)
        assert a.keys() == b.keys() == {"det", "offsets", "target", "irm"}
        assert all(np.array_equal(a[k], b[k]) for k in a)
    index = json.loads((tmp_path / "index.json").read_text())
    assert index["data_key"] == CFG.data_key() and sorted(index["shards"]) == sorted(names)
    assert cached_scenes(tmp_path, CFG) == cached_scenes(root, CFG)
    assert sum(cached_scenes(tmp_path, CFG).values()) == len(
        RadarDataset(tmp_path, names, CFG.grid, with_irm=True)
    )
    # the same samples as the in-process path of one scene
    direct = scene_shard(SOURCE.load(names[0]), CFG, with_irm=True)
    assert all(np.array_equal(direct[k], a) for k, a in _arrays(root, names[0]).items())


def test_an_interrupted_build_resumes_with_the_missing_scenes(serial, tmp_path):
    root, names = serial
    build_cache(SimSource((0,), duration_s=1.0), tmp_path, CFG, with_irm=True)
    # a build killed while writing a shard leaves a temporary folder, never a shard
    (tmp_path / ".sim-000004.tmp-99999").mkdir()
    (tmp_path / ".sim-000004.tmp-99999" / "det.npy").write_bytes(b"half")
    first = (tmp_path / names[0] / "target.npy").stat().st_mtime_ns
    seen = []
    build_cache(SOURCE, tmp_path, CFG, with_irm=True, workers=2, progress=seen.append)
    assert sorted(seen) == sorted(names)
    assert (tmp_path / names[0] / "target.npy").stat().st_mtime_ns == first  # not redone
    assert not list(tmp_path.glob(".*.tmp-*"))
    for name in names:
        a, b = _arrays(root, name), _arrays(tmp_path, name)
        assert all(np.array_equal(a[k], b[k]) for k in a)


@dataclass(frozen=True)
class _Broken(SimSource):
    """A source whose one scene fails to load (module level: it must pickle)."""

    def load(self, name):
        if name == "sim-000004":
            raise OSError("recording truncated")
        return super().load(name)


def test_a_failing_scene_is_named_and_the_others_are_cached(tmp_path):
    source = _Broken((0, 4, 7), duration_s=1.0)
    with pytest.raises(CacheError, match=r"1 of 3 scenes .*sim-000004: OSError: recording trunc"):
        build_cache(source, tmp_path, CFG, workers=2)
    assert sorted(cached_scenes(tmp_path, CFG)) == ["sim-000000", "sim-000007"]
    with pytest.raises(FileNotFoundError, match="sim-000004.*build_cache"):
        RadarDataset(tmp_path, source.names(), CFG.grid)


def test_a_cache_of_other_settings_is_refused(serial):
    root, _ = serial
    other = TrainConfig(**{**CFG.__dict__, "frame_stride": 5})
    with pytest.raises(CacheError, match="other settings"):
        build_cache(SOURCE, root, other)


def test_scene_names_that_are_no_file_names_get_their_own_shards(tmp_path):
    scene = simulate_scene(0, SimConfig(duration_s=1.0))

    class Named:
        def __init__(self, name):
            self.name = name

        def __iter__(self):
            return iter(scene)

    names = build_cache([Named("a/b"), Named("a_b"), Named("..")], tmp_path, CFG)
    assert names == ["a/b", "a_b", ".."]
    assert len([p for p in tmp_path.iterdir() if p.is_dir()]) == 3
    assert cached_scenes(tmp_path, CFG) == {"a/b": 2, "a_b": 2, "..": 2}  # 20 frames, every 10th
    assert len(RadarDataset(tmp_path, names, CFG.grid)) == 6


def test_a_build_killed_midway_resumes_to_the_same_cache(serial, tmp_path):
    """The driver process dies (os._exit, as a kill) right after its first shard; the next
    build computes the rest, and the cache equals an uninterrupted one."""
    import subprocess
    import sys

    root, names = serial
    script = (
        "import os, sys\n"
        "from evgrid.learn.train import build_cache\n"
        "from evgrid.sources import SimSource\n"
        "from evgrid.ism.evnet import EvNetConfig\n"
        "from evgrid.learn.train import TrainConfig\n"
        "CFG = TrainConfig(epochs=1, batch_size=2, workers=0, frame_stride=10,\n"
        "                  model=EvNetConfig(in_channels=6, width=4, depth=2))\n"
        "build_cache(SimSource((0, 4, 7), duration_s=1.0), sys.argv[1], CFG, with_irm=True,\n"
        "            progress=lambda name: os._exit(9))\n"
    )
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path)], timeout=300)
    assert r.returncode == 9
    assert len(cached_scenes(tmp_path, CFG)) == 1  # one shard, complete; the others absent
    seen = []
    assert build_cache(SOURCE, tmp_path, CFG, with_irm=True, progress=seen.append) == names
    assert sorted(seen) == sorted(names)
    assert cached_scenes(tmp_path, CFG) == cached_scenes(root, CFG)
    for name in names:
        a, b = _arrays(root, name), _arrays(tmp_path, name)
        assert all(np.array_equal(a[k], b[k]) for k in a)
