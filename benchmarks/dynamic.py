"""The dynamic score against the simulator's moving objects: precision and recall per map, their
sensitivity to the parameters, and the area movers leave behind with and without the gate.

Run: ``PYTHONPATH=src python benchmarks/dynamic.py [--seeds 4 9 14] [--duration 10] [--deep]
[--nav] [--variants NAME ...] [--rules NAME ...] [--json out.json]``. Each simulated scene is
mapped once: the mapper's maps (``ray_ilm`` and ``ray_irm``; with ``--deep`` also ``deep_acc``
and ``fused``, which load the shipped Ev-Net; with ``--nav`` also ``nav``, whose area left
behind is reported) carry the default :class:`~evgrid.fusion.DynamicParams`, and one attached
map set per variant of :data:`VARIANTS` carries that variant (extra rows of the same one-pass
update, fed the same Doppler cue). At every keyframe the cells above each threshold of
``--thresholds`` (and, for ``support`` k, the cells whose k x k neighbourhood holds one) are
compared with the truth mask (:func:`evgrid.observers.truth_masks`: cells of moving objects that
the current ray ILM or ray IRM observed); counts are pooled over keyframes and scenes. The area
movers leave behind (:class:`evgrid.observers.MoverTrail`) is averaged over keyframes and
scenes. Prints one table per map: precision / recall / IoU per (variant, threshold), the default
marked, for each call rule of ``--rules`` (:data:`CALL_RULES`: prototypes of calls that also
read the current lidar ISM); then the areas, and what the gate costs on static structure (truly
occupied cells no mover covered, against the truth at the scene's end). ``--centred-discs``
centres the Doppler cue's discs on their detections (the rule before 2026-12-03) instead of
behind them.

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np
from scipy.ndimage import distance_transform_edt, maximum_filter

from evgrid.classes import FREE, OCCUPIED
from evgrid.config import MapperConfig
from evgrid.evaluate import detection_scores, dynamic_confusion, tile_confusions_vs_truth
from evgrid.fusion import DynamicParams, MapSet
from evgrid.grid import EvidentialMap, Warper
from evgrid.mapper import MapUpdate, OccupancyMapper
from evgrid.observers import MoverTrail, TruthTracker, truth_masks
from evgrid_sim import SimConfig, simulate_scene

D0 = DynamicParams()
#: Variants of the default: (name, DynamicParams, support) with support the side of the
#: neighbourhood whose largest score calls a cell (1: the cell alone).
VARIANTS: dict[str, tuple[DynamicParams, int]] = {
    "default": (D0, 1),
    "no doppler": (replace(D0, doppler_mass=0.0), 1),
    "doppler > 1 m/s": (replace(D0, doppler_mps=1.0), 1),
    "doppler > 3 m/s": (replace(D0, doppler_mps=3.0), 1),
    "radius 0.5 m": (replace(D0, doppler_radius_m=0.5), 1),
    "radius 0.75 m": (replace(D0, doppler_radius_m=0.75), 1),
    "radius 1.5 m": (replace(D0, doppler_radius_m=1.5), 1),
    "doppler mass 0.25": (replace(D0, doppler_mass=0.25), 1),
    "doppler mass 1": (replace(D0, doppler_mass=1.0), 1),
    "decay 0.5": (replace(D0, decay=0.5), 1),
    "decay 0.6": (replace(D0, decay=0.6), 1),
    "decay 0.9": (replace(D0, decay=0.9), 1),
    "support 3": (D0, 3),
    "gate": (replace(D0, gate_maps=True), 1),
    "no nav gate": (replace(D0, gate_nav=False), 1),
    "gate at 0.05": (replace(D0, gate_maps=True, gate_threshold=0.05), 1),
    "gate at 0.03": (replace(D0, gate_maps=True, gate_threshold=0.03), 1),
    "gate at 0.02": (replace(D0, gate_maps=True, gate_threshold=0.02), 1),
    "doppler > 1 m/s, gate": (replace(D0, doppler_mps=1.0, gate_maps=True), 1),
}


def _ilm_now(update: MapUpdate, r0: int, c0: int, h: int, w: int) -> np.ndarray:
    """The current ray ILM's masses over the cells ``(r0, c0, h, w)``; vacuous where it has none."""
    out = np.zeros((h, w, 3), np.float32)
    out[..., 2] = 1.0
    win = update.windows.get("ray_ilm")
    if win is None:
        return out
    wh, ww = win.covered.shape
    ra, ca = win.r0 - r0, win.c0 - c0
    dst = out[max(ra, 0) : ra + wh, max(ca, 0) : ca + ww]
    sub = (slice(max(-ra, 0), None), slice(max(-ca, 0), None))
    src = win.masses[sub][: dst.shape[0], : dst.shape[1]]
    cov = win.covered[sub][: dst.shape[0], : dst.shape[1]]
    dst[cov] = src[cov]
    return out


