"""The dynamic score's cost in `evgrid bench`'s worst case, split into its parts.

Run: ``PYTHONPATH=src taskset -c 1 python benchmarks/dynamic_cost.py [--repeat 20]``. The
scene of :func:`evgrid_lab.bench._dynamic_cost` (six maps, 512 x 512 ISMs informative in every cell,
45 deg yaw, ``BENCH_MOVING_DETECTIONS`` moving detections spread over the window), four map sets
updated in turns (:func:`evgrid_lab.bench.interleaved_timings`): the score off; the conflict score
alone (no gate, no Doppler cue); with the gate on every scored map; with the gate and the Doppler
cue. Prints one JSON line: the median ms per update with the score off, and what each variant
adds to it (``conflict``, ``gate``, ``all``; ``doppler`` = all - gate). One numba thread; to
compare two commits, run their trees in separate processes alternated (``PYTHONPATH=<tree>/src``).

Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import math

import numba
import numpy as np
from harness import machine

from evgrid import fusion
from evgrid.geometry import SE2, GridSpec
from evgrid_lab.bench import bench_moving_detections, interleaved_ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=20, help="updates of each set, in turns")
    args = ap.parse_args()
    numba.set_num_threads(1)
    grid = GridSpec()
    rng = np.random.default_rng(0)  # the ISMs and pose of evgrid_lab.bench.run_bench
    a = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    b = rng.dirichlet([1, 1, 1], grid.shape).astype(np.float32)
    pose = SE2(3.3, -1.7, math.radians(45))
    isms = {"ray_ilm": a, "ray_irm": b, "deep_irm": a}
    moving = bench_moving_detections(grid, pose)  # those of evgrid_lab.bench._dynamic_cost
    d = fusion.DynamicParams
    sets = {
        "off": (fusion.MapSet(grid, dynamic=d(enabled=False)), None),
        "conflict": (fusion.MapSet(grid, dynamic=d()), None),
        "gate": (fusion.MapSet(grid, dynamic=d(gate_maps=True)), None),
        "all": (fusion.MapSet(grid, dynamic=d(gate_maps=True)), moving),
    }
    ms = interleaved_ms(
        {k: (lambda s=s, m=m: s.update(pose, isms, m)) for k, (s, m) in sets.items()},
        args.repeat,
    )
    out = {"off": round(ms["off"], 2)}
    out |= {k: round(ms[k] - ms["off"], 2) for k in ("conflict", "gate", "all")}
    out["doppler"] = round(ms["all"] - ms["gate"], 2)
    out["machine"] = machine()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
