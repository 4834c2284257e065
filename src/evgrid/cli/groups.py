"""Option groups: dataclasses whose fields are a command's options (``--sim-dir`` is
``sim_dir``); those of simulate and bench are also config files (their kinds registered here)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from evgrid.config import FORMATS, KIND_MODULES, document, resolve_config, to_dict
from evgrid.validation import check_int, check_number


def _abs(path: str) -> str:
    return os.path.abspath(os.path.expanduser(path))


def _check(scenes: int, seed: int, duration: float) -> None:
    check_int("", "--scenes", scenes, min=1)
    check_int("", "--seed", seed, min=0)
    check_number("", "--duration", duration, min=0.0, min_open=True)


@dataclass(frozen=True)
class DataOptions:
    """The data options of map, evaluate, demo, sweep-m-u-min and config show: the simulator by
    default, or a folder of simulated scenes, nuScenes, or recordings."""

    nuscenes: str | None = None  # a nuScenes dataroot (needs evgrid[nuscenes])
    version: str = "v1.0-trainval"
    split: str = "val"  # train, val (nuScenes: any official split), or all
    sim_dir: str | None = None  # a folder written by `evgrid simulate`
    bag: tuple[str, ...] = ()  # recordings, one scene each (needs --rig)
    rig: str | None = None
    scenes: int = 3  # simulator: scenes of the split
    seed: int = 0  # simulator: the first seed drawn from
    duration: float = 20.0  # simulator: seconds a scene
    scene: tuple[str, ...] = ()  # only these scenes

    def __post_init__(self) -> None:
        _check(self.scenes, self.seed, self.duration)

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

    nuscenes: str | None = None
    version: str = "v1.0-trainval"
    train_split: str = "train"
    val_split: str = "val"
    bag: tuple[str, ...] = ()
    val_bag: tuple[str, ...] = ()
    rig: str | None = None
    scenes: int = 40
    val_scenes: int = 10
    seed: int = 0  # the training run's seed, and the first simulator seed
    duration: float = 20.0
    random_radar: bool = True

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


@dataclass(frozen=True)
class SimulateOptions:
    """What ``evgrid simulate`` writes; each field is an option (``--lidar-rate`` is
    ``lidar_rate``). ``radar_channels``: ``NAME`` or ``NAME=MOUNT`` (a nuScenes radar position),
    comma-separated (default: nuScenes' five); ``radar_rate``: one rate in Hz or one per channel;
    ``sweep_faults``: the fraction of radar sweeps dropped, of those repeated, and of those
    delivered late (each); ``ego_returns``: lidar returns from the vehicle's own body."""

    scenes: int = 1
    seed: int = 0
    format: str = "npz"
    duration: float = 20.0
    environment: str = "mixed"
    version: str = "v1.0-sim"
    lidar_rate: float = 20.0
    radar_channels: str | None = None
    radar_rate: str | None = None
    ego_returns: bool = True
    sweep_faults: float = 0.0

    def __post_init__(self) -> None:
        from evgrid_sim.config import ENVIRONMENTS
        from evgrid_sim.writer import FORMATS as WRITTEN

        if self.format not in WRITTEN:
            raise ValueError(f"--format must be one of {', '.join(WRITTEN)}, got {self.format!r}")
        if self.environment not in ENVIRONMENTS:
            raise ValueError(
                f"--environment must be one of {ENVIRONMENTS}, got {self.environment!r}"
            )
        _check(self.scenes, self.seed, self.duration)
        check_number("", "--sweep-faults", self.sweep_faults, min=0.0, max=1.0)

    def sim_config(self):
        """The simulator's configuration these options describe."""
        from evgrid_sim import SimConfig, WorldConfig
        from evgrid_sim.config import LidarConfig, SimRadarRig, SweepFaults

        rig = SimRadarRig()
        if self.radar_channels:
            pairs = [c.strip().split("=", 1) for c in self.radar_channels.split(",") if c.strip()]
            mounts = tuple(p[-1] for p in pairs) if any(len(p) == 2 for p in pairs) else ()
            rig = replace(rig, radar_channels=tuple(p[0] for p in pairs), radar_mounts=mounts)
        if self.radar_rate:
            try:
                rig = replace(rig, radar_rates_hz=tuple(map(float, self.radar_rate.split(","))))
            except ValueError:
                raise ValueError(
                    f"--radar-rate must be numbers separated by commas, got {self.radar_rate!r}"
                ) from None
        if f := self.sweep_faults:
            rig = replace(rig, faults=SweepFaults(drop=f, duplicate=f, reorder=f))
        lidar = LidarConfig(rate_hz=self.lidar_rate, self_returns=self.ego_returns)
        world = WorldConfig(environment=self.environment)
        return SimConfig(duration_s=self.duration, world=world, rig=rig, lidar=lidar)


@dataclass(frozen=True)
class SimulateConfig:
    """A simulate run's ``config.json``: the options under ``simulate`` (at the top their
    ``format`` and ``version`` would clash with the file's own tags)."""

    simulate: SimulateOptions = field(default_factory=SimulateOptions)


@dataclass(frozen=True)
class BenchOptions:
    """What ``evgrid bench`` runs (its options; ``--end-to-end`` is ``end_to_end``), kept
    beside its ``--out FILE`` as ``FILE``'s stem + ``.config.json`` so that ``evgrid bench
    --config`` runs the same bench again."""

    duration: float = 6.0
    checkpoint: str | None = None
    end_to_end: float | None = None
    repeats: int = 3

    def __post_init__(self) -> None:
        check_number("", "--duration", self.duration, min=0.0, min_open=True)
        if self.end_to_end is not None:
            check_number("", "--end-to-end", self.end_to_end, min=0.0)
        check_int("", "--repeats", self.repeats, min=1)


FORMATS.update({SimulateConfig: "evgrid-simulate", BenchOptions: "evgrid-bench"})
KIND_MODULES["evgrid-train"] = "evgrid.train_run"  # imports torch: only for such a file


def simulate_options(values: dict, config: str | Path | None = None) -> SimulateOptions:
    """A simulate run's options: the ``config.json`` of an earlier run (errors name the file and
    field), else the defaults, with ``values`` (field -> value, from the command line) over them."""
    if config is None:
        return SimulateOptions(**values)
    overrides = [(f"simulate.{k}", v) for k, v in values.items()]
    return resolve_config(SimulateConfig, config, overrides).simulate


def bench_options(values: dict, config: str | os.PathLike | None = None) -> BenchOptions:
    """The bench's options: as :func:`simulate_options`, from a bench's ``.config.json``."""
    if config is None:
        return BenchOptions(**values)
    return resolve_config(BenchOptions, config, list(values.items()))


def write_bench_config(opts: BenchOptions, out: str | os.PathLike) -> Path:
    """Write ``opts`` beside the bench result ``out``: ``bench.json`` -> ``bench.config.json``,
    so that benches written into one folder keep theirs apart."""
    from evgrid.io import write_json

    return write_json(Path(out).with_name(Path(out).stem + ".config.json"), document(opts))
