"""The dynamic score against the simulator's moving objects: precision and recall per map, and
their sensitivity to the decay and the threshold.

Run: ``PYTHONPATH=src python benchmarks/dynamic.py [--seeds 4 9 14] [--duration 10]
[--deep]``. Each simulated scene is mapped once: the mapper's maps (``ray_ilm`` and
``ray_irm``; with ``--deep`` also ``deep_acc`` and ``fused``, which load the shipped Ev-Net)
carry the default :class:`~evgrid.fusion.DynamicParams`, and one attached map set per other
decay of ``--decays`` carries that decay (extra rows of the same one-pass update). At every
keyframe the cells above each threshold of ``--thresholds`` are compared with the truth mask
(:func:`evgrid.observers.moving_and_observed`: cells of moving objects that the current ray
ILM or ray IRM observed); counts are pooled over keyframes and scenes. Prints one table per
map: precision / recall per (decay, threshold), the default marked.

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from evgrid.config import MapperConfig
from evgrid.data import SimConfig, simulate_scene
from evgrid.evaluate import detection_scores, dynamic_confusion
from evgrid.fusion import DynamicParams, MapSet
from evgrid.grid import Warper
from evgrid.mapper import MapUpdate, OccupancyMapper
from evgrid.observers import moving_and_observed


class _Counter:
    """Per (decay, map, threshold) the (tp, fp, fn) of the cells called dynamic, at keyframes."""

    def __init__(self, sets: dict[float, MapSet], thresholds: list[float]):
        self.sets = sets
        self.thresholds = thresholds
        self.counts: dict[tuple[float, str, float], np.ndarray] = {}
        self._warper: Warper | None = None

    def on_update(self, update: MapUpdate) -> None:
        if not update.frame.is_keyframe:
            return
        if self._warper is None:
            self._warper = Warper(update.maps.grid, "moving objects")
        found = moving_and_observed(update, self._warper)
        if found is None:
            return
        r0, c0, moving, observed = found
        h, w = moving.shape
        for decay, s in self.sets.items():
            for name in s.dynamic_maps:
                score = s[name].read_dynamic(r0, c0, h, w)
                for t in self.thresholds:
                    c = self.counts.setdefault((decay, name, t), np.zeros(3, np.int64))
                    c += dynamic_confusion(score, t, moving, observed)


def map_scene(
    seed: int, duration_s: float, maps: tuple[str, ...], decays: list[float], thresholds
) -> dict:
    default = DynamicParams()
    config = replace(MapperConfig(maps=maps), dynamic=default)
    extra = {
        d: MapSet(config.grid, config.fusion, maps, config.tile_cells, replace(default, decay=d))
        for d in decays
        if d != default.decay
    }
    counter = _Counter({}, thresholds)
    mapper = OccupancyMapper(config, observers=(counter,), extra=tuple(extra.values()))
    counter.sets = {default.decay: mapper.maps, **extra}
    for frame in simulate_scene(seed, SimConfig(duration_s=duration_s)):
        mapper.process(frame)
    return counter.counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4, 9, 14])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of each scene")
    ap.add_argument("--deep", action="store_true", help="also deep_acc and fused (Ev-Net)")
    ap.add_argument("--decays", type=float, nargs="+", default=[0.3, 0.5, 0.7, 1.0])
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.2, 0.5])
    args = ap.parse_args()
    maps = ("ray_ilm", "ray_irm", *(("deep_acc", "fused") if args.deep else ()))
    total: dict = {}
    for seed in args.seeds:
        t = time.perf_counter()
        for k, c in map_scene(seed, args.duration, maps, args.decays, args.thresholds).items():
            total[k] = total.get(k, 0) + c
        print(f"scene seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    d0 = DynamicParams()
    print(f"\n{len(args.seeds)} simulated scenes ({args.seeds}), {args.duration:g} s each;")
    print(f"precision / recall (default decay {d0.decay}, threshold {d0.threshold}: *)")
    names = sorted({k[1] for k in total}, key=maps.index)
    for name in names:
        print(f"\n{name}\n\n| decay | " + " | ".join(f"> {t:g}" for t in args.thresholds) + " |")
        print("|---" * (len(args.thresholds) + 1) + "|")
        for d in sorted(args.decays):
            cells = []
            for t in args.thresholds:
                s = detection_scores(*map(int, total[(d, name, t)]))
                mark = "*" if (d, t) == (d0.decay, d0.threshold) else ""
                cells.append(f"{s['precision']:.2f} / {s['recall']:.2f}{mark}")
            print(f"| {d:g} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
