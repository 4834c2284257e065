"""``evgrid live`` and ``evgrid replay``: ROS 2 without ROS (docs/live.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from evgrid.cli.base import CONFIG, SET, command

_O = typer.Option


@command(extra=True)
def live(
    ctx: typer.Context,
    rig: Path = _O(..., "--rig", help="The rig file of --bag: topics, frames, fields."),
    out: Path = _O(None, "--out", help="Where the maps are saved (nav2/, maps/)."),
    config: Path = CONFIG, sets: list[str] = SET,
    map_rate: float = _O(1.0, "--map-rate", help="/map publications per second."),
    map_max_cells: int = _O(16777216, "--map-max-cells", help="/map: the whole map up to N cells"),
    map_window: float = _O(200.0, "--map-window", help="beyond: a square of M metres around"),
    publish: str = _O("", "--publish", help="NAMES: also /evgrid/NAME/occupancy."),
    grid_map: bool = _O(False, "--grid-map", help="Also /evgrid/NAME/grid_map (masses)."),
    save_every: float = _O(0.0, "--save-every", help="Save the maps every SECONDS too."),
    duration: float = _O(None, "--duration", help="Stop after SECONDS."),
) -> None:  # fmt: skip
    """Map what a running robot publishes (ROS 2, no ROS installation): the rig's topics on
    ROS_DOMAIN_ID, /map out for nav2, Foxglove and RViz (docs/live.md). Ctrl-C or SIGTERM
    saves the maps into --out (nav2/map.pgm + map.yaml; maps/ with --save-maps) and exits 0.
    Example: evgrid live --rig rig.yaml --out out/live --publish fused --save-every 60"""
    from evgrid.ros import require

    require("cyclonedds", "live")
    from evgrid.cli.groups import DataOptions
    from evgrid.cli.options import MAP_OPTIONS, options_to_overrides, parse_overrides
    from evgrid.config import RunConfig, resolve_config
    from evgrid.data.bag import load_rig
    from evgrid.live.node import LiveNode, LiveOptions, report_line, run_live

    overrides, data = options_to_overrides(ctx.args, MAP_OPTIONS, RunConfig, DataOptions)
    if data:
        raise typer.BadParameter(f"evgrid live maps the rig's topics, not {sorted(data)}")
    preset = [("mapper.maps", ["nav"])]
    run = resolve_config(RunConfig, config, [*preset, *overrides, *parse_overrides(sets or ())])
    opts = LiveOptions(
        map_rate_hz=map_rate, map_max_cells=map_max_cells, map_window_m=map_window,
        publish=tuple(n for n in publish.split(",") if n), grid_map=grid_map,
        save_every_s=save_every, save_maps=run.outputs.save_maps,
    )  # fmt: skip
    node = LiveNode(load_rig(rig), run.mapper, run.outputs, out, opts, say=typer.echo)
    typer.echo(report_line(run_live(node, duration)))


@command()
def replay(
    recording: Path = typer.Argument(..., help="A ROS 2 bag (folder) or an MCAP file."),
    rig: Path = _O(..., "--rig", help="The rig file: which topics to play."),
    rate: float = _O(1.0, "--rate", help="Speed: 2 plays twice as fast."),
    loop: bool = _O(False, "--loop", help="Play on and on, time going on."),
    recorded_stamps: bool = _O(False, "--recorded-stamps", help="Keep the recorded stamps."),
    wait: float = _O(5.0, "--wait", help="Seconds to wait for subscribers first."),
) -> None:  # fmt: skip
    """Publish a recording's topics onto DDS at their recorded timing, as ros2 bag play does
    (for evgrid live, demos, users without ROS; docs/live.md).
    Example: evgrid replay drive.mcap --rig rig.yaml --loop"""
    from evgrid.ros import require

    require("cyclonedds", "live")
    from evgrid.data.bag import load_rig
    from evgrid.live.replay import replay_until_signal

    stamps = "recorded" if recorded_stamps else "now"
    r = replay_until_signal(recording, load_rig(rig), rate, loop, stamps, wait, say=typer.echo)
    typer.echo(r.line())
