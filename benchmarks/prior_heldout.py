"""What the deep IRM's prior calls occupied where nothing is: on the training family and on
world families Ev-Net never trained on (issue 38).

Maps ``--scenes`` simulated scenes of ``--duration`` seconds of each family (``irregular``: the
training family's val-split seeds from ``--first-seed``, default 2000, none of them reserved or
used in training; ``highway``; ``open_road``, the held-out family of docs/simulator.md) with
``--checkpoint`` (default the shipped Ev-Net), once with the deep IRM's guards off and once with
``MapperConfig.prior_guard``'s defaults (docs/equations.md#the-deep-irms-guards), through
:func:`evgrid.runs.map_scene`. Per family and setting, pooled over the scenes:

* ``irm``: the share of truly free cells (the simulator's truth on the keyframes' local grids)
  whose largest deep IRM mass is occupied, on the deep IRM's single frames (as they enter the
  maps, after the guards);
* ``deep_acc`` / ``deep_replace`` / ``deep_disc``: the same share of each deep map over the truth
  of the last keyframe;
* ``lidar free -> disc occ``: the share of the ``ray_ilm`` map's free cells that ``deep_disc``
  calls occupied, over the whole map at the end (the issue's measure on real recordings);
* ``path occ``: cells within 1 m of the vehicle's path that each deep map marks occupied;
* free / occupied IoU against the truth after 1 s (``convergence_truth``, evgrid.runs).

Run: ``PYTHONPATH=src python benchmarks/prior_heldout.py --scenes 3 --duration 4``. Measures and
prints; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, replace

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from evgrid.classes import FREE, OCCUPIED  # noqa: E402
from evgrid.config import MapperConfig, OutputConfig  # noqa: E402
from evgrid.evaluate import classify  # noqa: E402
from evgrid.ism.prior_guard import PriorGuardParams  # noqa: E402
from evgrid.runs import map_scene  # noqa: E402
from evgrid.sources import SimSource  # noqa: E402
from evgrid.store import ALL_RESIDENT_M, StoreParams  # noqa: E402

DEEP = ("deep_acc", "deep_replace", "deep_disc")
FAMILIES = ("irregular", "highway", "open_road")
PATH_M = 1.0


@dataclass(frozen=True)
class FamilySource(SimSource):
    """Simulated scenes of one world family (``WorldConfig.layout``)."""

    layout: str = "irregular"

    def config(self, seed: int):
        c = super().config(seed)
        return replace(c, world=replace(c.world, layout=self.layout))


class Watch:
    """At each keyframe: the deep IRM's single frame and each deep map against the truth."""

    def __init__(self):
        self.irm = np.zeros(2, np.int64)  # truly free cells called occupied, truly free cells
        self.last: dict[str, np.ndarray] = {}
        self.maps = None

    def on_update(self, u) -> None:
        self.maps = u.maps
        truth = u.frame.occupancy
        if truth is None or "deep_irm" not in u.isms:
            return
        free = truth == 0
        self.irm += (np.count_nonzero(free & (classify(u.isms["deep_irm"]) == OCCUPIED)),
                     np.count_nonzero(free))  # fmt: skip
        grid = u.maps.grid
        rows, cols = np.nonzero(free)
        xy = u.pose.apply(np.stack(grid.cell_to_xy(rows, cols), axis=1))
        mr, mc = grid.map_xy_to_cell(xy[:, 0], xy[:, 1])
        r0, c0 = mr.min(), mc.min()
        for name in DEEP:
            m, _ = u.maps[name].read(r0, c0, mr.max() - r0 + 1, mc.max() - c0 + 1)
            occ = classify(m)[mr - r0, mc - c0] == OCCUPIED
            self.last[name] = np.array([np.count_nonzero(occ), len(occ)])


def _path_cells(grid, trajectory, shape, r0, c0) -> np.ndarray:
    """A mask of the dense map's cells within PATH_M of the vehicle's path."""
    xy = np.asarray(trajectory)[:, :2]
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    fine = np.arange(0.0, s[-1] + 1e-9, 0.05)
    px, py = np.interp(fine, s, xy[:, 0]), np.interp(fine, s, xy[:, 1])
    rows, cols = np.indices(shape)
    cx, cy = grid.map_cell_to_xy(rows + r0, cols + c0)
    near = np.zeros(shape, bool)
    for x, y in zip(px, py):
        near |= (cx - x) ** 2 + (cy - y) ** 2 <= PATH_M**2
    return near


