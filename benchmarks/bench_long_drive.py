"""Long drives and odometry glitches: does a frame cost the same in the tenth minute as in the
first?

Maps simulated drives of 20, 120 and 600 s (six maps, truth scores at every keyframe, figures
and the GIF, as ``evgrid map`` does), each in its own process, and prints per-frame
milliseconds (mapper and observers) in the first and last tenth of the drive, the peak resident
memory and the map area. Then maps a 20 s drive with one ego pose moved 1 km (an odometry
glitch) and with none, and prints what the glitch cost. Measures and prints; asserts nothing.

    python benchmarks/bench_long_drive.py                   # 20, 120, 600 s
    python benchmarks/bench_long_drive.py --durations 20 120
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
from harness import machine_line, sim_scene


def _glitched(frames, index: int, jump_m: float):
    """The frames of a scene with frame ``index``'s ego pose (and its sweeps') moved ``jump_m``
    metres in x."""
    from evgrid.geometry import SE3

    for f in frames:
        if f.index == index:
            shift = SE3(np.eye(3), np.array([jump_m, 0.0, 0.0]))
            lidar = dataclasses.replace(f.lidar, ego_pose=shift @ f.lidar.ego_pose)
            radar = {
                ch: tuple(dataclasses.replace(s, ego_pose=shift @ s.ego_pose) for s in sw)
                for ch, sw in f.radar.items()
            }
            f = dataclasses.replace(f, ego_pose=shift @ f.ego_pose, lidar=lidar, radar=radar)
        yield f


def child(seed: int, duration: float, glitch_m: float) -> dict:
    """One drive, in this process: metrics that matter here and the peak RSS."""
    from evgrid.runs import map_scene

    scene = sim_scene(seed, duration)
    frames = _glitched(scene, len(scene) // 2, glitch_m) if glitch_m else scene
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = map_scene(frames, f"{tmp}/out", name=scene.name)
        wall = time.perf_counter() - t0
    m = res.metrics
    fused = m.get("vs_truth", {}).get("fused", {})
    return {
        "duration_s": duration,
        "glitch_m": glitch_m,
        "frames": m["frames"],
        "wall_s": wall,
        "frame_ms": m["frame_ms"],
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "map_area_km2": m["map_area_km2"],
        "fused_vs_truth": fused,
        "counts": m["counts"],
    }


def _run(seed: int, duration: float, glitch_m: float = 0.0) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", str(seed), str(duration), str(glitch_m)],
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        return {
            "duration_s": duration,
            "glitch_m": glitch_m,
            "error": out.stderr.strip().splitlines()[-1:],
        }
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[20.0, 120.0, 600.0])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(int(args.child[0]), float(args.child[1]), float(args.child[2]))))
        return
    print(f"long drives (seed {args.seed}; six maps, truth at keyframes, figures and GIF)")
    print(machine_line())
    print(
        f"{'drive s':>8} {'frames':>7} {'wall s':>7} {'ms/frame first 10%':>19} {'last 10%':>9} "
        f"{'last/first':>10} "
        f"{'peak RSS GB':>11} {'area km2':>8} {'GB/km2':>7}"
    )
    for d in args.durations:
        r = _run(args.seed, d)
        if "error" in r:
            print(f"{d:>8g} failed: {r['error']}")
            continue
        fm = r["frame_ms"]
        print(
            f"{d:>8g} {r['frames']:>7d} {r['wall_s']:>7.1f} {fm['first_tenth_mean']:>19.1f} "
            f"{fm['last_tenth_mean']:>9.1f} "
            f"{fm['last_tenth_mean'] / fm['first_tenth_mean']:>10.2f} {r['peak_rss_gb']:>11.2f} "
            f"{r['map_area_km2']:>8.3f} "
            f"{r['peak_rss_gb'] / max(r['map_area_km2'], 1e-9):>7.1f}"
        )
    print("\nan odometry glitch: one ego pose of a 20 s drive moved 1 km")
    print(
        f"{'glitch m':>8} {'wall s':>7} {'peak RSS GB':>11} {'fused free IoU':>14} {'occ IoU':>7}  "
        "skipped"
    )
    for g in (0.0, 1000.0):
        r = _run(args.seed, 20.0, g)
        if "error" in r:
            print(f"{g:>8g} failed: {r['error']}")
            continue
        f = r["fused_vs_truth"]
        skipped = {k: v for k, v in r["counts"].items() if v and k not in ("frames", "updates")}
        print(
            f"{g:>8g} {r['wall_s']:>7.1f} {r['peak_rss_gb']:>11.2f} "
            f"{f.get('free', float('nan')):>14.3f} "
            f"{f.get('occupied', float('nan')):>7.3f}  {skipped}"
        )


if __name__ == "__main__":
    main()
