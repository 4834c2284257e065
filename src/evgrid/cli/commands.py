"""The ``evgrid`` commands: each parses, builds its config, and calls the library; options
beyond the few common ones override config fields (:mod:`evgrid.cli.options`)."""

from __future__ import annotations

from pathlib import Path

import typer

from evgrid.cli.base import CHECKPOINT, CONFIG, ENGINE, OUT, OVERWRITE, RESUME, SET  # isort: skip
from evgrid.cli.base import app, command, config_app, workers  # isort: skip

__all__ = ["app"]


def _map(ctx, name, out, config, sets, n, engine, resume, overwrite, preset=(), data0={}):
    """A mapping run (map, evaluate, demo) or a sweep of ``m_u_min``; failed scenes fail it."""
    from evgrid.budget import check_budget
    from evgrid.cli.options import MAP_OPTIONS, config_from_args
    from evgrid.config import RunConfig, SweepConfig
    from evgrid.console import ConsoleEvents, failures, map_report, print_text, sweep_report
    from evgrid.outdir import default_out
    from evgrid.runs import map_scenes, sweep_m_u_min
    from evgrid.sources import source_from_dict

    if resume and overwrite:  # else a folder of finished scenes under several configs
        raise ValueError("--resume keeps the finished scenes, --overwrite replaces them: not both")
    sweep = name == "sweep-m-u-min"
    out = out or (default_out(name, resume) if resume else None)
    cls = SweepConfig if sweep else RunConfig
    run = config_from_args(cls, ctx.args, config, sets or (), preset, data0, resume and out)
    check_budget(run.mapper, getattr(run, "outputs", None), workers=n, options=MAP_OPTIONS)
    out = out or default_out(name)
    if not sweep and run.outputs.viewer and n > 1:
        raise typer.BadParameter("--viewer shows one scene at a time: use --workers 1")
    source, names = source_from_dict(run.source), run.scenes and list(run.scenes)
    with ConsoleEvents() as events:
        summary = (
            sweep_m_u_min(source, list(run.values), out, run.mapper, names, n, overwrite,
                          engine=engine, events=events)
            if sweep else
            map_scenes(source, out, run.mapper, run.outputs, names, n, overwrite=overwrite,
                       engine=engine, resume=resume, events=events)
        )  # fmt: skip
    print_text((sweep_report if sweep else map_report)(summary, out))
    if failed := failures(summary["failed"], out):
        raise RuntimeError(failed)
    return summary


def _mapping(name: str, n: int, doc: str, preset=(), data0={}) -> None:
    """A mapping command: `map`, or a preset of it."""

    def cmd(
        ctx: typer.Context, out: Path = OUT, config: Path = CONFIG, sets: list[str] = SET,
        workers: int = workers(n), engine: str = ENGINE, resume: bool = RESUME,
        overwrite: bool = OVERWRITE,
    ) -> None:  # fmt: skip
        _map(ctx, name, out, config, sets, workers, engine, resume, overwrite, preset, data0)

    cmd.__doc__ = doc
    command(name, extra=True)(cmd)


_mapping("map", 1, """Map scenes: the six maps of the paper's Table I, figures, GIFs, metrics.

    \b
    Examples:
      evgrid map --scenes 5 --out out/sim-val
      evgrid map --config out/sim-val/config.json --out out/sim-val-again
      evgrid map --nuscenes /data/nuscenes --version v1.0-mini --split mini_val --out out/mini
      evgrid map --bag drive.mcap --rig rig.yaml --export nav2,mcap --out out/drive
    """)  # fmt: skip
# `evaluate` is `map` without figures, saved maps or exports, over 10 scenes by default
_mapping("evaluate", 2, """Evaluate the six maps over a split: per-class mIoU against ray_ilm
    (and the truth in simulation); `map` without figures: config.json, summary.json, table.md.

    Example: evgrid evaluate --scenes 10 --workers 2
    """, [("outputs.figures", False), ("outputs.save_maps", False), ("outputs.exports", []),
    ("outputs.viewer", False)], {"scenes": 10})  # fmt: skip


