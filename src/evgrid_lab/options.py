"""The simulator's option groups: what ``evgrid simulate`` writes and what ``evgrid bench`` runs.
Each field is an option of its command (``--lidar-rate`` is ``lidar_rate``; its ``#:`` comment is
the option's help) and both are config files of their own kinds (``evgrid-simulate``,
``evgrid-bench``), so that a run can be repeated with ``--config``."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from evgrid.config import FORMATS, document, resolve_config
from evgrid.validation import check_int, check_number
from evgrid_sim.config import ENVIRONMENTS, LAYOUTS
from evgrid_sim.writer import FORMATS as WRITTEN


def check_scenes(scenes: int, seed: int, duration: float) -> None:
    """The simulator's scene count, first seed and scene length, named as options."""
    check_int("", "--scenes", scenes, min=1)
    check_int("", "--seed", seed, min=0)
    check_number("", "--duration", duration, min=0.0, min_open=True)


@dataclass(frozen=True)
class SimulateOptions:
    """What ``evgrid simulate`` writes."""

    scenes: int = 1  #: scenes simulated, seeds seed, seed+1, ... (seed % 5 == 4 is 'val')
    seed: int = 0  #: the first simulator seed
    format: str = "npz"  #: npz|nuscenes|ros2|ros1|mcap (recordings need evgrid[ros])
    duration: float = 20.0  #: seconds a scene (s)
    environment: str = "mixed"  #: the world: urban|suburban|mixed
    #: the streets: irregular|grid towns, or a highway (a dual carriageway at 25-35 m/s)
    layout: str = "irregular"
    version: str = "v1.0-sim"  #: the nuScenes version folder written (--format nuscenes)
    lidar_rate: float = 20.0  #: lidar sweeps per second (Hz)
    #: radars: NAME or NAME=MOUNT (a nuScenes radar position), comma-separated (none: nuScenes'
    #: five)
    radar_channels: str | None = None
    radar_rate: str | None = None  #: radar sweeps per second (Hz): one rate, or one per channel
    ego_returns: bool = True  #: lidar returns from the vehicle's own body
    #: the fraction of radar sweeps dropped, of those repeated, and of those delivered late (each)
    sweep_faults: float = 0.0

    def __post_init__(self) -> None:
        if self.format not in WRITTEN:
            raise ValueError(f"--format must be one of {', '.join(WRITTEN)}, got {self.format!r}")
        if self.environment not in ENVIRONMENTS:
            raise ValueError(
                f"--environment must be one of {ENVIRONMENTS}, got {self.environment!r}"
            )
        if self.layout not in LAYOUTS:
            raise ValueError(f"--layout must be one of {LAYOUTS}, got {self.layout!r}")
        check_scenes(self.scenes, self.seed, self.duration)
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
        world = WorldConfig(environment=self.environment, layout=self.layout)
        return SimConfig(duration_s=self.duration, world=world, rig=rig, lidar=lidar)


@dataclass(frozen=True)
class SimulateConfig:
    """A simulate run's ``config.json``: the options under ``simulate`` (at the top their
    ``format`` and ``version`` would clash with the file's own tags)."""

    simulate: SimulateOptions = field(default_factory=SimulateOptions)


@dataclass(frozen=True)
class BenchOptions:
    """What ``evgrid bench`` runs, kept beside its ``--out FILE`` as ``FILE``'s stem +
    ``.config.json`` so that ``evgrid bench --config`` runs the same bench again."""

    duration: float = 6.0  #: length of the simulated scene used (s)
    checkpoint: str | None = None  #: Ev-Net weights (none: the shipped checkpoint)
    end_to_end: float | None = None  #: also map this many seconds end to end (s)
    repeats: int = 3  #: passes; medians over them

    def __post_init__(self) -> None:
        check_number("", "--duration", self.duration, min=0.0, min_open=True)
        if self.end_to_end is not None:
            check_number("", "--end-to-end", self.end_to_end, min=0.0)
        check_int("", "--repeats", self.repeats, min=1)


FORMATS.update({SimulateConfig: "evgrid-simulate", BenchOptions: "evgrid-bench"})


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
