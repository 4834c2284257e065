"""Ev-Net's trunk on each inference option, one core: speed and exactness against torch eager.

Run: ``python benchmarks/bench_runtime.py [--repeats 30] [--compile] [--reduced]``. Options: torch
eager (channels-last, what the torch runtime runs), torch.jit trace + freeze, torch.compile (with
``--compile``: it compiles for minutes on a small machine), ONNX Runtime fp32 (``evgrid[fast]``);
with ``--reduced`` also the reduced precisions: torch bf16, ONNX Runtime fp16 (the graph converted
with fp32 inputs and outputs) and ONNX Runtime int8 (static QDQ quantization, u8 activations, s8
per-channel weights, calibrated on the timed buffer itself: the most favourable case for int8).
Each is timed in turns on the pooled input of the synthetic street's radar sweeps, so all see
the same machine load; the table gives the median and minimum ms, and how far the masses of
each option are from the plain path's (full image, whole Ev-Net on torch): max |dm| and the
number of cells whose largest mass changes.
"""

from __future__ import annotations

import argparse
import copy
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from harness import in_turns, machine_line

from evgrid.ism.deep import DeepIrm, evidence_to_masses, radar_image
from evgrid.ism.runtime import OrtRuntime, evnet_trunk, make_runtime, ort_available, trunk_onnx
from evgrid_sim.synthetic import street_radar_sweeps


def _reduced(model, pooled: np.ndarray) -> dict:
    """The reduced-precision options: torch bf16, ONNX Runtime fp16 and int8."""
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.transformers.float16 import convert_float_to_float16

    bf16 = (
        evnet_trunk(copy.deepcopy(model)).to(torch.bfloat16).to(memory_format=torch.channels_last)
    )  # .to is in place

    def run_bf16(p: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            x = torch.from_numpy(p).to(torch.bfloat16).to(memory_format=torch.channels_last)
            return bf16(x)[0].float().numpy()

    fp32 = trunk_onnx(model, pooled.shape[1:])
    fp16 = convert_float_to_float16(
        onnx.load_from_string(fp32), keep_io_types=True
    ).SerializeToString()

    class _Once(CalibrationDataReader):
        def __init__(self):
            self.left = [{"pooled": pooled}]

        def get_next(self):
            return self.left.pop() if self.left else None

    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        src.write_bytes(fp32)
        logging.getLogger().setLevel(logging.ERROR)  # its advice to pre-process, printed per call
        quantize_static(
            str(src),
            str(dst),
            _Once(),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
        )
        int8 = dst.read_bytes()
    shape = pooled.shape[1:]
    return {
        "torch bf16": run_bf16,
        "onnxruntime fp16": OrtRuntime.from_graph(fp16, shape),
        "onnxruntime int8": OrtRuntime.from_graph(int8, shape),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument(
        "--compile", action="store_true", help="also try torch.compile (slow to compile)"
    )
    ap.add_argument(
        "--reduced", action="store_true", help="also try bf16, fp16 and int8 (needs onnxruntime)"
    )
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
                return compiled(torch.from_numpy(p).to(memory_format=torch.channels_last))[
                    0
                ].numpy()

        t = time.perf_counter()
        run_compiled(pooled)
        print(f"torch.compile: compiled in {time.perf_counter() - t:.0f} s")
        options["torch compile"] = run_compiled
    if ort_available():
        options["onnxruntime fp32"] = make_runtime(
            deep.model, (pooled.shape[1], m, m), "onnxruntime"
        )
    if args.reduced:
        if not ort_available():
            raise SystemExit("--reduced needs onnx and onnxruntime: pip install 'evgrid[fast]'")
        options.update(_reduced(deep.model, pooled))

    ts = in_turns({k: (lambda fn=fn: fn(pooled)) for k, fn in options.items()}, args.repeats)
    print(machine_line())
    print(f"{'option':<20} {'median ms':>10} {'min ms':>8} {'max |dm|':>10} {'class changes':>14}")
    for k, fn in options.items():
        masses = evidence_to_masses(fn(pooled), deep.grid)
        dm = float(np.abs(masses - plain).max())
        changes = int((masses.argmax(-1) != plain.argmax(-1)).sum())
        med, mn = ts[k]["median_ms"], ts[k]["min_ms"]
        print(f"{k:<20} {med:>10.2f} {mn:>8.2f} {dm:>10.2e} {changes:>14d}")


if __name__ == "__main__":
    main()
