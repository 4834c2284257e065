"""Training Ev-Net on scenes (simulated or nuScenes): dataset cache, training loop, validation.

Samples (paper sec. V-C, docs/decisions.md#ev-net-targets-and-loss): at every ``frame_stride``-th lidar frame, the
input is the radar detection image of the last ``n_sweeps`` sweeps of each radar in the
current ego frame, the target the ray ILM of the same frame (m_o > 0 occupied, m_f > 0 free,
else unknown). Inputs are cached sparse (detection tables, a few kB a sample) and rasterised
in the DataLoader workers; targets as uint8 rasters, memory-mapped.

The radar detections pass ``TrainConfig.radar_filter`` and the lidar sweeps
``TrainConfig.self_returns`` exactly as in mapping (:class:`~evgrid.mapper.OccupancyMapper`);
the checkpoint records the radar filter (metadata ``extra["radar_filter"]``) so that mapping
with another one warns.

Runs unchanged under ``torchrun --nproc_per_node=K`` (DistributedDataParallel, NCCL on GPUs,
gloo on CPUs); rank 0 validates, logs and writes checkpoints.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import random
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from evgrid.classes import FREE, OCCUPIED, UNKNOWN
from evgrid.data.frame import Frame
from evgrid.data.radar_filter import RadarFilter
from evgrid.data.radar_variants import RadarRanges
from evgrid.evaluate import CLASSES
from evgrid.geometry import GridSpec
from evgrid.io import atomic_write, write_json
from evgrid.ism.deep import CHANNELS, RadarImageParams, detections_to_image, radar_detections
from evgrid.ism.evnet import EvNet, EvNetConfig, save_checkpoint
from evgrid.ism.self_returns import SelfReturnParams
from evgrid.learn.loss import evidential_loss
from evgrid.validation import check_int, check_number

__all__ = [
    "TrainConfig",
    "ilm_classes",
    "scene_samples",
    "build_cache",
    "RadarDataset",
    "train",
    "TrainResult",
]


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides a training run; saved beside its results as ``config.json``."""

    epochs: int = 20
    batch_size: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    workers: int = 2
    frame_stride: int = 4
    flip: bool = True
    threads: int = 0  # torch intra-op threads; 0 = torch's default
    grid: GridSpec = field(default_factory=GridSpec)
    model: EvNetConfig = field(default_factory=lambda: EvNetConfig(in_channels=len(CHANNELS)))
    image: RadarImageParams = field(default_factory=RadarImageParams)
    radar_filter: RadarFilter = field(default_factory=RadarFilter)  # as in mapping
    self_returns: SelfReturnParams = field(
        default_factory=SelfReturnParams
    )  # the targets' ray ILM, as in mapping
    #: Simulated data only: a radar drawn per scene from these ranges (None: the calibrated radar).
    radar_ranges: RadarRanges | None = None

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "frame_stride"):
            check_int(self, name, min=1)
        check_int(self, "workers", min=0)
        check_number(self, "lr", min=0.0, min_open=True)
        if self.model.in_channels != len(CHANNELS):
            raise ValueError(
                f"the model must take {len(CHANNELS)} input channels ({CHANNELS}), got {self.model.in_channels}"
            )

    def to_dict(self) -> dict:
        """Plain-JSON form (evgrid.serial, the serialiser of every parameter dataclass)."""
        from evgrid.serial import to_dict

        return to_dict(self)

    def data_key(self) -> str:
        """Hash of the settings that decide the cached samples."""
        key = json.dumps(
            {
                "grid": self.grid.to_dict(),
                "image": asdict(self.image),
                "stride": self.frame_stride,
                "v": 2,
                "radar_filter": self.radar_filter.to_dict(),
                "self_returns": asdict(self.self_returns),
                "radar_ranges": self.radar_ranges.to_dict() if self.radar_ranges else None,
            },
            sort_keys=True,
        )
        return hashlib.sha1(key.encode()).hexdigest()[:12]


# --- samples ------------------------------------------------------------------------------------


def ilm_classes(masses: np.ndarray) -> np.ndarray:
    """Target classes from ray ILM masses: m_o > 0 OCCUPIED, else m_f > 0 FREE, else UNKNOWN.

    See docs/decisions.md#ev-net-targets-and-loss.
    """
    out = np.full(masses.shape[:-1], UNKNOWN, dtype=np.uint8)
    out[masses[..., 0] > 0] = FREE
    out[masses[..., 1] > 0] = OCCUPIED
    return out


