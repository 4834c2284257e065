"""Self-returns on simulated rigs: what the default filter removes and what it does to the
ray_ilm map.

``--bodies``: the phantom trail on short drives of vehicles that are not the nuScenes car
(``evgrid.data.mounts.OTHER_VEHICLES``: a car with a roof box, a van, a truck cab, and the
nuScenes car itself): occupied ray_ilm cells within 1 m of the driven path, without body
returns, with them and the filter before the body is grown from the prior
(``grow_travel_m=0``), and with the default filter.

    PYTHONPATH=src python benchmarks/rigs_self_returns.py --bodies --seeds 4,9 --duration 3

For each rig (the nuScenes rig: 20 Hz lidar, five 13 Hz radars; and a 10 Hz lidar with three
4 Hz radars, read back through the nuScenes layout) and each seed, the ray_ilm map is built
three ways: a car without self-returns, a car with them mapped with ``--self-returns off``, and
with them mapped with the default (auto). Prints the fraction of free cells within 10 m of the
driven path, and, per nuScenes-like sweep, the body returns and what the default removed.

    PYTHONPATH=src python benchmarks/rigs_self_returns.py --seeds 4,9 --duration 10
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
from harness import machine_line

from evgrid.classes import OCCUPIED
from evgrid.config import MapperConfig
from evgrid.data.mounts import NUSCENES_CAR, OTHER_VEHICLES, Vehicle
from evgrid.evaluate import classify
from evgrid.mapper import OccupancyMapper
from evgrid.preprocess import SelfReturnFilter, SelfReturnParams
from evgrid_sim import SimConfig, simulate_scene
from evgrid_sim.config import LidarConfig, SimRadarRig
from evgrid_sim.lidar import EGO_HIT, LidarModel
from tests.helpers import free_fraction_near_path

RIGS = {
    "nuscenes (20 Hz lidar, 5 x 13 Hz radar)": (20.0, SimRadarRig()),
    "10 Hz lidar, 3 x 4 Hz radar (nuScenes layout)": (
        10.0,
        SimRadarRig(
            radar_channels=("RADAR_FRONT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT"),
            radar_rates_hz=(4.0,),
        ),
    ),
}


def free_near_path(mapper: OccupancyMapper, radius_m: float = 10.0) -> float:
    """Fraction of the ray_ilm map's cells within ``radius_m`` of the driven path that are free."""
    return free_fraction_near_path(mapper.maps["ray_ilm"], mapper.trajectory, radius_m)


