"""evgrid live in real time: latency and dropped frames replaying a simulated 10 Hz lidar + 4 Hz
radar rig at 1x, the cost of publishing /map, and a soak (a looped replay) with its memory curve.

    python benchmarks/live.py latency --duration 20          # nav (live's default), fused+nav
    python benchmarks/live.py publish                        # /map per million cells
    python benchmarks/live.py soak --minutes 30              # memory, latency, drops per minute

The live node runs in this process pinned to one core; `evgrid replay` runs in a subprocess on
another. DDS stays on the loopback interface, on a ROS_DOMAIN_ID drawn in 100-200. Prints the
CPU flags and the load average with every figure.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    from evgrid.live.dds import loopback_config

    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randrange(100, 200)))
    os.environ["CYCLONEDDS_URI"] = loopback_config()
    return {**os.environ, "PYTHONPATH": str(ROOT / "src")}


def _machine() -> str:
    flags = ""
    with open("/proc/cpuinfo") as fh:
        for line in fh:
            if line.startswith("flags"):
                wanted = ("avx2", "avx512f", "fma", "sse4_2")
                flags = " ".join(f for f in line.split(":")[1].split() if f in wanted)
                break
    return f"CPU flags {flags}; {os.cpu_count()} cores; load average {os.getloadavg()}"


def _recording(folder: Path, duration: float) -> tuple[Path, Path]:
    cmd = [
        sys.executable, "-m", "evgrid.cli", "simulate", "--format", "ros2", "--out", str(folder),
        "--duration", str(duration), "--lidar-rate", "10", "--radar-rate", "4",
        "--radar-channels", "RADAR_FRONT,RADAR_BACK_LEFT,RADAR_BACK_RIGHT",
    ]  # fmt: skip
    subprocess.run(cmd, check=True, env=_env(), capture_output=True)
    return folder / "sim-000000", folder / "sim-000000.rig.yaml"


def _pin(core: int) -> None:
    if hasattr(os, "sched_setaffinity") and core < (os.cpu_count() or 1):
        os.sched_setaffinity(0, {core})


def _run(bag: Path, rig_path: Path, maps: tuple[str, ...], loop_s: float | None = None,
         on_tick=None, keep: bool = False) -> dict:  # fmt: skip
    from evgrid.config import RunConfig
    from evgrid.data.bag import load_rig
    from evgrid.live.node import LiveNode, LiveOptions

    rig = load_rig(rig_path)
    run = RunConfig()
    node = LiveNode(
        rig, replace(run.mapper, maps=maps), run.outputs, None,
        LiveOptions(status_every_s=60.0), say=lambda s: None,
    )  # fmt: skip
    node.start()
    cmd = [sys.executable, "-m", "evgrid.cli", "replay", str(bag), "--rig", str(rig_path)]
    if loop_s:
        cmd.append("--loop")
    pre = ["taskset", "-c", "1"] if (os.cpu_count() or 1) > 1 else []
    play = subprocess.Popen(pre + cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    stop = threading.Event()
    while play.poll() is None and not stop.is_set():
        node.step()
        if on_tick:
            on_tick(node, time.monotonic() - t0)
        if loop_s and time.monotonic() - t0 > loop_s:
            play.terminate()
    t = time.monotonic()
    while time.monotonic() - t < 1.5:
        node.step()
    if keep:  # still on the graph: the caller closes it
        return {"node": node, "dropped": node.drops()}
    return node.close()


def latency(args: argparse.Namespace) -> None:
    _env()
    _pin(0)
    with tempfile.TemporaryDirectory() as tmp:
        bag, rig = _recording(Path(tmp) / "rec", args.duration)
        print(f"replaying a simulated {args.duration:g} s drive (10 Hz lidar, 3 x 4 Hz radar) at "
              f"1x into evgrid live on one core; {_machine()}")  # fmt: skip
        for maps in (
            ("nav",),
            ("fused", "nav"),
            ("ray_ilm", "deep_acc", "deep_replace", "deep_disc", "ray_irm", "fused", "nav"),
        ):
            r = _run(bag, rig, maps)
            lat, upd = r["latency_ms"], r["update_latency_ms"]
            print(
                f"maps {'+'.join(maps)}: {r['updates']} updates of {r['lidar_sweeps']} sweeps, "
                f"dropped {sum(r['dropped'].values())} {r['dropped'] or ''}; stamp -> map updated "
                f"median {upd['median']:.0f} / p95 {upd['p95']:.0f} / max {upd['max']:.0f} ms; "
                f"stamp -> /map published median {lat['median']:.0f} / p95 {lat['p95']:.0f} / "
                f"max {lat['max']:.0f} ms ({r['published']} publications); load {os.getloadavg()}"
            )


def publish(args: argparse.Namespace) -> None:
    _env()
    _pin(0)
    from evgrid.export.mcap import MapCells, occupancy_grid_msg, occupancy_grid_of
    from evgrid.export.nav2 import classify
    from evgrid.live.dds import MAP_QOS, Graph
    from evgrid.ros import typestore

    store = typestore(2)
    graph = Graph()
    w = graph.writer("/map", "nav_msgs/msg/OccupancyGrid", MAP_QOS)
    rd = graph.reader("/map", "nav_msgs/msg/OccupancyGrid", MAP_QOS)
    print(
        "/map of an n x n map: the message from the masses (classifying every cell, as an "
        "export does) or from the classes evgrid live keeps, then serialise and write (a "
        f"subscriber in this process); medians of {args.repeats}; {_machine()}"
    )
    rng = np.random.default_rng(0)
    res = 0.078125
    for n in (512, 1024, 2048):
        m = rng.dirichlet((1, 1, 1), size=(n, n)).astype(np.float32)
        cells = MapCells(m, np.ones((n, n), bool), 0, 0, res)
        cls = classify(m, cells.covered)
        times: dict[str, list[float]] = {"from masses": [], "from classes": [], "serialise": [],
                                         "write": []}  # fmt: skip
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            occupancy_grid_msg(cells, 1, "odom", store)
            t1 = time.perf_counter()
            msg = occupancy_grid_of(cls, 0, 0, res, 1, "odom", store)
            t2 = time.perf_counter()
            raw = store.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid")
            t3 = time.perf_counter()
            w.write(raw)
            t4 = time.perf_counter()
            rd.take()
            for k, a, b in (("from masses", t0, t1), ("from classes", t1, t2),
                            ("serialise", t2, t3), ("write", t3, t4)):  # fmt: skip
                times[k].append((b - a) * 1e3)
        per = {k: float(np.median(v)) / (n * n / 1e6) for k, v in times.items()}
        print(
            f"{n} x {n}: "
            + ", ".join(f"{k} {float(np.median(v)):.1f} ms" for k, v in times.items())
            + "; per million cells: "
            + ", ".join(f"{k} {v:.1f} ms" for k, v in per.items())
        )
    graph.close()


def agree(args: argparse.Namespace) -> None:
    """A subscriber joining after a 1x replay ended: its /map against the offline nav2 export."""
    _env()
    _pin(0)
    from evgrid.config import RunConfig
    from evgrid.data.bag import load_bag, load_rig
    from evgrid.export.nav2 import UNKNOWN, classify, map_to_occupancy
    from evgrid.live.dds import MAP_QOS, Graph
    from evgrid.mapper import OccupancyMapper
    from evgrid.ros import typestore

    with tempfile.TemporaryDirectory() as tmp:
        bag, rig_path = _recording(Path(tmp) / "rec", args.duration)
        run = RunConfig()
        off = OccupancyMapper(replace(run.mapper, maps=("nav",)))
        for f in load_bag(bag, load_rig(rig_path)):
            off.process(f)
        r = _run(bag, rig_path, ("nav",), keep=True)
    graph = Graph()
    late = graph.reader("/map", "nav_msgs/msg/OccupancyGrid", MAP_QOS)
    got: list = []
    end = time.monotonic() + 10
    while not got and time.monotonic() < end:
        got = late.take()
        time.sleep(0.05)
    r["node"].close()
    graph.close()
    msg = typestore(2).deserialize_cdr(got[-1][0], "nav_msgs/msg/OccupancyGrid")
    m = off.maps.maps["nav"]
    r0, c0, h, w = m.covered_bounds()
    masses, cov = m.read(r0, c0, h, w)
    want, _ = map_to_occupancy(classify(masses, cov, run.outputs.nav2.thresholds), r0, c0,
                               m.grid.resolution)  # fmt: skip
    live = np.asarray(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    if live.shape != want.shape:
        print(f"/map is {live.shape}, the offline export {want.shape}: grids differ")
        return
    known = (live != UNKNOWN) | (want != UNKNOWN)
    share = float((live[known] == want[known]).mean())
    print(f"{args.duration:g} s simulated drive at 1x, dropped {r['dropped'] or 0}: a late "
          f"subscriber's /map agrees with the offline nav2 export on {100 * share:.2f} % of the "
          f"{int(known.sum())} cells either calls known; {_machine()}")  # fmt: skip


def soak(args: argparse.Namespace) -> None:
    _env()
    _pin(0)
    from evgrid.live.node import _rss_mb

    curve: list[tuple[float, float, int, int, float]] = []
    last = [-1e9]

    def tick(node, t):
        if t - last[0] >= args.every:
            last[0] = t
            lat = list(node.stats.update_latency_ms)[-50:]
            curve.append((t, _rss_mb(), node.mapper.n_updates, sum(node.drops().values()),
                          float(np.median(lat)) if lat else float("nan")))  # fmt: skip
            print(f"{t / 60:6.1f} min: RSS {curve[-1][1]:.0f} MB, {curve[-1][2]} updates, "
                  f"dropped {curve[-1][3]}, stamp -> map updated median (last 50) "
                  f"{curve[-1][4]:.0f} ms; load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip

    with tempfile.TemporaryDirectory() as tmp:
        bag, rig = _recording(Path(tmp) / "rec", args.duration)
        print(f"soak: a {args.duration:g} s simulated drive replayed with --loop for "
              f"{args.minutes:g} min into evgrid live (nav); {_machine()}", flush=True)  # fmt: skip
        r = _run(bag, rig, ("nav",), args.minutes * 60, tick)
    print(f"end: {r['updates']} updates, dropped {r['dropped']}, latency {r['latency_ms']}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    a = sub.add_parser("latency")
    a.add_argument("--duration", type=float, default=20.0)
    b = sub.add_parser("publish")
    b.add_argument("--repeats", type=int, default=5)
    d = sub.add_parser("agree")
    d.add_argument("--duration", type=float, default=4.0)
    c = sub.add_parser("soak")
    c.add_argument("--minutes", type=float, default=30.0)
    c.add_argument("--duration", type=float, default=20.0)
    c.add_argument("--every", type=float, default=30.0)
    args = p.parse_args()
    {"latency": latency, "publish": publish, "soak": soak, "agree": agree}[args.what](args)


if __name__ == "__main__":
    main()