def scene_samples(
    frames: Iterable[Frame], config: TrainConfig, with_irm: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """Yield ``(detections, target classes, ray-IRM classes or None)`` for every ``frame_stride``-th frame."""
    from evgrid.data.sweeps import RadarBuffer
    from evgrid.ism import ray_ilm, ray_irm
    from evgrid.ism.self_returns import SelfReturnFilter

    buffer = RadarBuffer(config.image.n_sweeps)
    self_returns = SelfReturnFilter(config.self_returns)
    for k, frame in enumerate(frames):
        for sweep in frame.radar_sweeps():
            buffer.push(config.radar_filter(sweep)[0])  # the mapper's filter, before its buffer
        if k % config.frame_stride:
            continue
        sweeps = buffer.sweeps()
        det = radar_detections(sweeps, frame.ego_pose, frame.timestamp, config.image)
        target = ilm_classes(ray_ilm(self_returns(frame.lidar), grid=config.grid))
        irm = ilm_classes(ray_irm(sweeps, frame.ego_pose, grid=config.grid)) if with_irm else None
        yield det, target, irm


def _scene_files(root: Path, name: str) -> dict[str, Path]:
    return {k: root / f"{name}.{k}.npy" for k in ("det", "offsets", "target", "irm")} | {
        "done": root / f"{name}.done.json"
    }


def build_cache(
    scenes: Iterable,
    root: str | os.PathLike,
    config: TrainConfig,
    with_irm: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[str]:
    """Write the samples of each scene (an iterable of Frames with a ``name``) under ``root``; skip cached scenes.

    Returns the scene names. A scene's files count only once its ``.done.json`` is written
    (last), so an interrupted build is redone, never half-read.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    names = []
    for scene in scenes:
        name = str(scene.name)
        names.append(name)
        files = _scene_files(root, name)
        if files["done"].exists() and (not with_irm or files["irm"].exists()):
            if progress:
                progress(name)
            continue
        dets, targets, irms = [], [], []
        for det, target, irm in scene_samples(scene, config, with_irm):
            dets.append(det)
            targets.append(target)
            if irm is not None:
                irms.append(irm)
        if not dets:
            raise ValueError(f"scene {name!r} gave no samples (is it empty?)")
        offsets = np.cumsum([0] + [len(d) for d in dets]).astype(np.int64)
        arrays = {
            "det": np.concatenate(dets).astype(np.float32),
            "offsets": offsets,
            "target": np.stack(targets),
        }
        if with_irm:
            arrays["irm"] = np.stack(irms)
        for key, arr in arrays.items():
            atomic_write(files[key], lambda f, a=arr: np.save(f, a))
        write_json(files["done"], {"samples": len(dets)})
        if progress:
            progress(name)
    return names


class RadarDataset(Dataset):
    """Cached samples of some scenes: ``(input (C, n, n) float32, target (n, n) int64)`` pairs."""

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
            files = _scene_files(self.root, name)
            if not files["done"].exists():
                raise FileNotFoundError(
                    f"scene {name!r} is not cached under {self.root} (run build_cache first)"
                )
            offsets = np.load(files["offsets"])
            entry = {
                "det": files["det"],
                "offsets": offsets,
                "target": files["target"],
                "irm": files["irm"],
            }
            self._scenes.append(entry)
            self._index += [(si, k) for k in range(len(offsets) - 1)]
        self._open: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._index)

    def _arrays(self, si: int) -> dict[str, np.ndarray]:
        # memory-mapped lazily in each worker process
        if si not in self._open:
            e = self._scenes[si]
            d = {
                "det": np.load(e["det"], mmap_mode="r"),
                "target": np.load(e["target"], mmap_mode="r"),
            }
            if self.with_irm:
                d["irm"] = np.load(e["irm"], mmap_mode="r")
            self._open[si] = d
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


@torch.no_grad()
def evaluate_model(
    model: torch.nn.Module, loader: DataLoader, device: torch.device
) -> tuple[dict[str, float], dict[str, float], float]:
    """Per-class IoU of the model's cell classes and of the ray IRM's, against the ray ILM targets; mean loss."""
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


def train(
    config: TrainConfig,
    cache_dir: str | os.PathLike,
    train_scenes: Sequence[str],
    val_scenes: Sequence[str],
    out_dir: str | os.PathLike,
    resume: bool = False,
    on_epoch: Callable[[int, dict], None] | None = None,
    on_batch: Callable[[int, int, int], None] | None = None,
    config_document: dict | None = None,
) -> TrainResult:
    """Train Ev-Net on cached scenes; write ``config.json``, ``metrics.csv``, ``last`` and ``best`` checkpoints.

    ``config.json`` holds ``config_document`` if given (the whole run's config, its data
    included: evgrid.train_run), else ``config.to_dict()``.

    ``on_epoch(epoch, row)`` gets each epoch's logged row, ``on_batch(epoch, batch, n_batches)``
    each finished batch (rank 0 only).
    """
    rank, world, local_rank = _dist()
    out = Path(out_dir)
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(
            out / "config.json",
            lambda f: f.write(json.dumps(config_document or config.to_dict(), indent=2).encode()),
        )
    _seed_all(config.seed + rank)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")

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

    model = EvNet(config.model).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    total = config.epochs * max(1, len(loader))
    warm = max(1, total // 20)

    def lr_factor(step: int) -> float:
        # linear warm-up, then cosine to 2 % of lr; from the config, so a resumed run may add epochs
        if step < warm:
            return (step + 1) / warm
        q = min(1.0, (step - warm) / max(1, total - warm))
        return 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * q))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor)
    start_epoch, best_score, best_epoch, best, baseline = 0, -math.inf, -1, {}, {}
    state_path = out / "resume.pt"
    if resume and state_path.exists():
        st = torch.load(state_path, map_location=device, weights_only=True)  # data only, never code
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        start_epoch, best_score, best_epoch = (
            int(st["epoch"]) + 1,
            float(st["best_score"]),
            int(st["best_epoch"]),
        )
        best = json.loads(st["best"])
        baseline = json.loads(st["baseline"])
        torch.set_rng_state(st["rng"])
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[local_rank] if device.type == "cuda" else None
        )

    writer = None
    if rank == 0:
        try:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(out / "tensorboard"))
        except Exception:  # tensorboard is optional; the CSV log always exists
            writer = None
    csv_path = out / "metrics.csv"
    fields = (
        ["epoch", "train_loss", "val_loss"]
        + [f"val_{c}" for c in CLASSES]
        + [f"ray_irm_{c}" for c in CLASSES]
        + ["lr", "seconds"]
    )
    epoch_times = []
    for epoch in range(start_epoch, config.epochs):
        if sampler is not None:
            sampler.set_epoch(epoch)
        net.train()
        t0 = time.perf_counter()
        losses = []
        for b, (x, t) in enumerate(loader):
            x, t = x.to(device), t.to(device)
            opt.zero_grad(set_to_none=True)
            loss = evidential_loss(net(x), t)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            if on_batch and rank == 0:
                on_batch(epoch, b + 1, len(loader))
        if world > 1:
            import torch.distributed as dist

            dist.barrier()
        seconds = time.perf_counter() - t0
        epoch_times.append(seconds)
        if rank != 0:
            continue
        val, irm, val_loss = evaluate_model(model, val_loader, device)
        baseline = irm
        row = {
            "epoch": epoch,
            "train_loss": float(np.mean(losses)) if losses else math.nan,
            "val_loss": val_loss,
            **{f"val_{c}": val[c] for c in CLASSES},
            **{f"ray_irm_{c}": irm[c] for c in CLASSES},
            "lr": sched.get_last_lr()[0],
            "seconds": seconds,
        }
        new = not csv_path.exists() or epoch == 0
        with open(csv_path, "w" if new else "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            if new:
                w.writeheader()
            w.writerow(row)
        if writer:
            for k, v in row.items():
                if k != "epoch":
                    writer.add_scalar(k, v, epoch)
        score = float(np.nanmean([val[c] for c in CLASSES]))
        extra = {
            "epoch": epoch,
            "val_iou": val,
            "ray_irm_iou": irm,
            "grid": config.grid.to_dict(),
            "config": config.to_dict(),
            "radar_filter": config.radar_filter.to_dict(),
        }
        save_checkpoint(model, out / "last.safetensors", extra)
        if score > best_score:
            best_score, best_epoch, best = score, epoch, val
            save_checkpoint(model, out / "best.safetensors", extra)
        st = {
            "model": model.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "epoch": epoch,
            "best_score": best_score,
            "best_epoch": best_epoch,
            "best": json.dumps(best),
            "baseline": json.dumps(baseline),
            "rng": torch.get_rng_state(),
        }
        import io

        buf = io.BytesIO()
        torch.save(st, buf)
        atomic_write(state_path, lambda f: f.write(buf.getvalue()))
        if on_epoch:
            on_epoch(epoch, row)
    if writer:
        writer.close()
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()
    return TrainResult(
        out, best_epoch, best, baseline, float(np.mean(epoch_times)) if epoch_times else math.nan
    )