def occupied_near_path(mapper: OccupancyMapper, radius_m: float = 1.0) -> int:
    """Cells of the ray_ilm map within ``radius_m`` of the driven path (the polyline through
    the map updates' poses) that are classified occupied."""
    import cv2

    m = mapper.maps["ray_ilm"]
    masses, _, r0, c0 = m.to_dense()
    path = np.full(masses.shape[:2], 255, np.uint8)
    pts = []
    for x, y, _ in mapper.trajectory:
        rc, cc = m.grid.map_xy_to_cell(x, y)
        pts.append((int(cc) - c0, int(rc) - r0))
    cv2.polylines(path, [np.array(pts, np.int32)], False, 0, 1)
    near = cv2.distanceTransform(path, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * m.grid.resolution
    return int((classify(masses)[near <= radius_m] == OCCUPIED).sum())


def vehicle_scene(seed: int, cfg: SimConfig, vehicle: Vehicle):
    """A simulated scene whose lidar sits on ``vehicle`` and sees its body."""
    sc = simulate_scene(seed, cfg)
    sc._lidar = LidarModel(cfg.lidar, vehicle.lidar, vehicle.body_boxes)
    return sc


def phantom_trail(seed: int, duration: float, vehicle: Vehicle) -> dict[str, float]:
    """Occupied cells within 1 m of the path: no body returns / grow off / default."""
    out: dict[str, float] = {}
    runs = (
        ("no body", False, SelfReturnParams()),
        ("before", True, SelfReturnParams(grow_travel_m=0.0)),
        ("after", True, SelfReturnParams()),
    )
    for name, body, params in runs:
        cfg = SimConfig(duration_s=duration, lidar=LidarConfig(self_returns=body))
        mapper = OccupancyMapper(MapperConfig(maps=("ray_ilm",), self_returns=params))
        for f in vehicle_scene(seed, cfg, vehicle):
            mapper.process(f)
        out[name] = occupied_near_path(mapper)
        xy = np.array(mapper.trajectory)[:, :2]
        out["path_m"] = float(np.hypot(*np.diff(xy, axis=0).T).sum())
        if name == "after":
            box = mapper.preprocess.self_returns.body_box
            out["box"] = tuple(round(v, 2) for v in box.as_tuple()) if box else None
    return out


def bodies(seeds: list[int], duration: float) -> None:
    print(machine_line())
    print(f"occupied ray_ilm cells within 1 m of the path ({duration:g} s drives, seeds {seeds})")
    print("| vehicle | seed | path (m) | no body returns | before | after | body box after |")
    print("|---|---|---|---|---|---|---|")
    for v in (NUSCENES_CAR, *OTHER_VEHICLES.values()):
        for seed in seeds:
            t = time.perf_counter()
            r = phantom_trail(seed, duration, v)
            print(
                f"| {v.name} | {seed} | {r['path_m']:.1f} | {r['no body']} | {r['before']} | "
                f"{r['after']} | {r['box']} |  ({time.perf_counter() - t:.0f} s)",
                flush=True,
            )


def scene_frames(seed: int, cfg: SimConfig, via_nuscenes: bool):
    sc = simulate_scene(seed, cfg)
    if not via_nuscenes:
        return sc
    from evgrid.data.nuscenes import load_nuscenes
    from evgrid.data.nuscenes_format import write_nuscenes

    root = tempfile.mkdtemp(prefix="evgrid-rig-")
    write_nuscenes([sc], root, splits={"val": [sc.name]})
    return load_nuscenes(root, "v1.0-sim", split="val")[0]


def map_free(frames, mode: str) -> tuple[float, dict]:
    mapper = OccupancyMapper(
        MapperConfig(maps=("ray_ilm",), self_returns=SelfReturnParams(mode=mode))
    )
    for f in frames:
        mapper.process(f)
    return free_near_path(mapper), mapper.counts()


def removal_stats(seed: int, duration: float) -> dict[str, float]:
    """Per 20 Hz nuScenes-like sweep: body returns, removed by the default, of them body, other."""
    sc = simulate_scene(seed, SimConfig(duration_s=duration))
    f = SelfReturnFilter(SelfReturnParams())
    body = removed = removed_body = 0
    n = 0
    for i in range(0, len(sc), 2):  # the sweeps the 10 Hz map updates see
        sweep, hit = sc.lidar_sweep(i)
        keep_ids = {tuple(p) for p in f(sweep).points[:, :3].tolist()}
        gone = np.array([tuple(p) not in keep_ids for p in sweep.points[:, :3].tolist()])
        is_body = hit == EGO_HIT
        body += int(is_body.sum())
        removed += int(gone.sum())
        removed_body += int((gone & is_body).sum())
        n += 1
    return {
        "sweeps": n,
        "body_per_sweep": body / n,
        "removed_per_sweep": removed / n,
        "body_removed_pct": 100.0 * removed_body / max(body, 1),
        "other_removed_per_sweep": (removed - removed_body) / n,
        "learnt_box": f.learnt_box.as_tuple() if f.learnt_box else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="4,9")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--bodies", action="store_true", help="the phantom trail of other bodies")
    a = ap.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    if a.bodies:
        bodies(seeds, a.duration)
        return
    print(
        "free fraction of ray_ilm cells within 10 m of the path "
        f"({a.duration:g} s scenes, seeds {seeds})"
    )
    print(
        "| rig | seed | no self-returns | self-returns, --self-returns off "
        "| self-returns, default (auto) |"
    )
    print("|---|---|---|---|---|")
    for name, (rate, rig) in RIGS.items():
        via = rate == 10.0
        for seed in seeds:
            t = time.perf_counter()
            row = []
            for sr, mode in ((False, "auto"), (True, "off"), (True, "auto")):
                lidar = LidarConfig(rate_hz=rate, self_returns=sr)
                cfg = SimConfig(duration_s=a.duration, lidar=lidar, rig=rig)
                row.append(map_free(scene_frames(seed, cfg, via), mode)[0])
            took = time.perf_counter() - t
            print(
                f"| {name} | {seed} | {row[0]:.4f} | {row[1]:.4f} | {row[2]:.4f} |  ({took:.0f} s)",
                flush=True,
            )
    for seed in seeds:
        stats = removal_stats(seed, a.duration)
        print(f"default filter on nuScenes-like sweeps, seed {seed}: {stats}", flush=True)


if __name__ == "__main__":
    main()
