"""Ev-Net in the polar frame against the Cartesian one, by range band (issue 38, item 2).

Maps ``--scenes`` held-out simulated scenes of ``--duration`` seconds (the val split's seeds
from ``--first-seed``, default 2000; seeds from 3000 on are reserved and refused) once with
each checkpoint of ``--checkpoints`` (``label=path``, comma-separated; the same frames for
all), the deep IRM's guards off (the network alone), through :func:`evgrid.runs.map_scene`.
At every keyframe, the deep IRM's single frame (classes by the largest mass, ties unknown) is
scored by range band from the ego (``--bands``, metres; the grid's corners reach 28.3 m):

* against the truth: free and occupied IoU over the cells whose truth is observable
  (:func:`evgrid.evaluate.observable`: occupied only on object surfaces), and the share of
  truly free cells called occupied;
* against the ray ILM of the same frame, classed as the paper's single-frame target
  (:func:`evgrid.learn.targets.ilm_classes`; 15 m reach): free, occupied and unknown IoU.

Intersections and unions are summed over keyframes and scenes. ``--pairs A:B,...`` also prints
the difference A - B of each band's truth IoU, per scene, as a mean with its 95 % bootstrap
interval over scenes (paired: the same frames), for each pair and for the pairs' mean (e.g. a
polar and a Cartesian net trained with each of two seeds). Run:
``PYTHONPATH=src python benchmarks/prior_polar.py --checkpoints cart=A.safetensors,polar=B.sft``.
Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from harness import machine_line  # noqa: E402

from evgrid.classes import FREE, OCCUPIED, UNKNOWN  # noqa: E402
from evgrid.config import MapperConfig, OutputConfig  # noqa: E402
from evgrid.evaluate import bootstrap_interval, classify, observable  # noqa: E402
from evgrid.ism.prior_guard import PriorGuardParams  # noqa: E402
from evgrid.learn.targets import ilm_classes  # noqa: E402
from evgrid.runs import map_scene  # noqa: E402
from evgrid.sources import SimSource  # noqa: E402

RESERVED_FROM = 3000  # validation seeds from here on are kept for checks run elsewhere


class BandScores:
    """Per range band, summed over keyframes: intersections and unions of each class of one ISM
    against the truth and against the ray ILM, and truly free cells called occupied."""

    def __init__(self, ism: str, bands: list[tuple[float, float]]):
        self.ism, self.bands = ism, bands
        self.band_of: np.ndarray | None = None
        nb = len(bands)
        self.truth = np.zeros((nb, 2, 2), np.int64)  # band, (free, occ), (inter, union)
        self.ilm = np.zeros((nb, 3, 2), np.int64)  # band, class, (inter, union)
        self.free_as_occ = np.zeros((nb, 2), np.int64)  # band, (called occupied, truly free)
        self.per_scene: list[np.ndarray] = []  # each scene's truth counts
        self._mark = self.truth.copy()

    def end_scene(self) -> None:
        self.per_scene.append(self.truth - self._mark)
        self._mark = self.truth.copy()

    def on_update(self, u) -> None:
        truth = u.frame.occupancy
        if truth is None or self.ism not in u.isms or "ray_ilm" not in u.isms:
            return
        if self.band_of is None:
            grid = u.maps.grid
            rows, cols = np.indices(grid.shape)
            r = np.hypot(*grid.cell_to_xy(rows, cols))
            self.band_of = np.full(grid.shape, -1, np.int64)
            for k, (lo, hi) in enumerate(self.bands):
                self.band_of[(r >= lo) & (r < hi)] = k
        pred = classify(u.isms[self.ism])
        t_cls = np.where(truth == 0, FREE, OCCUPIED).astype(np.uint8)
        seen = observable(t_cls)
        ref = ilm_classes(u.isms["ray_ilm"])
        for k in range(len(self.bands)):
            band = self.band_of == k
            m = band & seen
            for j, c in enumerate((FREE, OCCUPIED)):
                a, b = (pred == c) & m, (t_cls == c) & m
                self.truth[k, j] += (np.count_nonzero(a & b), np.count_nonzero(a | b))
            for c in (FREE, OCCUPIED, UNKNOWN):
                a, b = (pred == c) & band, (ref == c) & band
                self.ilm[k, c] += (np.count_nonzero(a & b), np.count_nonzero(a | b))
            free = band & (t_cls == FREE)
            self.free_as_occ[k] += (np.count_nonzero(free & (pred == OCCUPIED)),
                                    np.count_nonzero(free))  # fmt: skip


def _pct(a) -> str:
    return f"{100.0 * a[0] / a[1]:.1f}" if a[1] else "n/a"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", required=True, help="label=path,label=path")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--bands", default="0,10,20,28.3", help="band edges in metres")
    ap.add_argument("--pairs", default="", help="A:B,... labels whose difference A - B to print")
    args = ap.parse_args()
    edges = [float(v) for v in args.bands.split(",")]
    bands = list(zip(edges[:-1], edges[1:]))
    checkpoints = dict(item.split("=", 1) for item in args.checkpoints.split(","))
    seeds = SimSource.split("val", args.scenes, args.first_seed).seeds
    if max(seeds) >= RESERVED_FROM:
        raise SystemExit(f"seeds {seeds} reach the reserved validation seeds (>= {RESERVED_FROM})")
    print(machine_line())
    print(f"{args.scenes} val scenes of {args.duration:g} s, seeds {list(seeds)}; keyframes' "
          "single frames, deep IRM guards off")  # fmt: skip
    src = SimSource(seeds, args.duration)
    scores = {label: BandScores("deep_irm", bands) for label in checkpoints}
    seconds = dict.fromkeys(checkpoints, 0.0)
    for name in src.names():
        frames = list(src.load(name))  # simulated once, mapped with every checkpoint
        for label, path in checkpoints.items():
            config = MapperConfig(
                maps=("ray_ilm", "deep_acc"),
                checkpoint=path,
                prior_guard=PriorGuardParams(support_m=None, path_m=None),
            )
            t = time.perf_counter()
            map_scene(frames, None, config, OutputConfig(figures=False), name=name,
                      observers=(scores[label],))  # fmt: skip
            seconds[label] += time.perf_counter() - t
            scores[label].end_scene()
        print(f"  {name} done", flush=True)
    head = ("| ISM | band m | truth free IoU | truth occ IoU | truly free called occ % | "
            "ray ILM free IoU | ray ILM occ IoU | ray ILM unknown IoU |")  # fmt: skip
    print(head)
    print("|" + " --- |" * (head.count("|") - 1))
    for label, s in scores.items():
        for k, (lo, hi) in enumerate(bands):
            print(f"| {label} | {lo:g}-{hi:g} | {_pct(s.truth[k, 0])} | {_pct(s.truth[k, 1])} | "
                  f"{_pct(s.free_as_occ[k])} | {_pct(s.ilm[k, FREE])} | "
                  f"{_pct(s.ilm[k, OCCUPIED])} | {_pct(s.ilm[k, UNKNOWN])} |")  # fmt: skip
    print("mapping s: " + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()))
    if args.pairs:
        _print_differences(scores, [tuple(p.split(":")) for p in args.pairs.split(",")], bands)


def _iou(c: np.ndarray) -> float:
    return c[0] / c[1] if c[1] else math.nan


def _print_differences(scores: dict, pairs: list[tuple[str, str]], bands: list) -> None:
    """Per band and truth class: A - B per scene, mean and bootstrap interval (points)."""
    head = "| A - B | band m | truth free IoU, points | truth occ IoU, points |"
    print(head)
    print("|" + " --- |" * (head.count("|") - 1))
    n_scenes = len(scores[pairs[0][0]].per_scene)
    rows = {f"{a} - {b}": [(a, b)] for a, b in pairs}
    if len(pairs) > 1:
        rows["mean of the pairs"] = pairs
    for label, group in rows.items():
        for k, (lo, hi) in enumerate(bands):
            cells = []
            for j in range(2):
                diffs = [np.mean([_iou(scores[a].per_scene[s][k, j]) -
                                  _iou(scores[b].per_scene[s][k, j]) for a, b in group])
                         for s in range(n_scenes)]  # fmt: skip
                ci = bootstrap_interval(diffs)
                cells.append(f"{100 * ci['mean']:+.1f} ({100 * ci['lo']:+.1f} to "
                             f"{100 * ci['hi']:+.1f}), {ci['n']} scenes")  # fmt: skip
            print(f"| {label} | {lo:g}-{hi:g} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