def _near(mask: np.ndarray, radius_m: float, res: float) -> np.ndarray:
    if not mask.any():
        return np.zeros_like(mask)
    return distance_transform_edt(~mask) * res <= radius_m


#: Call rules other than the score alone (prototypes, not the library's call): (called, the
#: current ray ILM's masses, grid resolution) -> the cells called dynamic. "not free now": the
#: current lidar ISM does not say free (m_f > m_o, informative); "near a moving return, R": and
#: within R m of a cell where the current lidar ISM says occupied (m_o > m_f) and the score too.
CALL_RULES = {
    "score": lambda a, s, res: a,
    "not free now": lambda a, s, res: a & ~((s[..., 0] > s[..., 1]) & (s[..., 2] < 1.0)),
    **{
        f"near a moving return, {r:g} m": (
            lambda r: (
                lambda a, s, res: (
                    a
                    & ~((s[..., 0] > s[..., 1]) & (s[..., 2] < 1.0))
                    & _near(a & (s[..., 1] > s[..., 0]), r, res)
                )
            )
        )(r)
        for r in (0.5, 0.75, 1.0)
    },
}


class _Counter:
    """Per (variant, map, threshold) the (tp, fp, fn) of the cells called dynamic at keyframes,
    and per (variant, map) the area movers left behind at each keyframe."""

    def __init__(self, sets: dict[str, MapSet], thresholds: list[float], rules: list[str]):
        self.sets = sets
        self.thresholds = thresholds
        self.rules = rules
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
        ilm = _ilm_now(update, r0, c0, h, w)
        res = update.maps.grid.resolution
        for v, s in self.sets.items():
            support = VARIANTS[v][1]
            for name in s.dynamic_maps:
                score = s[name].read_dynamic(r0, c0, h, w)
                if support > 1:
                    score = maximum_filter(score, size=support)
                for t in self.thresholds:
                    for rule in self.rules:
                        called = CALL_RULES[rule](score > t, ilm, res).astype(np.float32)
                        c = self.counts.setdefault((v, name, t, rule), np.zeros(3, np.int64))
                        c += dynamic_confusion(called, 0.5, moving, observed)
            for name in s.names:
                area = self._trail.left_behind(s[name], r0, c0, free)[1]
                self.left.setdefault((v, name), []).append(area)


def static_confusions(counter: _Counter, truth: EvidentialMap) -> dict[tuple[str, str], np.ndarray]:
    """Per (variant, map) the confusion counts ``(3, 3)`` (truth rows, map columns) against the
    truth at the scene's end over the cells no mover covered at a keyframe: what the gate costs
    on static structure."""
    static = EvidentialMap(truth.grid, truth.tile_cells)
    trail = counter._trail.tiles if counter._trail is not None else {}
    for key, t in truth.tiles.items():
        keep = ~trail[key] if key in trail else np.ones(t.shape[:2], bool)
        tile, cov = static.tile(key)
        tile[keep] = t[keep]
        cov[...] = truth.covered_tiles[key] & keep
    out = {}
    for v, s in counter.sets.items():
        c = sum(
            (tile_confusions_vs_truth(s.maps, static, None, k) for k in list(static.tiles)),
            np.zeros((len(s.names), 3, 3), np.int64),
        )
        out |= {(v, n): c[i] for i, n in enumerate(s.names)}
    return out


