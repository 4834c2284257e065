"""A long run that stops is not lost (docs/store.md): a scene's resumable state every
``checkpoint_every_s`` of the drive, ``--resume`` continues from it, and the maps are those of a
run never stopped, bit for bit."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from evgrid.checkpoint import CHECKPOINT_VERSION, checkpoint_path, load_checkpoint
from evgrid.config import MapperConfig, OutputConfig
from evgrid.grid import load_map
from evgrid.runs import STORE_FOLDER, map_scene
from evgrid.store import StoreError, StoreParams, TileStore

SRC = str(Path(__file__).resolve().parents[1] / "src")
# ray_ilm and, for the nav2 export, the navigation map; a radius that pages tiles out and in
CONFIG = MapperConfig(maps=("ray_ilm",), store=StoreParams(resident_m=20.0), tile_cells=64)
OUTPUTS = OutputConfig(
    figures=False, convergence=False, save_maps=True, checkpoint_every_s=1.0, exports=("nav2",)
)


def _frames(stop: int | None = None):
    from evgrid_sim import SimConfig, simulate_scene

    for i, frame in enumerate(simulate_scene(3, SimConfig(duration_s=3.0))):
        if i == stop:
            raise KeyboardInterrupt  # the run stops here, after a checkpoint
        yield frame


def _same_maps(a: Path, b: Path) -> None:
    names = sorted(p.name for p in (a / "maps").iterdir())
    assert names == sorted(p.name for p in (b / "maps").iterdir()) and names
    for name in names:
        ma, mb = load_map(a / "maps" / name), load_map(b / "maps" / name)
        for x, y in zip(ma.to_dense(), mb.to_dense()):
            assert np.array_equal(x, y), name


def test_a_stopped_scene_resumes_from_its_checkpoint_with_the_same_maps(tmp_path, caplog):
    whole = map_scene(_frames(), tmp_path / "whole", CONFIG, OUTPUTS, overwrite=True)
    assert whole.metrics["checkpoints"]["n"] >= 2
    stop = random.Random(35).randrange(21, 28)  # after the checkpoint at 2 s of the drive
    with pytest.raises(KeyboardInterrupt):
        map_scene(_frames(stop), tmp_path / "cut", CONFIG, OUTPUTS, overwrite=True)
    assert checkpoint_path(tmp_path / "cut" / STORE_FOLDER).exists()
    cut = map_scene(_frames(), tmp_path / "cut", CONFIG, OUTPUTS, overwrite=True, resume=True)
    assert any(r.message.startswith("resuming scene at frame ") for r in caplog.records)
    assert cut.metrics["frames"] == whole.metrics["frames"]
    _same_maps(tmp_path / "whole", tmp_path / "cut")
    pgm = "nav2/map.pgm"
    assert (tmp_path / "whole" / pgm).read_bytes() == (tmp_path / "cut" / pgm).read_bytes()
    assert not (tmp_path / "cut" / STORE_FOLDER).exists()  # complete: the store went


def test_a_damaged_checkpoint_or_one_of_another_version_is_refused_naming_the_file(
    tmp_path, caplog
):
    with pytest.raises(KeyboardInterrupt):
        map_scene(_frames(25), tmp_path / "cut", CONFIG, OUTPUTS, overwrite=True)
    path = checkpoint_path(tmp_path / "cut" / STORE_FOLDER)
    whole = path.read_bytes()
    data = bytearray(whole)
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match=f"{path}: the checkpoint is damaged"):
        load_checkpoint(path, TileStore(path.parent), lambda: None)
    data[-100] ^= 0xFF
    data[8:12] = (CHECKPOINT_VERSION + 1).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError, match=f"{path}: a checkpoint of version"):
        map_scene(_frames(), tmp_path / "cut", CONFIG, OUTPUTS, overwrite=True, resume=True)
    # a checkpoint of another config: the scene is mapped from its first frame
    path.write_bytes(whole)
    other = OutputConfig(figures=False, save_maps=True, checkpoint_every_s=1.0)
    done = map_scene(_frames(), tmp_path / "cut", CONFIG, other, overwrite=True, resume=True)
    assert any("checkpoint is of another config" in r.message for r in caplog.records)
    assert done.metrics["checkpoints"]["n"] >= 2


def _evgrid(out: Path, *more: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    args = ["map", "--scenes", "1", "--seed", "7", "--duration", "4", "--maps", "ray_ilm"]
    args += ["--checkpoint-every", "1", "--save-maps", "--no-figures", "--out", str(out), *more]
    return subprocess.Popen(
        [sys.executable, "-m", "evgrid.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_evgrid_map_killed_after_a_checkpoint_resumes_to_the_maps_of_a_whole_run(tmp_path):
    whole = _evgrid(tmp_path / "whole")
    cut = _evgrid(tmp_path / "cut")
    scene = None
    deadline = time.monotonic() + 120
    while scene is None and time.monotonic() < deadline and cut.poll() is None:
        found = list((tmp_path / "cut").glob(f"*/{STORE_FOLDER}/checkpoint.pkl"))
        scene = found[0].parents[1] if found else None
        time.sleep(0.02)
    assert scene is not None, cut.communicate()
    time.sleep(random.Random(7).uniform(0.0, 0.3))  # a random frame after the checkpoint
    assert cut.poll() is None, "the run ended before it could be killed"
    cut.send_signal(signal.SIGKILL)
    cut.wait()
    assert whole.wait(120) == 0, whole.communicate()
    again = _evgrid(tmp_path / "cut", "--resume")
    _, err = again.communicate(timeout=120)
    assert again.returncode == 0, err
    assert f"resuming {scene.name} at frame " in err
    _same_maps(tmp_path / "whole" / scene.name, scene)
