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

    \b
    Example:
      evgrid live --rig rig.yaml --out out/live --publish fused --save-every 60
    """
    from evgrid.ros import require

    require("cyclonedds", "live")
    from evgrid.cli.groups import DataOptions
    from evgrid.cli.options import MAP_OPTIONS, options_to_overrides, parse_overrides
    from evgrid.config import RunConfig, resolve_config
    from evgrid.data.bag import load_rig
    from evgrid.live.node import LiveNode, LiveOptions, run_live

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
    r = run_live(
        LiveNode(load_rig(rig), run.mapper, run.outputs, out, opts, say=typer.echo), duration
    )
    lat = r["latency_ms"]
    typer.echo(
        f"evgrid live: stopped after {r['updates']} updates of {r['lidar_sweeps']} lidar sweeps; "
        f"dropped {sum(r['dropped'].values())} {r['dropped'] or ''}; {r['published']} /map "
        f"publications, latency median {lat['median']:.0f} ms, p95 {lat['p95']:.0f} ms"
        + "".join(f"\nwrote {f}" for f in r["files"])
    )


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

    Example: evgrid replay drive.mcap --rig rig.yaml --loop
    """
    import signal
    import threading

    from evgrid.ros import require

    require("cyclonedds", "live")
    from evgrid.data.bag import load_rig
    from evgrid.live.replay import replay as play

    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *_: stop.set())
    stamps = "recorded" if recorded_stamps else "now"
    r = play(recording, load_rig(rig), rate, loop, stamps, wait, stop=stop.is_set, say=typer.echo)
    typer.echo(
        f"evgrid replay: {r.messages} messages in {r.passes} pass(es), {r.seconds:.1f} s; "
        f"latest {r.late_ms_max:.0f} ms behind its time"
    )
