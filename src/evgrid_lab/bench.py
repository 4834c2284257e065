"""``evgrid bench``: per-component and per-frame timings on one core, as a JSON-ready dict.

Sections of the result:

* ``per_frame``: map a simulated scene with all six maps and with ``fused`` alone; the median
  milliseconds of each component per map update (``step_total``: one whole update), the median
  over ``repeats`` runs. ``warp`` is the ISMs' check and padding; the sampling and the rules
  are in ``fuse`` (one pass, :meth:`evgrid.fusion.MapSet.update`). To compare commits, run
  ``benchmarks/bench_commits.py``, which runs each commit's bench in turns.
* ``deep_irm_parts_ms``: the deep IRM's steps on one buffer of radar sweeps, for each path and
  each installed runtime, with how far the fast path's masses are from the plain path's.
* ``rig``: per-frame time of a 10 Hz lidar + 4 Hz radar rig, every frame a map update.
* ``end_to_end``: frames per second of mapping a whole simulated scene with figures and GIF
  (what ``evgrid map`` costs), simulation included.
* ``kernels_ms``: the algebra and the warp on 512 x 512 grids.
* ``dynamic_score_ms``: one update of the six maps from 512 x 512 ISM grids (every cell
  informative, at 45 degrees: the largest window) with the dynamic score on (with the gate on
  every scored map and the Doppler cue of 64 moving detections) and off, timed in turns
  (medians), and the difference: what the score costs per update, all maps together; and
  ``nav_gate``, what the gated copies of nav's inputs add when nav is mapped. ``scene_on``,
  ``scene_off``, ``scene_cost``: the same for the six maps' pass on the simulated scene (its
  ISMs and moving detections, the score at its defaults), whole runs in turns.
"""

from __future__ import annotations

import math
import os
import platform
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np


def timings_ms(fn, prep=None, repeat: int = 20) -> np.ndarray:
    """Wall times of ``repeat`` calls of ``fn()`` in ms after one warm-up call; ``prep()`` runs
    untimed before each."""
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


def interleaved_timings(fns: dict[str, Any], repeat: int = 20) -> dict[str, np.ndarray]:
    """Wall times in ms of ``repeat`` calls of each ``fns[name]()`` after a warm-up call, taken in
    turns so that all see the same load."""
    for fn in fns.values():
        fn()
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t)
    return {k: np.asarray(v) * 1e3 for k, v in ts.items()}


def interleaved_ms(fns: dict[str, Any], repeat: int = 20) -> dict[str, float]:
    """Median wall time in ms of each ``fns[name]()`` (see :func:`interleaved_timings`)."""
    return {k: float(np.median(v)) for k, v in interleaved_timings(fns, repeat).items()}


def _map_frames(
    frames: Sequence, maps: tuple[str, ...], deep, update_rate_hz: float = 10.0, dynamic=None
) -> tuple[Any, np.ndarray]:
    """Map ``frames`` (``dynamic``: a :class:`~evgrid.fusion.DynamicParams`, else the
    default); return the mapper and each frame's ``process`` time (ms)."""
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper

    config = MapperConfig(maps=maps, update_rate_hz=update_rate_hz)
    if dynamic is not None:
        config = replace(config, dynamic=dynamic)
    mapper = OccupancyMapper(config, deep=deep)
    ts = np.empty(len(frames))
    for k, f in enumerate(frames):
        t = time.perf_counter()
        mapper.process(f)
        ts[k] = time.perf_counter() - t
    return mapper, ts * 1e3


def _per_frame(frames: Sequence, deep, repeats: int) -> dict[str, Any]:
    from evgrid import fusion

    out: dict[str, Any] = {}
    for label, maps in (("six_maps", fusion.MAP_NAMES), ("fused_only", ("fused",))):
        _map_frames(frames[:4], maps, deep)  # warm up: compilation, first allocations
        runs: list[dict[str, float]] = []
        every: dict[str, list[float]] = {}
        walls: list[float] = []
        for _ in range(repeats):
            mapper, ts = _map_frames(frames, maps, deep)
            runs.append(mapper.timing_summary())
            for k, v in mapper.timings.items():
                every.setdefault(k, []).extend(v)
            walls.append(float(ts.sum()) * 1e-3)
        keys = runs[0].keys()
        out[label] = {
            "components_ms": {k: float(np.median([r[k] for r in runs])) for k in keys},
            # the fastest tenth of the updates: what a quiet core gives on a shared machine
            "components_ms_p10": {k: float(np.percentile(every[k], 10)) for k in keys},
            "step_total_ms_runs": [r["step_total"] for r in runs],
            "updates": mapper.n_updates,
            "frames": len(frames),
            "frames_per_second": len(frames) / float(np.median(walls)),
        }
    return out


