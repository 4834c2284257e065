"""Memory of the simulator alone (docs/store.md): RSS after building a scene and its first
frame, and the time and RSS of simulating frames along the drive.

Each scene is built in its own process, importing evgrid_sim from each ``--src`` in turn
(default: this tree's ``src``; give another tree's ``src`` to compare on a loaded machine).
The child prints the RSS after the imports, after ``simulate_scene`` and after frame 0
(VmRSS, and VmHWM, the peak so far), the build time, then simulates ``--frames`` consecutive
frames starting at ``--at`` (a fraction of the drive) and prints their mean time and the RSS
after them. Measures and prints; asserts nothing.

    nice -n 10 python benchmarks/bench_sim_memory.py --durations 30 240 600 1800
    nice -n 10 python benchmarks/bench_sim_memory.py --durations 600 --src src /other/tree/src
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, os, sys, time
os.environ.setdefault("NUMBA_NUM_THREADS", "1")
duration, seed, n, at = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])

def mib():
    d = {}
    for line in open("/proc/self/status"):
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            d[k] = round(int(v.split()[0]) / 1024.0, 1)
    return d

from evgrid_sim import SimConfig, simulate_scene
out = {"imports": mib()}
t = time.perf_counter()
scene = simulate_scene(seed, SimConfig(duration_s=duration))
out["build_s"] = round(time.perf_counter() - t, 2)
out["scene"] = mib()
scene.frame(0)
out["frame0"] = mib()
i0 = min(int(at * len(scene)), max(len(scene) - n, 0))
t = time.perf_counter()
for i in range(i0, min(i0 + n, len(scene))):
    scene.frame(i)
out["ms_per_frame"] = round(1000 * (time.perf_counter() - t) / max(min(n, len(scene) - i0), 1), 1)
out["frames"] = mib()
out["n_static"], out["movers"] = scene.world.n_static, len(scene.world.movers)
print(json.dumps(out), flush=True)
"""


def run(src: str, duration: float, seed: int, frames: int, at: float) -> dict:
    env = {**os.environ, "PYTHONPATH": str(Path(src).resolve())}
    args = [sys.executable, "-c", CHILD, str(duration), str(seed), str(frames), str(at)]
    p = subprocess.run(args, env=env, capture_output=True, text=True)
    if p.returncode != 0:
        return {"rc": p.returncode, "error": p.stderr.strip().splitlines()[-1:]}
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    here = str(Path(__file__).resolve().parents[1] / "src")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[30.0, 240.0, 600.0])
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--frames", type=int, default=200, help="frames simulated after frame 0")
    ap.add_argument("--at", type=float, default=0.5, help="where they start, share of the drive")
    ap.add_argument("--src", nargs="+", default=[here], help="trees' src folders, run in turns")
    a = ap.parse_args()
    for d in a.durations:
        for src in a.src:  # in turns
            r = run(src, d, a.seed, a.frames, a.at)
            print(f"{src} {d:g} s: {json.dumps(r)}", flush=True)


if __name__ == "__main__":
    main()
