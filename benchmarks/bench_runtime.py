"""Ev-Net's trunk on each inference option, one core: speed and exactness against torch eager.

Run: ``python benchmarks/bench_runtime.py [--repeats 30] [--compile]``. Options: torch eager
(channels-last, what the torch runtime runs), torch.jit trace + freeze, torch.compile (with
``--compile``: it compiles for minutes on a small machine), ONNX Runtime fp32 (``evgrid[fast]``).
Each is timed in turns on the pooled input of the synthetic street's radar sweeps, so all see
the same machine load; the table gives the median and minimum ms, and how far the masses of
each option are from the plain path's (full image, whole Ev-Net on torch): max |dm| and the
number of cells whose largest mass changes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from evgrid.ism.deep import DeepIrm, evidence_to_masses, radar_image
from evgrid.ism.runtime import evnet_trunk, make_runtime, ort_available
from evgrid.ism.synthetic import street_radar_sweeps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--compile", action="store_true", help="also try torch.compile (slow to compile)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    deep = DeepIrm(runtime="torch")
    sweeps, ego = street_radar_sweeps()
    plain = deep.predict_image(radar_image(sweeps, ego, deep.grid, None, deep.params))
    pooled = deep.pooled_input(sweeps, ego).copy()
    x = torch.from_numpy(pooled).to(memory_format=torch.channels_last)
    m = pooled.shape[-1]

    options = {"torch eager": make_runtime(deep.model, (pooled.shape[1], m, m), "torch")}
    trunk = evnet_trunk(deep.model)
    with torch.no_grad():
        frozen = torch.jit.freeze(torch.jit.trace(trunk, x).eval())

    def run_frozen(p: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return frozen(torch.from_numpy(p).to(memory_format=torch.channels_last))[0].numpy()

    options["torch jit freeze"] = run_frozen
    if args.compile:
        compiled = torch.compile(trunk)

        def run_compiled(p: np.ndarray) -> np.ndarray:
            with torch.inference_mode():
                return compiled(torch.from_numpy(p).to(memory_format=torch.channels_last))[0].numpy()

        t = time.perf_counter()
        run_compiled(pooled)
        print(f"torch.compile: compiled in {time.perf_counter() - t:.0f} s")
        options["torch compile"] = run_compiled
    if ort_available():
        options["onnxruntime fp32"] = make_runtime(deep.model, (pooled.shape[1], m, m), "onnxruntime")

    for fn in options.values():
        fn(pooled)
    ts: dict[str, list[float]] = {k: [] for k in options}
    for _ in range(args.repeats):
        for k, fn in options.items():
            t = time.perf_counter()
            fn(pooled)
            ts[k].append((time.perf_counter() - t) * 1e3)
    print(f"{'option':<20} {'median ms':>10} {'min ms':>8} {'max |dm|':>10} {'class changes':>14}")
    for k, fn in options.items():
        masses = evidence_to_masses(fn(pooled), deep.grid)
        dm = float(np.abs(masses - plain).max())
        changes = int((masses.argmax(-1) != plain.argmax(-1)).sum())
        print(f"{k:<20} {np.median(ts[k]):>10.2f} {np.min(ts[k]):>8.2f} {dm:>10.2e} {changes:>14d}")


if __name__ == "__main__":
    main()