def _deep_parts(deep, sweeps, ego_pose, now_us: int, repeat: int) -> dict[str, Any]:
    """The deep IRM's steps, each path and runtime, on one buffer of sweeps; exactness against the
    plain path."""
    from evgrid.ism.deep import evidence_to_masses, radar_image
    from evgrid.ism.runtime import make_runtime, ort_available

    grid = deep.grid
    n_det = int(sum(len(s.points) for s in sweeps))
    image = radar_image(sweeps, ego_pose, grid, now_us, deep.params)
    plain = deep.predict_image(image)
    pooled = deep.pooled_input(sweeps, ego_pose, now_us).copy()
    m = grid.n_cells // deep.pool
    names = ["torch"] + (["onnxruntime"] if ort_available() else [])
    runtimes = {
        n: deep.runtime
        if deep.runtime.name == n
        else make_runtime(deep.model, (len(pooled[0]), m, m), n, deep.threads)
        for n in names
    }
    ev = deep.runtime(pooled)
    ts = interleaved_timings(
        {
            "old: radar_image": lambda: radar_image(sweeps, ego_pose, grid, now_us, deep.params),
            "old: predict_image (whole Ev-Net on torch, from_evidence)": lambda: deep.predict_image(
                image
            ),
            "new: pooled_input": lambda: deep.pooled_input(sweeps, ego_pose, now_us),
            **{f"new: net on {n}": (lambda r=r: r(pooled)) for n, r in runtimes.items()},
            "new: upsample_and_masses": lambda: evidence_to_masses(ev, grid),
            "new: predict (all)": lambda: deep.predict(sweeps, ego_pose, now_us),
        },
        repeat,
    )
    res: dict[str, Any] = {
        "detections": n_det,
        "runtime": deep.runtime.name,
        "ms": {k: float(np.median(v)) for k, v in ts.items()},
        "ms_min": {k: float(v.min()) for k, v in ts.items()},
        "exactness_vs_plain": {},
    }
    for n, run in runtimes.items():
        masses = evidence_to_masses(run(pooled), grid)
        res["exactness_vs_plain"][n] = {
            "max_abs_mass_diff": float(np.abs(masses - plain).max()),
            "class_changes": int((masses.argmax(-1) != plain.argmax(-1)).sum()),
        }
    return res


def _rig(deep, seed: int, duration_s: float) -> dict[str, Any]:
    """Per-frame time of a 10 Hz lidar + 4 Hz radar rig, every frame a map update."""
    from evgrid import fusion
    from evgrid_sim import SimConfig, simulate_scene
    from evgrid_sim.config import LidarConfig, RadarConfig

    cfg = SimConfig(
        duration_s=duration_s,
        keyframe_every=5,
        lidar=LidarConfig(rate_hz=10.0),
        radar=RadarConfig(rate_hz=4.0),
    )
    frames = list(simulate_scene(seed, cfg))
    out: dict[str, Any] = {"lidar_hz": 10.0, "radar_hz": 4.0, "frames": len(frames)}
    for label, maps in (("six_maps", fusion.MAP_NAMES), ("fused_only", ("fused",))):
        _map_frames(frames[:3], maps, deep)
        mapper, ts = _map_frames(frames, maps, deep)
        out[label] = {
            "frame_ms_median": float(np.median(ts)),
            "frame_ms_p90": float(np.percentile(ts, 90)),
            "frame_ms_mean": float(ts.mean()),
            "updates": mapper.n_updates,
            "real_time_factor": float(len(frames) / 10.0 / (ts.sum() * 1e-3)),
        }
    return out


