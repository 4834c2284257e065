"""The ``evgrid`` command line (typer). Heavy modules are imported inside each command.

A command that fails prints one line, ``evgrid: error: ...``, and exits with status 1;
``evgrid --debug COMMAND`` (or ``EVGRID_DEBUG=1``) shows the traceback instead.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

import evgrid

app = typer.Typer(
    name="evgrid",
    help="Evidential occupancy grid maps from lidar and radar, with deep inverse sensor models as priors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"evgrid {evgrid.__version__}")
        raise typer.Exit()


_STATE = {"debug": os.environ.get("EVGRID_DEBUG", "") not in ("", "0")}


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    debug: bool = typer.Option(
        False, "--debug", help="Show the full traceback when a command fails."
    ),
) -> None:
    """evgrid: evidential occupancy mapping (Bauer et al., deep ISMs as priors)."""
    _STATE["debug"] = debug or os.environ.get("EVGRID_DEBUG", "") not in ("", "0")


def _message(e: BaseException) -> str:
    """A failure as one line: the exception's own message (a KeyError's without quotes), else its type."""
    text = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
    text = " ".join(str(text).split())
    if isinstance(e, (ValueError, OSError, KeyError, RuntimeError, ImportError)):
        return text or type(e).__name__
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _command(*args: Any, **kwargs: Any) -> Callable:
    """``app.command`` whose failures print one line (see the module docstring)."""

    def register(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def run(*a: Any, **k: Any) -> Any:
            try:
                return fn(*a, **k)
            except (typer.Exit, typer.Abort, typer.TyperException, KeyboardInterrupt):
                raise
            except Exception as e:
                if _STATE["debug"]:
                    raise
                typer.echo(f"evgrid: error: {_message(e)}", err=True)
                raise typer.Exit(1) from None

        return app.command(*args, **kwargs)(run)

    return register


#: Counts of metrics.json that are not data dropped or skipped.
_NOT_DROPS = ("frames", "updates", "lidar_self_returns_removed", "lidar_self_return_voxels")


@_command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Output folder (created if missing)."),
    scenes: int = typer.Option(
        1, "--scenes", min=1, help="Number of scenes; scene k uses seed S + k."
    ),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed S of the first scene."),
    fmt: str = typer.Option(
        "npz",
        "--format",
        help="'npz': one DIR/sim-<seed>.npz per scene; 'nuscenes': the nuScenes "
        "layout; 'ros2' (MCAP storage), 'ros1' or 'mcap': one recording and rig file per scene "
        "(needs evgrid[ros]).",
    ),
    duration: float = typer.Option(20.0, "--duration", help="Scene length in seconds."),
    environment: str = typer.Option(
        "mixed", "--environment", help="urban, suburban, or mixed (drawn per seed)."
    ),
    version: str = typer.Option(
        "v1.0-sim", "--version", help="Version folder for --format nuscenes."
    ),
    lidar_rate: float = typer.Option(
        20.0, "--lidar-rate", help="Lidar sweeps per second (frames), Hz: 20 as nuScenes, or 10."
    ),
    radar_channels: str = typer.Option(
        None,
        "--radar-channels",
        help="Comma-separated radar channels, NAME or "
        "NAME=MOUNT (a nuScenes radar position); default: nuScenes' five.",
    ),
    radar_rate: str = typer.Option(
        None,
        "--radar-rate",
        help="Radar sweeps per second, Hz: one rate, or one per "
        "channel separated by commas (default 13).",
    ),
    ego_returns: bool = typer.Option(
        True,
        "--ego-returns/--no-ego-returns",
        help="Lidar returns from the ego vehicle's own body, as a roof lidar has.",
    ),
    sweep_faults: float = typer.Option(
        0.0,
        "--sweep-faults",
        min=0.0,
        max=1.0,
        help="Fraction of radar sweeps "
        "dropped, and of those repeated, and of those delivered late (each).",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output."),
) -> None:
    """Simulate nuScenes-like scenes (lidar, radars, odometry, true occupancy) and write them to DIR.

    Seeds with seed % 5 == 4 form the 'val' split, the others 'train' (in splits.json for
    --format nuscenes, and in the index.json of --format npz).

    Example (a 10 Hz lidar, three radars at 4 Hz):
      evgrid simulate --format nuscenes --out data/rig --lidar-rate 10 --radar-rate 4
        --radar-channels RADAR_FRONT,RADAR_BACK_LEFT,RADAR_BACK_RIGHT
    """
    import json

    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from evgrid.data.sim import simulate_scene
    from evgrid.data.sim.config import ENVIRONMENTS
    from evgrid.io import write_json
    from evgrid.sources import sim_split

    if fmt not in ("npz", "nuscenes", *_BAG_FORMATS):
        raise typer.BadParameter(
            f"--format must be npz, nuscenes, ros2, ros1 or mcap, got {fmt!r}",
            param_hint="--format",
        )
    if environment not in ENVIRONMENTS:
        raise typer.BadParameter(
            f"--environment must be one of {ENVIRONMENTS}, got {environment!r}",
            param_hint="--environment",
        )
    try:
        config = _sim_config(
            duration, environment, lidar_rate, radar_channels, radar_rate, ego_returns, sweep_faults
        )
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    seeds = [seed + k for k in range(scenes)]
    out.mkdir(parents=True, exist_ok=True)
    total = scenes * config.n_frames
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, transient=False) as progress:
        task = progress.add_task("simulating", total=total)
        if fmt in _BAG_FORMATS:
            _write_recordings(seeds, config, out, fmt, overwrite, progress, task)
        elif fmt == "npz":
            from evgrid.data.sim.store import save_sim_scene

            index_path = out / "index.json"
            index = json.loads(index_path.read_text())["scenes"] if index_path.is_file() else []
            for s in seeds:
                scene = simulate_scene(s, config)
                path = out / f"{scene.name}.npz"
                if path.exists() and not overwrite:
                    raise typer.BadParameter(
                        f"{path} exists; pass --overwrite to replace it", param_hint="--out"
                    )
                progress.update(task, description=scene.name)
                save_sim_scene(scene, path, on_frame=lambda i: progress.advance(task))
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
        else:
            from evgrid.data.nuscenes_format import write_nuscenes

            splits: dict[str, list[str]] = {"train": [], "val": []}
            sims = []
            for s in seeds:
                sims.append(simulate_scene(s, config))
                splits[sim_split(s)].append(sims[-1].name)

            def on_frame(name: str, i: int) -> None:
                progress.update(task, description=name)
                progress.advance(task)

            try:
                write_nuscenes(
                    sims,
                    out,
                    version=version,
                    splits=splits,
                    overwrite=overwrite,
                    on_frame=on_frame,
                )
            except FileExistsError as e:
                raise typer.BadParameter(f"{e} (pass --overwrite)", param_hint="--out") from e
    typer.echo(f"wrote {scenes} scene(s) to {out}")


#: `evgrid simulate --format` -> (rosbags storage, file suffix): a ROS 2 bag folder, a ROS 1 .bag, a plain .mcap.
_BAG_FORMATS = {"ros2": ("mcap", ""), "ros1": ("ros1", ".bag"), "mcap": ("plain-mcap", ".mcap")}


def _write_recordings(seeds, config, out: Path, fmt: str, overwrite: bool, progress, task) -> None:
    """Simulated scenes as recordings with their rig files (what `evgrid map --bag --rig` reads)."""
    import shutil

    from evgrid.data.bag_writer import write_bag
    from evgrid.data.sim import simulate_scene

    storage, suffix = _BAG_FORMATS[fmt]
    for s in seeds:
        scene = simulate_scene(s, config)
        path = out / f"{scene.name}{suffix}"
        rig = path.with_name(path.name + ".rig.yaml")
        if path.exists() or rig.exists():
            if not overwrite:
                raise typer.BadParameter(
                    f"{path} exists; pass --overwrite to replace it", param_hint="--out"
                )
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
            rig.unlink(missing_ok=True)
        progress.update(task, description=scene.name)

        def frames():
            for f in scene:
                progress.advance(task)
                yield f

        write_bag(frames(), path, storage=storage, rig_path=rig, scene_name=scene.name)


def _sim_config(
    duration, environment, lidar_rate, radar_channels, radar_rate, ego_returns, sweep_faults
):
    """The SimConfig of `evgrid simulate`'s options."""
    from dataclasses import replace

    from evgrid.data.sim import SimConfig, WorldConfig
    from evgrid.data.sim.config import LidarConfig, SimRadarRig, SweepFaults

    rig = SimRadarRig()
    if radar_channels:
        pairs = [c.strip().split("=", 1) for c in radar_channels.split(",") if c.strip()]
        rig = replace(
            rig,
            radar_channels=tuple(p[0] for p in pairs),
            radar_mounts=tuple(p[-1] for p in pairs) if any(len(p) == 2 for p in pairs) else (),
        )
    if radar_rate:
        try:
            rig = replace(rig, radar_rates_hz=tuple(float(r) for r in radar_rate.split(",")))
        except ValueError:
            raise ValueError(
                f"--radar-rate must be numbers separated by commas, got {radar_rate!r}"
            ) from None
    if sweep_faults:
        rig = replace(
            rig, faults=SweepFaults(drop=sweep_faults, duplicate=sweep_faults, reorder=sweep_faults)
        )
    return SimConfig(
        duration_s=duration,
        world=WorldConfig(environment=environment),
        rig=rig,
        lidar=LidarConfig(rate_hz=lidar_rate, self_returns=ego_returns),
    )


