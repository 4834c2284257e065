"""The deep IRM's cost per map update for Ev-Net trunks of several widths and depths, in turns.

Run: ``python benchmarks/bench_evnet_cost.py [--configs 12x4,8x4,12x4p] [--repeats 30]``.
Each ``WIDTHxDEPTH`` is an :class:`~evgrid.ism.evnet.EvNetConfig` (pool and channels at their
defaults; a trailing ``p``: in the polar frame, its default bins), saved with fresh weights
(cost does not depend on them) and run through
:meth:`DeepIrm.predict` (pooled input, trunk, upsampling into masses) on the synthetic street's
radar sweeps, one thread, every configuration timed in turns (A, B, A, B) so all see the same
machine load. Prints the median and minimum ms and each trunk's parameters.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from harness import in_turns, machine_line

from evgrid.geometry import GridSpec
from evgrid.ism.deep import DeepIrm
from evgrid.ism.evnet import EvNet, EvNetConfig, save_checkpoint
from evgrid_sim.synthetic import street_radar_sweeps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--configs", default="12x4,8x4,8x3", help="WIDTHxDEPTH, comma-separated")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--runtime", default="auto", help="the DeepIrm runtime (default auto)")
    args = ap.parse_args()
    torch.manual_seed(0)
    grid = GridSpec()
    sweeps, ego = street_radar_sweeps(n_sweeps=10, n_detections=100, seed=0)
    fns, params = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.configs.split(","):
            w, d = (int(v) for v in spec.removesuffix("p").split("x"))
            cfg = EvNetConfig(
                width=w, depth=d, frame="polar" if spec.endswith("p") else "cartesian"
            )
            net = EvNet(cfg).eval()
            params[spec] = sum(p.numel() for p in net.parameters())
            path = save_checkpoint(net, Path(tmp) / f"{spec}.safetensors", {"grid": grid.to_dict()})
            irm = DeepIrm(path, grid, threads=1, runtime=args.runtime)
            irm.predict(sweeps, ego)  # builds the runtime
            fns[spec] = lambda irm=irm: irm.predict(sweeps, ego)
        res = in_turns(fns, args.repeats)
    print(machine_line())
    print(f"DeepIrm.predict, runtime {args.runtime}, 1 thread, {args.repeats} calls each in turns")
    print(f"{'trunk':8s} {'params':>9s} {'median ms':>10s} {'min ms':>8s}")
    for spec, r in res.items():
        print(f"{spec:8s} {params[spec]:9,d} {r['median_ms']:10.2f} {r['min_ms']:8.2f}")


if __name__ == "__main__":
    main()
