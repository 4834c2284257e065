"""Memory of long drives with the tile store (docs/store.md): peak RSS, RSS along the drive, the
store's bytes per km^2 and the time per frame.

Each drive is mapped in its own process (a simulated scene, six maps plus nav, the defaults,
no figures, the exports asked for), importing evgrid from ``--src`` (default: this tree's
``src``; give another tree's ``src`` to measure it the same way, in turns). Every
``--every`` simulated seconds the child prints the drive's time, its RSS now and at peak
(VmRSS, VmHWM), the mean milliseconds per frame since the last line and the bytes and tiles
in the scene's tile store; after the drive, a line per end-of-run step (the tiles paged out,
each export's close, the metrics) with the RSS before and after it and VmHWM after it, so
that the step where VmHWM rises is where the peak comes. Measures and prints; asserts nothing.

    nice -n 5 python benchmarks/bench_store_memory.py --durations 30 240 --export nav2
    nice -n 5 python benchmarks/bench_store_memory.py --durations 600 --export nav2,mcap,rerun
    nice -n 5 python benchmarks/bench_store_memory.py --durations 1800 --every 60
    python benchmarks/bench_store_memory.py --durations 30 --src /path/to/other/tree/src
    python benchmarks/bench_store_memory.py --durations 1800 --every 60 --keep-store out/s1800
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

CHILD = r"""
import json, os, sys, tempfile, time
from pathlib import Path
duration, seed, every = float(sys.argv[1]), int(sys.argv[2]), float(sys.argv[4])
exports, out, keep = sys.argv[3], Path(sys.argv[5]), sys.argv[6]
import evgrid
from evgrid.config import MapperConfig, OutputConfig
from evgrid_sim import SimConfig, simulate_scene
from evgrid.fusion import MAP_NAMES
from evgrid.runs import map_scene

def status():
    d = {}
    for line in open("/proc/self/status"):
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            d[k] = int(v.split()[0]) / 1024.0
    return d

def store_size(folder):
    # bytes of every tile file (older generations a checkpoint keeps included: the disk used),
    # and the tiles of the fused map (its keys, each once): the area the store covers
    n, keys = 0, set()
    if folder.is_dir():
        for g in os.scandir(folder):
            if g.is_dir():
                for f in os.scandir(g.path):
                    if f.name.endswith(".tile"):
                        n += f.stat().st_size
                        if g.name == "fused":
                            keys.add(f.name.split(".g")[0])
    return n, len(keys)

frames = simulate_scene(seed, SimConfig(duration_s=duration))
total = len(frames)
name = "drive"
state = {"i": 0, "t": time.perf_counter(), "i0": 0, "next": every}
# The simulator builds its world for the whole drive up front (frames are made lazily, one at a
# time): the RSS here, before a frame is mapped, is the simulator's and the libraries' share.
print(json.dumps({"evgrid": evgrid.__file__, "frames": total, "sim_rss": status()}), flush=True)

def progress():
    state["i"] += 1
    t_sim = state["i"] / total * duration
    if t_sim + 1e-9 >= state["next"] or state["i"] == total:
        now = time.perf_counter()
        n = state["i"] - state["i0"]
        b, tiles = store_size(out / name / "store")
        ms = (now - state["t"]) / max(n, 1) * 1e3
        rec = {"t_s": round(t_sim, 1), **status(), "ms_per_frame": ms}
        print(json.dumps({**rec, "store_bytes": b, "store_fused_tiles": tiles}), flush=True)
        state.update(t=now, i0=state["i"], next=state["next"] + every)
    if keep and state["i"] == total:  # the store as the last frame left it (hard links)
        import shutil
        shutil.copytree(out / name / "store", keep, copy_function=os.link)

# a line after each end-of-run step: VmHWM rising in a step is where the peak comes
def watch(owner, attr, label):
    fn = getattr(owner, attr, None)
    if fn is None:  # a tree without that step
        return
    def stepped(*a, **k):
        before = status()
        try:
            return fn(*a, **k)
        finally:
            after = status()
            rec = {"step": label, "rss_before": before["VmRSS"], "rss_after": after["VmRSS"]}
            print(json.dumps({**rec, "VmHWM": after["VmHWM"]}), flush=True)
    setattr(owner, attr, stepped)