# --- mapping, evaluation, training, benchmark ------------------------------------------------------

_DATA_OPTIONS = (
    "nuscenes",
    "version",
    "split",
    "sim_dir",
    "scenes",
    "seed",
    "duration",
    "bag",
    "rig",
)


def _source(
    nuscenes: Path | None,
    version: str,
    split: str,
    sim_dir: Path | None,
    scenes: int,
    seed: int,
    duration: float,
    bag: list[Path] | None = None,
    rig: Path | None = None,
):
    """The scene source named by the common data options (the simulator when none is given)."""
    from evgrid.sources import BagSource, NuScenesSource, SimFilesSource, SimSource

    given = [
        name
        for name, v in (("--nuscenes", nuscenes), ("--sim-dir", sim_dir), ("--bag", bag or None))
        if v is not None
    ]
    if len(given) > 1:
        raise typer.BadParameter(
            f"give one data source, not {' and '.join(given)}", param_hint=given[0]
        )
    if bag:
        if rig is None:
            raise typer.BadParameter(
                "--bag needs --rig RIG.yaml (topics, frames and fields; see docs/ros.md)",
                param_hint="--rig",
            )
        return BagSource(tuple(str(b) for b in bag), str(rig))
    if rig is not None:
        raise typer.BadParameter("--rig goes with --bag", param_hint="--rig")
    if nuscenes is not None:
        return NuScenesSource(str(nuscenes), version, None if split == "all" else split)
    if sim_dir is not None:
        return SimFilesSource(str(sim_dir), None if split == "all" else split)
    if split == "all":
        return SimSource(tuple(range(seed, seed + scenes)), duration)
    return SimSource.split(split, scenes, seed, duration)