def _end_to_end(deep, seed: int, duration_s: float) -> dict[str, Any]:
    """Frames per second of mapping a simulated scene (simulation, maps, scores, figures, GIF)."""
    from evgrid.runs import map_scene
    from evgrid_sim import SimConfig, simulate_scene

    scene = simulate_scene(seed, SimConfig(duration_s=duration_s))
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        res = map_scene(scene, os.path.join(tmp, "scene"), deep=deep, name=scene.name)
        wall = time.perf_counter() - t
    frames = res.metrics["frames"]
    return {
        "scene_s": duration_s,
        "frames": frames,
        "wall_s": wall,
        "frames_per_second": frames / wall,
        "mapping_s": res.metrics["seconds"],
        "figures_and_gif_s": wall - res.metrics["seconds"],
    }


#: Moving radar detections per update in the dynamic score's timing: the simulator's five radars
#: give about 50 an update faster than 1 m/s (clutter included), up to about 80.
BENCH_MOVING_DETECTIONS = 64


def bench_moving_detections(grid, pose) -> np.ndarray:
    """The moving detections of the dynamic score's worst case: ``BENCH_MOVING_DETECTIONS``
    spread over 90 % of the local grid at ``pose``, at 5 m/s, seen from the ego's position
    (``(k, 5)``, as :func:`evgrid.doppler.moving_detections` gives)."""
    rng = np.random.default_rng(1)
    h = 0.9 * grid.half_extent
    local = rng.uniform(-h, h, (BENCH_MOVING_DETECTIONS, 2))
    radar = np.broadcast_to((pose.x, pose.y), local.shape)
    return np.column_stack([pose.apply(local), np.full(len(local), 5.0), radar])


def _dynamic_cost(grid, a, b, pose, repeat: int) -> dict[str, float]:
    """Milliseconds of one update of the six maps with the dynamic score on (the conflict, the
    gate on every scored map, and the Doppler cue of ``BENCH_MOVING_DETECTIONS`` moving
    detections in the window) and off, in turns, and the score's cost (their difference);
    ``nav_gate``: with ``nav`` too, the cost of the gated copies of its inputs (gate_nav on and
    off, the score on)."""
    from evgrid import fusion

    isms = {"ray_ilm": a, "ray_irm": b, "deep_irm": a}
    moving = bench_moving_detections(grid, pose)
    on = fusion.DynamicParams(gate_maps=True)
    sets = {
        "on": (fusion.MapSet(grid, dynamic=on), moving),
        "off": (fusion.MapSet(grid, dynamic=fusion.DynamicParams(enabled=False)), None),
    }
    with_nav = (*fusion.MAP_NAMES, fusion.NAV_MAP)
    sets |= {
        f"nav_gate_{k}": (
            fusion.MapSet(grid, names=with_nav, dynamic=fusion.DynamicParams(gate_nav=k == "on")),
            moving,
        )
        for k in ("on", "off")
    }
    ms = interleaved_ms(
        {k: (lambda s=s, m=m: s.update(pose, isms, m)) for k, (s, m) in sets.items()}, repeat
    )
    return {
        "on": ms["on"],
        "off": ms["off"],
        "cost": ms["on"] - ms["off"],
        "nav_gate": ms["nav_gate_on"] - ms["nav_gate_off"],
    }


def _dynamic_scene_cost(frames: Sequence, deep, repeats: int) -> dict[str, float]:
    """The six maps' pass (``fuse``, ms per update: the median of each run's median) on the
    bench scene with the dynamic score at its defaults (conflict, Doppler cue) and off, whole
    runs in turns, and the difference: what the score costs on a real drive."""
    from evgrid import fusion

    med: dict[str, list[float]] = {"on": [], "off": []}
    for _ in range(repeats):
        for k in med:
            d = fusion.DynamicParams(enabled=k == "on")
            mapper, _ = _map_frames(frames, fusion.MAP_NAMES, deep, dynamic=d)
            med[k].append(float(np.median(mapper.timings["fuse"])))
    on, off = float(np.median(med["on"])), float(np.median(med["off"]))
    return {"scene_on": on, "scene_off": off, "scene_cost": on - off}


#: What the per-frame figures are.
_PER_FRAME_NOTE = (
    "components_ms are medians per map update (the median over runs of each run's median), "
    "components_ms_p10 the 10th percentile over all updates; step_total is one whole update of "
    "all listed maps"
)


