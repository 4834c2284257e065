"""Benchmark of the geometric ISMs on one core: ray ILM, ray IRM, and OctoMap for scale.

Run: ``python benchmarks/bench_ism.py [--repeats 30] [--threads 2]``. Prints a table of
milliseconds per call (median and minimum over the repeats, after a warm-up call that
compiles or loads the numba kernels). Targets (issue 3), printed, not asserted:

* ray ILM of a ~34,000-point 32-beam sweep, filtering and projection included: <= 3 ms;
* ray IRM of 5 radars x 10 sweeps x 100 detections: <= 15 ms;
* OctoMap (0.1 m, 15 m max range) inserting the same lidar sweep: expected >= 100x slower.

Data: the synthetic street of :mod:`evgrid_sim.synthetic` (facades, parked cars, a truck,
poles; lidar shaped like the nuScenes LIDAR_TOP; the five nuScenes radars on a vehicle
driving at 8 m/s), plus an "open road" radar case in which every detection lies beyond the
grid, so that every cone runs to the grid's edge (the IRM's worst case).
"""

from __future__ import annotations

import os

# One core for OctoMap too (its insertPointCloud is OpenMP-parallel); set before importing it.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import math  # noqa: E402
from collections.abc import Callable  # noqa: E402

import numpy as np  # noqa: E402
from harness import machine_line, median_min_ms  # noqa: E402

from evgrid.data.frame import RadarSweep  # noqa: E402
from evgrid.geometry import GridSpec  # noqa: E402
from evgrid.ism import ray_ilm, ray_irm  # noqa: E402
from evgrid_sim.synthetic import street_lidar_sweep, street_radar_sweeps  # noqa: E402


def open_road(sweeps: list[RadarSweep], seed: int = 1) -> list[RadarSweep]:
    """The same sweeps, every detection moved to 25-80 m, within +-57 degrees of the boresight."""
    rng = np.random.default_rng(seed)
    out = []
    for s in sweeps:
        n = len(s.points)
        r, a = rng.uniform(25.0, 80.0, n), rng.uniform(-1.0, 1.0, n)
        pts = s.points.copy()
        pts[:, 0], pts[:, 1] = r * np.cos(a), r * np.sin(a)
        out.append(RadarSweep(pts, s.sensor_to_ego, s.ego_pose, s.timestamp, s.channel))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=30, help="timed calls per row (default 30)")
    ap.add_argument(
        "--octomap-repeats", type=int, default=3, help="timed OctoMap insertions (default 3)"
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=2,
        help="thread count of the extra multi-threaded rows (default 2)",
    )
    args = ap.parse_args()

    grid = GridSpec()
    lidar = street_lidar_sweep(seed=0)
    sweeps, now = street_radar_sweeps(n_sweeps=10, n_detections=100, seed=0)
    sweeps_open = open_road(sweeps)
    n_det = sum(len(s.points) for s in sweeps)
    out = np.empty(grid.shape + (3,), dtype=np.float32)

    rows: list[tuple[str, float, float, str]] = []

    def row(name: str, fn: Callable[[], object], note: str, repeats: int = args.repeats) -> float:
        med, mn = median_min_ms(fn, repeats)
        rows.append((name, med, mn, note))
        return med

    ilm_ms = row(
        "ray ILM, reused out buffer",
        lambda: ray_ilm(lidar, out=out),
        f"{len(lidar.points)} points, 1 thread",
    )
    row("ray ILM, fresh output array", lambda: ray_ilm(lidar), "allocates 3 MB each call")
    row(
        f"ray ILM, {args.threads} threads",
        lambda: ray_ilm(lidar, out=out, threads=args.threads),
        "",
    )
    row(
        "ray IRM, street",
        lambda: ray_irm(sweeps, now, out=out),
        f"5 radars x 10 sweeps, {n_det} detections, 1 thread",
    )
    row("ray IRM, street, fresh output", lambda: ray_irm(sweeps, now), "")
    row(
        f"ray IRM, street, {args.threads} threads",
        lambda: ray_irm(sweeps, now, out=out, threads=args.threads),
        "",
    )
    row(
        "ray IRM, open road (worst case)",
        lambda: ray_irm(sweeps_open, now, out=out),
        "all cones run to the grid edge",
    )

    octo_ms = math.nan
    try:
        import octomap
    except ImportError:
        octo_note = "octomap-python not installed (pip install evgrid[bench])"
    else:
        pts = np.ascontiguousarray(lidar.sensor_to_ego.apply(lidar.points[:, :3]), dtype=np.float64)
        origin = np.ascontiguousarray(lidar.sensor_to_ego.translation, dtype=np.float64)

        def insert() -> None:
            tree = octomap.OcTree(0.1)
            tree.insertPointCloud(pts, origin, maxrange=15.0)

        omp = os.environ.get("OMP_NUM_THREADS")
        octo_note = f"OcTree(0.1), maxrange 15 m, fresh tree, OMP_NUM_THREADS={omp}"
        octo_ms = row("OctoMap insertPointCloud", insert, octo_note, repeats=args.octomap_repeats)

    w = max(len(r[0]) for r in rows)
    print(
        f"\nISM benchmark: {grid.n_cells}x{grid.n_cells} cells over {grid.length_m:g} m; ms per "
        f"call over {args.repeats} calls\n{machine_line()}\n"
    )
    print(f"{'':{w}}  {'median':>8}  {'min':>8}  notes")
    for name, med, mn, note in rows:
        print(f"{name:{w}}  {med:8.3f}  {mn:8.3f}  {note}")
    print()
    print(
        f"targets: ray ILM <= 3 ms: {'met' if ilm_ms <= 3 else 'MISSED'} ({ilm_ms:.2f} ms); "
        f"ray IRM <= 15 ms: {'met' if rows[3][1] <= 15 else 'MISSED'} ({rows[3][1]:.2f} ms street, "
        f"{rows[6][1]:.2f} ms open road)"
    )
    if math.isfinite(octo_ms):
        print(f"OctoMap / ray ILM: {octo_ms / ilm_ms:.0f}x (expected >= 100x)")


if __name__ == "__main__":
    main()