_NUSCENES = typer.Option(
    None, "--nuscenes", help="nuScenes dataroot (needs evgrid[nuscenes]); default: the simulator."
)
_VERSION = typer.Option(
    "v1.0-trainval", "--version", help="nuScenes version folder, e.g. v1.0-mini or v1.0-sim."
)
_SIM_DIR = typer.Option(
    None, "--sim-dir", help="A folder written by `evgrid simulate` (npz format)."
)
_BAG = typer.Option(
    None,
    "--bag",
    help="A ROS 1 bag, ROS 2 bag (sqlite3 or MCAP) or MCAP file; repeatable, one scene "
    "each (needs evgrid[ros] and --rig).",
)
_RIG = typer.Option(
    None,
    "--rig",
    help="The rig file of --bag: topics, frames, fields (docs/ros.md, docs/rig_example.yaml).",
)
_EXPORT = typer.Option(
    None,
    "--export",
    help="Also write, per scene: nav2 (PGM + YAML of the final maps), mcap (maps "
    "and poses for Foxglove), rerun (.rrd); comma-separated.",
)
_SCENES = typer.Option(3, "--scenes", min=1, help="Simulator: number of scenes of the split.")
_SEED = typer.Option(0, "--seed", min=0, help="Simulator: first seed to draw scenes from.")
_DURATION = typer.Option(20.0, "--duration", help="Simulator: scene length in seconds.")
_SPLIT = typer.Option("val", "--split", help="train, val (nuScenes: any official split), or all.")
_CONFIG = typer.Option(
    None,
    "--config",
    help="A run's config.json: map the same scenes the same way (options given here override it).",
)
_CHECKPOINT = typer.Option(
    None, "--checkpoint", help="Ev-Net checkpoint; default: the shipped one."
)
_M_U_MIN = typer.Option(
    None, "--m-u-min", help="Lower limit on the deep IRM's unknown mass (default 0.3)."
)
_UPDATE_RATE = typer.Option(
    None,
    "--update-rate",
    help="Map updates per second, Hz (default 10, the paper's); keyframes are always updated.",
)
_MAPS = typer.Option(None, "--maps", help="Comma-separated subset of the six maps.")
_LIDAR_MIN_RANGE = typer.Option(
    None,
    "--lidar-min-range",
    min=0.0,
    help="Ignore lidar returns closer than this to the lidar (m, horizontally); 0 keeps all.",
)
_SELF_RETURNS = typer.Option(
    None,
    "--self-returns",
    help="The ego vehicle's own lidar returns: auto (found as "
    "returns fixed in the vehicle's frame while it moves; default), box (those in --body-box) or off.",
)
_BODY_BOX = typer.Option(
    None,
    "--body-box",
    help="The vehicle's body in the ego frame, 'x0,y0,z0,x1,y1,z1' (m); "
    "implies --self-returns box unless another mode is given (default: the nuScenes car).",
)
_RADAR_FILTER = typer.Option(
    None,
    "--radar-filter",
    help="Radar detections kept: none (all; default) or nuscenes "
    "(the devkit's invalid_state/dyn_prop/ambig_state defaults); use the checkpoint's.",
)
_MAX_SPEED = typer.Option(
    None, "--max-speed", help="Odometry sanity: faster ego motion is a glitch, m/s (default 100)."
)
_OVERWRITE = typer.Option(
    False, "--overwrite", help="Write into --out even if it holds results of another run."
)


