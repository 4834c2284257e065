"""``evgrid simulate``: simulated scenes written as files, in one of three layouts.

* ``npz``: ``DIR/<scene>.npz`` per scene and ``DIR/index.json`` (name, seed, split, file,
  environment, frames), rewritten after each scene so that an interrupted run indexes what it
  wrote; another seed into the same folder joins the index.
* ``nuscenes``: the nuScenes layout (``DIR/<version>/...``, ``splits.json``), read by the devkit.
* ``ros2``, ``ros1``, ``mcap``: one recording and its rig file per scene (needs evgrid[ros]).

Seeds with seed % 5 == 4 form the ``val`` split, the others ``train``.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from evgrid.io import write_json
from evgrid.validation import check_int, check_number

__all__ = [
    "SimulateOptions",
    "SimulateConfig",
    "FORMATS",
    "CONFIG_FORMAT",
    "check_out",
    "simulate_options",
    "write_simulated",
]

#: The ``format`` tag of the ``config.json`` that ``evgrid simulate`` writes.
CONFIG_FORMAT = "evgrid-simulate"

#: ``--format`` -> (rosbags storage, file suffix) of the recording formats.
_BAGS = {"ros2": ("mcap", ""), "ros1": ("ros1", ".bag"), "mcap": ("plain-mcap", ".mcap")}
FORMATS: tuple[str, ...] = ("npz", "nuscenes", *_BAGS)


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

        if self.format not in FORMATS:
            raise ValueError(f"--format must be one of {', '.join(FORMATS)}, got {self.format!r}")
        if self.environment not in ENVIRONMENTS:
            raise ValueError(
                f"--environment must be one of {ENVIRONMENTS}, got {self.environment!r}"
            )
        check_int("", "--scenes", self.scenes, min=1)
        check_int("", "--seed", self.seed, min=0)
        check_number("", "--duration", self.duration, min=0.0, min_open=True)
        check_number("", "--sweep-faults", self.sweep_faults, min=0.0, max=1.0)

    def sim_config(self):
        """The simulator's configuration these options describe."""
        from evgrid_sim import SimConfig, WorldConfig
        from evgrid_sim.config import LidarConfig, SimRadarRig, SweepFaults

        rig = SimRadarRig()
        if self.radar_channels:
            pairs = [c.strip().split("=", 1) for c in self.radar_channels.split(",") if c.strip()]
            rig = replace(
                rig,
                radar_channels=tuple(p[0] for p in pairs),
                radar_mounts=tuple(p[-1] for p in pairs) if any(len(p) == 2 for p in pairs) else (),
            )
        if self.radar_rate:
            try:
                rates = tuple(float(r) for r in self.radar_rate.split(","))
            except ValueError:
                raise ValueError(
                    f"--radar-rate must be numbers separated by commas, got {self.radar_rate!r}"
                ) from None
            rig = replace(rig, radar_rates_hz=rates)
        if self.sweep_faults:
            f = self.sweep_faults
            rig = replace(rig, faults=SweepFaults(drop=f, duplicate=f, reorder=f))
        return SimConfig(
            duration_s=self.duration,
            world=WorldConfig(environment=self.environment),
            rig=rig,
            lidar=LidarConfig(rate_hz=self.lidar_rate, self_returns=self.ego_returns),
        )


@dataclass(frozen=True)
class SimulateConfig:
    """A simulate run's ``config.json``: the options under ``simulate`` (at the top their
    ``format`` and ``version`` would clash with the file's own tags)."""

    simulate: SimulateOptions = field(default_factory=SimulateOptions)


def _register() -> None:
    from evgrid.config import FORMATS as CONFIG_FORMATS

    CONFIG_FORMATS[SimulateConfig] = CONFIG_FORMAT  # config.json tags and checks its kind


_register()  # at import, so that config.load_config knows the kind


def simulate_options(values: dict, config: str | Path | None = None) -> SimulateOptions:
    """The options of a simulate run: the ``config.json`` at ``config`` (of an earlier run;
    errors name the file and field), else the defaults, with ``values`` (field -> value, from
    the command line) over them."""
    if config is None:
        return SimulateOptions(**values)
    from evgrid.config import resolve_config

    _register()
    overrides = [(f"simulate.{k}", v) for k, v in values.items()]
    return resolve_config(SimulateConfig, config, overrides).simulate


