"""The ``evgrid`` command line (typer): commands parse, build the config, and call the library.

Options beyond the few common ones are overrides of the config's fields: ``--set KEY=VALUE``
sets any field (``--set mapper.fusion.m_u_min=0.4``), and the short options listed in each
command's help (``--m-u-min 0.4``) are named overrides (evgrid.config.MAP_OPTIONS). A command
that fails prints one line, ``evgrid: error: ...``, and exits with status 1; ``evgrid --debug
COMMAND`` (or ``EVGRID_DEBUG=1``) shows the traceback instead. Ctrl-C exits with 130.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

import evgrid

# rich markup off: it would eat the [extra] names of install hints ("evgrid[ros]")
app = typer.Typer(
    name="evgrid",
    help="Evidential occupancy grid maps from lidar and radar, with deep ISMs as priors.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
    rich_markup_mode=None,
)
config_app = typer.Typer(help="Show the resolved config of a run.", rich_markup_mode=None)
app.add_typer(config_app, name="config")
_STATE = {"debug": os.environ.get("EVGRID_DEBUG", "") not in ("", "0")}
#: The options of a command's help beyond its own: data options and config overrides.
_EXTRA = {"allow_extra_args": True, "ignore_unknown_options": True}


def _version(value: bool) -> None:
    if value:
        typer.echo(f"evgrid {evgrid.__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    debug: bool = typer.Option(False, "--debug", help="Show the traceback when a command fails."),
) -> None:
    """evgrid: evidential occupancy mapping (Bauer et al., deep ISMs as priors)."""
    _STATE["debug"] = debug or os.environ.get("EVGRID_DEBUG", "") not in ("", "0")


class _Command(typer.core.TyperCommand):
    """A command whose help ends with the options it takes from the config (written when asked
    for: the config's modules are slow to import)."""

    def format_epilog(self, ctx: Any, formatter: Any) -> None:
        from evgrid.config import command_options_help

        self.epilog = command_options_help(self.name)
        super().format_epilog(ctx, formatter)


def _command(*args: Any, typer_app: typer.Typer = app, **kwargs: Any) -> Callable:
    """``app.command`` whose failures print one line (see the module docstring)."""

    def register(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def run(*a: Any, **k: Any) -> Any:
            try:
                return fn(*a, **k)
            except (typer.Exit, typer.Abort, typer.BadParameter):
                raise
            except KeyboardInterrupt as e:
                typer.echo(f"evgrid: {e or 'interrupted'}", err=True)
                raise typer.Exit(130) from None
            except Exception as e:
                if _STATE["debug"]:
                    raise
                from evgrid.console import error_line

                typer.echo(f"evgrid: error: {error_line(e)}", err=True)
                raise typer.Exit(1) from None

        if kwargs.pop("extra", False):
            kwargs.update(context_settings=_EXTRA, cls=_Command)
        return typer_app.command(*args, **kwargs)(run)

    return register


_OUT = typer.Option(
    None, "--out", help="Results folder; default: a new out/COMMAND/TIME, linked as latest."
)
_CONFIG = typer.Option(None, "--config", help="A run's config.json: the same run (options win).")
_SET = typer.Option(None, "--set", help="KEY=VALUE: any config field, e.g. mapper.threads=2.")
_OVERWRITE = typer.Option(False, "--overwrite", help="Write into --out even if it holds results.")
_RESUME = typer.Option(
    False, "--resume", help="Continue the run in --out (default: the latest): keep complete scenes."
)
_ENGINE = typer.Option("local", "--engine", help="local (a process pool) or ray (the ray extra).")


def _workers(n: int) -> Any:
    return typer.Option(n, "--workers", min=1, help="Scenes run at once (one process each).")


def _map(ctx, command, out, config, sets, workers, engine, resume, overwrite, preset=(), data0={}):
    from evgrid.config import RunConfig, config_from_args
    from evgrid.console import ConsoleEvents, failures, map_report, print_text
    from evgrid.outdir import default_out
    from evgrid.runs import map_scenes
    from evgrid.sources import source_from_dict

    out = out or default_out(command, resume)
    run = config_from_args(RunConfig, ctx.args, config, sets or (), preset, data0, resume and out)
    if run.outputs.viewer and workers > 1:
        raise typer.BadParameter("--viewer shows one scene at a time: use --workers 1")
    with ConsoleEvents() as events:
        summary = map_scenes(
            source_from_dict(run.source), out, run.mapper, run.outputs,
            run.scenes and list(run.scenes), workers, overwrite=overwrite, engine=engine,
            resume=resume, events=events,
        )  # fmt: skip
    print_text(map_report(summary, out))
    if failed := failures(summary["failed"], out):
        raise RuntimeError(failed)
    return summary


def _mapping(command: str, workers: int, doc: str, preset=(), data0={}) -> Callable:
    """A mapping command: `map`, or a preset of it."""

    def cmd(
        ctx: typer.Context, out: Path = _OUT, config: Path = _CONFIG, sets: list[str] = _SET,
        workers: int = _workers(workers), engine: str = _ENGINE, resume: bool = _RESUME,
        overwrite: bool = _OVERWRITE,
    ) -> None:  # fmt: skip
        _map(ctx, command, out, config, sets, workers, engine, resume, overwrite, preset, data0)

    cmd.__doc__ = doc
    return _command(command, extra=True)(cmd)


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


@_command(extra=True)
def demo(
    ctx: typer.Context, out: Path = typer.Option(Path("out/demo"), "--out"),
    workers: int = _workers(2), overwrite: bool = _OVERWRITE,
) -> None:  # fmt: skip
    """Map three simulated validation scenes with the shipped Ev-Net: OUT/metrics.json ({"maps":
    {name: {"free", "occupied", "unknown"}}, ...}), table.md, per scene figures and a GIF."""
    from evgrid.io import write_json

    summary = _map(ctx, "demo", out, None, None, workers, "local", False, overwrite)
    write_json(out / "metrics.json", summary)


@_command(extra=True)
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
    from evgrid.config import options_to_overrides
    from evgrid.console import bar
    from evgrid.sim_writer import SimulateOptions, check_out, simulate_options, write_simulated

    _, values = options_to_overrides(ctx.args, {}, SimulateOptions, SimulateOptions)
    opts, out = simulate_options(values, config), check_out(out)
    total = opts.scenes * opts.sim_config().n_frames
    with bar("simulating", total) as advance:
        names = write_simulated(opts, out, overwrite, on_frame=advance)
    typer.echo(f"wrote {len(names)} scene(s) to {out}")


@_command(extra=True)
def train(
    ctx: typer.Context, out: Path = typer.Option(Path("out/train"), "--out", help="Run folder."),
    config: Path = _CONFIG, sets: list[str] = _SET,
    resume: bool = typer.Option(False, "--resume", help="Continue the training in --out."),
) -> None:  # fmt: skip
    """Train Ev-Net (the deep IRM) on simulated scenes, nuScenes or recordings against the ray
    ILM; writes config.json (train again with --config), metrics.csv and checkpoints. Several
    GPUs or processes: the same command under torchrun -m evgrid.cli train ... (README).

    Example: evgrid train --scenes 40 --val-scenes 10 --epochs 12 --out out/train
    """
    from evgrid.console import print_text, train_report, training_events
    from evgrid.train_run import run_training, train_config_from_args

    run = train_config_from_args(ctx.args, config, sets or (), out if resume else None)
    with training_events() as events:
        print_text(train_report(run_training(run, out, resume, **events), out))


@_command("sweep-m-u-min", extra=True)
def sweep_m_u_min_cmd(
    ctx: typer.Context, out: Path = _OUT, config: Path = _CONFIG, sets: list[str] = _SET,
    workers: int = _workers(2), engine: str = _ENGINE, overwrite: bool = _OVERWRITE,
) -> None:  # fmt: skip
    """Sweep the lower limit m_u_min: mIoU of deep_replace, deep_disc and fused against ray_ilm
    (JSON + plot); writes config.json (re-run with --config).

    Example: evgrid sweep-m-u-min --scenes 4 --values 0.1,0.2,0.3,0.4,0.5 --out out/sweep
    """
    from evgrid.config import SweepConfig, config_from_args
    from evgrid.console import ConsoleEvents, failures, print_text, sweep_report
    from evgrid.outdir import default_out
    from evgrid.runs import sweep_m_u_min
    from evgrid.sources import source_from_dict

    run = config_from_args(SweepConfig, ctx.args, config, sets or (), data_defaults={"scenes": 4})
    out = out or default_out("sweep-m-u-min")
    with ConsoleEvents() as events:
        res = sweep_m_u_min(
            source_from_dict(run.source), list(run.values), out, run.mapper,
            run.scenes and list(run.scenes), workers, overwrite, engine=engine, events=events,
        )  # fmt: skip
    print_text(sweep_report(res, out))
    if failed := failures(res["failed"], out):
        raise RuntimeError(failed)


@_command(extra=True, typer_app=config_app)
def show(
    ctx: typer.Context, config: Path = _CONFIG, sets: list[str] = _SET,
    defaults: bool = typer.Option(False, "--defaults", help="The defaults, nothing given."),
) -> None:  # fmt: skip
    """Print the config a map run would use (or a --config file of any kind) as JSON."""
    import json

    from evgrid.config import RunConfig, config_from_args, document, load_config

    if defaults and (config or sets or ctx.args):
        raise typer.BadParameter("--defaults shows the defaults: give no other option")
    plain = config and not (sets or ctx.args)  # a file of any kind, as it is
    run = (
        load_config(config, None)
        if plain
        else config_from_args(RunConfig, ctx.args, config, sets or ())
    )
    typer.echo(json.dumps(document(run), indent=2))


@_command("export")
def export_cmd(
    map_file: Path = typer.Argument(..., help="A map saved by evgrid (.npz, --save-maps)."),
    fmt: str = typer.Option(..., "--format", help="nav2 (PGM + YAML), mcap (Foxglove), rerun."),
    out: Path = typer.Option(None, "--out", help="Output stem or file; default: beside the map."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing files."),
) -> None:
    """Export a saved map for nav2's map_server, Foxglove or rerun (thresholds: docs/ros.md).

    Example: evgrid export out/map/sim-000004/maps/fused.npz --format nav2
    """
    from evgrid.export import FORMATS, export_map
    from evgrid.grid import load_map

    if fmt not in FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    target = out or map_file.with_suffix("")
    # lazily: the tiles stay on disk and are read one at a time (docs/store.md)
    written = export_map(
        load_map(map_file, lazy=True), target, fmt, map_file.stem, overwrite=overwrite
    )
    typer.echo("\n".join(f"wrote {path}" for path in written))


@_command()
def transfer(
    out: Path = typer.Option(Path("out/transfer"), "--out", help="Results folder."),
    checkpoint: Path = typer.Option(None, "--checkpoint", help="Default: the shipped one."),
    scenes: int = typer.Option(4, "--scenes", min=1, help="Held-out scenes per radar."),
    seed: int = typer.Option(1000, "--seed", min=0, help="First simulator seed."),
    duration: float = typer.Option(10.0, "--duration", help="Scene length in seconds."),
    workers: int = _workers(1),
    engine: str = _ENGINE,
) -> None:
    """Score Ev-Net's single frames on radars inside and outside its training ranges (the deep
    and the ray IRM's IoU per class against the ray ILM). Example: evgrid transfer --scenes 4"""
    from evgrid.console import bar
    from evgrid.train_run import run_transfer

    with bar("radars", None, unit="radars") as advance:
        text = run_transfer(out, checkpoint, scenes, seed, duration, advance, engine, workers)
    typer.echo(f"{text}\nwrote {out / 'transfer.json'} and {out / 'transfer.md'}")


@_command("upgrade-checkpoint")
def upgrade_checkpoint_cmd(
    src: Path = typer.Argument(..., help="An Ev-Net checkpoint of an older format."),
    dst: Path = typer.Argument(None, help="Where to write it (default: replace SRC, atomically)."),
) -> None:
    """Rewrite an Ev-Net checkpoint in the current format (with its checksum); same weights."""
    from evgrid.ism.evnet import upgrade_checkpoint

    typer.echo(f"wrote {upgrade_checkpoint(src, dst or src)}")


@_command()
def bench(
    ctx: typer.Context,
    seconds: float = typer.Option(6.0, "--duration", help="Length of the scene used (s)."),
    checkpoint: Path = typer.Option(None, "--checkpoint", help="Default: the shipped one."),
    end_to_end: float = typer.Option(None, "--end-to-end", help="Seconds mapped end to end."),
    repeats: int = typer.Option(3, "--repeats", min=1, help="Passes; medians over them."),
    out: Path = typer.Option(None, "--out", help="Also write the JSON here (and .config.json)."),
    config: Path = typer.Option(None, "--config", help="A bench's .config.json (options win)."),
) -> None:
    """Time every component and the per-frame updates on one core; print JSON. With --out
    FILE, FILE's stem + .config.json holds the options (bench again with --config).

    Example: evgrid bench --end-to-end 20   # and a whole 20 s run mapped end to end
    """
    import json

    from click.core import ParameterSource

    from evgrid.bench import bench_options, run_bench, write_bench_config
    from evgrid.io import write_json

    given = {
        "duration": seconds, "checkpoint": str(checkpoint) if checkpoint else None,
        "end_to_end": end_to_end, "repeats": repeats,
    }  # fmt: skip
    names = {"duration": "seconds"}  # the field -> this function's parameter
    # a config's values stand unless the option is given on the command line
    typed = ParameterSource.COMMANDLINE
    values = {
        k: v for k, v in given.items()
        if config is None or ctx.get_parameter_source(names.get(k, k)) == typed
    }  # fmt: skip
    opts = bench_options(values, config)
    res = run_bench(opts.duration, opts.checkpoint, opts.repeats, end_to_end_s=opts.end_to_end)
    typer.echo(json.dumps(res, indent=2))
    if out is not None:
        write_json(out, res)
        write_bench_config(opts, out)


if __name__ == "__main__":
    app()