def _self_returns(base, mode=None, body_box=None):
    """``base`` (SelfReturnParams) with --self-returns and --body-box applied."""
    from dataclasses import replace

    from evgrid.ism.self_returns import parse_body_box

    cfg = base
    if body_box is not None:
        box = parse_body_box(body_box)
        cfg = replace(cfg, body=box, prior=box, mode=mode or "box")
    if mode is not None:
        cfg = replace(cfg, mode=mode)
    return cfg


def _mapper_config(
    base,
    m_u_min=None,
    checkpoint=None,
    update_rate=None,
    maps=None,
    lidar_min_range=None,
    max_speed=None,
    self_returns=None,
    body_box=None,
    radar_filter=None,
):
    """``base`` (a MapperConfig) with the mapper options given on the command line applied."""
    from dataclasses import replace

    from evgrid.data.radar_filter import RadarFilter

    cfg = base
    if self_returns is not None or body_box is not None:
        cfg = replace(cfg, self_returns=_self_returns(cfg.self_returns, self_returns, body_box))
    if radar_filter is not None:
        cfg = replace(cfg, radar_filter=RadarFilter.named(radar_filter))
    if m_u_min is not None:
        cfg = replace(cfg, fusion=replace(cfg.fusion, m_u_min=m_u_min))
    if checkpoint is not None:
        cfg = replace(cfg, checkpoint=str(checkpoint))
    if update_rate is not None:
        cfg = replace(cfg, update_rate_hz=update_rate)
    if maps:
        cfg = replace(cfg, maps=tuple(n.strip() for n in maps.split(",")))
    if lidar_min_range is not None:
        cfg = replace(cfg, lidar=replace(cfg.lidar, min_range_m=lidar_min_range))
    if max_speed is not None:
        cfg = replace(cfg, poses=replace(cfg.poses, max_speed_mps=max_speed))
    return cfg


def _run_setup(ctx: typer.Context, config_path: Path | None, data: dict, scene: list[str] | None):
    """(source, scene names or None, base RunConfig) from --config and the data options (given ones win)."""
    from evgrid.config import RunConfig, load_run_config
    from evgrid.sources import source_from_dict

    run = load_run_config(config_path) if config_path is not None else RunConfig()
    given = [
        n
        for n in _DATA_OPTIONS
        if ctx.get_parameter_source(n) is not None
        and ctx.get_parameter_source(n).name == "COMMANDLINE"
    ]
    if run.source is not None and not given:
        source = source_from_dict(run.source)
    else:
        source = _source(**data)
    names = list(scene) if scene else (list(run.scenes) if run.scenes and not given else None)
    return source, names, run


def _run_maps(source, out: Path, config, outputs, names, workers: int, overwrite: bool) -> dict:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from evgrid.runs import map_scenes
    from evgrid.sources import scenes_of

    todo = scenes_of(source, names)
    console = Console()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    ) as p:
        task = p.add_task(f"mapping {len(todo)} scene(s)", total=len(todo))

        def done(m: dict) -> None:
            p.advance(task)
            counts = m.get("counts", {})
            dropped = {k: v for k, v in counts.items() if v and k not in _NOT_DROPS}
            extra = f"; dropped or skipped: {dropped}" if dropped else ""
            if counts.get("lidar_self_returns_removed"):
                extra += f"; {counts['lidar_self_returns_removed']} lidar self-returns removed"
            p.console.print(
                f"  {m['scene']}: {m['frames']} frames, {m['frames_per_second']:.1f} frames/s{extra}"
            )

        summary = map_scenes(
            source, out, config, outputs, todo, workers, on_scene=done, overwrite=overwrite
        )
    console.print((out / "table.md").read_text())
    console.print(
        f"frames per second (all scenes): {summary['frames_per_second']:.1f}; results in {out}"
    )
    return summary


