"""The cost of paging a tile out to the tile store and back (docs/store.md).

Maps a short simulated scene with every tile in memory (six maps plus nav, the defaults), then
times moving every tile of every map to a store and bringing it back (``Pager.page_out`` and
``page_in``: compression, the atomic write, the read and decompression), and a read that leaves
the tile on disk (``peek``). Prints milliseconds and bytes per tile. Measures and prints;
asserts nothing.

    nice -n 5 python benchmarks/bench_store_paging.py --duration 10
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=4)
    a = ap.parse_args()
    from evgrid.config import MapperConfig
    from evgrid.fusion import MAP_NAMES
    from evgrid.mapper import OccupancyMapper
    from evgrid.store import StoreParams, TileStore
    from evgrid_sim import SimConfig, simulate_scene

    print("cpu flags:", open("/proc/cpuinfo").read().split("flags")[1].split("\n")[0][:200])
    config = MapperConfig(maps=(*MAP_NAMES, "nav"), store=StoreParams(resident_m=1e9))
    mapper = OccupancyMapper(config)
    for f in simulate_scene(a.seed, SimConfig(duration_s=a.duration)):
        mapper.process(f)
    maps = mapper.maps
    maps.maps["nav"]  # noqa: B018 - brought up to date
    with tempfile.TemporaryDirectory() as tmp:
        store = TileStore(tmp)
        maps.attach_store(store)
        rows = [r.map for r in maps._rows]
        raw = sum(m.nbytes for m in rows)
        n = sum(len(m._tiles) for m in rows)
        t0 = time.perf_counter()
        written = sum(m.pager.page_out(list(m._tiles)) for m in rows)
        t1 = time.perf_counter()
        for m in rows:
            for k in list(m.pager.stored):
                m.tiles[k]  # noqa: B018 - a read that leaves the tile on disk
        t2 = time.perf_counter()
        for m in rows:
            for k in list(m.pager.stored):
                m.tile(k)
        t3 = time.perf_counter()
    out_ms, peek_ms, in_ms = ((b - a_) / n * 1e3 for a_, b in ((t0, t1), (t1, t2), (t2, t3)))
    print(
        f"{n} tiles of {len(rows)} maps ({a.duration:g} s drive): raw {raw / n / 1e6:.2f} MB a "
        f"tile, on disk {written / n / 1e6:.3f} MB a tile (ratio {raw / written:.1f}); "
        f"page out {out_ms:.2f} ms, read from disk {peek_ms:.2f} ms, page in {in_ms:.2f} ms "
        "a tile"
    )
    sizes = np.array([m.nbytes for m in rows])
    print("bytes in memory after paging back:", int(sizes.sum()))


if __name__ == "__main__":
    main()
