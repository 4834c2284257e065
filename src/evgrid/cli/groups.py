"""Option groups: dataclasses whose fields are a command's options (``--sim-dir`` is
``sim_dir``; its comment is the option's help); simulate's and bench's are the simulator's."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from evgrid.config import KIND_MODULES, to_dict
from evgrid.validation import check_int, check_number


def _abs(path: str) -> str:
    return os.path.abspath(os.path.expanduser(path))


@dataclass(frozen=True)
class DataOptions:
    """The data options of map, evaluate, demo, sweep-m-u-min and config show: the simulator by
    default, or a folder of simulated scenes, nuScenes, or recordings."""

    nuscenes: str | None = None  # a nuScenes dataroot (needs evgrid[nuscenes])
    version: str = "v1.0-trainval"  # the nuScenes version (a folder of the dataroot)
    split: str = "val"  # train, val (nuScenes: any official split), or all
    sim_dir: str | None = None  # a folder written by `evgrid simulate`
    bag: tuple[str, ...] = ()  # recordings, one scene each (needs --rig)
    rig: str | None = None  # the recordings' rig.yaml: topics, frames, fields (docs/ros.md)
    scenes: int = 3  # simulator: scenes of the split
    seed: int = 0  # simulator: the first seed drawn from
    duration: float = 20.0  # simulator: seconds a scene
    scene: tuple[str, ...] = ()  # only these scenes

    def __post_init__(self) -> None:
        check_int("", "--scenes", self.scenes, min=1)
        check_int("", "--seed", self.seed, min=0)
        check_number("", "--duration", self.duration, min=0.0, min_open=True)

    def source(self) -> Any:
        """The scene source these options name (the simulator when none is given); paths are
        made absolute, so that a run's config.json holds where its data is."""
        from evgrid.sources import BagSource, NuScenesSource, SimFilesSource, SimSource

        named = (("--nuscenes", self.nuscenes), ("--sim-dir", self.sim_dir), ("--bag", self.bag))
        if len(given := [n for n, v in named if v]) > 1:
            raise ValueError(f"give one data source, not {' and '.join(given)}")
        split = None if self.split == "all" else self.split
        if self.bag:
            if self.rig is None:
                raise ValueError("--bag needs --rig RIG.yaml (topics, frames, fields; docs/ros.md)")
            return BagSource(tuple(_abs(b) for b in self.bag), _abs(self.rig))
        if self.rig is not None:
            raise ValueError("--rig goes with --bag")
        if self.nuscenes is not None:
            return NuScenesSource(_abs(self.nuscenes), self.version, split)
        if self.sim_dir is not None:
            return SimFilesSource(_abs(self.sim_dir), split)
        if split is None:
            return SimSource(tuple(range(self.seed, self.seed + self.scenes)), self.duration)
        return SimSource.split(split, self.scenes, self.seed, self.duration)


@dataclass(frozen=True)
class TrainData:
    """``evgrid train``'s data options (``--val-bag`` is ``val_bag``): the simulator by default
    (``scenes`` training and ``val_scenes`` validation scenes from ``seed`` on, each scene's radar
    drawn from the training ranges unless ``random_radar`` is off), nuScenes splits, or
    recordings (``bag`` and ``val_bag`` with their ``rig``)."""

    nuscenes: str | None = None  # a nuScenes dataroot (needs evgrid[nuscenes])
    version: str = "v1.0-trainval"  # the nuScenes version (a folder of the dataroot)
    train_split: str = "train"  # nuScenes: the training split
    val_split: str = "val"  # nuScenes: the validation split
    bag: tuple[str, ...] = ()  # training recordings (needs --val-bag, --rig)
    val_bag: tuple[str, ...] = ()  # validation recordings
    rig: str | None = None  # the recordings' rig.yaml (docs/ros.md)
    scenes: int = 40  # simulator: training scenes
    val_scenes: int = 10  # simulator: validation scenes
    seed: int = 0  # the training run's seed, and the first simulator seed
    duration: float = 20.0  # simulator: seconds a scene
    random_radar: bool = True  # simulator: each scene's radar drawn from the training ranges

    def overrides(self) -> list[tuple[str, Any]]:
        """The config fields these options decide: both sources, the seed, the radar ranges."""
        from evgrid.sources import BagSource, NuScenesSource, SimSource, source_to_dict
        from evgrid_sim.radar_variants import TRAINING_RANGES

        ranges = None
        if self.bag or self.val_bag:
            if not (self.bag and self.val_bag and self.rig) or self.nuscenes is not None:
                raise ValueError(
                    "training on recordings needs --bag, --val-bag and --rig (and no --nuscenes)"
                )
            tr, va = (
                BagSource(tuple(map(_abs, b)), _abs(self.rig)) for b in (self.bag, self.val_bag)
            )
        elif self.nuscenes is not None:
            root = _abs(self.nuscenes)
            tr, va = (
                NuScenesSource(root, self.version, s) for s in (self.train_split, self.val_split)
            )
        else:
            ranges = TRAINING_RANGES if self.random_radar else None
            tr, va = (
                SimSource.split(split, n, self.seed, self.duration, radar_ranges=ranges)
                for split, n in (("train", self.scenes), ("val", self.val_scenes))
            )
        return [
            ("source", source_to_dict(tr)), ("val_source", source_to_dict(va)),
            ("train.seed", self.seed), ("train.radar_ranges", to_dict(ranges) if ranges else None),
        ]  # fmt: skip


# `evgrid simulate` and `evgrid bench` take the simulator's option groups (evgrid_lab.options);
# their config files are read by importing it
KIND_MODULES.update({"evgrid-simulate": "evgrid_lab.options", "evgrid-bench": "evgrid_lab.options"})
KIND_MODULES["evgrid-train"] = "evgrid.train_run"  # imports torch: only for such a file
