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
from pathlib import Path

from evgrid.io import write_json

__all__ = ["FORMATS", "check_out", "write_simulated"]

#: The recording formats -> (rosbags storage, file suffix).
_BAGS = {"ros2": ("mcap", ""), "ros1": ("ros1", ".bag"), "mcap": ("plain-mcap", ".mcap")}
FORMATS: tuple[str, ...] = ("npz", "nuscenes", *_BAGS)


def write_simulated(
    config,
    seeds: list[int],
    out: str | Path,
    fmt: str = "npz",
    version: str = "v1.0-sim",
    overwrite: bool = False,
    on_frame: Callable[[str], None] | None = None,
    config_document: dict | None = None,
) -> list[str]:
    """Simulate the scenes of ``seeds`` with the simulator's ``config`` (a
    :class:`~evgrid_sim.SimConfig`) and write them under ``out`` in ``fmt`` (one of
    :data:`FORMATS`; ``version``: the nuScenes layout's); ``on_frame(scene name)`` after each
    frame. Returns the scene names. An existing scene is refused unless ``overwrite``
    (FileExistsError naming it). ``config_document`` (what ``evgrid simulate --config`` reads
    back) is written first as ``out/config.json``; the last run into a folder writes it."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    out = check_out(out)
    out.mkdir(parents=True, exist_ok=True)
    if config_document is not None:
        write_json(out / "config.json", config_document)
    tick = on_frame or (lambda name: None)
    if fmt in _BAGS:
        return _write_recordings(seeds, config, out, fmt, overwrite, tick)
    if fmt == "npz":
        return _write_npz(seeds, config, out, overwrite, tick)
    return _write_nuscenes(seeds, config, out, version, overwrite, tick)


def check_out(out: str | Path) -> Path:
    """``out`` as a folder to write scenes into: a FileExistsError naming it if it is a file."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} is a file; simulate writes a folder")
    return out


def _write_npz(seeds, config, out: Path, overwrite: bool, tick) -> list[str]:
    from evgrid_sim import simulate_scene
    from evgrid_sim.scene import sim_split
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
    from evgrid_sim import simulate_scene
    from evgrid_sim.scene import sim_split

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
