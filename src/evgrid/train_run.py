"""``evgrid train`` as a library: its config (the training parameters and the scenes trained and
validated on), which scenes those are, and the sample cache built before training.

A training run writes :class:`TrainRunConfig` as ``OUT/config.json``; ``evgrid train --config
OUT/config.json`` trains again on the same scenes the same way. The training parameters are
:class:`evgrid.learn.train.TrainConfig`, serialised by :func:`evgrid.config.to_dict`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from evgrid.config import FORMATS, document, resolve_config, to_dict
from evgrid.learn.train import TrainConfig

__all__ = [
    "TrainRunConfig",
    "TrainData",
    "TRAIN_OPTIONS",
    "resolve_train_config",
    "train_config_from_args",
    "run_training",
    "run_transfer",
]


@dataclass(frozen=True)
class TrainRunConfig:
    """A training run: the parameters, the training scenes and the validation scenes (each a
    source as :func:`evgrid.sources.source_to_dict` writes it)."""

    train: TrainConfig = field(default_factory=TrainConfig)
    source: dict[str, Any] | None = None
    val_source: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        from evgrid.sources import source_from_dict

        for s in (self.source, self.val_source):
            if s is not None:
                source_from_dict(s)


FORMATS[TrainRunConfig] = "evgrid-train"

#: ``evgrid train``'s short options, each an override of :class:`TrainRunConfig`'s fields.
TRAIN_OPTIONS: dict[str, tuple[str, ...]] = {
    "epochs": ("train.epochs",),
    "batch-size": ("train.batch_size",),
    "lr": ("train.lr",),
    "workers": ("train.workers",),
    "frame-stride": ("train.frame_stride",),
    "width": ("train.model.width",),
    "depth": ("train.model.depth",),
    "self-returns": ("train.self_returns.mode",),
    "body-box": (
        "train.self_returns.mode=box",
        "train.self_returns.body",
        "train.self_returns.prior",
    ),
    "radar-filter": ("train.radar_filter.mode",),
}


@dataclass(frozen=True)
class TrainData:
    """``evgrid train``'s data options (``--val-bag`` is ``val_bag``): the simulator by default
    (``scenes`` training and ``val_scenes`` validation scenes from ``seed`` on, each scene's radar
    drawn from the training ranges unless ``random_radar`` is off), nuScenes splits, or
    recordings (``bag`` and ``val_bag`` with their ``rig``)."""

    nuscenes: str | None = None
    version: str = "v1.0-trainval"
    train_split: str = "train"
    val_split: str = "val"
    bag: tuple[str, ...] = ()
    val_bag: tuple[str, ...] = ()
    rig: str | None = None
    scenes: int = 40
    val_scenes: int = 10
    seed: int = 0  # the training run's seed, and the first simulator seed
    duration: float = 20.0
    random_radar: bool = True

    def overrides(self) -> list[tuple[str, Any]]:
        """The config fields these options decide: both sources, the seed, the radar ranges."""
        from evgrid.data.radar_variants import TRAINING_RANGES
        from evgrid.sources import BagSource, NuScenesSource, SimSource, source_to_dict

        ranges = None
        if self.bag or self.val_bag:
            if not (self.bag and self.val_bag and self.rig) or self.nuscenes is not None:
                raise ValueError(
                    "training on recordings needs --bag, --val-bag and --rig (and no --nuscenes)"
                )
            rig = os.path.abspath(self.rig)
            tr = BagSource(tuple(map(os.path.abspath, self.bag)), rig)
            va = BagSource(tuple(map(os.path.abspath, self.val_bag)), rig)
        elif self.nuscenes is not None:
            root = os.path.abspath(self.nuscenes)
            tr = NuScenesSource(root, self.version, self.train_split)
            va = NuScenesSource(root, self.version, self.val_split)
        else:
            ranges = TRAINING_RANGES if self.random_radar else None
            tr = SimSource.split(
                "train", self.scenes, self.seed, self.duration, radar_ranges=ranges
            )
            va = SimSource.split(
                "val", self.val_scenes, self.seed, self.duration, radar_ranges=ranges
            )
        return [
            ("source", source_to_dict(tr)),
            ("val_source", source_to_dict(va)),
            ("train.seed", self.seed),
            ("train.radar_ranges", to_dict(ranges) if ranges else None),
        ]


def resolve_train_config(
    path: str | os.PathLike | None,
    overrides: list[tuple[str, Any]],
    data: TrainData | None,
) -> TrainRunConfig:
    """The training run's config: the file (else the defaults), the data options (when given,
    or when there is no file), then the overrides."""
    if path is None and data is None:
        data = TrainData()
    return resolve_config(TrainRunConfig, path, [*(data.overrides() if data else []), *overrides])


def run_training(
    run: TrainRunConfig,
    out: str | os.PathLike,
    resume: bool = False,
    on_cache: Callable[[str, int, int], None] | None = None,
    on_epoch: Callable[[int, dict], None] | None = None,
    on_batch: Callable[[int, int, int], None] | None = None,
):
    """Cache the samples of both sources (rank 0; cached scenes are kept), then train; writes
    ``OUT/config.json`` (this config) and what :func:`evgrid.learn.train.train` writes.
    ``on_cache(split, done, total)`` after each scene cached. Returns the training result."""
    from evgrid.outdir import locked

    if run.source is None or run.val_source is None:
        raise ValueError("a training config needs both 'source' and 'val_source' (scenes)")
    out = Path(out)
    if int(os.environ.get("RANK", "0")) != 0:  # the other ranks of torchrun share rank 0's lock
        return _run_training(run, out, resume, on_cache, on_epoch, on_batch)
    with locked(out):
        return _run_training(run, out, resume, on_cache, on_epoch, on_batch)


def _run_training(run, out, resume, on_cache, on_epoch, on_batch):
    from evgrid.learn.train import build_cache, train
    from evgrid.sources import source_from_dict

    config = run.train
    cache = out / "cache" / config.data_key()
    sources = {"train": source_from_dict(run.source), "val": source_from_dict(run.val_source)}
    names: dict[str, list[str]] = {}
    if int(os.environ.get("RANK", "0")) == 0:
        for split, src in sources.items():
            todo = src.names()
            count = iter(range(1, len(todo) + 1))
            names[split] = build_cache(
                (src.load(n) for n in todo),
                cache,
                config,
                with_irm=split == "val",
                progress=lambda n, s=split, t=len(todo): on_cache and on_cache(s, next(count), t),
            )
    else:
        names = {split: src.names() for split, src in sources.items()}
    return train(
        config,
        cache,
        names["train"],
        names["val"],
        out,
        resume=resume,
        on_epoch=on_epoch,
        on_batch=on_batch,
        config_document=document(run),
    )


def train_config_from_args(
    args: list[str],
    path: str | os.PathLike | None = None,
    sets: list[str] = (),
    resume: str | os.PathLike | None = None,
) -> TrainRunConfig:
    """``evgrid train``'s config from command-line words: the file (else, resuming the run
    folder ``resume``, its config.json; else the defaults), the data options of
    :class:`TrainData`, the short options of :data:`TRAIN_OPTIONS`, then ``--set``."""
    from evgrid.config import options_to_overrides, parse_overrides

    if path is None and resume and (Path(resume) / "config.json").is_file():
        path = Path(resume) / "config.json"  # the run being continued

    overrides, data = options_to_overrides(args, TRAIN_OPTIONS, TrainRunConfig, TrainData)
    overrides += parse_overrides(sets)
    return resolve_train_config(path, overrides, TrainData(**data) if data else None)


def _transfer_one(args: tuple) -> dict:
    from evgrid.learn.transfer import measure_transfer

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
    from evgrid.learn.transfer import transfer_markdown, transfer_sources

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