def _deep_parts_at_scene_end(frames: list[Any], deep: Any, timing_repeat: int) -> dict[str, Any]:
    """The deep IRM's steps timed on the sweeps buffered at the scene's last frame."""
    mapper, _ = _map_frames(frames, ("fused",), deep)
    sweeps = mapper.buffer.sweeps(deep.params.n_sweeps)
    return _deep_parts(deep, sweeps, frames[-1].ego_pose, frames[-1].timestamp, timing_repeat)


def _grid_costs(
    grid: Any, frames: list[Any], deep: Any, repeats: int, rep: int
) -> tuple[dict[str, float], dict[str, Any]]:
    """The kernels' medians on random mass grids (ms, ``rep`` calls each), and the dynamic
    score's cost on those grids and on the scene's frames."""
    from evgrid import fusion, mass
    from evgrid.geometry import SE2
    from evgrid.grid import Warper

    rng = np.random.default_rng(0)
    a = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    b = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    cur, out = a.copy(), np.empty_like(a)
    params = fusion.FusionParams()
    warper = Warper(grid)
    one_map = fusion.MapSet(grid, params, names=("deep_disc",))
    pose = SE2(3.3, -1.7, math.radians(45))  # 45 degrees: the largest window
    kernels = {
        "dempster_512": median_ms(lambda: mass.dempster(a, b, out), repeat=rep),
        "deep_disc_update_512": median_ms(
            lambda: fusion.update_deep_disc(cur, b, params), repeat=rep
        ),
        "fused_update_512": median_ms(lambda: fusion.update_fused(cur, b, a, params), repeat=rep),
        "warp_512_yaw45": median_ms(lambda: warper.warp(a, pose), repeat=rep),
        "warp_and_deep_disc_fuse_512_yaw45": median_ms(
            lambda: one_map.update(pose, {"deep_irm": a}), repeat=rep
        ),
    }
    dynamic = _dynamic_cost(grid, a, b, pose, rep) | _dynamic_scene_cost(frames, deep, repeats)
    return kernels, dynamic


def _machine() -> dict[str, Any]:
    """The processor, its cores and the load the timings ran under."""
    return {
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "threads": 1,
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def run_bench(
    duration_s: float = 6.0,
    checkpoint: str | None = None,
    repeats: int = 3,
    rig_s: float | None = None,
    end_to_end_s: float | None = None,
    timing_repeat: int = 20,
) -> dict[str, Any]:
    """Time the mapper on simulated scenes and the kernels on 512 x 512 grids, one core (see the
    module doc).

    ``rig_s`` and ``end_to_end_s`` are the lengths of the rig and end-to-end scenes (default
    ``duration_s``; 0 skips; a whole nuScenes-like scene is ``end_to_end_s=20``);
    ``timing_repeat`` calls time each kernel and each deep IRM step.
    """
    import numba
    import torch

    from evgrid.geometry import GridSpec
    from evgrid.ism.deep import DeepIrm
    from evgrid_sim import SimConfig, simulate_scene

    numba.set_num_threads(1)
    torch.set_num_threads(1)
    grid = GridSpec()
    deep = DeepIrm(checkpoint, grid, threads=1)
    scene = simulate_scene(4, SimConfig(duration_s=duration_s))
    frames = list(scene)

    runs = _per_frame(frames, deep, repeats)
    parts = _deep_parts_at_scene_end(frames, deep, timing_repeat)

    kernels, dynamic = _grid_costs(grid, frames, deep, repeats, timing_repeat)
    result: dict[str, Any] = {
        "dynamic_score_ms": dynamic,
        "machine": _machine(),
        "scene": {"name": scene.name, "duration_s": duration_s},
        "checkpoint": str(deep.checkpoint),
        "runtime": deep.runtime.name,
        "per_frame": runs,
        "deep_irm_parts_ms": parts,
        "kernels_ms": kernels,
        "note": _PER_FRAME_NOTE,
    }
    for key, length, run in (("rig", rig_s, _rig), ("end_to_end", end_to_end_s, _end_to_end)):
        length = duration_s if length is None else length
        if length > 0:
            result[key] = run(deep, 4, length)
    return result
