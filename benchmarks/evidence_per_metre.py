"""Evidence per metre against the paper's per look, paired on the same simulated scenes.

Maps each scene twice with the default MapperConfig, once with ``mapper.evidence.mode =
per_look`` (before: the paper's constants) and once with the default ``per_metre`` (after), and
prints for each: Table I (against ``ray_ilm``), IoU against the simulator's truth, the
convergence of free IoU against the truth after 1, 2, 5 and 10 s, and the share of the truly
free cells the ``ray_ilm`` map has seen (m_u < 1) that it calls free (its free recall); then
the paired differences after minus before with their 95 % bootstrap intervals over scenes.

``--family highway``: highway drives (``WorldConfig(layout="highway")``) at ``--speed`` m/s
(default 30), seeds from 0. ``--family city``: the simulator's validation scenes from seed
1000 on (the scenes of benchmarks/claims_at_scale.py), towns at city speeds. Each scene's
metrics go to ``OUT/<family>/<mode>/<scene>.json`` as it finishes; a second run keeps them.

Run (one core): ``PYTHONPATH=src nice -n 5 python benchmarks/evidence_per_metre.py --family
highway --scenes 5 --duration 10``. Prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from evgrid.classes import CLASSES  # noqa: E402
from evgrid.config import MapperConfig, OutputConfig  # noqa: E402
from evgrid.evaluate import FREE, bootstrap_interval, classify  # noqa: E402
from evgrid.ism.evidence import EvidenceParams  # noqa: E402
from evgrid.observers import TruthTracker  # noqa: E402
from evgrid.runs import map_scene  # noqa: E402
from evgrid.sources import SimSource  # noqa: E402
from evgrid_sim import SimConfig, WorldConfig, scene_name, simulate_scene  # noqa: E402

MODES = ("per_look", "per_metre")


class _Keep:
    """Watches the updates: the true occupancy, and the map set at the end."""

    def __init__(self, config: MapperConfig) -> None:
        self.truth = TruthTracker(config.grid, config.tile_cells)
        self.maps = None

    def on_update(self, update) -> None:
        self.truth.on_update(update)
        self.maps = update.maps


def free_recall(keep: _Keep) -> float:
    """The share of the truly free cells the ray_ilm map has seen (evidence on them: m_u < 1)
    that it calls free."""
    lidar = keep.maps["ray_ilm"]
    seen = called = 0
    for key, truth in keep.truth.map.tiles.items():
        if key not in lidar.tiles:
            continue
        free = keep.truth.map.covered_tiles[key] & (classify(truth) == FREE)
        m = lidar.tiles[key]
        look = free & lidar.covered_tiles[key] & (m[..., 2] < 1.0)
        seen += int(look.sum())
        called += int((look & (classify(m) == FREE)).sum())
    return called / seen if seen else math.nan


def scenes(family: str, n: int, duration: float, speed: float) -> list[tuple[str, Any]]:
    """(name, scene factory) of each scene."""
    if family == "highway":
        cfg = SimConfig(
            duration_s=duration,
            world=WorldConfig(layout="highway", highway_speed_mps=(speed, speed)),
        )
        return [(scene_name(s), lambda s=s: simulate_scene(s, cfg)) for s in range(n)]
    source = SimSource.split("val", n, first_seed=1000, duration_s=duration)
    return [(name, lambda name=name: source.load(name)) for name in source.names()]


def map_one(make, name: str, mode: str, reference_m: float | None = None) -> dict[str, Any]:
    evidence = EvidenceParams(mode=mode)
    if reference_m is not None:
        evidence = replace(evidence, reference_m=reference_m)
    config = MapperConfig(evidence=evidence)
    outputs = replace(OutputConfig(), figures=False, save_maps=False, exports=())
    keep = _Keep(config)
    scene = make()
    m = map_scene(scene, None, config, outputs, name=name, observers=(keep,)).metrics
    v = scene.trajectory.speed_at(np.arange(0.0, scene.config.duration_s, 0.1))
    return {
        "scene": name,
        "ray_ilm_free_recall": free_recall(keep),
        "mean_speed_mps": float(v.mean()),
        **{k: m[k] for k in ("vs_ray_ilm", "vs_truth", "convergence_truth", "seconds")},
        "frames": m["frames"],
        "timings_ms": m["timings_ms"],
        "counts": {},
    }


def _pct(ci: dict[str, float], signed: bool = False) -> str:
    if not ci or ci["n"] == 0 or math.isnan(ci["mean"]):
        return "n/a"
    f = "+.1f" if signed else ".1f"
    mid = f"{100 * ci['mean']:{f}}"
    return mid if ci["n"] < 2 else f"{mid} ({100 * ci['lo']:{f}} to {100 * ci['hi']:{f}})"


def _rows(per: dict[str, list[dict]]) -> list[tuple[str, Any]]:
    """(label, getter) of every figure compared."""
    first = per[MODES[0]][0]
    rows: list[tuple[str, Any]] = [("ray_ilm free recall", lambda m: m["ray_ilm_free_recall"])]
    for n in first["vs_ray_ilm"]:
        for c in CLASSES:
            rows.append((f"Table I {n} {c}", lambda m, n=n, c=c: m["vs_ray_ilm"][n][c]))
    for n in first["vs_truth"]:
        for c in ("free", "occupied"):
            rows.append((f"vs truth {n} {c}", lambda m, n=n, c=c: m["vs_truth"][n][c]))
    conv = first["convergence_truth"]
    for n in conv["maps"]:
        for i, t in enumerate(conv["t_s"]):
            rows.append(
                (f"free vs truth after {t:g} s {n}",
                 lambda m, n=n, i=i: m["convergence_truth"]["maps"][n]["free"][i])
            )  # fmt: skip
    return rows


def report(per: dict[str, list[dict]]) -> str:
    names = [m["scene"] for m in per[MODES[0]]]
    by = {mode: {m["scene"]: m for m in per[mode]} for mode in MODES}
    common = [n for n in names if all(n in by[mode] for mode in MODES)]
    speed = np.mean([by[MODES[0]][n]["mean_speed_mps"] for n in common])
    lines = [
        f"{len(common)} scene(s) paired, mean ego speed {speed:.1f} m/s; IoU in %, mean (95% "
        "bootstrap interval over scenes); after - before in percentage points, paired",
        "",
        "| figure | before (per_look) | after (per_metre) | after - before |",
        "|---|---|---|---|",
    ]
    for label, get in _rows(per):

        def val(mode: str, n: str) -> float | None:
            v = get(by[mode][n])
            return None if v is None or (isinstance(v, float) and math.isnan(v)) else v

        before = bootstrap_interval(val("per_look", n) for n in common)
        after = bootstrap_interval(val("per_metre", n) for n in common)
        diffs = [
            val("per_metre", n) - val("per_look", n)
            for n in common
            if val("per_metre", n) is not None and val("per_look", n) is not None
        ]
        d = bootstrap_interval(diffs)
        if before["n"] == 0 and after["n"] == 0:
            continue  # (convergence after the scene's end)
        lines.append(f"| {label} | {_pct(before)} | {_pct(after)} | {_pct(d, True)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--family", choices=("highway", "city"), default="highway")
    ap.add_argument("--scenes", type=int, default=5)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--speed", type=float, default=30.0, help="highway ego speed, m/s")
    ap.add_argument("--out", type=Path, default=Path("out/evidence_per_metre"))
    ap.add_argument(
        "--reference-m", type=float, default=None, help="per_metre's reference distance (m)"
    )
    a = ap.parse_args(argv)
    per: dict[str, list[dict]] = {mode: [] for mode in MODES}
    t0 = time.perf_counter()
    for name, make in scenes(a.family, a.scenes, a.duration, a.speed):
        for mode in MODES:
            path = a.out / a.family / mode / f"{name}.json"
            if path.exists():
                m = json.loads(path.read_text())
            else:
                m = map_one(make, name, mode, a.reference_m)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(m))
            per[mode].append(m)
            print(
                f"{name} {mode}: ray_ilm free recall {m['ray_ilm_free_recall']:.3f}, "
                f"{m['mean_speed_mps']:.1f} m/s ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
    print(f"\n{a.family}, {a.duration:g} s scenes\n")
    print(report(per))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
