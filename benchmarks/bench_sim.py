"""Benchmark of the simulator: time per 20 s scene (one core), per sensor, and sensor statistics.

Run: ``PYTHONPATH=src python benchmarks/bench_sim.py [--seeds 0 6] [--duration 20]``.
Prints, does not assert. The target is <= 30 s for a 20 s scene with all sensors.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from evgrid.data.frame import RADAR_CHANNELS  # noqa: E402
from evgrid_sim import RADAR_CLUTTER, RADAR_GHOST, SimConfig, simulate_scene  # noqa: E402


def _occupancy_stats(scene, frame) -> tuple[float, float, float]:
    """(band points on true obstacles, obstacle outline cells seen, occupied cells seen)."""
    g = scene.config.grid
    occ = (frame.occupancy > 0).astype(np.uint8)
    p = frame.lidar.sensor_to_ego.apply(frame.lidar.points[:, :3])
    band = (p[:, 2] > scene.config.occupancy_z_min_m) & (p[:, 2] < scene.config.occupancy_z_max_m)
    r, c = g.xy_to_cell(p[band, 0], p[band, 1])
    ok = g.contains_cell(r, c)
    r, c = r[ok], c[ok]
    k3 = np.ones((3, 3), np.uint8)
    hit = np.zeros(g.shape, np.uint8)
    hit[r, c] = 1
    outline = occ & (1 - cv2.erode(occ, k3))
    return (
        float(cv2.dilate(occ, k3)[r, c].mean()) if len(r) else float("nan"),
        float(cv2.dilate(hit, k3)[outline > 0].mean()) if outline.any() else float("nan"),
        float(hit[occ > 0].mean()) if occ.any() else float("nan"),
    )


def bench(seed: int, duration: float) -> None:
    cfg = SimConfig(duration_s=duration)
    t0 = time.perf_counter()
    scene = simulate_scene(seed, cfg)
    t_world = time.perf_counter() - t0

    t0 = time.perf_counter()
    frames = 0
    for _ in scene:
        frames += 1
    t_total = time.perf_counter() - t0

    # The same work again, sensor by sensor.
    t0 = time.perf_counter()
    n_lidar = [len(scene.lidar_sweep(i)[0].points) for i in range(len(scene))]
    t_lidar = time.perf_counter() - t0
    t0 = time.perf_counter()
    counts = {ch: [] for ch in RADAR_CHANNELS}
    labels = []
    for ch in RADAR_CHANNELS:
        for j in range(len(scene.radar_timestamps[ch])):
            sweep, lab = scene.radar_sweep(ch, j)
            counts[ch].append(len(sweep.points))
            labels.append(lab)
    t_radar = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in scene.keyframe_indices:
        scene.occupancy(int(i))
    t_occ = time.perf_counter() - t0
    stats = np.array([_occupancy_stats(scene, scene.frame(int(i))) for i in scene.keyframe_indices])
    lab = np.concatenate(labels)
    frac = np.bincount(lab, minlength=3) / max(len(lab), 1)
    n_radar = sum(len(v) for v in counts.values())
    x, y, _ = scene.trajectory.pose_at(np.array([0.0, duration]))
    print(
        f"\nscene {scene.name} ({scene.world.environment}, {scene.world.n_static} static boxes, "
        f"{len(scene.world.movers)} movers), "
        f"{duration:g} s, {frames} frames, ego travels {np.hypot(x[1] - x[0], y[1] - y[0]):.0f} m"
    )
    print(f"  world + route generation  {t_world:6.2f} s")
    print(
        f"  full frame iteration      {t_total:6.2f} s   <- simulated time per {duration:g} s "
        "scene (+ world)"
    )
    print(
        f"    lidar  {len(scene):4d} sweeps     {t_lidar:6.2f} s  "
        f"({1e3 * t_lidar / len(scene):.1f} ms a sweep)"
    )
    print(
        f"    radar  {n_radar:4d} sweeps     {t_radar:6.2f} s  "
        f"({1e3 * t_radar / max(n_radar, 1):.2f} ms a sweep)"
    )
    print(f"    occupancy {len(scene.keyframe_indices):3d} keyframes {t_occ:6.2f} s")
    print(
        f"  lidar points a sweep      mean {np.mean(n_lidar):.0f}  min {np.min(n_lidar)}  max "
        f"{np.max(n_lidar)}"
    )
    for ch, c in counts.items():
        print(
            f"  {ch:18s}        mean {np.mean(c):5.1f} detections a sweep (min {np.min(c)}, max "
            f"{np.max(c)})"
        )
    print(
        f"  radar labels              real {frac[0]:.3f}  clutter {frac[RADAR_CLUTTER]:.3f}  ghost "
        f"{frac[RADAR_GHOST]:.3f}"
    )
    print(
        f"  lidar vs true occupancy   band points on obstacles {np.nanmean(stats[:, 0]):.3f}, "
        f"obstacle outline cells seen {np.nanmean(stats[:, 1]):.3f}, occupied cells seen "
        f"{np.nanmean(stats[:, 2]):.4f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 6])
    ap.add_argument("--duration", type=float, default=20.0)
    args = ap.parse_args()
    t0 = time.perf_counter()
    simulate_scene(10_000, SimConfig(duration_s=0.2)).frame(0)  # compile or load the numba kernels
    print(f"numba warm-up (compile or cache load): {time.perf_counter() - t0:.2f} s")
    for s in args.seeds:
        bench(s, args.duration)


if __name__ == "__main__":
    main()