@_command("map")
def map_cmd(
    ctx: typer.Context,
    out: Path = typer.Option(Path("out/map"), "--out", help="Results folder."),
    config: Path = _CONFIG,
    nuscenes: Path = _NUSCENES,
    version: str = _VERSION,
    split: str = _SPLIT,
    scene: list[str] = typer.Option(None, "--scene", help="Only these scene names (repeatable)."),
    sim_dir: Path = _SIM_DIR,
    bag: list[Path] = _BAG,
    rig: Path = _RIG,
    scenes: int = _SCENES,
    seed: int = _SEED,
    duration: float = _DURATION,
    checkpoint: Path = _CHECKPOINT,
    m_u_min: float = _M_U_MIN,
    update_rate: float = _UPDATE_RATE,
    maps: str = _MAPS,
    lidar_min_range: float = _LIDAR_MIN_RANGE,
    max_speed: float = _MAX_SPEED,
    self_returns: str = _SELF_RETURNS,
    body_box: str = _BODY_BOX,
    radar_filter: str = _RADAR_FILTER,
    workers: int = typer.Option(
        1, "--workers", min=1, help="Scenes mapped in parallel (one process each)."
    ),
    save_maps: bool = typer.Option(
        None, "--save-maps/--no-save-maps", help="Also write every map as .npz."
    ),
    export: str = _EXPORT,
    viewer: bool = typer.Option(
        None,
        "--viewer/--no-viewer",
        help="Watch the maps grow in a live rerun viewer "
        "(needs evgrid[rerun] and a display; one worker).",
    ),
    overwrite: bool = _OVERWRITE,
) -> None:
    """Map scenes: the six maps of the paper's Table I, figures, GIFs, metrics.

    Examples:
      evgrid map --scenes 5 --out out/sim-val
      evgrid map --config out/sim-val/config.json --out out/sim-val-again
      evgrid map --nuscenes /data/nuscenes --version v1.0-mini --split mini_val --out out/mini
      evgrid map --bag drive.mcap --rig rig.yaml --export nav2,mcap --out out/drive
    """
    from dataclasses import replace

    data = dict(
        nuscenes=nuscenes,
        version=version,
        split=split,
        sim_dir=sim_dir,
        scenes=scenes,
        seed=seed,
        duration=duration,
        bag=bag,
        rig=rig,
    )
    source, names, run = _run_setup(ctx, config, data, scene)
    mapper = _mapper_config(
        run.mapper,
        m_u_min,
        checkpoint,
        update_rate,
        maps,
        lidar_min_range,
        max_speed,
        self_returns,
        body_box,
        radar_filter,
    )
    outputs = run.outputs if save_maps is None else replace(run.outputs, save_maps=save_maps)
    if export is not None:
        outputs = replace(outputs, exports=tuple(e.strip() for e in export.split(",") if e.strip()))
    if viewer is not None:
        outputs = replace(outputs, viewer=viewer)
    if outputs.viewer and workers > 1:
        raise typer.BadParameter(
            "--viewer shows one scene at a time: use --workers 1", param_hint="--viewer"
        )
    _run_maps(source, out, mapper, outputs, names, workers, overwrite)


@_command()
def evaluate(
    ctx: typer.Context,
    out: Path = typer.Option(Path("out/evaluate"), "--out", help="Results folder."),
    config: Path = _CONFIG,
    nuscenes: Path = _NUSCENES,
    version: str = _VERSION,
    split: str = _SPLIT,
    scene: list[str] = typer.Option(None, "--scene", help="Only these scene names (repeatable)."),
    sim_dir: Path = _SIM_DIR,
    bag: list[Path] = _BAG,
    rig: Path = _RIG,
    scenes: int = typer.Option(
        10, "--scenes", min=1, help="Simulator: number of validation scenes."
    ),
    seed: int = _SEED,
    duration: float = _DURATION,
    checkpoint: Path = _CHECKPOINT,
    m_u_min: float = _M_U_MIN,
    update_rate: float = _UPDATE_RATE,
    lidar_min_range: float = _LIDAR_MIN_RANGE,
    max_speed: float = _MAX_SPEED,
    self_returns: str = _SELF_RETURNS,
    body_box: str = _BODY_BOX,
    radar_filter: str = _RADAR_FILTER,
    workers: int = typer.Option(
        2, "--workers", min=1, help="Scenes evaluated in parallel (one process each)."
    ),
    overwrite: bool = _OVERWRITE,
) -> None:
    """Evaluate the six maps over a split: per-class mIoU against ray_ilm (and the truth in simulation).

    Like `map` without figures; writes config.json, summary.json and table.md (beside the paper's Table I).

    Examples:
      evgrid evaluate --scenes 10 --workers 2
      evgrid evaluate --nuscenes /data/nuscenes --split val --workers 8
    """
    from dataclasses import replace

    data = dict(
        nuscenes=nuscenes,
        version=version,
        split=split,
        sim_dir=sim_dir,
        scenes=scenes,
        seed=seed,
        duration=duration,
        bag=bag,
        rig=rig,
    )
    source, names, run = _run_setup(ctx, config, data, scene)
    mapper = _mapper_config(
        run.mapper,
        m_u_min,
        checkpoint,
        update_rate,
        None,
        lidar_min_range,
        max_speed,
        self_returns,
        body_box,
        radar_filter,
    )
    outputs = replace(run.outputs, figures=False, save_maps=False, exports=(), viewer=False)
    _run_maps(source, out, mapper, outputs, names, workers, overwrite)