def write_simulated(
    opts: SimulateOptions,
    out: str | Path,
    overwrite: bool = False,
    on_frame: Callable[[str], None] | None = None,
) -> list[str]:
    """Simulate ``opts.scenes`` scenes from ``opts.seed`` on and write them under ``out`` in
    ``opts.format``; ``on_frame(scene name)`` after each frame. Returns the scene names.
    An existing scene is refused unless ``overwrite`` (FileExistsError naming it).
    ``out/config.json`` holds ``opts`` (``evgrid simulate --config`` runs them again); the
    last run into a folder writes it."""
    from evgrid.config import document

    out = check_out(out)
    config = opts.sim_config()
    seeds = [opts.seed + k for k in range(opts.scenes)]
    out.mkdir(parents=True, exist_ok=True)
    _register()
    write_json(out / "config.json", document(SimulateConfig(opts)))
    tick = on_frame or (lambda name: None)
    if opts.format in _BAGS:
        return _write_recordings(seeds, config, out, opts.format, overwrite, tick)
    if opts.format == "npz":
        return _write_npz(seeds, config, out, overwrite, tick)
    return _write_nuscenes(seeds, config, out, opts.version, overwrite, tick)


def check_out(out: str | Path) -> Path:
    """``out`` as a folder to write scenes into: a FileExistsError naming it if it is a file."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} is a file; simulate writes a folder")
    return out


def _write_npz(seeds, config, out: Path, overwrite: bool, tick) -> list[str]:
    from evgrid.sources import sim_split
    from evgrid_sim import simulate_scene
    from evgrid_sim.store import save_sim_scene

    index_path = out / "index.json"
    index = json.loads(index_path.read_text())["scenes"] if index_path.is_file() else []
    names = []
    for s in seeds:
        scene = simulate_scene(s, config)
        path = out / f"{scene.name}.npz"
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
        save_sim_scene(scene, path, on_frame=lambda i, n=scene.name: tick(n))
        index = [e for e in index if e.get("name") != scene.name]
        index.append(
            {
                "name": scene.name,
                "seed": s,
                "split": sim_split(s),
                "file": path.name,
                "environment": scene.world.environment,
                "frames": len(scene),
            }
        )
        # Rewritten after each scene: an interrupted run still indexes what it wrote.
        index.sort(key=lambda e: e["name"])
        write_json(index_path, {"format": "evgrid-sim-npz", "scenes": index})
        names.append(scene.name)
    return names


def _write_nuscenes(seeds, config, out: Path, version: str, overwrite: bool, tick) -> list[str]:
    from evgrid.data.nuscenes_format import write_nuscenes
    from evgrid.sources import sim_split
    from evgrid_sim import simulate_scene

    splits: dict[str, list[str]] = {"train": [], "val": []}
    sims = [simulate_scene(s, config) for s in seeds]
    for s, sim in zip(seeds, sims):
        splits[sim_split(s)].append(sim.name)
    try:
        write_nuscenes(
            sims,
            out,
            version=version,
            splits=splits,
            overwrite=overwrite,
            on_frame=lambda name, i: tick(name),
        )
    except FileExistsError as e:
        raise FileExistsError(f"{e} (pass --overwrite)") from None
    return [s.name for s in sims]


def _write_recordings(seeds, config, out: Path, fmt: str, overwrite: bool, tick) -> list[str]:
    """Simulated scenes as recordings with their rig files (what `evgrid map --bag --rig` reads)."""
    from evgrid.data.bag_writer import write_bag
    from evgrid_sim import simulate_scene

    storage, suffix = _BAGS[fmt]
    names = []
    for s in seeds:
        scene = simulate_scene(s, config)
        path = out / f"{scene.name}{suffix}"
        rig = path.with_name(path.name + ".rig.yaml")
        if path.exists() or rig.exists():
            if not overwrite:
                raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
            rig.unlink(missing_ok=True)

        def frames(scene=scene):
            for f in scene:
                tick(scene.name)
                yield f

        write_bag(frames(), path, storage=storage, rig_path=rig, scene_name=scene.name)
        names.append(scene.name)
    return names
