"""``evgrid bench``: per-component and per-frame timings on one core, as a JSON-ready dict."""

from __future__ import annotations

import math
import os
import platform
import time
from typing import Any

import numpy as np


def timings_ms(fn, prep=None, repeat: int = 20) -> np.ndarray:
    """Wall times of ``repeat`` calls of ``fn()`` in ms after one warm-up call; ``prep()`` runs untimed before each."""
    if prep:
        prep()
    fn()
    ts = []
    for _ in range(repeat):
        if prep:
            prep()
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return np.asarray(ts) * 1e3


def median_ms(fn, prep=None, repeat: int = 20) -> float:
    """Median wall time of ``fn()`` in ms (see :func:`timings_ms`)."""
    return float(np.median(timings_ms(fn, prep, repeat)))


def run_bench(duration_s: float = 6.0, checkpoint: str | None = None) -> dict[str, Any]:
    """Map a simulated scene with all six maps and with ``fused`` alone; time kernels on 512 x 512 grids."""
    import numba
    import torch

    from evgrid import fusion, mass
    from evgrid.data import SimConfig, simulate_scene
    from evgrid.geometry import SE2, GridSpec
    from evgrid.grid import Warper
    from evgrid.ism.deep import DeepIrm
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper

    numba.set_num_threads(1)
    torch.set_num_threads(1)
    grid = GridSpec()
    deep = DeepIrm(checkpoint, grid, threads=1)
    scene = simulate_scene(4, SimConfig(duration_s=duration_s))
    frames = list(scene)

    runs = {}
    for label, maps in (("six_maps", fusion.MAP_NAMES), ("fused_only", ("fused",))):
        mapper = OccupancyMapper(MapperConfig(maps=maps), deep=deep)
        for f in frames[:4]:  # warm up (compilation, first allocations)
            mapper.process(f)
        mapper = OccupancyMapper(MapperConfig(maps=maps), deep=deep)
        t = time.perf_counter()
        for f in frames:
            mapper.process(f)
        wall = time.perf_counter() - t
        runs[label] = {
            "components_ms": mapper.timing_summary(),
            "updates": mapper.n_updates,
            "frames": len(frames),
            "frames_per_second": len(frames) / wall,
            "updates_per_second": mapper.n_updates / wall,
        }

    rng = np.random.default_rng(0)
    a = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    b = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    cur, out = a.copy(), np.empty_like(a)
    params = fusion.FusionParams()
    warper = Warper(grid)
    one_map = fusion.MapSet(grid, params, names=("deep_disc",))
    pose = SE2(3.3, -1.7, math.radians(45))  # 45 degrees: the largest window
    kernels = {
        "dempster_512": median_ms(lambda: mass.dempster(a, b, out)),
        "deep_disc_update_512": median_ms(lambda: fusion.update_deep_disc(cur, b, params)),
        "fused_update_512": median_ms(lambda: fusion.update_fused(cur, b, a, params)),
        "warp_512_yaw45": median_ms(lambda: warper.warp(a, pose)),
        "warp_and_deep_disc_fuse_512_yaw45": median_ms(lambda: one_map.update(pose, {"deep_irm": a})),
    }
    return {
        "machine": {"processor": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "threads": 1},
        "scene": {"name": scene.name, "duration_s": duration_s},
        "checkpoint": str(deep.checkpoint),
        "per_frame": runs,
        "kernels_ms": kernels,
        "note": "components_ms are medians per map update; step_total is one whole update of all listed maps",
    }
