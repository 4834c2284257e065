"""Training Ev-Net on scenes (simulated, nuScenes or recordings): sample cache, training loop,
validation.

Samples (paper sec. V-C, docs/decisions.md#ev-net-targets-and-loss): at every
``frame_stride``-th lidar frame, the input is the radar detection image of the last
``n_sweeps`` sweeps of each radar in the current ego frame, the target the classes of the lidar
frames around it or of the frame alone (``TrainConfig.target``, :mod:`evgrid.learn.targets`;
docs/training.md#targets). Inputs are cached sparse (detection
tables, a few kB a sample) and rasterised in the DataLoader workers; targets as uint8 rasters,
memory-mapped.

The cache is one *shard* a scene (a folder of ``.npy`` files and its ``meta.json``) and an
``index.json``. Shards are computed in parallel through :func:`evgrid.engine.fan_out` (the
local pool or Ray); the driver alone writes them, each into a temporary folder renamed into
place once complete, so a shard is complete or absent, and an interrupted build resumes with
the scenes it lacks (docs/training.md).

Frames are cleaned by :class:`evgrid.preprocess.Preprocessor`, the mapper's own: the radar
detections pass ``TrainConfig.radar_filter`` and the lidar sweeps ``TrainConfig.self_returns``
exactly as in mapping (:class:`~evgrid.mapper.OccupancyMapper`; no pose gate in training);
the checkpoint records the radar filter (metadata ``extra["radar_filter"]``) so that mapping
with another one warns, and, when fine-tuned (``TrainConfig.init``), its parent checkpoint.

Runs unchanged under ``torchrun --nproc_per_node=K`` (DistributedDataParallel, NCCL on GPUs,
gloo on CPUs); rank 0 validates, logs and writes checkpoints. On CUDA the forward pass runs
in mixed precision (``TrainConfig.precision``); on the CPU in float32.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import logging
import math
import os
import random
import re
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from evgrid.data.frame import Frame
from evgrid.engine import ENGINES, fan_out
from evgrid.evaluate import CLASSES
from evgrid.geometry import GridSpec
from evgrid.io import atomic_write, atomic_write_bytes, write_json
from evgrid.ism.deep import CHANNELS, RadarImageParams, detections_to_image, radar_detections
from evgrid.ism.evnet import EvNet, EvNetConfig, load_checkpoint, save_checkpoint
from evgrid.learn.loss import LOSSES, evidential_loss, training_loss
from evgrid.learn.targets import TargetConfig, TargetWindow, ilm_classes
from evgrid.package import SHIPPED_CHECKPOINTS, shipped_checkpoint
from evgrid.preprocess import RadarFilter, SelfReturnParams
from evgrid.validation import check_choice, check_int, check_number

__all__ = [
    "TrainConfig",
    "PRECISIONS",
    "CacheError",
    "ilm_classes",
    "scene_samples",
    "scene_shard",
    "build_cache",
    "cached_scenes",
    "RadarDataset",
    "fine_tune_config",
    "saved_train_config",
    "TargetConfig",
    "CHECKPOINT_NAMES",
    "checkpoint_path",
    "Precision",
    "batch_loss",
    "train",
    "TrainResult",
]

logger = logging.getLogger(__name__)

#: ``TrainConfig.precision``: ``auto`` = bf16 on a CUDA device that has it, else fp16 on CUDA;
#: float32 on the CPU whatever the setting (mixed precision is a GPU feature).
PRECISIONS: tuple[str, ...] = ("auto", "fp32", "bf16", "fp16")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides a training run; saved beside its results as ``config.json``."""

    epochs: int = 20  #: passes over the training samples
    batch_size: int = 4  #: samples a step
    lr: float = 2e-3  #: AdamW's learning rate
    weight_decay: float = 1e-4
    seed: int = 0
    #: DataLoader worker processes
    workers: int = 2
    frame_stride: int = 4  #: every this many lidar frames of a scene is a sample
    flip: bool = True
    threads: int = 0  # torch intra-op threads; 0 = torch's default
    grid: GridSpec = field(default_factory=GridSpec)
    model: EvNetConfig = field(default_factory=lambda: EvNetConfig(in_channels=len(CHANNELS)))
    image: RadarImageParams = field(default_factory=RadarImageParams)
    radar_filter: RadarFilter = field(default_factory=RadarFilter)  # as in mapping
    #: the targets' ray ILM filter of the vehicle's own returns, as in mapping
    self_returns: SelfReturnParams = field(default_factory=SelfReturnParams)
    #: Simulated data only: the ranges the simulated sources draw a radar per scene from, as
    #: JSON (``evgrid_sim.radar_variants.RadarRanges``; None: the calibrated radar). Recorded
    #: here for the cache key and the checkpoint; the source does the drawing.
    radar_ranges: dict[str, Any] | None = None
    #: an Ev-Net checkpoint to fine-tune from (none: train from scratch); docs/training.md
    init: str | None = None
    #: what builds the sample cache: local (a process pool) or ray (evgrid[ray])
    engine: str = "local"
    cache_workers: int = 1  #: cache jobs at once
    #: mixed precision on CUDA: auto|fp32|bf16|fp16 (auto: bf16 where the GPU has it, else fp16)
    precision: str = "auto"
    #: the targets: the lidar accumulated around each sample, or the paper's single frame
    target: TargetConfig = field(default_factory=TargetConfig)
    #: the training loss (evgrid.learn.loss.LOSSES): paper+cor (the paper's eqs. (36)-(37) plus
    #: a correct-evidence term that keeps learning where evidence is low) or paper (as trained)
    loss: str = "paper+cor"

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "frame_stride", "cache_workers"):
            check_int(self, name, min=1)
        check_int(self, "workers", min=0)
        check_number(self, "lr", min=0.0, min_open=True)
        check_choice("TrainConfig", "engine", self.engine, choices=ENGINES)
        check_choice("TrainConfig", "precision", self.precision, choices=PRECISIONS)
        check_choice("TrainConfig", "loss", self.loss, choices=LOSSES)
        if self.init is not None and not isinstance(self.init, str):
            raise ValueError(f"TrainConfig.init must be a path or None, got {self.init!r}")
        if self.model.in_channels != len(CHANNELS):
            raise ValueError(
                f"the model must take {len(CHANNELS)} input channels ({CHANNELS}), got "
                f"{self.model.in_channels}"
            )

    def to_dict(self) -> dict:
        """Plain-JSON form (evgrid.serial, the serialiser of every parameter dataclass)."""
        from evgrid.serial import to_dict

        return to_dict(self)

    def data_key(self) -> str:
        """Hash of the settings that decide the cached samples (and the cache's layout)."""
        key = json.dumps(
            {
                "grid": self.grid.to_dict(),
                "image": asdict(self.image),
                "stride": self.frame_stride,
                "v": 3,
                "radar_filter": self.radar_filter.to_dict(),
                "self_returns": asdict(self.self_returns),
                "radar_ranges": self.radar_ranges,
                # single-frame targets keep the key (and the caches) they had before targets
                # had a config
                **({} if self.target.kind == "single_frame" else {"target": asdict(self.target)}),
            },
            sort_keys=True,
        )
        return hashlib.sha1(key.encode()).hexdigest()[:12]


