"""Benchmark of the training-sample cache: samples per second built serially (one worker, in
this process) and in parallel (a pool of workers through evgrid.engine), on simulated scenes.

Run: ``PYTHONPATH=src python benchmarks/bench_cache.py [--scenes 4] [--duration 4]
[--workers 2] [--engine local]``. Prints, does not assert; the figures go to
docs/training.md with the commit and the CPU they came from. Every run builds a fresh cache in
a temporary folder, and checks that the parallel shards equal the serial ones.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # one core a worker, as the engine's jobs

import numpy as np  # noqa: E402
from harness import machine  # noqa: E402

from evgrid.learn.train import TrainConfig, build_cache, cached_scenes  # noqa: E402
from evgrid.sources import SimSource  # noqa: E402


def _timed(source: SimSource, config: TrainConfig, root: Path, **kw) -> tuple[float, int]:
    t0 = time.perf_counter()
    build_cache(source, root, config, **kw)
    seconds = time.perf_counter() - t0
    return seconds, sum(cached_scenes(root, config).values())


def _same(a: Path, b: Path, names: list[str]) -> bool:
    for name in names:
        for f in sorted((a / name).glob("*.npy")):
            if not np.array_equal(np.load(f), np.load(b / name / f.name)):
                return False
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--engine", default="local")
    ap.add_argument("--frame-stride", type=int, default=4)
    args = ap.parse_args()
    source = SimSource(tuple(range(100, 100 + args.scenes)), duration_s=args.duration)
    config = TrainConfig(frame_stride=args.frame_stride)
    with tempfile.TemporaryDirectory() as d:
        serial, par = Path(d) / "serial", Path(d) / "parallel"
        s_time, n = _timed(source, config, serial, workers=1, engine="local")
        p_time, n_par = _timed(source, config, par, workers=args.workers, engine=args.engine)
        same = n == n_par and _same(serial, par, source.names())
    print(
        json.dumps(
            {
                "machine": machine(),
                "scenes": args.scenes,
                "duration_s": args.duration,
                "samples": n,
                "serial_samples_per_s": round(n / s_time, 2),
                f"{args.engine}_{args.workers}_workers_samples_per_s": round(n / p_time, 2),
                "speed_up": round(s_time / p_time, 2),
                "parallel_shards_equal_serial": same,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