import importlib
import evgrid.runs as runs
from evgrid.mapper import OccupancyMapper
watch(OccupancyMapper, "page_out_all", "page_out_all")
for fmt, cls in (("nav2", "Nav2Exporter"), ("mcap", "McapExporter"), ("rerun", "RerunRecorder")):
    watch(getattr(importlib.import_module(f"evgrid.export.{fmt}"), cls), "close", f"{fmt} close")
watch(runs, "_scene_metrics", "metrics")
exp = tuple(e for e in exports.split(",") if e)
config = MapperConfig(maps=(*MAP_NAMES, "nav"))
outputs = OutputConfig(figures=False, exports=exp)
t0 = time.perf_counter()
res = map_scene(frames, out / name, config, outputs, name=name, progress=progress, overwrite=True)
m = json.loads((out / name / "metrics.json").read_text())
rec = {"done": True, "seconds": time.perf_counter() - t0, **status()}
rec.update(map_area_km2=m["map_area_km2"], frame_ms=m["frame_ms"])
rec.update(page_out_ms=m["timings_ms"].get("page_out"), tile_cells=config.tile_cells)
rec.update(checkpoints=m.get("checkpoints"))  # the resumable states' cost (docs/store.md)
print(json.dumps({**rec, "resolution": config.grid.resolution}), flush=True)
"""


def run(
    src: str, duration: float, seed: int, exports: str, every: float, tmp: Path, keep: str = ""
) -> dict:
    env = {**os.environ, "PYTHONPATH": src}
    out = tmp / f"d{duration:g}-{time.time_ns()}"
    cmd = [sys.executable, "-c", CHILD, str(duration), str(seed), exports, str(every), str(out)]
    cmd += [keep]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)
    lines = []
    for line in proc.stdout:
        d = json.loads(line)
        lines.append(d)
        print(f"  {src} {duration:g}s: {line.strip()}", flush=True)
    proc.wait()
    done = lines[-1] if lines and lines[-1].get("done") else {}
    return {"src": src, "duration": duration, "wall_s": time.perf_counter() - t0,
            "rc": proc.returncode, "curve": lines[1:-1], **done}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--durations", type=float, nargs="+", default=[30.0, 240.0])
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--export", default="nav2")
    ap.add_argument("--every", type=float, default=10.0, help="simulated seconds between lines")
    here = str(Path(__file__).resolve().parents[1] / "src")
    ap.add_argument("--src", nargs="+", default=[here], help="trees' src folders, run in turns")
    ap.add_argument("--tmp", default=None, help="where the runs write (default: a temp folder)")
    ap.add_argument(
        "--keep-store",
        default="",
        help="copy (hard links) the tile store as the drive's last frame left it to this "
        "folder (one drive), to re-measure its bytes later",
    )
    a = ap.parse_args()
    import tempfile

    tmp = Path(a.tmp or tempfile.mkdtemp(prefix="evgrid-bench-store-"))
    print("cpu flags:", open("/proc/cpuinfo").read().split("flags")[1].split("\n")[0][:200])
    rows = []
    for d in a.durations:
        for src in a.src:  # in turns
            r = run(src, d, a.seed, a.export, a.every, tmp, a.keep_store)
            rows.append(r)
            area = r.get("map_area_km2") or float("nan")
            last = max((c.get("store_bytes", 0) for c in r["curve"]), default=0)
            tiles = max((c.get("store_fused_tiles", 0) for c in r["curve"]), default=0)
            tile_km2 = (r.get("tile_cells", 256) * r.get("resolution", 0.1)) ** 2 * 1e-6
            per_km2 = last / (tiles * tile_km2) / 1e9 if tiles else float("nan")
            print(
                f"{src} {d:g} s: rc {r['rc']}, peak RSS {r.get('VmHWM', float('nan')):.0f} MiB, "
                f"wall {r['wall_s']:.0f} s, mapping {r.get('seconds', float('nan')):.0f} s, "
                f"area {area:.3f} km^2, store {last / 1e6:.0f} MB for {tiles} fused tiles "
                f"({per_km2:.2f} GB/km^2 of store, all maps), frame ms {r.get('frame_ms')}, "
                f"page-out ms (median) {r.get('page_out_ms')}",
                flush=True,
            )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