#: Checkpoints that may be named instead of given by path (``--init shipped``).
CHECKPOINT_NAMES: tuple[str, ...] = tuple(SHIPPED_CHECKPOINTS)


def checkpoint_path(init: str | os.PathLike) -> str:
    """The checkpoint file that ``init`` names: a name of :data:`CHECKPOINT_NAMES` is a
    checkpoint shipped with evgrid (``shipped`` the default deep IRM's), anything else a path."""
    return str(shipped_checkpoint(str(init)) or init)


def fine_tune_config(config: TrainConfig, init: str | os.PathLike) -> TrainConfig:
    """``config`` set to fine-tune from checkpoint ``init`` (a path, or a name of
    :data:`CHECKPOINT_NAMES`): its architecture, and (when the checkpoint saved its training
    config) its grid and input image, since the inputs must be made as the parent's were. The
    rest (epochs, learning rate, data, filters) is ``config``'s.
    """
    init = checkpoint_path(init)
    ck = load_checkpoint(init)
    out = replace(config, init=init, model=ck.model.config)
    saved = ck.extra.get("config")
    if isinstance(saved, dict):
        parent = saved_train_config(saved, f"{init}: training config")
        out = replace(out, grid=parent.grid, image=parent.image)
    return out


def saved_train_config(saved: dict, where: str) -> TrainConfig:
    """The :class:`TrainConfig` a checkpoint saved (``extra["config"]``); one saved before
    targets had a config (no ``target``) trained on single-frame targets, and reads so."""
    from evgrid.config import from_dict

    if isinstance(saved, dict) and "target" not in saved:
        saved = {**saved, "target": {"kind": "single_frame"}}
    return from_dict(TrainConfig, saved, where)


# --- samples ------------------------------------------------------------------------------------


