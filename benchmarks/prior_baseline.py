"""How much of Ev-Net's single-frame score is the street's shape: a prior that never sees radar.

Run: ``PYTHONPATH=src python benchmarks/prior_baseline.py --run out/train [--scenes 40 --val-scenes
8]`` after ``evgrid train --out out/train ...`` (it reads that run's sample cache). The prior is,
for each cell of the ego-centred grid, the class the ray ILM target holds most often over the
training samples; it is scored on the validation samples with the same per-class IoU as the
training's validation (cells pooled over all samples). Beside it, the run's best epoch as
``metrics.csv`` gives it. Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.config import from_dict
from evgrid.learn.train import TrainConfig
from evgrid.sources import SimSource

_NAMES = {FREE: "free", OCCUPIED: "occupied", UNKNOWN: "unknown"}


def _targets(cache: Path, names: list[str]):
    for name in names:
        path = cache / f"{name}.target.npy"
        if not path.exists():
            raise SystemExit(
                f"{path}: not in the run's cache (train with the same --scenes/--val-scenes/--seed)"
            )
        yield np.load(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--run", type=Path, default=Path("out/train"), help="an `evgrid train --out` folder"
    )
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--val-scenes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    config = from_dict(
        TrainConfig,
        json.loads((args.run / "config.json").read_text()),
        str(args.run / "config.json"),
    )
    cache = args.run / "cache" / config.data_key()
    train = SimSource.split("train", args.scenes, args.seed).names()
    val = SimSource.split("val", args.val_scenes, args.seed).names()

    counts = np.zeros((3,) + config.grid.shape, np.int64)
    for t in _targets(cache, train):
        for k in range(3):
            counts[k] += (t == k).sum(axis=0)
    prior = counts.argmax(axis=0).astype(np.uint8)  # ties: the lower class index

    inter, union = np.zeros(3), np.zeros(3)
    for t in _targets(cache, val):
        for k in range(3):
            inter[k] += np.count_nonzero((prior == k) & (t == k))
            union[k] += np.count_nonzero((prior == k) | (t == k))
    iou = {_NAMES[k]: inter[k] / union[k] if union[k] else float("nan") for k in range(3)}

    rows = list(csv.DictReader(open(args.run / "metrics.csv")))
    best = max(
        rows,
        key=lambda r: np.nanmean([float(r[f"val_{c}"]) for c in ("free", "occupied", "unknown")]),
    )
    print(
        f"{len(train)} training and {len(val)} validation scenes; the prior calls "
        + ", ".join(
            f"{100 * float((prior == k).mean()):.1f} % of cells {_NAMES[k]}" for k in range(3)
        )
    )
    print("| IoU against the ray ILM | free | occupied | unknown |")
    print("|---|---|---|---|")
    print(
        "| prior: each cell's most frequent training class, no radar | "
        + " | ".join(f"{iou[c]:.3f}" for c in ("free", "occupied", "unknown"))
        + " |"
    )
    print(
        f"| Ev-Net, best epoch ({best['epoch']}) | "
        + " | ".join(f"{float(best[f'val_{c}']):.3f}" for c in ("free", "occupied", "unknown"))
        + " |"
    )
    print(
        "| ray IRM, one time step | "
        + " | ".join(f"{float(best[f'ray_irm_{c}']):.3f}" for c in ("free", "occupied", "unknown"))
        + " |"
    )


if __name__ == "__main__":
    main()
