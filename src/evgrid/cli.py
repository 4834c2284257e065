"""The ``evgrid`` command line (typer). Heavy modules are imported inside each command."""

from __future__ import annotations

from pathlib import Path

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


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """evgrid: evidential occupancy mapping (Bauer et al., deep ISMs as priors)."""


def _sim_split(seed: int) -> str:
    # Every fifth seed is validation: a scene's split depends on its seed alone, not on N.
    return "val" if seed % 5 == 4 else "train"


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Output folder (created if missing)."),
    scenes: int = typer.Option(1, "--scenes", min=1, help="Number of scenes; scene k uses seed S + k."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed S of the first scene."),
    fmt: str = typer.Option("npz", "--format", help="'npz': one DIR/sim-<seed>.npz per scene; 'nuscenes': the nuScenes layout."),
    duration: float = typer.Option(20.0, "--duration", help="Scene length in seconds."),
    environment: str = typer.Option("mixed", "--environment", help="urban, suburban, or mixed (drawn per seed)."),
    version: str = typer.Option("v1.0-sim", "--version", help="Version folder for --format nuscenes."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output."),
) -> None:
    """Simulate nuScenes-like scenes (lidar, 5 radars, odometry, true occupancy) and write them to DIR.

    Seeds with seed % 5 == 4 form the 'val' split, the others 'train' (in splits.json for
    --format nuscenes, and in the index.json of --format npz).
    """
    import json

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from evgrid.data.io import atomic_write_text
    from evgrid.data.sim import SimConfig, WorldConfig, simulate_scene
    from evgrid.data.sim.config import ENVIRONMENTS

    if fmt not in ("npz", "nuscenes"):
        raise typer.BadParameter(f"--format must be 'npz' or 'nuscenes', got {fmt!r}", param_hint="--format")
    if environment not in ENVIRONMENTS:
        raise typer.BadParameter(f"--environment must be one of {ENVIRONMENTS}, got {environment!r}", param_hint="--environment")
    try:
        config = SimConfig(duration_s=duration, world=WorldConfig(environment=environment))
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--duration") from e
    seeds = [seed + k for k in range(scenes)]
    out.mkdir(parents=True, exist_ok=True)
    total = scenes * config.n_frames
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=False) as progress:
        task = progress.add_task("simulating", total=total)
        if fmt == "npz":
            from evgrid.data.sim.store import save_sim_scene

            index_path = out / "index.json"
            index = json.loads(index_path.read_text())["scenes"] if index_path.is_file() else []
            for s in seeds:
                scene = simulate_scene(s, config)
                path = out / f"{scene.name}.npz"
                if path.exists() and not overwrite:
                    raise typer.BadParameter(f"{path} exists; pass --overwrite to replace it", param_hint="--out")
                progress.update(task, description=scene.name)
                save_sim_scene(scene, path, on_frame=lambda i: progress.advance(task))
                index = [e for e in index if e.get("name") != scene.name]
                index.append({"name": scene.name, "seed": s, "split": _sim_split(s), "file": path.name,
                              "environment": scene.world.environment, "frames": len(scene)})
                # Rewritten after each scene: an interrupted run still indexes what it wrote.
                index.sort(key=lambda e: e["name"])
                atomic_write_text(index_path, json.dumps({"format": "evgrid-sim-npz", "scenes": index}, indent=1))
        else:
            from evgrid.data.nuscenes_format import write_nuscenes

            splits: dict[str, list[str]] = {"train": [], "val": []}
            sims = []
            for s in seeds:
                sims.append(simulate_scene(s, config))
                splits[_sim_split(s)].append(sims[-1].name)

            def on_frame(name: str, i: int) -> None:
                progress.update(task, description=name)
                progress.advance(task)

            try:
                write_nuscenes(sims, out, version=version, splits=splits, overwrite=overwrite, on_frame=on_frame)
            except FileExistsError as e:
                raise typer.BadParameter(f"{e} (pass --overwrite)", param_hint="--out") from e
    typer.echo(f"wrote {scenes} scene(s) to {out}")


if __name__ == "__main__":
    app()