def scene_samples(
    frames: Iterable[Frame], config: TrainConfig, with_irm: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """Yield ``(detections, target classes, ray-IRM classes or None)`` for every
    ``frame_stride``-th frame. Accumulated targets (``config.target``) need the frames up to
    ``after_s`` past a sample, so its sample comes that much later in the stream."""
    from evgrid.data.sweeps import RadarBuffer
    from evgrid.ism import ray_ilm, ray_irm
    from evgrid.preprocess import Preprocessor

    buffer = RadarBuffer(config.image.n_sweeps)
    # frames cleaned as the mapper cleans them (radar validity filter before the sweep buffer,
    # the vehicle's own lidar returns before the ray ILM); no pose gate: training takes the
    # poses as given
    clean = Preprocessor.from_config(config, gate_poses=False)
    window = TargetWindow(config.target, config.grid)
    accumulated = config.target.kind == "accumulated"
    pending: list[tuple[np.ndarray, Any, np.ndarray | None]] = []  # (det, lidar, irm)
    for k, frame in enumerate(frames):
        for sweep in clean.radar_sweeps(frame):
            buffer.push(sweep)
        if accumulated:
            window.push(clean.lidar(frame.lidar))
            while pending and window.complete_for(pending[0][1]):
                det, lidar, irm = pending.pop(0)
                yield det, window.target(lidar), irm
        if k % config.frame_stride:
            if accumulated:
                window.drop_before(pending[0][1].timestamp if pending else frame.timestamp)
            continue
        sweeps = buffer.sweeps()
        det = radar_detections(sweeps, frame.ego_pose, frame.timestamp, config.image)
        irm = ilm_classes(ray_irm(sweeps, frame.ego_pose, grid=config.grid)) if with_irm else None
        if accumulated:
            pending.append((det, window.last, irm))
            window.drop_before(pending[0][1].timestamp)
            continue
        # the lidar of sampled frames only, as the mapper cleans only the frames it maps
        yield det, ilm_classes(ray_ilm(clean.lidar(frame.lidar), grid=config.grid)), irm
    for det, lidar, irm in pending:  # the scene's last samples: their windows end with it
        yield det, window.target(lidar), irm


def scene_shard(
    frames: Iterable[Frame], config: TrainConfig, with_irm: bool = False, name: str = "scene"
) -> dict[str, np.ndarray]:
    """The cached form of one scene's samples: detections of all samples (``det``), where
    each sample's rows start (``offsets``), target classes (``target``) and, with
    ``with_irm``, the ray IRM's classes (``irm``)."""
    dets, targets, irms = [], [], []
    for det, target, irm in scene_samples(frames, config, with_irm):
        dets.append(det)
        targets.append(target)
        if irm is not None:
            irms.append(irm)
    if not dets:
        raise ValueError(f"scene {name!r} gave no samples (is it empty?)")
    arrays = {
        "det": np.concatenate(dets).astype(np.float32),
        "offsets": np.cumsum([0] + [len(d) for d in dets]).astype(np.int64),
        "target": np.stack(targets),
    }
    if with_irm:
        arrays["irm"] = np.stack(irms)
    return arrays


# --- the cache: one shard a scene, an index -----------------------------------------------------

_INDEX = "index.json"
_LAYOUT = 3


class CacheError(ValueError):
    """Scenes that could not be cached (each named with its error), or a cache that does not
    match the settings."""


def _shard_dir(root: Path, name: str) -> Path:
    """A scene's shard folder: its name where that is a safe file name, else a safe form of it
    with a hash (so that two names never share a folder)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", name)
    if safe != name or safe.startswith("."):
        safe = f"{safe.lstrip('.')}-{hashlib.sha1(name.encode()).hexdigest()[:8]}"
    return root / safe


def _shard_meta(root: Path, name: str) -> dict | None:
    """A complete shard's ``meta.json`` (None where the scene has no shard)."""
    path = _shard_dir(root, name) / "meta.json"
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise CacheError(f"{path}: unreadable shard metadata ({e}); delete the folder") from e
    if not isinstance(meta, dict) or meta.get("scene") != name:
        raise CacheError(f"{path}: not the shard of scene {name!r}; delete the folder")
    return meta


def _fsynced_save(path: Path, array: np.ndarray) -> None:
    with open(path, "wb") as f:
        np.save(f, array)
        f.flush()
        os.fsync(f.fileno())


def _write_shard(root: Path, name: str, arrays: dict[str, np.ndarray], key: str) -> dict:
    """Write a scene's shard: every file into a temporary folder, ``meta.json`` last, then the
    folder renamed into place (a rename is atomic), so a reader sees all of it or none."""
    final = _shard_dir(root, name)
    tmp = root / f".{final.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for k, a in arrays.items():
        _fsynced_save(tmp / f"{k}.npy", a)
    meta = {
        "scene": name,
        "samples": int(len(arrays["offsets"]) - 1),
        "irm": "irm" in arrays,
        "data_key": key,
    }
    write_json(tmp / "meta.json", meta)
    if final.exists():  # a shard without the ray IRM's classes, replaced by one with them
        old = root / f".{final.name}.old-{os.getpid()}"
        os.rename(final, old)
        os.rename(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, final)
    return meta


def _read_index(root: Path, key: str) -> dict[str, dict]:
    path = root / _INDEX
    if not path.is_file():
        return {}
    try:
        index = json.loads(path.read_text())
        shards, layout, data_key = index["shards"], index["layout"], index["data_key"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CacheError(f"{path}: unreadable cache index ({e}); delete it to rebuild it") from e
    if layout != _LAYOUT or data_key != key:
        raise CacheError(
            f"{path}: the cache holds samples of other settings (data key {data_key!r}, layout "
            f"{layout!r}; these settings: {key!r}, layout {_LAYOUT}); use another folder"
        )
    return dict(shards)


def _write_index(root: Path, shards: dict[str, dict], key: str) -> None:
    write_json(root / _INDEX, {"layout": _LAYOUT, "data_key": key, "shards": shards})


def _cache_job(args: tuple) -> dict[str, np.ndarray]:
    """One scene's shard arrays, computed in a worker (which loads the scene itself)."""
    source, name, config, with_irm = args
    return scene_shard(source.load(name), config, with_irm, name)


def _is_source(scenes: object) -> bool:
    return callable(getattr(scenes, "names", None)) and callable(getattr(scenes, "load", None))


def _remove_stale_shards(root: Path) -> None:
    """Remove what a build killed while writing a shard left in ``root``."""
    for pattern in (".*.tmp-*", ".*.old-*"):
        for stale in root.glob(pattern):
            shutil.rmtree(stale, ignore_errors=True)


def _cache_by_engine(
    source: Any,
    config: TrainConfig,
    with_irm: bool,
    engine: str,
    workers: int,
    cached: Callable[[str], bool],
    done: Callable[[str, dict[str, np.ndarray]], None],
    progress: Callable[[str], None] | None,
) -> tuple[list[str], dict[str, str]]:
    """:func:`build_cache` of a scene source: the scenes not cached yet loaded and computed as
    jobs of ``engine``; the scenes' names and, per scene that failed, its error."""
    names = [str(n) for n in source.names()]
    todo = [n for n in names if not cached(n)]
    for name in names:
        if name not in todo and progress:
            progress(name)
    jobs = [(n, (source, n, config, with_irm)) for n in todo]
    errors: dict[str, str] = {}
    for outcome in fan_out(_cache_job, jobs, engine=engine, workers=workers):
        if outcome.ok:
            done(outcome.key, outcome.result)
        else:
            errors[outcome.key] = outcome.error
    return names, errors


def _cache_here(
    scenes: Iterable,
    config: TrainConfig,
    with_irm: bool,
    cached: Callable[[str], bool],
    done: Callable[[str, dict[str, np.ndarray]], None],
    progress: Callable[[str], None] | None,
) -> list[str]:
    """:func:`build_cache` of an iterable of scenes, computed here one after another; the
    scenes' names."""
    names = []
    for scene in scenes:
        name = str(scene.name)
        names.append(name)
        if cached(name):
            if progress:
                progress(name)
            continue
        done(name, scene_shard(scene, config, with_irm, name))
    return names


def build_cache(
    scenes: Iterable | Any,
    root: str | os.PathLike,
    config: TrainConfig,
    with_irm: bool = False,
    progress: Callable[[str], None] | None = None,
    *,
    engine: str | None = None,
    workers: int | None = None,
) -> list[str]:
    """Cache the samples of each scene under ``root`` (one shard a scene and an index); skip
    scenes already cached. Returns the scene names in order.

    ``scenes``: a scene source (``names()`` and ``load(name)``, :mod:`evgrid.sources`), whose
    scenes are loaded and computed by ``workers`` jobs at once on ``engine`` (defaults:
    ``config.engine`` and ``config.cache_workers``); or an iterable of scenes (Frames with a
    ``name``), computed here one after another. The driver writes every file. A scene that
    fails is reported by name once the others are done (:class:`CacheError`); the shards that
    were written stay, so running again computes only what is missing.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    key = config.data_key()
    shards = _read_index(root, key)
    _remove_stale_shards(root)

    def cached(name: str) -> bool:
        meta = _shard_meta(root, name)
        if meta is None or (with_irm and not meta.get("irm")):
            return False
        shards[name] = meta
        return True

    def done(name: str, arrays: dict[str, np.ndarray]) -> None:
        shards[name] = _write_shard(root, name, arrays, key)
        _write_index(root, shards, key)
        if progress:
            progress(name)

    if _is_source(scenes):
        n_workers = workers if workers is not None else config.cache_workers
        run = (config, with_irm, engine or config.engine, n_workers)
        names, errors = _cache_by_engine(scenes, *run, cached, done, progress)
    else:
        names, errors = _cache_here(scenes, config, with_irm, cached, done, progress), {}
    _write_index(root, shards, key)
    if errors:
        listed = "; ".join(f"{n}: {e}" for n, e in errors.items())
        raise CacheError(f"{len(errors)} of {len(names)} scenes could not be cached: {listed}")
    return names


def cached_scenes(root: str | os.PathLike, config: TrainConfig) -> dict[str, int]:
    """Scene name -> number of samples of every complete shard under ``root``."""
    root = Path(root)
    shards = _read_index(root, config.data_key())
    return {n: int(m["samples"]) for n, m in shards.items() if _shard_meta(root, n) is not None}


class RadarDataset(Dataset):
    """Cached samples of some scenes: ``(input (C, n, n) float32, target (n, n) int64)`` pairs
    (and the ray IRM's classes with ``with_irm``)."""

    def __init__(
        self,
        root: str | os.PathLike,
        scenes: Sequence[str],
        grid: GridSpec,
        flip: bool = False,
        with_irm: bool = False,
    ):
        self.root = Path(root)
        self.grid = grid
        self.flip = flip
        self.with_irm = with_irm
        self._index: list[tuple[int, int]] = []
        self._scenes = []
        for si, name in enumerate(scenes):
            meta = _shard_meta(self.root, name)
            if meta is None:
                raise FileNotFoundError(
                    f"scene {name!r} is not cached under {self.root} (run build_cache first)"
                )
            if with_irm and not meta.get("irm"):
                raise FileNotFoundError(
                    f"scene {name!r} is cached under {self.root} without the ray IRM's classes "
                    "(run build_cache with with_irm=True)"
                )
            folder = _shard_dir(self.root, name)
            offsets = np.load(folder / "offsets.npy")
            self._scenes.append({"folder": folder, "offsets": offsets})
            self._index += [(si, k) for k in range(len(offsets) - 1)]
        self._open: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._index)

    def _arrays(self, si: int) -> dict[str, np.ndarray]:
        # memory-mapped lazily in each worker process
        if si not in self._open:
            folder = self._scenes[si]["folder"]
            keys = ("det", "target", "irm") if self.with_irm else ("det", "target")
            self._open[si] = {k: np.load(folder / f"{k}.npy", mmap_mode="r") for k in keys}
        return self._open[si]

    def __getitem__(self, i: int):
        si, k = self._index[i]
        a = self._arrays(si)
        off = self._scenes[si]["offsets"]
        det = np.array(a["det"][off[k] : off[k + 1]])
        target = np.array(a["target"][k])
        irm = np.array(a["irm"][k]) if self.with_irm else None
        if self.flip and random.random() < 0.5:
            # mirror left-right: y -> -y (columns reversed), Doppler's y component negated
            det[:, 1] *= -1.0
            det[:, 4] *= -1.0
            target = target[:, ::-1].copy()
        x = torch.from_numpy(detections_to_image(det, self.grid))
        t = torch.from_numpy(target.astype(np.int64))
        if irm is not None:
            return x, t, torch.from_numpy(irm.astype(np.int64))
        return x, t


# --- training -----------------------------------------------------------------------------------


@dataclass
class TrainResult:
    """Where a run wrote its files and its best validation figures."""

    out_dir: Path
    best_epoch: int
    best: dict[str, float]
    ray_irm_baseline: dict[str, float]
    seconds_per_epoch: float
    #: the forward pass's dtype: ``float32``, or ``bfloat16`` / ``float16`` on CUDA
    precision: str = "float32"
    samples_per_second: float = math.nan
    #: fine-tuning: the parent checkpoint's IoU on this run's validation scenes before any
    #: step (beside ``best``, whether fine-tuning helped), and the one it recorded on its own
    parent_val: dict[str, float] | None = None
    parent_recorded_val: dict[str, float] | None = None


def _seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _worker_init(worker_id: int) -> None:
    s = torch.initial_seed() % 2**32
    random.seed(s)
    np.random.seed(s)


def _dist() -> tuple[int, int, int]:
    """(rank, world size, local rank), initialising torch.distributed under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1, 0
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), world, int(os.environ.get("LOCAL_RANK", "0"))


class Precision:
    """Mixed precision of the forward pass: ``torch.autocast`` to bf16 or fp16 on CUDA, with a
    gradient scaler for fp16 (whose range is too small for small gradients); float32 on the
    CPU (mixed precision is a GPU feature: on the CPU bf16 runs slower than float32)."""

    def __init__(self, setting: str, device: torch.device):
        self.device = device
        self.dtype: torch.dtype | None = None
        if device.type == "cuda" and setting != "fp32":
            bf16 = setting == "bf16" or (setting == "auto" and torch.cuda.is_bf16_supported())
            self.dtype = torch.bfloat16 if bf16 else torch.float16
        elif setting in ("bf16", "fp16"):
            logger.info("precision %s asked for on %s: training in float32", setting, device)
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.dtype == torch.float16)

    @property
    def name(self) -> str:
        return str(self.dtype or torch.float32).removeprefix("torch.")

    def autocast(self) -> contextlib.AbstractContextManager:
        if self.dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=self.dtype)

    def step(self, loss: torch.Tensor, opt: torch.optim.Optimizer) -> None:
        """Backward pass and optimiser step (scaled for fp16; a step with inf gradients is
        skipped by the scaler)."""
        self.scaler.scale(loss).backward()
        self.scaler.step(opt)
        self.scaler.update()


def batch_loss(
    net: torch.nn.Module,
    x: torch.Tensor,
    t: torch.Tensor,
    precision: Precision,
    loss: str = "paper",
):
    """Forward pass in ``precision``; the loss named ``loss`` (:data:`LOSSES`) in float32 (the
    expected squared error sums many small terms)."""
    with precision.autocast():
        e = net(x)
    return training_loss(loss, e.float(), t)


@torch.no_grad()
def evaluate_model(
    model: torch.nn.Module, loader: DataLoader, device: torch.device
) -> tuple[dict[str, float], dict[str, float], float]:
    """Per-class IoU of the model's cell classes and of the ray IRM's, against the ray ILM
    targets; mean loss. Always in float32."""
    from evgrid.evaluate import classify
    from evgrid.mass import from_evidence

    model.eval()
    inter = {"deep": np.zeros(3), "irm": np.zeros(3)}
    union = {"deep": np.zeros(3), "irm": np.zeros(3)}
    losses = []
    for x, t, irm in loader:
        e = model(x.to(device))
        losses.append(float(evidential_loss(e, t.to(device))))
        pred = classify(from_evidence(e.permute(0, 2, 3, 1).cpu().numpy()))
        ref = t.numpy()
        for key, p in (("deep", pred), ("irm", irm.numpy())):
            for k in range(3):
                inter[key][k] += np.count_nonzero((p == k) & (ref == k))
                union[key][k] += np.count_nonzero((p == k) | (ref == k))
    out = {
        key: {
            c: (inter[key][k] / union[key][k] if union[key][k] else math.nan)
            for k, c in enumerate(CLASSES)
        }
        for key in inter
    }
    return out["deep"], out["irm"], float(np.mean(losses)) if losses else math.nan


_FIELDS = (
    ["epoch", "train_loss", "val_loss"]
    + [f"val_{c}" for c in CLASSES]
    + [f"ray_irm_{c}" for c in CLASSES]
    + ["lr", "seconds"]
)


@dataclass
class _Run:
    """One training run's state, as the steps of :func:`train` pass it on."""

    config: TrainConfig
    out: Path
    rank: int
    world: int
    device: torch.device
    model: EvNet
    net: torch.nn.Module
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    precision: Precision
    loader: DataLoader
    val_loader: DataLoader
    sampler: Any = None
    start_epoch: int = 0
    best_score: float = -math.inf
    best_epoch: int = -1
    best: dict = field(default_factory=dict)
    baseline: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    epoch_times: list = field(default_factory=list)
    samples: int = 0


def _loaders(
    config: TrainConfig,
    cache_dir: str | os.PathLike,
    train_scenes: Sequence[str],
    val_scenes: Sequence[str],
    rank: int,
    world: int,
) -> tuple[DataLoader, DataLoader, Any]:
    """Shuffled training batches (a rank's share under torchrun) and validation batches."""
    train_ds = RadarDataset(cache_dir, train_scenes, config.grid, flip=config.flip)
    val_ds = RadarDataset(cache_dir, val_scenes, config.grid, with_irm=True)
    sampler = None
    if world > 1:
        from torch.utils.data.distributed import DistributedSampler

        sampler = DistributedSampler(
            train_ds, num_replicas=world, rank=rank, seed=config.seed, shuffle=True
        )
    g = torch.Generator()
    g.manual_seed(config.seed)
    loader = DataLoader(
        train_ds,
        batch_size=config.batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        num_workers=config.workers,
        worker_init_fn=_worker_init,
        generator=g,
        drop_last=len(train_ds) >= config.batch_size,
        persistent_workers=config.workers > 0,
    )
    val_loader = DataLoader(
        val_ds,
        batch_size=config.batch_size,
        num_workers=config.workers,
        worker_init_fn=_worker_init,
    )
    return loader, val_loader, sampler


def _initial_model(config: TrainConfig, device: torch.device) -> tuple[EvNet, dict]:
    """A fresh Ev-Net, or the parent checkpoint's (``config.init``) -> (model, what the
    checkpoints record of the parent)."""
    if config.init is None:
        return EvNet(config.model).to(device), {}
    ck = load_checkpoint(config.init)
    if ck.model.config != config.model:
        raise ValueError(
            f"TrainConfig.model is {config.model}, but the checkpoint to fine-tune from "
            f"({config.init}) is a {ck.model.config}; build the config with fine_tune_config"
        )
    parent = {
        "path": str(config.init),
        "sha256": hashlib.sha256(Path(config.init).read_bytes()).hexdigest(),
        "epoch": ck.extra.get("epoch"),
        "radar_filter": ck.extra.get("radar_filter"),
        "data": ck.extra.get("data"),
        "val_iou": ck.extra.get("val_iou"),  # on the parent's own validation scenes
    }
    return ck.model.train().to(device), parent


def _schedule(opt: torch.optim.Optimizer, total: int) -> torch.optim.lr_scheduler.LambdaLR:
    warm = max(1, total // 20)

    def lr_factor(step: int) -> float:
        # linear warm-up, then cosine down to 0.02 of lr; from the config, so a resumed run may
        # add epochs
        if step < warm:
            return (step + 1) / warm
        q = min(1.0, (step - warm) / max(1, total - warm))
        return 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * q))

    return torch.optim.lr_scheduler.LambdaLR(opt, lr_factor)


def _resume(run: _Run, state_path: Path) -> None:
    """Continue from the last epoch's state (data only, never code)."""
    st = torch.load(state_path, map_location=run.device, weights_only=True)
    run.model.load_state_dict(st["model"])
    run.opt.load_state_dict(st["optimizer"])
    run.sched.load_state_dict(st["scheduler"])
    if "scaler" in st:
        run.precision.scaler.load_state_dict(st["scaler"])
    run.start_epoch = int(st["epoch"]) + 1
    run.best_score, run.best_epoch = float(st["best_score"]), int(st["best_epoch"])
    run.best = json.loads(st["best"])
    run.baseline = json.loads(st["baseline"])
    torch.set_rng_state(st["rng"])


def _save_state(run: _Run, epoch: int, state_path: Path) -> None:
    st = {
        "model": run.model.state_dict(),
        "optimizer": run.opt.state_dict(),
        "scheduler": run.sched.state_dict(),
        "scaler": run.precision.scaler.state_dict(),
        "epoch": epoch,
        "best_score": run.best_score,
        "best_epoch": run.best_epoch,
        "best": json.dumps(run.best),
        "baseline": json.dumps(run.baseline),
        "rng": torch.get_rng_state(),
    }
    buf = io.BytesIO()
    torch.save(st, buf)
    atomic_write(state_path, lambda f: f.write(buf.getvalue()))


def _train_epoch(run: _Run, epoch: int, on_batch) -> list[float]:
    """One pass over the training batches -> the batches' losses."""
    if run.sampler is not None:
        run.sampler.set_epoch(epoch)
    run.net.train()
    losses = []
    for b, (x, t) in enumerate(run.loader):
        x, t = x.to(run.device), t.to(run.device)
        run.opt.zero_grad(set_to_none=True)
        loss = batch_loss(run.net, x, t, run.precision, run.config.loss)
        run.precision.step(loss, run.opt)
        run.sched.step()
        losses.append(loss.item())
        run.samples += len(x)
        if on_batch and run.rank == 0:
            on_batch(epoch, b + 1, len(run.loader))
    if run.world > 1:
        import torch.distributed as dist

        dist.barrier()
    return losses


def _log_epoch(run: _Run, epoch: int, losses: list[float], seconds: float, writer) -> dict:
    """Validate, add the epoch's row to ``metrics.csv`` (and tensorboard), write the
    ``last`` and ``best`` checkpoints -> the row."""
    config = run.config
    val, irm, val_loss = evaluate_model(run.model, run.val_loader, run.device)
    run.baseline = irm
    row = {
        "epoch": epoch,
        "train_loss": float(np.mean(losses)) if losses else math.nan,
        "val_loss": val_loss,
        **{f"val_{c}": val[c] for c in CLASSES},
        **{f"ray_irm_{c}": irm[c] for c in CLASSES},
        "lr": run.sched.get_last_lr()[0],
        "seconds": seconds,
    }
    _write_metrics(run.out / "metrics.csv", epoch, row)
    if writer:
        for k, v in row.items():
            if k != "epoch":
                writer.add_scalar(k, v, epoch)
    extra = {
        "epoch": epoch,
        "val_iou": val,
        "ray_irm_iou": irm,
        "grid": config.grid.to_dict(),
        "config": config.to_dict(),
        "radar_filter": config.radar_filter.to_dict(),
        "precision": run.precision.name,
        **run.extra,
    }
    save_checkpoint(run.model, run.out / "last.safetensors", extra)
    score = float(np.nanmean([val[c] for c in CLASSES]))
    if score > run.best_score:
        run.best_score, run.best_epoch, run.best = score, epoch, val
        save_checkpoint(run.model, run.out / "best.safetensors", extra)
    return row


def _write_metrics(path: Path, epoch: int, row: dict) -> None:
    """Rewrite ``metrics.csv`` atomically with the rows of the epochs before ``epoch`` (from a
    resumed run's file) and ``row``: an interrupted write never leaves a torn last line, and
    an epoch run again after a resume is not listed twice."""
    rows = []
    if epoch > 0 and path.is_file():
        with open(path, newline="", encoding="utf-8") as f:
            for r in csv.DictReader(f):
                try:
                    if int(r["epoch"]) < epoch:
                        rows.append(r)
                except (KeyError, TypeError, ValueError):  # not a row of ours: dropped
                    continue
    text = io.StringIO()
    w = csv.DictWriter(text, fieldnames=_FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows([*rows, row])
    atomic_write_bytes(path, text.getvalue().encode("utf-8"))


def _tensorboard(out: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(str(out / "tensorboard"))
    except Exception:  # tensorboard is optional; the CSV log always exists
        return None


def _setup(
    config: TrainConfig,
    cache_dir: str | os.PathLike,
    train_scenes: Sequence[str],
    val_scenes: Sequence[str],
    out: Path,
    data: dict | None,
    config_document: dict | None = None,
) -> _Run:
    """Process group, seeds, device, data, model (fresh or the parent's), optimiser."""
    rank, world, local_rank = _dist()
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "config.json", config_document or config.to_dict())
    _seed_all(config.seed + rank)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    loader, val_loader, sampler = _loaders(config, cache_dir, train_scenes, val_scenes, rank, world)
    model, parent = _initial_model(config, device)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[local_rank] if device.type == "cuda" else None
        )
    extra = {"parent": parent} if parent else {}
    if data:
        extra["data"] = data
    return _Run(
        config=config,
        out=out,
        rank=rank,
        world=world,
        device=device,
        model=model,
        net=net,
        opt=opt,
        sched=_schedule(opt, config.epochs * max(1, len(loader))),
        precision=Precision(config.precision, device),
        loader=loader,
        val_loader=val_loader,
        sampler=sampler,
        extra=extra,
    )


def train(
    config: TrainConfig,
    cache_dir: str | os.PathLike,
    train_scenes: Sequence[str],
    val_scenes: Sequence[str],
    out_dir: str | os.PathLike,
    resume: bool = False,
    on_epoch: Callable[[int, dict], None] | None = None,
    on_batch: Callable[[int, int, int], None] | None = None,
    data: dict | None = None,
    config_document: dict | None = None,
) -> TrainResult:
    """Train Ev-Net on cached scenes; write ``config.json`` (which reloads into a
    :class:`TrainConfig` with :func:`evgrid.config.from_dict`), ``metrics.csv``, ``last`` and
    ``best`` checkpoints. ``config.json`` holds ``config_document`` if given (the whole run's
    config, its data included: evgrid.train_run).

    With ``config.init`` the run fine-tunes that checkpoint, and the checkpoints record it
    (``extra["parent"]``: path, SHA-256, epoch, radar filter, data). ``data`` says what the
    samples came from (e.g. the source, the recording rig, the recordings) and is recorded as
    ``extra["data"]``. ``on_epoch(epoch, row)`` gets each epoch's logged row,
    ``on_batch(epoch, batch, n_batches)`` each finished batch (rank 0 only).
    """
    out = Path(out_dir)
    run = _setup(config, cache_dir, train_scenes, val_scenes, out, data, config_document)
    if "parent" in run.extra and run.rank == 0:
        # the parent on these validation scenes, before any step: the score to beat
        val, _, _ = evaluate_model(run.model, run.val_loader, run.device)
        run.extra["parent"]["val_iou_here"] = val
    state_path = out / "resume.pt"
    if resume and state_path.exists():
        _resume(run, state_path)
    writer = _tensorboard(out) if run.rank == 0 else None
    for epoch in range(run.start_epoch, config.epochs):
        t0 = time.perf_counter()
        losses = _train_epoch(run, epoch, on_batch)
        seconds = time.perf_counter() - t0
        run.epoch_times.append(seconds)
        if run.rank != 0:
            continue
        row = _log_epoch(run, epoch, losses, seconds, writer)
        _save_state(run, epoch, state_path)
        if on_epoch:
            on_epoch(epoch, row)
    if writer:
        writer.close()
    return _finish(run, out)


def _finish(run: _Run, out: Path) -> TrainResult:
    """Leave the process group (several processes) and sum up the run."""
    if run.world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()
    seconds = float(np.sum(run.epoch_times)) if run.epoch_times else math.nan
    return TrainResult(
        out,
        run.best_epoch,
        run.best,
        run.baseline,
        float(np.mean(run.epoch_times)) if run.epoch_times else math.nan,
        run.precision.name,
        run.samples / seconds if run.epoch_times else math.nan,
        run.extra.get("parent", {}).get("val_iou_here"),
        run.extra.get("parent", {}).get("val_iou"),
    )