@_command()
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", help="Results folder."),
    scenes: int = typer.Option(3, "--scenes", min=1, help="Simulated validation scenes to map."),
    duration: float = typer.Option(20.0, "--duration", help="Scene length in seconds."),
    workers: int = typer.Option(2, "--workers", min=1, help="Scenes mapped in parallel."),
    overwrite: bool = _OVERWRITE,
) -> None:
    """Simulate a few validation scenes, map them with the shipped Ev-Net, write metrics, table, figures, GIFs.

    Writes OUT/metrics.json ({"maps": {name: {"free", "occupied", "unknown"}}, ...}), OUT/table.md and,
    per scene, maps.png, isms.png, convergence.png and maps.gif.
    """
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.io import write_json
    from evgrid.sources import SimSource

    summary = _run_maps(
        SimSource.split("val", scenes, 0, duration),
        out,
        MapperConfig(),
        OutputConfig(),
        None,
        workers,
        overwrite,
    )
    write_json(out / "metrics.json", summary)


@_command()
def train(
    out: Path = typer.Option(
        Path("out/train"), "--out", help="Run folder: config, metrics.csv, checkpoints, cache."
    ),
    nuscenes: Path = _NUSCENES,
    version: str = _VERSION,
    bag: list[Path] = typer.Option(
        None, "--bag", help="Train on these recordings (repeatable; needs --rig and --val-bag)."
    ),
    val_bag: list[Path] = typer.Option(
        None, "--val-bag", help="Validate on these recordings (repeatable)."
    ),
    rig: Path = _RIG,
    train_split: str = typer.Option("train", "--train-split", help="Split to train on."),
    val_split: str = typer.Option("val", "--val-split", help="Split to validate on."),
    scenes: int = typer.Option(40, "--scenes", min=1, help="Simulator: training scenes."),
    val_scenes: int = typer.Option(10, "--val-scenes", min=1, help="Simulator: validation scenes."),
    seed: int = typer.Option(
        0, "--seed", min=0, help="Seed of the training run (and first simulator seed)."
    ),
    duration: float = _DURATION,
    epochs: int = typer.Option(20, "--epochs", min=1),
    batch_size: int = typer.Option(4, "--batch-size", min=1),
    lr: float = typer.Option(2e-3, "--lr"),
    workers: int = typer.Option(2, "--workers", min=0, help="DataLoader workers."),
    frame_stride: int = typer.Option(
        4, "--frame-stride", min=1, help="Use every Nth lidar frame as a sample."
    ),
    width: int = typer.Option(12, "--width", min=1, help="Ev-Net width of the first stage."),
    depth: int = typer.Option(4, "--depth", min=2, help="Ev-Net stages."),
    self_returns: str = _SELF_RETURNS,
    body_box: str = _BODY_BOX,
    radar_filter: str = _RADAR_FILTER,
    random_radar: bool = typer.Option(
        True,
        "--random-radar/--calibrated-radar",
        help="Simulator: draw each scene's "
        "radar (sensitivity, noise, clutter, ghosts, which radars, rate) from the "
        "training ranges (docs/decisions.md#training-on-many-radars), or use the calibrated radar for all.",
    ),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in --out."),
) -> None:
    """Train Ev-Net (the deep IRM) on simulated scenes or nuScenes, against the ray ILM.

    Multi-GPU / multi-process: the same command under torchrun, e.g.
      torchrun --nproc_per_node=4 -m evgrid.cli train --nuscenes /data/nuscenes --out out/train

    Examples:
      evgrid train --scenes 40 --val-scenes 10 --epochs 12 --out out/train
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from evgrid.data.radar_filter import RadarFilter
    from evgrid.data.radar_variants import TRAINING_RANGES
    from evgrid.ism.evnet import EvNetConfig
    from evgrid.ism.self_returns import SelfReturnParams
    from evgrid.learn.train import TrainConfig, build_cache
    from evgrid.learn.train import train as run_training

    console = Console()
    try:
        config = TrainConfig(
            epochs=epochs,
            batch_size=batch_size,
            lr=lr,
            seed=seed,
            workers=workers,
            frame_stride=frame_stride,
            model=EvNetConfig(in_channels=6, width=width, depth=depth),
            radar_filter=RadarFilter.named(radar_filter or "none"),
            self_returns=_self_returns(SelfReturnParams(), self_returns, body_box),
            radar_ranges=TRAINING_RANGES
            if random_radar and not (bag or val_bag or nuscenes)
            else None,
        )
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    if bag or val_bag:
        if not (bag and val_bag and rig) or nuscenes is not None:
            raise typer.BadParameter(
                "training on recordings needs --bag, --val-bag and --rig (and no --nuscenes)",
                param_hint="--bag",
            )
        from evgrid.sources import BagSource

        tr, va = (
            BagSource(tuple(map(str, bag)), str(rig)),
            BagSource(tuple(map(str, val_bag)), str(rig)),
        )
    elif nuscenes is not None:
        from evgrid.sources import NuScenesSource

        tr, va = (
            NuScenesSource(str(nuscenes), version, train_split),
            NuScenesSource(str(nuscenes), version, val_split),
        )
    else:
        from evgrid.sources import SimSource

        ranges = config.radar_ranges
        tr = SimSource.split("train", scenes, seed, duration, radar_ranges=ranges)
        va = SimSource.split("val", val_scenes, seed, duration, radar_ranges=ranges)
    cache = out / "cache" / config.data_key()
    rank = int(__import__("os").environ.get("RANK", "0"))
    names = {}
    if rank == 0:
        with Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
        ) as p:
            for split, src, irm in (("train", tr, False), ("val", va, True)):
                todo = src.names()
                task = p.add_task(f"caching {split} samples", total=len(todo))
                names[split] = build_cache(
                    (src.load(n) for n in todo),
                    cache,
                    config,
                    with_irm=irm,
                    progress=lambda n: p.advance(task),
                )
    else:
        names = {"train": tr.names(), "val": va.names()}

    def show(epoch: int, row: dict) -> None:
        console.print(
            f"epoch {epoch}: loss {row['train_loss']:.4f}, val IoU free {row['val_free']:.3f} "
            f"occupied {row['val_occupied']:.3f} unknown {row['val_unknown']:.3f} "
            f"(ray IRM free {row['ray_irm_free']:.3f}), {row['seconds']:.0f} s"
        )

    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        disable=rank != 0,
    ) as p:
        task = p.add_task("epoch 0", total=None)

        def batch(epoch: int, b: int, n: int) -> None:
            p.update(task, description=f"epoch {epoch}", completed=b, total=n)

        def epoch_done(epoch: int, row: dict) -> None:
            show(epoch, row)
            p.reset(task)

        res = run_training(
            config,
            cache,
            names["train"],
            names["val"],
            out,
            resume=resume,
            on_epoch=epoch_done,
            on_batch=batch,
        )
    if rank == 0:
        console.print(
            f"best epoch {res.best_epoch}: {res.best}; ray IRM baseline {res.ray_irm_baseline}; "
            f"{res.seconds_per_epoch:.0f} s per epoch; checkpoint {out / 'best.safetensors'}"
        )


@_command("sweep-m-u-min")
def sweep_m_u_min_cmd(
    out: Path = typer.Option(Path("out/sweep"), "--out", help="Results folder."),
    values: str = typer.Option(
        "0.1,0.2,0.3,0.4,0.5,0.6,0.7", "--values", help="Comma-separated m_u_min values."
    ),
    nuscenes: Path = _NUSCENES,
    version: str = _VERSION,
    split: str = typer.Option("val", "--split"),
    sim_dir: Path = _SIM_DIR,
    bag: list[Path] = _BAG,
    rig: Path = _RIG,
    scenes: int = typer.Option(4, "--scenes", min=1, help="Simulator: validation scenes."),
    seed: int = _SEED,
    duration: float = _DURATION,
    checkpoint: Path = _CHECKPOINT,
    workers: int = typer.Option(2, "--workers", min=1),
    overwrite: bool = _OVERWRITE,
) -> None:
    """Sweep the lower limit m_u_min: mIoU of deep_replace, deep_disc and fused against ray_ilm (JSON + plot).

    Example:
      evgrid sweep-m-u-min --scenes 4 --values 0.1,0.2,0.3,0.4,0.5 --out out/sweep
    """
    from evgrid.config import MapperConfig
    from evgrid.runs import sweep_m_u_min

    try:
        vals = [float(v) for v in values.split(",")]
    except ValueError as e:
        raise typer.BadParameter(
            f"--values must be numbers separated by commas, got {values!r}"
        ) from e
    source = _source(nuscenes, version, split, sim_dir, scenes, seed, duration, bag, rig)
    res = sweep_m_u_min(
        source,
        vals,
        out,
        _mapper_config(MapperConfig(), checkpoint=checkpoint),
        workers=workers,
        overwrite=overwrite,
    )
    for row in res["rows"]:
        typer.echo(
            f"m_u_min {row['m_u_min']:.2f}: "
            + ", ".join(f"{k} {v:.3f}" for k, v in row["mean_of_classes"].items())
        )
    typer.echo(f"chosen m_u_min = {res['chosen']}: {res['rule']}; plot: {out}/m_u_min_sweep.png")


@_command("export")
def export_cmd(
    map_file: Path = typer.Argument(
        ..., help="A map saved by evgrid (.npz: `evgrid map --save-maps`, save_map)."
    ),
    fmt: str = typer.Option(
        ..., "--format", help="nav2 (PGM + YAML for map_server), mcap (Foxglove), rerun (.rrd)."
    ),
    out: Path = typer.Option(
        None, "--out", help="Output stem (nav2) or file; default: beside the map."
    ),
) -> None:
    """Export a saved map for the tools that use it: nav2's map_server, Foxglove, rerun.

    nav2 thresholds (docs/ros.md): unknown where never observed or m_u > 0.5; else occupied where
    P(occ) = m_o + m_u/2 > 0.65, free where P(occ) < 0.196.

    Examples:
      evgrid export out/map/sim-000004/maps/fused.npz --format nav2
      evgrid export fused.npz --format mcap --out fused.mcap
    """
    from evgrid.export import FORMATS, export_map
    from evgrid.grid import load_map

    if fmt not in FORMATS:
        raise typer.BadParameter(
            f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}", param_hint="--format"
        )
    written = export_map(
        load_map(map_file), out or map_file.with_suffix(""), fmt, name=map_file.stem
    )
    for path in written:
        typer.echo(f"wrote {path}")


@_command()
def transfer(
    out: Path = typer.Option(
        Path("out/transfer"),
        "--out",
        help="Results folder: transfer.json, transfer.md, sample cache.",
    ),
    checkpoint: Path = _CHECKPOINT,
    scenes: int = typer.Option(
        4, "--scenes", min=1, help="Held-out (val) simulated scenes per radar."
    ),
    seed: int = typer.Option(1000, "--seed", min=0, help="First simulator seed."),
    duration: float = typer.Option(10.0, "--duration", help="Scene length in seconds."),
) -> None:
    """Score Ev-Net's single frames on radars inside and outside its training ranges.

    The same held-out scenes are seen through radars drawn from the training ranges, the
    calibrated radar, and radars outside the ranges (weaker, stronger, noisier, more clutter and
    ghosts, other placements, slower); each gets the deep IRM's and the ray IRM's IoU per class
    against the ray ILM.

    Example:
      evgrid transfer --scenes 4 --out out/transfer
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from evgrid.io import atomic_write_text, write_json
    from evgrid.ism.deep import default_checkpoint
    from evgrid.learn.transfer import measure_transfer, transfer_markdown, transfer_sources

    sources = transfer_sources(scenes, seed, duration)
    ckpt = checkpoint or default_checkpoint()
    out.mkdir(parents=True, exist_ok=True)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    ) as p:
        task = p.add_task("radars", total=len(sources))
        res = measure_transfer(
            ckpt,
            sources,
            out / "cache",
            progress=lambda name: p.update(task, advance=1, description=name),
        )
    text = transfer_markdown(res)
    write_json(
        out / "transfer.json",
        {
            "checkpoint": str(ckpt),
            "scenes": scenes,
            "seed": seed,
            "duration_s": duration,
            "radars": res,
        },
    )
    atomic_write_text(out / "transfer.md", text)
    typer.echo(text)
    typer.echo(f"wrote {out / 'transfer.json'} and {out / 'transfer.md'}")


