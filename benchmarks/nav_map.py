"""The navigation map against the truth on simulated scenes: is it safe, and does it add free space?

Run: ``PYTHONPATH=src python benchmarks/nav_map.py [--seeds 4 9 14] [--duration 8]
[--margin 0.5] [--occupied-min 0.1]``. Each simulated scene is mapped once with the shipped
Ev-Net; the mapper computes ``ray_ilm`` and ``fused``, and an attached map set computes ``nav``
from its own two (extra rows of the same pass). The simulator's true occupancy is accumulated as
the runs do (``TruthTracker``) and every map is compared with it cell by cell
(``tile_confusions_vs_truth``) over the observable true cells the maps covered. Printed per
map, over all scenes:

* ``occupied called free``: the share of truly occupied cells the map calls free (the danger
  for a robot; goal for ``nav``: no more than ``ray_ilm`` alone), over all of them, over the
  static ones, and over the cells a moving object ever covered (a mover that has left: the
  cell is free now, but the truth keeps the last state each cell was seen in);
* ``free IoU`` against the truth, and the free area (m²) the map calls free.

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from evgrid import mass
from evgrid.classes import FREE, OCCUPIED
from evgrid.config import MapperConfig
from evgrid.evaluate import iou_from_confusion, tile_confusions_vs_truth
from evgrid.fusion import MapSet
from evgrid.grid import EvidentialMap, Warper
from evgrid.mapper import OccupancyMapper
from evgrid.nav import NavParams
from evgrid.observers import TruthTracker
from evgrid_sim import SimConfig, simulate_scene

MAPS = ("ray_ilm", "fused", "nav")
PARTS = ("all", "static", "moving")


def _keep_moving(cell: np.ndarray, window: np.ndarray) -> None:
    cell[window[..., 1] > 0.5] = (0.0, 1.0, 0.0)


class EverMoving:
    """The cells a moving object (truth value 2) covered at any update of the scene."""

    def __init__(self, grid, tile_cells):
        self.map = EvidentialMap(grid, tile_cells)
        self._warper = Warper(grid)

    def on_update(self, update) -> None:
        occ = update.frame.occupancy
        if occ is None:
            return
        m = mass.vacuous(occ.shape)
        m[occ == 2] = (0.0, 1.0, 0.0)
        self.map.apply(self._warper.warp(m, update.pose), _keep_moving)


def _static(truth: EvidentialMap, moving: EvidentialMap) -> EvidentialMap:
    """The truth where no mover ever was; unknown where one was."""
    out = EvidentialMap(truth.grid, truth.tile_cells)
    for key, t in truth.tiles.items():
        m = moving.tiles.get(key)
        keep = ~(m[..., 1] > 0.5) if m is not None else np.ones(t.shape[:2], bool)
        tile, cov = out.tile(key)
        tile[keep] = t[keep]
        cov[...] = truth.covered_tiles[key] & keep
    return out


def map_scene(seed: int, duration_s: float, nav: NavParams) -> np.ndarray:
    """Confusion counts ``(parts, maps, 3, 3)`` of one scene (truth rows, map columns)."""
    config = replace(MapperConfig(maps=("ray_ilm", "fused")), nav=nav)
    nav_set = MapSet(config.grid, config.fusion, ("nav",), config.tile_cells, config.dynamic, nav)
    truth = TruthTracker(config.grid, config.tile_cells)
    moving = EverMoving(config.grid, config.tile_cells)
    mapper = OccupancyMapper(config, observers=(truth, moving), extra=(nav_set,))
    for frame in simulate_scene(seed, SimConfig(duration_s=duration_s)):
        mapper.process(frame)
    maps = {"ray_ilm": mapper.maps["ray_ilm"], "fused": mapper.maps["fused"], "nav": nav_set["nav"]}
    every, static = (
        sum(
            (tile_confusions_vs_truth(maps, t, None, k) for k in list(t.tiles)),
            np.zeros((len(maps), 3, 3), dtype=np.int64),
        )
        for t in (truth.map, _static(truth.map, moving.map))
    )
    # the cells movers covered: all but the static ones (a truth holding only those cells would
    # make most of them unobservable, see evaluate.observable)
    return np.stack([every, static, every - static])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4, 9, 14])
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of each scene")
    ap.add_argument("--margin", type=float, default=NavParams().margin_m, help="NavParams.margin_m")
    ap.add_argument(
        "--occupied-min",
        type=float,
        default=NavParams().occupied_min,
        help="NavParams.occupied_min",
    )
    ap.add_argument("--moving", choices=("avoid", "ignore"), default="avoid", help="avoid_moving")
    args = ap.parse_args()
    nav = NavParams(args.margin, args.occupied_min, args.moving == "avoid")
    c = np.zeros((len(PARTS), len(MAPS), 3, 3), dtype=np.int64)
    res_m2 = MapperConfig().grid.resolution ** 2
    for seed in args.seeds:
        t = time.perf_counter()
        c += map_scene(seed, args.duration, nav)
        print(f"scene seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"\n{len(args.seeds)} simulated scenes ({args.seeds}), {args.duration:g} s each, {nav}")
    print("\n| map | occupied called free: all | static | moving | free IoU | called free, m² |")
    print("|---|---|---|---|---|---|")
    for i, name in enumerate(MAPS):
        shares = []
        for p in range(len(PARTS)):
            occ = c[p, i, OCCUPIED].sum()
            n = c[p, i, OCCUPIED, FREE]
            shares.append(f"{100 * n / occ:.2f} % ({n:,})" if occ else "n/a")
        iou = iou_from_confusion(c[0, i])["free"]
        free_m2 = c[0, i, :, FREE].sum() * res_m2
        print(f"| {name} | {' | '.join(shares)} | {iou:.3f} | {free_m2:,.0f} |")


if __name__ == "__main__":
    main()
