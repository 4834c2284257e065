"""The navigation map against the truth on simulated scenes: is it safe, and does it add free space?

Run: ``PYTHONPATH=src python benchmarks/nav_map.py [--seeds 4 9 14] [--duration 8]``. Each
simulated scene is mapped once with the shipped Ev-Net; the mapper computes ``ray_ilm`` and
``fused`` and an attached map set computes ``nav`` in the same pass (extra rows of the one
update). The simulator's true occupancy is accumulated as the runs do (``TruthTracker``) and
every map is compared with it cell by cell (``tile_confusions_vs_truth``) over the observable
true cells the maps covered (the truth is accumulated over the same windows as the maps, so the
lidar map's coverage and the perception field are the same cells). Printed per map, over all
scenes:

* ``occupied called free``: the share of truly occupied cells the map calls free (the
  danger for a robot; goal for ``nav``: no more than ``ray_ilm`` alone);
* ``free IoU`` against the truth, and the free area (m²) the map calls free.

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from evgrid.classes import FREE, OCCUPIED
from evgrid.config import MapperConfig
from evgrid.data import SimConfig, simulate_scene
from evgrid.evaluate import iou_from_confusion, tile_confusions_vs_truth
from evgrid.fusion import MapSet
from evgrid.mapper import OccupancyMapper
from evgrid.observers import TruthTracker

MAPS = ("ray_ilm", "fused", "nav")


def map_scene(seed: int, duration_s: float) -> np.ndarray:
    """Confusion counts ``(maps, 3, 3)`` of one scene (truth rows, map columns)."""
    config = MapperConfig(maps=("ray_ilm", "fused"))
    nav = MapSet(config.grid, config.fusion, ("nav",), config.tile_cells)
    truth = TruthTracker(config.grid, config.tile_cells)
    mapper = OccupancyMapper(config, observers=(truth,), extra=(nav,))
    for frame in simulate_scene(seed, SimConfig(duration_s=duration_s)):
        mapper.process(frame)
    maps = {"ray_ilm": mapper.maps["ray_ilm"], "fused": mapper.maps["fused"], "nav": nav["nav"]}
    return sum(
        (tile_confusions_vs_truth(maps, truth.map, None, k) for k in list(truth.map.tiles)),
        np.zeros((len(maps), 3, 3), dtype=np.int64),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4, 9, 14])
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of each scene")
    args = ap.parse_args()
    c = np.zeros((len(MAPS), 3, 3), dtype=np.int64)
    res_m2 = MapperConfig().grid.resolution ** 2
    for seed in args.seeds:
        t = time.perf_counter()
        c += map_scene(seed, args.duration)
        print(f"scene seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"\n{len(args.seeds)} simulated scenes ({args.seeds}), {args.duration:g} s each")
    print("\n| map | occupied called free | free IoU | called free, m² |")
    print("|---|---|---|---|")
    for i, name in enumerate(MAPS):
        occ = c[i, OCCUPIED].sum()
        share = c[i, OCCUPIED, FREE] / occ if occ else float("nan")
        iou = iou_from_confusion(c[i])["free"]
        free_m2 = c[i, :, FREE].sum() * res_m2
        print(f"| {name} | {100 * share:.2f} % | {iou:.3f} | {free_m2:.0f} |")


if __name__ == "__main__":
    main()