@_command("upgrade-checkpoint")
def upgrade_checkpoint_cmd(
    src: Path = typer.Argument(..., help="An Ev-Net checkpoint of an older format."),
    dst: Path = typer.Argument(None, help="Where to write it (default: replace SRC, atomically)."),
) -> None:
    """Rewrite an Ev-Net checkpoint in the current format (with the checksum of its tensors); the weights stay the same."""
    from evgrid.ism.evnet import upgrade_checkpoint

    path = upgrade_checkpoint(src, dst or src)
    typer.echo(f"wrote {path}")


@_command()
def bench(
    seconds: float = typer.Option(
        6.0, "--duration", help="Length of the simulated scene used (s)."
    ),
    checkpoint: Path = typer.Option(
        None, "--checkpoint", help="Ev-Net checkpoint; default: the shipped one."
    ),
    end_to_end: float = typer.Option(
        None,
        "--end-to-end",
        help="Length (s) of the scene mapped end to end with "
        "figures and GIF (default: --duration).",
    ),
    repeats: int = typer.Option(
        3, "--repeats", min=1, help="Passes over the scene; medians over them."
    ),
    out: Path = typer.Option(None, "--out", help="Also write the JSON here."),
) -> None:
    """Time every component and the per-frame updates on one core; print JSON.

    Example:
      evgrid bench --out out/bench.json
      evgrid bench --end-to-end 20   # and a whole 20 s run mapped end to end
    """
    import json

    from evgrid.bench import run_bench
    from evgrid.io import write_json

    res = run_bench(
        seconds,
        str(checkpoint) if checkpoint else None,
        repeats=repeats,
        end_to_end_s=end_to_end,
    )
    typer.echo(json.dumps(res, indent=2))
    if out is not None:
        write_json(out, res)


if __name__ == "__main__":
    app()
