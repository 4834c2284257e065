"""Benchmark of the engines of evgrid.engine.fan_out: scenes per minute, Ray's fixed cost, ports.

Maps ``--scenes`` simulated validation scenes of ``--duration`` seconds (the shipped Ev-Net, no
figures) with the local engine at 1 and 2 workers, with Ray (a local instance) at 1 and 2
workers, and on a two-node Ray cluster on this machine (one CPU per node, 2 workers); times
Ray's fixed cost per run (a local instance started and shut down with no jobs); lists the TCP
ports the local Ray instance listens on, with evgrid's settings and with a plain ``ray.init()``;
and from the mapping rate estimates the wall time of nuScenes trainval (850 scenes of 20 s) on
1, 8 and 64 cores. Every measurement runs in a fresh interpreter (Ray reads its settings when
imported). Prints; asserts nothing.

Run: ``PYTHONPATH=src python benchmarks/bench_engine.py [--scenes 4] [--duration 10]``
(``--only ports`` for the ports alone). Results go to docs/cluster.md with the commit and the
CPU flags.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import machine_line

ROOT = Path(__file__).resolve().parents[1]
MODES = ("local-1", "local-2", "ray-1", "ray-2", "cluster-2")
NUSCENES_SCENES = 850  # trainval, 20 s each (the paper's 133,708 training samples come from 700)


# --- the jobs, run in a child interpreter -------------------------------------------------------


def map_one(args: tuple) -> dict:
    """Map one simulated scene without a results folder (module level: workers import it)."""
    from evgrid.config import MapperConfig, OutputConfig
    from evgrid.runs import map_scene
    from evgrid.sources import SimSource

    seed, duration_s = args
    source = SimSource((seed,), duration_s)
    (name,) = source.names()
    res = map_scene(source.load(name), None, MapperConfig(), OutputConfig(figures=False))
    return {"seconds": res.metrics["seconds"]}


def _jobs(scenes: int, duration_s: float) -> list[tuple[str, tuple]]:
    from evgrid.sources import SimSource

    seeds = SimSource.split("val", scenes, first_seed=2000).seeds  # apart from all other runs
    return [(f"sim-{s}", (s, duration_s)) for s in seeds]


def child_throughput(mode: str, scenes: int, duration_s: float) -> dict:
    from evgrid.engine import fan_out

    engine, workers = mode.split("-")
    jobs = _jobs(scenes, duration_s)
    if engine == "cluster":  # both nodes up before the clock starts
        import ray

        from tests.ray_cluster import wait_for_nodes

        ray.init(address=os.environ["RAY_ADDRESS"], log_to_driver=False)
        wait_for_nodes(ray, 2)
        ray.shutdown()
    t = time.perf_counter()
    out = list(
        fan_out(map_one, jobs, engine="local" if engine == "local" else "ray", workers=int(workers))
    )
    wall = time.perf_counter() - t
    errors = [o.error for o in out if not o.ok]
    return {
        "mode": mode,
        "wall_s": wall,
        "errors": errors,
        "mapping_s": sum(o.result["seconds"] for o in out if o.ok),
    }


def child_fixed_cost(repeat: int) -> dict:
    from evgrid.engine_ray import ray_session

    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        with ray_session(workers=2):
            pass
        times.append(time.perf_counter() - t)
    return {"fixed_s": times}


def _descendants(pid: int) -> set[int]:
    parent: dict[int, int] = {}
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                stat = Path(f"/proc/{p}/stat").read_text()
                parent[int(p)] = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found, frontier = {pid}, [pid]
    while frontier:
        cur = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == cur and c not in found]
        found.update(kids)
        frontier.extend(kids)
    return found


def _listening(pids: set[int]) -> list[tuple[str, str]]:
    """(process name, local address) of the TCP sockets these processes listen on (ss -ltnp)."""
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=True).stdout
    rows = []
    for line in out.splitlines():
        for part in line.split("users:")[1:]:
            for entry in part.strip("()").split("),("):
                name = entry.split('"')[1] if '"' in entry else "?"
                pid = int(entry.split("pid=")[1].split(",")[0]) if "pid=" in entry else -1
                if pid in pids:
                    rows.append((name, line.split()[3]))
    return sorted(set(rows))


def _one_task() -> int:
    return os.getpid()


def child_ports(plain: bool) -> dict:
    if plain:
        import ray

        tmp = tempfile.mkdtemp(prefix="evp", dir="/tmp")
        ray.init(_temp_dir=tmp)  # Ray's defaults, only a private temp dir
        ray.get(ray.remote(_one_task).remote())
        rows = _listening(_descendants(os.getpid()))
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)
        return {"ports": rows}
    from evgrid.engine_ray import ray_session

    with ray_session(workers=2) as ray:
        ray.get(ray.remote(_one_task).remote())
        rows = _listening(_descendants(os.getpid()))
    return {"ports": rows}


# --- the parent ---------------------------------------------------------------------------------


def _child(args: list[str], env: dict | None = None, timeout: float = 1800) -> dict:
    env = dict(env if env is not None else os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), str(ROOT / "benchmarks")])
    r = subprocess.run(
        [sys.executable, __file__, "--child", *args],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    if r.returncode or not lines:
        raise SystemExit(f"bench_engine: {args} failed: {r.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT ") :])


def _clean_env() -> dict:
    return {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}


def run_ports() -> None:
    for label, plain in (("evgrid's local instance", False), ("plain ray.init()", True)):
        rows = _child(["ports", "plain" if plain else "evgrid"], env=_clean_env())["ports"]
        print(f"\nlistening TCP sockets, {label}:")
        for name, addr in rows:
            print(f"  {name:<20} {addr}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3, help="runs of Ray's fixed cost")
    ap.add_argument("--only", choices=("ports", "throughput", "fixed"), default=None)
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        kind = a.child[0]
        if kind == "throughput":
            res = child_throughput(a.child[1], a.scenes, a.duration)
        elif kind == "fixed":
            res = child_fixed_cost(a.repeat)
        else:
            res = child_ports(plain=a.child[1] == "plain")
        print("RESULT " + json.dumps(res))
        return
    print(f"machine before: {machine_line()}")
    if a.only in (None, "ports"):
        run_ports()
    fixed = None
    if a.only in (None, "fixed"):
        fixed = statistics.median(_child(["fixed"] + [], env=_clean_env())["fixed_s"])
        print(
            f"\nRay's fixed cost per run (local instance start + shutdown, no jobs), median "
            f"of {a.repeat}: {fixed:.1f} s"
        )
    if a.only not in (None, "throughput"):
        return
    size = ["--scenes", str(a.scenes), "--duration", str(a.duration)]
    rates = {}
    cluster_ports: list = []
    print(f"\n{a.scenes} simulated scenes of {a.duration:g} s (shipped Ev-Net, no figures):")
    print(f"  {'engine':<10} {'wall s':>7} {'scenes/min':>11} {'mapping s':>10}")
    for mode in MODES:
        t_start = 0.0
        if mode.startswith("cluster"):
            from tests.ray_cluster import local_cluster

            t = time.perf_counter()
            with local_cluster(nodes=2, cpus_per_node=1) as cluster:
                t_start = time.perf_counter() - t
                res = _child(["throughput", mode, *size], env=cluster["env"])
                cluster_ports = _listening(_descendants(os.getpid()))
        else:
            res = _child(["throughput", mode, *size], env=_clean_env())
        if res["errors"]:
            print(f"  {mode}: errors {res['errors']}")
        rates[mode] = res
        extra = f" (head node up in {t_start:.0f} s, not counted)" if t_start else ""
        print(
            f"  {mode:<10} {res['wall_s']:7.1f} {60 * a.scenes / res['wall_s']:11.2f} "
            f"{res['mapping_s']:10.1f}{extra}",
            flush=True,
        )
    print("\nlistening TCP sockets of the two-node cluster (ray start --head, --address):")
    for name, addr in cluster_ports:
        print(f"  {name:<20} {addr}")
    # The estimate: core-seconds per driven second, from the local engine on one worker (no
    # engine overhead), scaled to 850 scenes of 20 s and divided over the cores, plus Ray's
    # fixed cost. An estimate: nuScenes frames are read, not simulated, and have other sizes.
    per_scene_s = rates["local-1"]["wall_s"] / a.scenes * (20.0 / a.duration)
    print(
        f"\nestimate for nuScenes trainval ({NUSCENES_SCENES} scenes of 20 s), from "
        f"{per_scene_s:.1f} core-seconds per 20 s scene (local-1, scaled by duration):"
    )
    for cores in (1, 8, 64):
        wall = -(-NUSCENES_SCENES // cores) * per_scene_s + (fixed or 0.0)
        print(f"  {cores:>3} cores: ~{wall / 3600:.1f} h")


if __name__ == "__main__":
    main()
