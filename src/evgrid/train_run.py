"""``evgrid train`` as a library: its config (the training parameters and the scenes trained and
validated on), which scenes those are, and the sample cache built before training.

The cache is built from the scene sources themselves (the engine's workers load the scenes:
``TrainConfig.engine`` and ``cache_workers``); under torchrun, by rank 0 before any process joins
the process group, while the other ranks wait for its marker (docs/training.md). ``--init``
fine-tunes a checkpoint (:func:`evgrid.learn.train.fine_tune_config`), and the checkpoints
record the data (:func:`data_record`).

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

from evgrid.config import FORMATS, document, resolve_config
from evgrid.learn.train import TrainConfig

__all__ = [
    "TrainRunConfig",
    "resolve_train_config",
    "run_training",
    "data_record",
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


def resolve_train_config(
    path: str | os.PathLike | None, overrides: list[tuple[str, Any]]
) -> TrainRunConfig:
    """The training run's config: the file (else the defaults), then the overrides (the
    command line's data options among them). With ``train.init`` (a checkpoint's path, or
    ``shipped``) the run fine-tunes that checkpoint: its architecture, grid and input image
    (:func:`evgrid.learn.train.fine_tune_config`)."""
    from evgrid.learn.train import checkpoint_path

    # a checkpoint's name becomes its path here: a config file holds paths (made absolute)
    overrides = [
        (k, checkpoint_path(v) if k == "train.init" and isinstance(v, str) else v)
        for k, v in overrides
    ]
    run = resolve_config(TrainRunConfig, path, overrides)
    return _fine_tuned(run) if run.train.init is not None else run


def _fine_tuned(run: TrainRunConfig) -> TrainRunConfig:
    """The run with the architecture, grid and input image of its parent checkpoint; an
    architecture asked for that is neither the default nor the parent's is an error."""
    from dataclasses import replace

    from evgrid.learn.train import fine_tune_config

    config = fine_tune_config(run.train, run.train.init)
    if run.train.model not in (TrainConfig().model, config.model):
        raise ValueError(
            f"--init {run.train.init}: that checkpoint is a {config.model}, but the config asks "
            f"for a {run.train.model}; fine-tuning keeps the parent's architecture (drop "
            "--width/--depth)"
        )
    return replace(run, train=config)


def data_record(run: TrainRunConfig) -> dict[str, Any]:
    """What a checkpoint records of the data it was trained on (``extra["data"]``): the kind
    of source, both sources as the config holds them, and for recordings the recording rig
    (path and content) and the recordings; for nuScenes the version and splits."""
    train, val = run.source or {}, run.val_source or {}
    out: dict[str, Any] = {"source": train.get("kind"), "train": train, "val": val}
    if train.get("kind") == "bag":
        rig = Path(train["rig"])
        try:
            text = rig.read_text()
        except (OSError, UnicodeDecodeError) as e:
            raise ValueError(f"{rig}: cannot read the recording rig ({e})") from None
        out.update(
            rig=str(rig),
            rig_text=text,
            recordings=list(train["paths"]),
            val_recordings=list(val.get("paths", ())),
        )
    elif train.get("kind") == "nuscenes":
        out.update(
            dataroot=train["dataroot"],
            version=train["version"],
            split=train["split"],
            val_split=val.get("split"),
        )
    return out


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
    from evgrid.learn.train import train

    config = run.train
    cache = out / "cache" / config.data_key()
    # Under torchrun the cache is built by rank 0 before any process joins the process group:
    # the group's start-up waits only so long for its members (minutes), a cache of a large
    # dataset takes hours. The other ranks wait for rank 0's marker on the file system.
    if _rank() == 0:
        names = _build_caches(run, cache, on_cache)
    else:
        names = _wait_for_cache(run, cache)
    return train(
        config,
        cache,
        names["train"],
        names["val"],
        out,
        resume=resume,
        on_epoch=on_epoch,
        on_batch=on_batch,
        data=data_record(run),
        config_document=document(run),
    )


def _rank() -> int:
    return int(os.environ.get("RANK", "0"))


