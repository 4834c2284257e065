"""Does Ev-Net work on a radar it never saw?

The same held-out simulated scenes (same towns, drives and lidar) are seen through radars
inside the training ranges and through each radar of
:data:`~evgrid_sim.radar_variants.OUT_OF_RANGE`; on each, the deep IRM's single-frame cell
classes are scored against the ray ILM (the training target), next to the ray IRM's.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from evgrid.ism.evnet import load_checkpoint
from evgrid.learn.train import (
    RadarDataset,
    TargetConfig,
    TrainConfig,
    build_cache,
    evaluate_model,
    saved_train_config,
)
from evgrid.preprocess import RadarFilter
from evgrid.sources import SimSource
from evgrid_sim.radar_variants import NOMINAL, OUT_OF_RANGE, TRAINING_RANGES, RadarRanges

__all__ = [
    "IN_RANGE",
    "CALIBRATED",
    "transfer_sources",
    "measure_transfer",
    "transfer_markdown",
    "run_transfer",
]

IN_RANGE = "in range (drawn per scene)"
CALIBRATED = "calibrated radar"


def transfer_sources(
    n_scenes: int, first_seed: int, duration_s: float, ranges: RadarRanges = TRAINING_RANGES
) -> dict[str, SimSource]:
    """The held-out (``val``) scenes seen through radars in ``ranges``, the calibrated radar, and
    every out-of-range radar."""
    seeds = SimSource.split("val", n_scenes, first_seed, duration_s).seeds
    sets = {
        IN_RANGE: SimSource(seeds, duration_s, radar_ranges=ranges),
        CALIBRATED: SimSource(seeds, duration_s, radar=NOMINAL),
    }
    sets.update({name: SimSource(seeds, duration_s, radar=v) for name, v in OUT_OF_RANGE.items()})
    return sets


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def measure_transfer(
    checkpoint: str | os.PathLike,
    sources: dict[str, SimSource],
    cache_root: str | os.PathLike,
    ranges: RadarRanges = TRAINING_RANGES,
    progress: Callable[[str], None] | None = None,
) -> dict[str, dict]:
    """Per radar set: the deep IRM's and the ray IRM's single-frame IoU per class, the samples
    scored, and which parameters lie outside ``ranges``."""
    ck = load_checkpoint(checkpoint)
    model = ck.model.eval()
    # samples made as in the checkpoint's training (grid, input image, stride, radar filter,
    # self-return filter); the radar of each set is its source's, not the training's ranges
    saved = ck.extra.get("config")
    if saved is not None:
        config = replace(
            saved_train_config(saved, f"{checkpoint}: training config"),
            workers=0,
            radar_ranges=None,
        )
    else:  # checkpoints written before the whole training config was saved
        config = TrainConfig(workers=0, target=TargetConfig(kind="single_frame"))
        if "radar_filter" in ck.extra:
            config = replace(config, radar_filter=RadarFilter.from_dict(ck.extra["radar_filter"]))
    results: dict[str, dict] = {}
    for name, src in sources.items():
        root = Path(cache_root) / _slug(name) / config.data_key()
        names = build_cache(src, root, config, with_irm=True)  # engine: config.engine
        ds = RadarDataset(root, names, config.grid, with_irm=True)
        deep, irm, _ = evaluate_model(model, DataLoader(ds, batch_size=4), torch.device("cpu"))
        variant = src.radar
        outside = ranges.outside(variant) if variant is not None else []
        results[name] = {
            "deep_irm": deep,
            "ray_irm": irm,
            "samples": len(ds),
            "scenes": len(names),
            "outside_training": outside,
            "radar": variant.to_dict() if variant is not None else ranges.to_dict(),
        }
        if progress:
            progress(name)
    return results


def transfer_markdown(results: dict[str, dict]) -> str:
    """The results of :func:`measure_transfer` as a Markdown table (IoU in %)."""
    pct = lambda x: "-" if x != x else f"{100 * x:.1f}"  # noqa: E731  (NaN: a class absent)
    lines = [
        "| radar | outside training | deep IRM free | occupied | unknown | ray IRM free | occupied "
        "| unknown | samples |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        d, i = r["deep_irm"], r["ray_irm"]
        lines.append(
            f"| {name} | {', '.join(r['outside_training']) or '-'} | {pct(d['free'])} | "
            f"{pct(d['occupied'])} | "
            f"{pct(d['unknown'])} | {pct(i['free'])} | {pct(i['occupied'])} | {pct(i['unknown'])} "
            f"| {r['samples']} |"
        )
    return "\n".join(lines) + "\n"


def _transfer_one(args: tuple) -> dict:
    ckpt, name, source, cache = args
    return measure_transfer(ckpt, {name: source}, cache)[name]


def run_transfer(
    out: str | os.PathLike,
    checkpoint: str | os.PathLike | None,
    scenes: int,
    seed: int,
    duration_s: float,
    progress: Callable[[str], None] | None = None,
    engine: str = "local",
    workers: int = 1,
) -> str:
    """``evgrid transfer``: score a checkpoint's single frames on radars inside and outside its
    training ranges, one radar a job (:func:`evgrid.engine.fan_out`); writes ``transfer.json``
    and ``transfer.md``, returns the Markdown. A radar whose job fails is an error naming it."""
    from evgrid.engine import fan_out
    from evgrid.io import atomic_write_text, write_json
    from evgrid.ism.deep import default_checkpoint

    out = Path(out)
    sources = transfer_sources(scenes, seed, duration_s)
    ckpt = str(checkpoint or default_checkpoint())
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(name, (ckpt, name, src, str(out / "cache"))) for name, src in sources.items()]
    found, failed = {}, {}
    for o in fan_out(_transfer_one, jobs, engine=engine, workers=workers):
        found[o.key] = o.result
        if not o.ok:
            failed[o.key] = o.error
        if progress:
            progress(o.key)
    if failed:
        raise RuntimeError(f"transfer: radar(s) failed: {failed}")
    res = {name: found[name] for name in sources}  # the order of the radars, not of finishing
    meta = {"checkpoint": str(ckpt), "scenes": scenes, "seed": seed, "duration_s": duration_s}
    write_json(out / "transfer.json", {**meta, "radars": res})
    text = transfer_markdown(res)
    atomic_write_text(out / "transfer.md", text)
    return text
