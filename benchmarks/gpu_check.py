"""The GPU check of training (issue 24): one epoch of Ev-Net on simulated scenes on the CUDA
GPU in mixed precision, samples per second, and the loss against a float32 CPU run on the
same batches from the same initial weights.

Run through ``benchmarks/gpu_check.sh`` (a few minutes on a machine with one CUDA GPU). On a
machine without a CUDA GPU it says so and exits with status 3, measuring nothing. Exits 1
when the GPU's loss is not finite or strays from the CPU's by more than ``--tolerance``
(relative, on the first batch, before the two runs' weights part).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from evgrid.ism.evnet import EvNet, load_checkpoint
from evgrid.learn.train import (
    Precision,
    RadarDataset,
    TrainConfig,
    batch_loss,
    build_cache,
    fine_tune_config,
)
from evgrid.sources import SimSource


def _epoch(model, loader, device: torch.device, precision: Precision, lr: float) -> dict:
    """One pass over ``loader`` -> per-batch losses, samples per second."""
    model = model.to(device).train()
    opt = torch.optim.AdamW(model.parameters(), lr=lr)
    losses, n = [], 0
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for x, t in loader:
        x, t = x.to(device, non_blocking=True), t.to(device, non_blocking=True)
        opt.zero_grad(set_to_none=True)
        loss = batch_loss(model, x, t, precision)
        precision.step(loss, opt)
        losses.append(loss.item())
        n += len(x)
    if device.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    return {"losses": losses, "samples_per_s": n / seconds, "seconds": seconds, "samples": n}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--precision", default="auto", choices=("auto", "bf16", "fp16", "fp32"))
    ap.add_argument("--cpu-batches", type=int, default=6, help="batches the CPU run repeats")
    ap.add_argument("--tolerance", type=float, default=0.05)
    ap.add_argument("--init", default=None, help="start from this checkpoint (default: random)")
    ap.add_argument(
        "--device",
        default="cuda",
        choices=("cuda", "cpu"),
        help="cpu: run the check's code on the CPU (tests the script; measures no GPU)",
    )
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        print(
            f"gpu_check: no CUDA GPU on this machine (torch {torch.__version__}, CUDA build "
            f"{torch.version.cuda}); nothing measured",
            file=sys.stderr,
        )
        return 3
    device = torch.device(args.device)
    workers = max(1, (os.cpu_count() or 2) - 1)
    config = TrainConfig(
        batch_size=args.batch_size, cache_workers=workers, precision=args.precision, flip=False
    )
    if args.init:
        config = fine_tune_config(config, args.init)
    source = SimSource(tuple(range(200, 200 + args.scenes)), duration_s=args.duration)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        names = build_cache(source, Path(d), config)
        cache_s = time.perf_counter() - t0
        ds = RadarDataset(Path(d), names, config.grid)

        def loader(n_batches: int | None = None) -> DataLoader:
            sub = (
                ds
                if n_batches is None
                else torch.utils.data.Subset(ds, range(min(len(ds), n_batches * args.batch_size)))
            )
            return DataLoader(
                sub,
                batch_size=args.batch_size,
                num_workers=workers,
                pin_memory=device.type == "cuda",
            )

        torch.manual_seed(0)
        parent = load_checkpoint(args.init).model if args.init else EvNet(config.model)
        start = parent.state_dict()

        def model() -> EvNet:
            m = EvNet(config.model)
            m.load_state_dict(start)
            return m

        _epoch(model(), loader(2), device, Precision(args.precision, device), config.lr)  # warm
        gpu = _epoch(model(), loader(), device, Precision(args.precision, device), config.lr)
        cpu = _epoch(
            model(),
            loader(args.cpu_batches),
            torch.device("cpu"),
            Precision("fp32", torch.device("cpu")),
            config.lr,
        )
    precision = Precision(args.precision, device)
    k = min(len(cpu["losses"]), len(gpu["losses"]))
    first = abs(gpu["losses"][0] - cpu["losses"][0]) / abs(cpu["losses"][0])
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    report = {
        "commit": commit,
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "precision": precision.name,
        "samples": gpu["samples"],
        "cache_seconds": round(cache_s, 1),
        "device_samples_per_s": round(gpu["samples_per_s"], 1),
        "cpu_samples_per_s": round(cpu["samples_per_s"], 2),
        "cpu_threads": torch.get_num_threads(),
        "loss_device_first_batches": [round(v, 5) for v in gpu["losses"][:k]],
        "loss_cpu_first_batches": [round(v, 5) for v in cpu["losses"][:k]],
        "first_batch_relative_difference": round(first, 5),
        "device_epoch_mean_loss": round(sum(gpu["losses"]) / len(gpu["losses"]), 5),
    }
    print(json.dumps(report, indent=1))
    finite = all(math.isfinite(v) for v in gpu["losses"])
    if not finite or first > args.tolerance:
        print(
            f"gpu_check: FAILED (loss finite: {finite}, first-batch difference {first:.3g} > "
            f"{args.tolerance})",
            file=sys.stderr,
        )
        return 1
    print("gpu_check: ok", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
