"""Benchmark: mapping a scene from a ROS 2 MCAP bag against the same scene from the simulator's npz
file.

Run: ``python benchmarks/bench_bag.py [--duration 10] [--seed 0] [--maps ray_ilm,ray_irm,fused]
[--storage mcap]``. Simulates one scene, writes it both as the simulator's ``.npz`` (what
``evgrid simulate`` writes, read by ``SimFilesSource``) and as a bag with its rig file
(``evgrid.data.bag_writer``), checks that both give bit-identical maps, and prints frames per
second of (a) reading the frames alone and (b) reading and mapping them, one core. Target
(issue 15), printed, not asserted: reading a bag is not the bottleneck, i.e. mapping from the
bag runs at (nearly) the speed of mapping from npz.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from harness import machine_line, map_timed

from evgrid.config import MapperConfig
from evgrid.data.bag import load_bag
from evgrid.data.bag_writer import write_bag
from evgrid.mapper import OccupancyMapper
from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim.store import load_sim_scene, save_sim_scene


def read_fps(scene) -> tuple[float, int]:
    t0 = time.perf_counter()
    n = sum(1 for _ in scene)
    return n / (time.perf_counter() - t0), n


def map_fps(scene, config: MapperConfig) -> tuple[float, OccupancyMapper]:
    mapper, ms = map_timed(scene, config)
    return 1e3 * len(ms) / sum(ms), mapper


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--maps",
        default="ray_ilm,ray_irm,fused",
        help="comma-separated maps (all: evgrid.fusion.MAP_NAMES)",
    )
    ap.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3", "ros1", "plain-mcap"))
    args = ap.parse_args()
    config = MapperConfig(maps=tuple(args.maps.split(",")))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = simulate_scene(args.seed, SimConfig(duration_s=args.duration))
        t0 = time.perf_counter()
        npz = save_sim_scene(scene, tmp / "scene.npz")
        t1 = time.perf_counter()
        name = {"ros1": "scene.bag", "plain-mcap": "scene.mcap"}.get(args.storage, "scene_bag")
        bag, rig = write_bag(load_sim_scene(npz), tmp / name, storage=args.storage)
        t2 = time.perf_counter()
        size = sum(p.stat().st_size for p in (bag.rglob("*") if bag.is_dir() else [bag]))
        print(
            f"scene {scene.name}: {len(scene)} frames, {args.duration:g} s; npz "
            f"{npz.stat().st_size / 2**20:.0f} MiB "
            f"written in {t1 - t0:.1f} s; {args.storage} bag {size / 2**20:.0f} MiB written in "
            f"{t2 - t1:.1f} s"
        )
        map_fps(load_sim_scene(npz), config)  # warm-up: numba kernels
        rows = []
        sources = (
            ("npz (SimFilesSource)", lambda: load_sim_scene(npz)),
            (f"bag ({args.storage})", lambda: load_bag(bag, rig)),
        )
        for label, load in sources:
            t0 = time.perf_counter()
            sc = load()
            open_s = time.perf_counter() - t0
            r, n = read_fps(sc)
            m, mapper = map_fps(load(), config)
            rows.append((label, open_s, r, m, mapper))
        print(machine_line())
        print(
            f"{'source':24s} {'open s':>7s} {'read fps':>9s} {'map fps':>8s}   maps: "
            f"{', '.join(config.maps)}"
        )
        for label, open_s, r, m, _ in rows:
            print(f"{label:24s} {open_s:7.2f} {r:9.1f} {m:8.1f}")
        a, b = rows[0][4].maps.maps, rows[1][4].maps.maps
        same = all(
            a[k].tiles.keys() == b[k].tiles.keys()
            and all(np.array_equal(a[k].tiles[t], b[k].tiles[t]) for t in a[k].tiles)
            for k in a
        )
        print(
            f"maps bit-identical: {same}; mapping from the bag at {rows[1][3] / rows[0][3]:.0%} of "
            "the npz speed"
        )


if __name__ == "__main__":
    main()