def _build_caches(run: TrainRunConfig, cache: Path, on_cache) -> dict[str, list[str]]:
    """Rank 0: cache both sources (the engine's workers load the scenes themselves); under
    torchrun, then tell the other ranks (:func:`_wait_for_cache`) the scenes, or the error."""
    from evgrid.io import write_json
    from evgrid.learn.train import build_cache
    from evgrid.sources import source_from_dict

    world = int(os.environ.get("WORLD_SIZE", "1"))
    marker = cache / _READY
    if world > 1:
        marker.unlink(missing_ok=True)
    names: dict[str, list[str]] = {}
    try:
        sources = {"train": source_from_dict(run.source), "val": source_from_dict(run.val_source)}
        _check_disjoint(sources)
        for split, src in sources.items():
            total = len(src.names())
            count = iter(range(1, total + 1))
            names[split] = build_cache(
                src,
                cache,
                run.train,
                with_irm=split == "val",
                progress=lambda n, s=split, t=total: on_cache and on_cache(s, next(count), t),
            )
    except BaseException as e:
        if world > 1:
            cache.mkdir(parents=True, exist_ok=True)
            err = " ".join(str(e).split()) or type(e).__name__
            write_json(marker, {"launch": _launch(), "error": err})
        raise
    if world > 1:
        write_json(marker, {"launch": _launch(), "stamp": _stamp(run), **names})
    return names


def _check_disjoint(sources: dict[str, Any]) -> None:
    """One cache holds the training and the validation scenes by name: a name in both would
    train on the validation scene (its shard replaces the training one). Refuse it."""
    train, val = sources["train"], sources["val"]
    paths = [set(map(os.path.realpath, getattr(s, "paths", ()))) for s in (train, val)]
    same = sorted(paths[0] & paths[1])
    if same:  # fine-tuning on one drive: its scores would be those of the data trained on
        raise ValueError(
            f"{', '.join(same)}: both a training and a validation recording (--bag and "
            "--val-bag); the validation scores would be those of the data trained on. To "
            "fine-tune on one drive, cut it in two by time with a bag tool (an MCAP with the "
            "mcap CLI's 'filter', a ROS 1 bag with 'rosbag filter', a ROS 2 bag with 'ros2 bag "
            "convert') and give one part to --bag, the other to --val-bag"
        )
    both = sorted(set(train.names()) & set(val.names()))
    if both:
        hint = ""
        if type(train).__name__ == "BagSource":
            hint = (
                " (one recording alone is named by the rig file's 'scene:', else by its file "
                "name: remove that line, or rename a file, so that the names differ)"
            )
        raise ValueError(
            f"scene(s) {both} are both training and validation scenes; give validation scenes "
            f"of other names{hint}"
        )


#: Rank 0's marker in the cache folder: the scenes cached, or the error that stopped it.
_READY = "ready.json"


def _stamp(run: TrainRunConfig) -> str:
    """What a cache marker must match: the sources and the settings of the samples."""
    import hashlib
    import json

    key = {"data_key": run.train.data_key(), "source": run.source, "val_source": run.val_source}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def _launch() -> str:
    """This torchrun launch (its rendezvous id, master port and restart), so that an error
    left by an earlier launch is not taken for this one's."""
    keys = ("TORCHELASTIC_RUN_ID", "MASTER_ADDR", "MASTER_PORT", "TORCHELASTIC_RESTART_COUNT")
    return ":".join(os.environ.get(k, "") for k in keys)


def _wait_for_cache(
    run: TrainRunConfig, cache: Path, poll_s: float = 2.0, timeout_s: float | None = None
) -> dict[str, list[str]]:
    """Ranks other than 0: wait (without a time limit unless ``timeout_s``: a cache can take
    hours) until rank 0 has cached both sources; return the scene names it wrote. Rank 0's
    error ends the wait with that error."""
    import json
    import time

    marker = cache / _READY
    stamp, launch = _stamp(run), _launch()
    t0 = time.monotonic()
    while True:
        try:
            got = json.loads(marker.read_text())
        except (OSError, ValueError):
            got = None  # not written yet (a marker is written atomically)
        if isinstance(got, dict):
            if got.get("stamp") == stamp:
                return {"train": list(got["train"]), "val": list(got["val"])}
            if got.get("error") is not None and got.get("launch") == launch:
                raise RuntimeError(f"rank 0 could not build the cache {cache}: {got['error']}")
        if timeout_s is not None and time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"rank 0 did not build the cache {cache} in {timeout_s:.0f} s")
        time.sleep(poll_s)