def scene_figures(frames: list, name: str, config) -> dict:
    watch = Watch()
    res = map_scene(
        frames, None, config, OutputConfig(), name=name, observers=(watch,), fixed_frame="world"
    )
    out = {"irm": watch.irm, **watch.last}
    ilm, _, r0, c0 = watch.maps["ray_ilm"].to_dense()
    shape = ilm.shape[:2]
    ilm_free = classify(ilm) == FREE
    near = _path_cells(config.grid, res.metrics["trajectory"], shape, r0, c0)
    for n in DEEP:
        m, _ = watch.maps[n].read(r0, c0, *shape)
        occ = classify(m) == OCCUPIED
        out[f"path_{n}"] = int(np.count_nonzero(near & occ))
        if n == "deep_disc":
            out["lidar_free"] = np.array(
                [np.count_nonzero(ilm_free & occ), np.count_nonzero(ilm_free)]
            )
    conv = res.metrics["convergence_truth"]["maps"]
    out["iou1"] = {n: (conv[n]["free"][0], conv[n]["occupied"][0]) for n in DEEP}
    return out


def _pct(a) -> str:
    return f"{100.0 * a[0] / a[1]:.2f} %" if a[1] else "n/a"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--checkpoint", default=None, help="Ev-Net weights (default: the shipped)")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument(
        "--support-m",
        type=float,
        default=PriorGuardParams().support_m,
        help="the support radius of the settings with support (default: the default)",
    )
    args = ap.parse_args()
    base = MapperConfig(
        maps=("ray_ilm",) + DEEP,
        checkpoint=args.checkpoint,
        frame="first_pose",
        store=StoreParams(resident_m=ALL_RESIDENT_M),
    )
    settings = {
        "guards off": PriorGuardParams(support_m=None, path_m=None),
        "support only": PriorGuardParams(support_m=args.support_m, path_m=None),
        "path only": PriorGuardParams(support_m=None),
        "both": PriorGuardParams(support_m=args.support_m),
    }
    seeds = SimSource.split("val", args.scenes, args.first_seed).seeds
    print(f"checkpoint: {args.checkpoint or 'shipped'}; {args.scenes} scenes of "
          f"{args.duration:g} s a family, seeds {seeds}; support_m {args.support_m:g}")  # fmt: skip
    head = ("| family | guards | irm | " + " | ".join(DEEP) + " | lidar free -> disc occ | "
            + " | ".join(f"path occ {n}" for n in DEEP)
            + " | " + " | ".join(f"{n} IoU free/occ 1 s" for n in DEEP)
            + " | mapping s |")  # fmt: skip
    print(head)
    print("|" + " --- |" * (head.count("|") - 1))
    for family in args.families.split(","):
        src = FamilySource(seeds, args.duration, layout=family)
        rows: dict[str, list] = {label: [] for label in settings}
        seconds = dict.fromkeys(settings, 0.0)
        for name in src.names():
            frames = list(src.load(name))  # simulated once, mapped in every setting
            for label, guard in settings.items():
                t = time.perf_counter()
                rows[label].append(scene_figures(frames, name, replace(base, prior_guard=guard)))
                seconds[label] += time.perf_counter() - t
        for label in settings:
            _print_row(family, label, rows[label], seconds[label])


def _print_row(family: str, label: str, rows: list, seconds: float) -> None:
    agg = {k: sum(r[k] for r in rows) for k in ("irm", "lidar_free", *DEEP)}
    path = [sum(r[f"path_{n}"] for r in rows) for n in DEEP]
    iou = [np.nanmean([[np.nan if v is None else v for v in r["iou1"][n]] for r in rows], axis=0)
           for n in DEEP]  # fmt: skip
    print(f"| {family} | {label} | {_pct(agg['irm'])} | "
          + " | ".join(_pct(agg[n]) for n in DEEP) + f" | {_pct(agg['lidar_free'])} | "
          + " | ".join(str(p) for p in path) + " | "
          + " | ".join(f"{100 * f:.1f} / {100 * o:.1f}" for f, o in iou)
          + f" | {seconds:.0f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
