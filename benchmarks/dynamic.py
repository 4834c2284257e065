"""The dynamic score against the simulator's moving objects: precision and recall per map, their
sensitivity to the parameters, and the area movers leave behind with and without the gate.

Run: ``PYTHONPATH=src python benchmarks/dynamic.py [--seeds 4 9 14] [--duration 10] [--deep]
[--nav] [--variants NAME ...] [--json out.json]``. Each simulated scene is mapped once: the
mapper's maps (``ray_ilm`` and ``ray_irm``; with ``--deep`` also ``deep_acc`` and ``fused``,
which load the shipped Ev-Net; with ``--nav`` also ``nav``, whose area left behind is reported)
carry the default :class:`~evgrid.fusion.DynamicParams`, and one attached map set per variant
of :data:`VARIANTS` carries that variant (extra rows of the same one-pass update, fed the same
Doppler cue). At every keyframe the cells above each threshold of ``--thresholds`` (and, for
``support`` k, the cells whose k x k neighbourhood holds one) are compared with the truth mask
(:func:`evgrid.observers.truth_masks`: cells of moving objects that the current ray ILM or ray
IRM observed); counts are pooled over keyframes and scenes. The area movers leave behind
(:class:`evgrid.observers.MoverTrail`) is averaged over keyframes and scenes. Prints one table
per map: precision / recall per (variant, threshold), the default marked; then the areas.

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np
from scipy.ndimage import maximum_filter

from evgrid.config import MapperConfig
from evgrid.data import SimConfig, simulate_scene
from evgrid.evaluate import detection_scores, dynamic_confusion
from evgrid.fusion import DynamicParams, MapSet
from evgrid.grid import Warper
from evgrid.mapper import MapUpdate, OccupancyMapper
from evgrid.observers import MoverTrail, truth_masks

D0 = DynamicParams()
#: Variants of the default: (name, DynamicParams, support) with support the side of the
#: neighbourhood whose largest score calls a cell (1: the cell alone).
VARIANTS: dict[str, tuple[DynamicParams, int]] = {
    "default": (D0, 1),
    "no doppler": (replace(D0, doppler_mass=0.0), 1),
    "doppler > 2 m/s": (replace(D0, doppler_mps=2.0), 1),
    "doppler > 3 m/s": (replace(D0, doppler_mps=3.0), 1),
    "radius 0.5 m": (replace(D0, doppler_radius_m=0.5), 1),
    "radius 2 m": (replace(D0, doppler_radius_m=2.0), 1),
    "doppler mass 0.25": (replace(D0, doppler_mass=0.25), 1),
    "doppler mass 1": (replace(D0, doppler_mass=1.0), 1),
    "decay 0.6": (replace(D0, decay=0.6), 1),
    "decay 0.9": (replace(D0, decay=0.9), 1),
    "support 3": (D0, 3),
    "gate": (replace(D0, gate_maps=True), 1),
    "gate, threshold 0.3": (replace(D0, gate_maps=True, threshold=0.3), 1),
    "no nav gate": (replace(D0, gate_nav=False), 1),
}


class _Counter:
    """Per (variant, map, threshold) the (tp, fp, fn) of the cells called dynamic at keyframes,
    and per (variant, map) the area movers left behind at each keyframe."""

    def __init__(self, sets: dict[str, MapSet], thresholds: list[float]):
        self.sets = sets
        self.thresholds = thresholds
        self.counts: dict[tuple[str, str, float], np.ndarray] = {}
        self.left: dict[tuple[str, str], list[float]] = {}
        self._warper: Warper | None = None
        self._trail: MoverTrail | None = None

    def on_update(self, update: MapUpdate) -> None:
        if not update.frame.is_keyframe:
            return
        if self._warper is None:
            self._warper = Warper(update.maps.grid, "moving objects")
            self._trail = MoverTrail(update.maps.grid, update.maps.tile_cells)
        found = truth_masks(update, self._warper)
        if found is None:
            return
        r0, c0, moving, observed, free = found
        self._trail.add(r0, c0, moving)
        h, w = moving.shape
        for v, s in self.sets.items():
            support = VARIANTS[v][1]
            for name in s.dynamic_maps:
                score = s[name].read_dynamic(r0, c0, h, w)
                if support > 1:
                    score = maximum_filter(score, size=support)
                for t in self.thresholds:
                    c = self.counts.setdefault((v, name, t), np.zeros(3, np.int64))
                    c += dynamic_confusion(score, t, moving, observed)
            for name in s.names:
                area = self._trail.left_behind(s[name], r0, c0, free)[1]
                self.left.setdefault((v, name), []).append(area)


def map_scene(
    seed: int, duration_s: float, maps: tuple[str, ...], thresholds, variants: list[str]
) -> _Counter:
    config = replace(MapperConfig(maps=maps), dynamic=D0)
    extra = {
        v: MapSet(config.grid, config.fusion, maps, config.tile_cells, d, nav=config.nav)
        for v, (d, _) in VARIANTS.items()
        if v != "default" and v in variants
    }
    counter = _Counter({}, thresholds)
    mapper = OccupancyMapper(config, observers=(counter,), extra=tuple(extra.values()))
    counter.sets = {"default": mapper.maps, **extra}
    for frame in simulate_scene(seed, SimConfig(duration_s=duration_s)):
        mapper.process(frame)
    return counter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4, 9, 14])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of each scene")
    ap.add_argument("--deep", action="store_true", help="also deep_acc and fused (Ev-Net)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.3, 0.5])
    ap.add_argument("--nav", action="store_true", help="also nav (and so fused, with Ev-Net)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), help="of VARIANTS")
    ap.add_argument("--json", help="write the pooled counts and areas here")
    args = ap.parse_args()
    maps = ("ray_ilm", "ray_irm", *(("deep_acc", "fused") if args.deep else ()))
    maps += ("nav",) if args.nav else ()
    variants = ["default", *(v for v in args.variants if v != "default")]
    total: dict = {}
    left: dict = {}
    for seed in args.seeds:
        t = time.perf_counter()
        c = map_scene(seed, args.duration, maps, args.thresholds, variants)
        for k, v in c.counts.items():
            total[k] = total.get(k, 0) + v
        for k, v in c.left.items():
            left.setdefault(k, []).extend(v)
        print(f"scene seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"\n{len(args.seeds)} simulated scenes ({args.seeds}), {args.duration:g} s each;")
    print(f"precision / recall (default threshold {D0.threshold}: *)")
    names = sorted({k[1] for k in total}, key=maps.index)
    for name in names:
        print(f"\n{name}\n\n| variant | " + " | ".join(f"> {t:g}" for t in args.thresholds) + " |")
        print("|---" * (len(args.thresholds) + 1) + "|")
        for v in variants:
            cells = []
            for t in args.thresholds:
                s = detection_scores(*map(int, total[(v, name, t)]))
                mark = "*" if t == D0.threshold else ""
                cells.append(f"{s['precision']:.2f} / {s['recall']:.2f}{mark}")
            print(f"| {v} | " + " | ".join(cells) + " |")
    shown = sorted({k[1] for k in left}, key=maps.index)
    print("\nleft behind (m^2, mean over keyframes):\n\n| variant | " + " | ".join(shown) + " |")
    print("|---" * (len(shown) + 1) + "|")
    for v in variants:
        print(f"| {v} | " + " | ".join(f"{np.mean(left[(v, n)]):.2f}" for n in shown) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "seeds": args.seeds,
                    "counts": {"|".join(map(str, k)): v.tolist() for k, v in total.items()},
                    "left_behind_m2": {"|".join(k): float(np.mean(v)) for k, v in left.items()},
                },
                f,
                indent=1,
            )


if __name__ == "__main__":
    main()