@command(extra=True)
def demo(
    ctx: typer.Context, out: Path = typer.Option(Path("out/demo"), "--out"),
    workers: int = workers(2), overwrite: bool = OVERWRITE,
) -> None:  # fmt: skip
    """Map three simulated validation scenes (or the data options' scenes) with the shipped
    Ev-Net: OUT/metrics.json ({"maps": {name: {"free", "occupied", "unknown"}}, ...}), table.md,
    per scene figures and a GIF. Example: evgrid demo --scenes 1 --duration 5 --out out/demo"""
    from evgrid.io import write_json

    summary = _map(ctx, "demo", out, None, None, workers, "local", False, overwrite)
    write_json(out / "metrics.json", summary)


@command(extra=True)
def simulate(
    ctx: typer.Context, out: Path = typer.Option(..., "--out", help="Output folder."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing scenes."),
    config: Path = typer.Option(None, "--config", help="A simulate config.json (options win)."),
) -> None:  # fmt: skip
    """Simulate nuScenes-like scenes (lidar, radars, odometry, true occupancy) into OUT: npz,
    nuscenes, or recordings (ros2, ros1, mcap: needs evgrid[ros]); seed % 5 == 4 is 'val'.
    Writes OUT/config.json (simulate again with --config).

    \b
    Example (a 10 Hz lidar, three radars at 4 Hz):
      evgrid simulate --format nuscenes --out data/rig --lidar-rate 10 --radar-rate 4
        --radar-channels RADAR_FRONT,RADAR_BACK_LEFT,RADAR_BACK_RIGHT
    """
    from evgrid.cli.options import options_to_overrides
    from evgrid.config import document
    from evgrid.console import bar
    from evgrid_lab.options import SimulateConfig, SimulateOptions, simulate_options
    from evgrid_sim.writer import check_out, write_simulated

    _, values = options_to_overrides(ctx.args, {}, SimulateOptions, SimulateOptions)
    opts, out = simulate_options(values, config), check_out(out)
    sim, seeds = opts.sim_config(), [opts.seed + k for k in range(opts.scenes)]
    with bar("simulating", opts.scenes * sim.n_frames) as advance:
        names = write_simulated(
            sim, seeds, out, opts.format, opts.version, overwrite, on_frame=advance,
            config_document=document(SimulateConfig(opts)),
        )  # fmt: skip
    typer.echo(f"wrote {len(names)} scene(s) to {out}")


@command(extra=True)
def train(
    ctx: typer.Context, out: Path = typer.Option(Path("out/train"), "--out", help="Run folder."),
    config: Path = CONFIG, sets: list[str] = SET,
    resume: bool = typer.Option(False, "--resume", help="Continue the training in --out."),
) -> None:  # fmt: skip
    """Train Ev-Net (the deep IRM) on simulated scenes, nuScenes or recordings against the ray
    ILM; writes config.json (train again with --config), metrics.csv and checkpoints. Several
    GPUs or processes: the same command under torchrun -m evgrid.cli train ... (docs/training.md).

    Example: evgrid train --scenes 40 --val-scenes 10 --epochs 12 --out out/train
    """
    from evgrid.cli.options import train_config_from_args
    from evgrid.console import print_text, train_report, training_events
    from evgrid.train_run import run_training

    run = train_config_from_args(ctx.args, config, sets or (), out if resume else None)
    with training_events() as events:
        print_text(train_report(run_training(run, out, resume, **events), out))


@command("sweep-m-u-min", extra=True)
def sweep_m_u_min_cmd(
    ctx: typer.Context, out: Path = OUT, config: Path = CONFIG, sets: list[str] = SET,
    workers: int = workers(2), engine: str = ENGINE, overwrite: bool = OVERWRITE,
) -> None:  # fmt: skip
    """Sweep the lower limit m_u_min: mIoU of deep_replace, deep_disc and fused against ray_ilm
    (JSON + plot); writes config.json (re-run with --config).
    Example: evgrid sweep-m-u-min --scenes 4 --values 0.1,0.2,0.3,0.4,0.5 --out out/sweep"""
    sweep = (ctx, "sweep-m-u-min", out, config, sets, workers, engine, False, overwrite)
    _map(*sweep, data0={"scenes": 4})


@command(extra=True, typer_app=config_app)
def show(
    ctx: typer.Context, config: Path = CONFIG, sets: list[str] = SET,
    defaults: bool = typer.Option(False, "--defaults", help="The defaults, nothing given."),
) -> None:  # fmt: skip
    """Print the config a map run would use (or a --config file of any kind) as JSON."""
    import json

    from evgrid.cli.options import config_from_args  # registers the cli's kinds of config file
    from evgrid.config import RunConfig, document, load_config

    if defaults and (config or sets or ctx.args):
        raise typer.BadParameter("--defaults shows the defaults: give no other option")
    if config and not (sets or ctx.args):  # a file of any kind, as it is
        run = load_config(config, None)
    else:
        run = config_from_args(RunConfig, ctx.args, config, sets or ())
    typer.echo(json.dumps(document(run), indent=2))


@command("export")
def export_cmd(
    map_file: Path = typer.Argument(..., help="A map saved by evgrid (.npz, --save-maps)."),
    fmt: str = typer.Option(..., "--format", help="nav2 (PGM + YAML), mcap (Foxglove), rerun."),
    out: Path = typer.Option(None, "--out", help="Output stem or file; default: beside the map."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing files."),
) -> None:
    """Export a saved map for nav2's map_server, Foxglove or rerun (thresholds: docs/ros.md).

    Example: evgrid export out/map/sim-000004/maps/fused.npz --format nav2
    """
    from evgrid.export import export_map
    from evgrid.grid import load_map

    target = out or map_file.with_suffix("")
    written = export_map(
        load_map(map_file, lazy=True), target, fmt, map_file.stem, overwrite=overwrite
    )
    typer.echo("\n".join(f"wrote {path}" for path in written))


@command()
def transfer(
    out: Path = typer.Option(Path("out/transfer"), "--out", help="Results folder."),
    checkpoint: Path = CHECKPOINT,
    scenes: int = typer.Option(4, "--scenes", min=1, help="Held-out scenes per radar."),
    seed: int = typer.Option(1000, "--seed", min=0, help="First simulator seed."),
    duration: float = typer.Option(10.0, "--duration", help="Scene length in seconds."),
    workers: int = workers(1),
    engine: str = ENGINE,
) -> None:
    """Score Ev-Net's single frames on radars inside and outside its training ranges (the deep
    and the ray IRM's IoU per class against the ray ILM). Example: evgrid transfer --scenes 4"""
    from evgrid.console import bar
    from evgrid_lab.transfer import run_transfer

    with bar("radars", None, unit="radars") as advance:
        text = run_transfer(out, checkpoint, scenes, seed, duration, advance, engine, workers)
    typer.echo(f"{text}\nwrote {out / 'transfer.json'} and {out / 'transfer.md'}")


@command("upgrade-checkpoint")
def upgrade_checkpoint_cmd(
    src: Path = typer.Argument(..., help="An Ev-Net checkpoint of an older format."),
    dst: Path = typer.Argument(None, help="Where to write it (default: replace SRC, atomically)."),
) -> None:
    """Rewrite an Ev-Net checkpoint in the current format (with its checksum); same weights.
    Example: evgrid upgrade-checkpoint old.safetensors new.safetensors"""
    from evgrid.ism.evnet import upgrade_checkpoint

    typer.echo(f"wrote {upgrade_checkpoint(src, dst or src)}")


@command()
def unlock(out: Path = typer.Argument(..., help="A results folder whose lock is stale.")) -> None:
    """Clear the lock a run that no longer lives left on a results folder (another host's, a
    crashed one's); a live run's lock on this host is refused. Example: evgrid unlock out/run"""
    from evgrid.outdir import break_lock

    holder = break_lock(out)
    was = f" (was pid {holder['pid']} on {holder['host']})" if holder else ""
    typer.echo(f"{out}: unlocked{was}")


@command(extra=True)
def bench(
    ctx: typer.Context,
    out: Path = typer.Option(None, "--out", help="Also write the JSON here (and .config.json)."),
    config: Path = typer.Option(None, "--config", help="A bench's .config.json (options win)."),
) -> None:
    """Time every component and the per-frame updates on one core; print JSON. With --out
    FILE, FILE's stem + .config.json holds the options (bench again with --config). Example:
    evgrid bench --end-to-end 20 (and a whole 20 s run mapped end to end)"""
    import json

    from evgrid.cli.options import options_to_overrides
    from evgrid.io import write_json
    from evgrid_lab.bench import run_bench
    from evgrid_lab.options import BenchOptions, bench_options, write_bench_config

    opts = bench_options(options_to_overrides(ctx.args, {}, BenchOptions, BenchOptions)[1], config)
    res = run_bench(opts.duration, opts.checkpoint, opts.repeats, end_to_end_s=opts.end_to_end)
    typer.echo(json.dumps(res, indent=2))
    if out is not None:
        write_json(out, res)
        write_bench_config(opts, out)
