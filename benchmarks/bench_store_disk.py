"""The tile store's bytes on disk per km^2 (docs/store.md#bytes-on-disk).

Maps a simulated drive (six maps plus nav, the defaults: 50 m resident radius, dynamic score,
nav's gated inputs) into a store in ``--out``, writes every tile still in memory to it at the
end (``flush``: the store then holds each map whole, newest generation only, no checkpoint),
and prints the bytes of each group's tile files, per km^2 of the tiles' area (the fused map's
tiles, 20 m squares by default) and per km^2 of the cells covered. Import evgrid from another
tree with ``PYTHONPATH`` to measure it on the same drive. Measures and prints; asserts nothing.

    PYTHONPATH=src nice -n 10 python benchmarks/bench_store_disk.py --duration 90 --out /tmp/s
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--duration", type=float, default=90.0)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--out", required=True, help="the store's folder (replaced)")
    a = ap.parse_args()
    import evgrid
    from evgrid.config import MapperConfig
    from evgrid.fusion import MAP_NAMES
    from evgrid.mapper import OccupancyMapper
    from evgrid.store import TileStore
    from evgrid_sim import SimConfig, simulate_scene

    print("evgrid:", evgrid.__file__)
    print("cpu flags:", open("/proc/cpuinfo").read().split("flags")[1].split("\n")[0][:200])
    out = Path(a.out)
    shutil.rmtree(out, ignore_errors=True)
    config = MapperConfig(maps=(*MAP_NAMES, "nav"))
    mapper = OccupancyMapper(config, store=TileStore(out))
    t0 = time.perf_counter()
    for frame in simulate_scene(a.seed, SimConfig(duration_s=a.duration)):
        mapper.process(frame)
    maps = mapper.maps.maps  # nav brought up to date
    t1 = time.perf_counter()
    rows = [r.map for r in mapper.maps._rows]
    for m in rows:
        m.flush()
    fused = maps["fused"]
    keys = list(fused.tiles)
    res, ts = config.grid.resolution, config.tile_cells
    tile_km2 = len(keys) * (ts * res) ** 2 * 1e-6
    covered_km2 = sum(int(fused.covered_tiles[k].sum()) for k in keys) * res**2 * 1e-6
    groups = {}
    for g in sorted(os.scandir(out), key=lambda e: e.name):
        if g.is_dir():
            groups[g.name] = sum(
                f.stat().st_size for f in os.scandir(g.path) if f.name.endswith(".tile")
            )
    total = sum(groups.values())
    print(
        json.dumps(
            {
                "duration_s": a.duration,
                "seed": a.seed,
                "mapping_s": round(t1 - t0, 1),
                "tiles": len(keys),
                "tile_km2": round(tile_km2, 5),
                "covered_km2": round(covered_km2, 5),
                "bytes": total,
                "GB_per_km2_of_tiles": round(total / tile_km2 / 1e9, 3),
                "GB_per_km2_covered": round(total / covered_km2 / 1e9, 3),
                "MB_per_group": {g: round(b / 1e6, 2) for g, b in groups.items()},
            }
        )
    )
    mapper.close()


if __name__ == "__main__":
    main()
