"""Tile files of two versions of the tile store, in turns in one process (docs/store.md).

Reads the newest tile files of a store written by ``--old`` (another tree's
``src/evgrid/store.py``, loaded as a module of its own: the store's format before this tree's),
then, tile key by tile key, writes and reads that key's tiles of every map with the old module
and with this tree's (``evgrid.store``: a gated copy in its map's file), checking that every
bit comes back, and prints the bytes of each and the milliseconds per map tile of a write
(encoding, compression, atomic write) and of a read (decompression, decoding), the median over
``--reps`` turns, in wall-clock time and in the process's CPU time (less sensitive to the load
of a shared machine). Turns alternate, so the load falls on both alike. Measures and prints;
asserts nothing but losslessness.

    nice -n 10 python benchmarks/bench_store_codec.py /tmp/s90 --old /work/main/src
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("store", help="a store written by --old's evgrid (e.g. bench_store_disk.py)")
    ap.add_argument("--old", required=True, help="the src folder of the tree that wrote it")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--keys", type=int, default=40, help="tile keys to use (every n-th)")
    a = ap.parse_args()
    import evgrid.store as new

    old = _load(Path(a.old) / "evgrid" / "store.py", "evgrid_store_old")
    print("cpu flags:", open("/proc/cpuinfo").read().split("flags")[1].split("\n")[0][:200])
    root = Path(a.store)
    files: dict[str, dict] = {}
    for g in sorted(root.iterdir()):
        if g.is_dir():
            latest: dict = {}
            for f in os.scandir(g):
                m = old._TILE_NAME.match(f.name)
                if m:
                    k, gen = (int(m[1]), int(m[2])), int(m[3])
                    if k not in latest or latest[k][0] < gen:
                        latest[k] = (gen, Path(f.path))
            files[g.name] = {k: p for k, (_, p) in latest.items()}
    keys = sorted(files["fused"])
    keys = keys[:: max(1, len(keys) // a.keys)]
    tiles = {g: {k: old.read_tile_file(p[k]) for k in keys if k in p} for g, p in files.items()}
    copies = {g[: -len(".gated")] for g in files if g.endswith(".gated")} & set(files)
    n_maps = sum(len(t) for t in tiles.values())
    m0 = tiles["fused"][keys[0]]["masses"]
    new._decode_masses(new._encode_masses(m0), m0.shape)  # numba's compilation, not timed
    times: dict[str, list[float]] = {
        "old write": [],
        "old read": [],
        "new write": [],
        "new read": [],
    }
    size = {"old": 0, "new": 0}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(a.reps):
            for which in ("old", "new") if rep % 2 == 0 else ("new", "old"):
                mod = old if which == "old" else new
                store = mod.TileStore(Path(tmp) / f"{which}{rep}")
                tw = tr = cw = cr = 0.0
                total = 0
                for g, by_key in tiles.items():
                    if which == "new" and g.endswith(".gated") and g[: -len(".gated")] in copies:
                        continue  # written with its map
                    grp = store.group(g)
                    for k, layers in by_key.items():
                        if which == "old":
                            t, c = time.perf_counter(), time.process_time()
                            total += grp.write(k, layers)
                            tw, cw = tw + time.perf_counter() - t, cw + time.process_time() - c
                            t, c = time.perf_counter(), time.process_time()
                            back = {"": grp.read(k)}
                            tr, cr = tr + time.perf_counter() - t, cr + time.process_time() - c
                            want = {"": layers}
                        else:
                            want = {"": layers}
                            if g in copies and k in tiles[g + ".gated"]:
                                want["gated"] = tiles[g + ".gated"][k]
                            t, c = time.perf_counter(), time.process_time()
                            total += grp.write(k, want)
                            tw, cw = tw + time.perf_counter() - t, cw + time.process_time() - c
                            t, c = time.perf_counter(), time.process_time()
                            back = {m: grp.read(k, m) for m in want}  # each as a pager reads it
                            tr, cr = tr + time.perf_counter() - t, cr + time.process_time() - c
                        for m, got in want.items():
                            for name, arr in got.items():
                                b = back[m][name]
                                assert np.array_equal(arr.view(np.uint8), b.view(np.uint8)), (g, k)
                for what, v in (("write", tw), ("read", tr), ("write CPU", cw), ("read CPU", cr)):
                    times.setdefault(f"{which} {what}", []).append(v / n_maps * 1e3)
                size[which] = total
    print(
        f"{len(keys)} tile keys, {n_maps} map tiles ({len(files)} groups in the old store): "
        f"old {size['old'] / 1e6:.1f} MB, new {size['new'] / 1e6:.1f} MB "
        f"({(size['new'] / size['old'] - 1) * 100:+.1f} %)"
    )
    for what, v in sorted(times.items()):
        print(
            f"  {what}: {statistics.median(v):.2f} ms a map tile "
            f"(turns: {', '.join(f'{x:.2f}' for x in v)})"
        )


if __name__ == "__main__":
    main()