def map_scene(
    seed: int,
    duration_s: float,
    maps: tuple[str, ...],
    thresholds,
    variants: list[str],
    rules: list[str],
) -> tuple[_Counter, dict[tuple[str, str], np.ndarray]]:
    config = replace(MapperConfig(maps=maps), dynamic=D0)
    extra = {
        v: MapSet(config.grid, config.fusion, maps, config.tile_cells, d, nav=config.nav)
        for v, (d, _) in VARIANTS.items()
        if v != "default" and v in variants
    }
    counter = _Counter({}, thresholds, rules)
    truth = TruthTracker(config.grid, config.tile_cells)
    mapper = OccupancyMapper(config, observers=(counter, truth), extra=tuple(extra.values()))
    counter.sets = {"default": mapper.maps, **extra}
    for frame in simulate_scene(seed, SimConfig(duration_s=duration_s)):
        mapper.process(frame)
    return counter, static_confusions(counter, truth.map)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[4, 9, 14])
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of each scene")
    ap.add_argument("--deep", action="store_true", help="also deep_acc and fused (Ev-Net)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.3, 0.5])
    ap.add_argument("--nav", action="store_true", help="also nav (and so fused, with Ev-Net)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), help="of VARIANTS")
    ap.add_argument(
        "--rules", nargs="+", default=["score"], choices=list(CALL_RULES), help="call rules"
    )
    ap.add_argument(
        "--centred-discs",
        action="store_true",
        help="the Doppler cue's discs centred on their detections (before 2026-12-03), not behind",
    )
    ap.add_argument("--json", help="write the pooled counts and areas here")
    args = ap.parse_args()
    if args.centred_discs:
        import evgrid.doppler

        evgrid.doppler.disc_centres = lambda moving, radius_m: moving[:, :2]
    maps = ("ray_ilm", "ray_irm", *(("deep_acc", "fused") if args.deep else ()))
    maps += ("nav",) if args.nav else ()
    variants = ["default", *(v for v in args.variants if v != "default")]
    total: dict = {}
    left: dict = {}
    static: dict = {}
    for seed in args.seeds:
        t = time.perf_counter()
        c, conf = map_scene(seed, args.duration, maps, args.thresholds, variants, args.rules)
        for k, v in conf.items():
            static[k] = static.get(k, 0) + v
        for k, v in c.counts.items():
            total[k] = total.get(k, 0) + v
        for k, v in c.left.items():
            left.setdefault(k, []).extend(v)
        print(f"scene seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"\n{len(args.seeds)} simulated scenes ({args.seeds}), {args.duration:g} s each;")
    print(f"precision / recall / IoU (default threshold {D0.threshold}: *)")
    names = sorted({k[1] for k in total}, key=maps.index)
    for name in names:
        print(f"\n{name}\n\n| variant | " + " | ".join(f"> {t:g}" for t in args.thresholds) + " |")
        print("|---" * (len(args.thresholds) + 1) + "|")
        for v in variants:
            for rule in args.rules:
                cells = []
                for t in args.thresholds:
                    s = detection_scores(*map(int, total[(v, name, t, rule)]))
                    mark = "*" if t == D0.threshold else ""
                    cells.append(f"{s['precision']:.2f} / {s['recall']:.2f} / {s['iou']:.2f}{mark}")
                label = v if rule == "score" else f"{v}, {rule}"
                print(f"| {label} | " + " | ".join(cells) + " |")
    shown = sorted({k[1] for k in left}, key=maps.index)
    print("\nleft behind (m^2, mean over keyframes):\n\n| variant | " + " | ".join(shown) + " |")
    print("|---" * (len(shown) + 1) + "|")
    for v in variants:
        print(f"| {v} | " + " | ".join(f"{np.mean(left[(v, n)]):.2f}" for n in shown) + " |")
    print(
        "\nstatic structure at the end (cells no mover covered): truly occupied cells called"
        " occupied, and called free\n\n| variant | " + " | ".join(shown) + " |"
    )
    print("|---" * (len(shown) + 1) + "|")
    for v in variants:
        cells = [
            f"{static[(v, n)][OCCUPIED, OCCUPIED]:,} / {static[(v, n)][OCCUPIED, FREE]:,}"
            for n in shown
        ]
        print(f"| {v} | " + " | ".join(cells) + " |")
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
