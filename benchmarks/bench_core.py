"""Benchmark of the core: the algebra, the deep_disc update, the warp into the map, the six maps.

Run: ``python benchmarks/bench_core.py [--json out.json]``. One thread, median of repeats.
Inputs are random masses on every cell (no vacuous cells to skip: the worst case) unless
named "ISM-like" (about half the cells vacuous, as a ray ISM's grid is).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from harness import machine, machine_line, timings_ms  # noqa: E402

from evgrid import fusion, mass  # noqa: E402
from evgrid.geometry import SE2, GridSpec  # noqa: E402
from evgrid.grid import Warper  # noqa: E402

timeit = functools.partial(timings_ms, repeat=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args()

    grid = GridSpec()
    rng = np.random.default_rng(0)
    a = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    b = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    ism_like = b.copy()
    ism_like[rng.random(grid.shape) < 0.5] = [0, 0, 1]
    out = np.empty_like(a)
    cur = a.copy()

    def reset() -> None:
        cur[:] = a

    params = fusion.FusionParams()
    res: dict[str, np.ndarray] = {}
    res["dempster 512x512 (mass.dempster)"] = timeit(lambda: mass.dempster(a, b, out))
    res["yager 512x512 (mass.yager)"] = timeit(lambda: mass.yager(a, b, out))
    res["deep_disc update 512x512 (limit + gamma + yager)"] = timeit(
        lambda: fusion.update_deep_disc(cur, b, params), reset
    )
    res["deep_replace update 512x512"] = timeit(
        lambda: fusion.update_deep_replace(cur, b, params), reset
    )
    res["fused update 512x512 (deep_disc + dempster)"] = timeit(
        lambda: fusion.update_fused(cur, b, ism_like, params), reset
    )

    # Warp + fuse one 512 x 512 local grid into a map through the public path (MapSet.update):
    # a dense grid (every cell informative, as the deep IRM's) with the deep_disc rule, at yaws
    # from 0 to 90 degrees (the window, and so the work, is largest at 45).
    warper = Warper(grid)
    for deg in range(0, 91, 15):
        pose = SE2(3.3, -1.7, math.radians(deg))
        res[f"warp 512x512 into map, yaw {deg} deg (dense)"] = timeit(lambda: warper.warp(b, pose))
        one = fusion.MapSet(grid, params, names=("deep_disc",))
        res[f"warp + deep_disc fuse into map, yaw {deg} deg (dense)"] = timeit(
            lambda: one.update(pose, {"deep_irm": b})
        )
    for deg in (0, 45):
        pose = SE2(3.3, -1.7, math.radians(deg))
        one = fusion.MapSet(grid, params, names=("ray_ilm",))
        res[f"warp + dempster fuse into map, yaw {deg} deg (ISM-like)"] = timeit(
            lambda: one.update(pose, {"ray_ilm": ism_like})
        )

    from evgrid.ism import ray_ilm
    from evgrid_sim.synthetic import street_lidar_sweep

    ilm = ray_ilm(street_lidar_sweep())  # a real ray ILM grid: a 15 m disc in a 40 m square
    for deg in (0, 45):
        pose = SE2(3.3, -1.7, math.radians(deg))
        one = fusion.MapSet(grid, params, names=("ray_ilm",))
        res[f"warp + dempster fuse into map, yaw {deg} deg (ray ILM of a street)"] = timeit(
            lambda: one.update(pose, {"ray_ilm": ilm})
        )

    ms = fusion.MapSet(grid, params)
    isms = {"ray_ilm": ism_like, "ray_irm": ism_like, "deep_irm": b}
    k = [0]

    def six() -> None:
        k[0] += 1
        ms.update(SE2(0.5 * k[0], 0.1 * k[0], 0.01 * k[0]), isms)

    res["six maps: 3 warps + 6 updates (moving pose)"] = timeit(six, repeat=20)

    width = max(len(k) for k in res)
    # the median is the figure; the minimum shows what the code does when the machine is quiet
    print(f"evgrid core benchmark - {machine_line()}, 1 thread, ms per call")
    print(f"  {'':<{width}}  {'median':>8}  {'min':>8}")
    for name, ts in res.items():
        print(f"  {name:<{width}}  {np.median(ts):8.3f}  {ts.min():8.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "machine": machine(),
                    **{
                        k: {"median_ms": float(np.median(v)), "min_ms": float(v.min())}
                        for k, v in res.items()
                    },
                },
                f,
                indent=2,
            )


if __name__ == "__main__":
    main()
