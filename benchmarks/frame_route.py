"""The code one frame crosses from a recording to the six maps: which of the package's modules
run, and how many lines they hold.

A simulated scene is written as a ROS 2 bag (MCAP storage) with its rig file, then mapped
frame by frame with the geometric ISMs and Ev-Net while a profiler records which source files
of ``evgrid`` execute code; writing the bag is not counted.

    python benchmarks/frame_route.py
"""

from __future__ import annotations

import cProfile
import json
import pstats
import sys
import tempfile
from pathlib import Path

import evgrid


def main() -> None:
    from evgrid.data.bag_writer import write_bag
    from evgrid.mapper import OccupancyMapper
    from evgrid.sources import BagSource
    from evgrid_sim import SimConfig, simulate_scene

    pkg = Path(evgrid.__file__).parent
    with tempfile.TemporaryDirectory() as tmp:
        bag, rig = write_bag(simulate_scene(0, SimConfig(duration_s=1.0)), Path(tmp) / "drive")
        prof = cProfile.Profile()
        prof.enable()
        source = BagSource((str(bag),), str(rig))
        mapper = OccupancyMapper()
        for frame in source.load(source.names()[0]):
            mapper.process(frame)
        prof.disable()
    files = {
        Path(f).resolve()
        for (f, _, _) in pstats.Stats(prof).stats
        if Path(f).resolve().is_relative_to(pkg.resolve())
    }
    rows = sorted(
        (str(f.relative_to(pkg.resolve())), len(f.read_text().splitlines())) for f in files
    )
    print(
        json.dumps(
            {"modules": len(rows), "lines": sum(n for _, n in rows), "files": rows}, indent=1
        )
    )


if __name__ == "__main__":
    sys.exit(main())
