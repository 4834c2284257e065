"""Exports: file sizes and run time with every export against none, on one simulated drive.

Maps one simulated scene as ``evgrid map`` does (six maps, figures, GIF), in turns without
exports and with ``nav2,mcap,rerun`` at their defaults, and prints each file's size, the best
wall time of each and their ratio. Runs on any evgrid commit that has ``evgrid.runs.map_scene``
(put that commit's ``src`` first on PYTHONPATH), so the same script measures before and after
(with the current code, the MCAP at ``McapParams``' defaults, whatever window the run's
``OutputConfig.export_window_m`` still says):

    git archive 6e6d98d src | tar -x -C /tmp/before
    PYTHONPATH=/tmp/before/src python benchmarks/bench_exports.py      # before
    PYTHONPATH=src python benchmarks/bench_exports.py                  # after

With the current code it also splits the MCAP into its final maps (written alone with
``write_maps_mcap``) and the rest (windows, poses), and extrapolates a long drive: the rest
grows with driving time, the final maps with the area mapped (``--extrapolate-s``,
``--extrapolate-km2``). Measures and prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path


def _files(folder: Path) -> dict[str, int]:
    return {
        str(p.relative_to(folder)): p.stat().st_size
        for p in sorted(folder.rglob("*"))
        if p.is_file() and (p.suffix in (".mcap", ".rrd", ".pgm", ".yaml"))
    }


class _Last:
    """Keeps the last update's maps (for the final-maps split)."""

    maps: dict = {}

    def on_update(self, update) -> None:
        self.maps = update.maps.maps


def run(frames, exports: tuple[str, ...], tmp: Path, k: int) -> tuple[float, dict, dict]:
    from evgrid.config import OutputConfig
    from evgrid.runs import map_scene

    out = tmp / f"run{k}-{'-'.join(exports) or 'none'}"
    last = _Last()
    outputs = dataclasses.replace(OutputConfig(), exports=exports)
    try:  # the exporter's own default window, where the run's config still carries another
        from evgrid.export.mcap import McapParams

        if hasattr(outputs, "export_window_m"):
            outputs = dataclasses.replace(outputs, export_window_m=McapParams().window_m)
    except ImportError:
        pass  # an older evgrid: its run's defaults as they were
    t0 = time.perf_counter()
    map_scene(
        frames,
        out,
        outputs=outputs,
        name="scene",
        observers=(last,),
    )
    return time.perf_counter() - t0, _files(out), last.maps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=4.0, help="seconds of driving")
    ap.add_argument("--repeat", type=int, default=2, help="turns of (none, all)")
    ap.add_argument("--exports", default="nav2,mcap,rerun")
    ap.add_argument("--extrapolate-s", type=float, default=600.0)
    ap.add_argument("--extrapolate-km2", type=float, default=0.2)
    args = ap.parse_args()

    from evgrid_sim import SimConfig, simulate_scene

    frames = list(simulate_scene(args.seed, SimConfig(duration_s=args.duration)))
    xy = [f.ego_pose.translation[:2] for f in frames]
    dist = sum(float(((b - a) ** 2).sum() ** 0.5) for a, b in zip(xy, xy[1:]))
    print(f"scene: seed {args.seed}, {args.duration:g} s, {len(frames)} frames, {dist:.1f} m")
    exports = tuple(e for e in args.exports.split(",") if e)
    times: dict[str, list[float]] = {"none": [], "all": []}
    sizes: dict[str, int] = {}
    maps: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeat):
            for key, ex in (("none", ()), ("all", exports)):
                wall, files, last = run(frames, ex, Path(tmp), k)
                times[key].append(wall)
                if ex:
                    sizes, maps = files, last
                print(f"  turn {k}: {key:4s} {wall:7.1f} s", flush=True)
        print("files with all exports (bytes):")
        for name, n in sizes.items():
            print(f"  {name:40s} {n:>12,d}  ({n / 1e6:.2f} MB)")
        best = {k: min(v) for k, v in times.items()}
        print(
            f"best wall time: none {best['none']:.1f} s, all {best['all']:.1f} s, "
            f"ratio {best['all'] / best['none']:.2f}"
        )
        _split(sizes, maps, Path(tmp), args)


def _split(sizes: dict, maps: dict, tmp: Path, args) -> None:
    try:
        from evgrid.export.mcap import write_maps_mcap
    except ImportError:
        return  # an older evgrid: no split
    mcap = [n for n in sizes if n.endswith(".mcap")]
    if not mcap or not maps:
        return
    final = write_maps_mcap(maps, tmp / "final_only.mcap")
    final_b = os.path.getsize(final)
    rest_b = sizes[mcap[0]] - final_b
    ref = maps.get("ray_ilm") or next(iter(maps.values()))
    res = ref.grid.resolution
    area_m2 = sum(int(c.sum()) for c in ref.covered_tiles.values()) * res * res
    per_s = rest_b / args.duration
    per_m2 = final_b / area_m2
    est = per_s * args.extrapolate_s + per_m2 * args.extrapolate_km2 * 1e6
    print(
        f"MCAP split: final maps {final_b:,d} B over {area_m2:,.0f} m2 mapped "
        f"({per_m2:.1f} B/m2), the rest {rest_b:,d} B ({per_s / 1e3:.1f} kB per s of driving)"
    )
    print(
        f"extrapolated MCAP for {args.extrapolate_s:g} s over {args.extrapolate_km2:g} km2: "
        f"{est / 1e6:.0f} MB (rest x time + final maps x area)"
    )


if __name__ == "__main__":
    main()
