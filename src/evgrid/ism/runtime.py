"""Inference runtimes for Ev-Net's trunk: ONNX Runtime when installed, torch otherwise.

The deep IRM's fast path (:meth:`evgrid.ism.deep.DeepIrm.predict`) builds Ev-Net's max-pooled
input itself and upsamples the evidence itself, so a runtime runs only the trunk between the
two: ``(1, C, n/p, n/p)`` pooled input -> ``(2, n/p, n/p)`` evidence ``[e_f, e_o]`` >= 0.

ONNX Runtime fp32 runs the trunk faster than torch eager on one core, with masses equal within
1e-6 (the figures, with their commit and machine: docs/speed.md); torch stays the training
framework and the fallback when ``onnxruntime`` is missing (the ``fast`` extra).
The ONNX graph is exported from the loaded model in memory on first use, so a checkpoint is the
only file to ship.
"""

from __future__ import annotations

import io
import logging
import warnings
from typing import Protocol

import numpy as np

from evgrid.package import install_hint

__all__ = [
    "RUNTIMES",
    "EvNetRuntime",
    "TorchRuntime",
    "OrtRuntime",
    "evnet_trunk",
    "make_runtime",
    "trunk_onnx",
    "ort_available",
]

logger = logging.getLogger(__name__)

#: Runtime names: ``auto`` is ``onnxruntime`` when it is installed, else ``torch``.
RUNTIMES: tuple[str, ...] = ("auto", "onnxruntime", "torch")

_warned_fallback = False


class EvNetRuntime(Protocol):
    """Runs Ev-Net's trunk on a pooled input ``(1, C, h, w)`` float32; returns evidence ``(2, h,
    w)`` float32."""

    name: str

    def __call__(self, pooled: np.ndarray) -> np.ndarray: ...


def evnet_trunk(model):
    """A torch module computing ``model``'s evidence from its max-pooled input, before the final
    upsample.

    Ev-Net's forward is ``pool_in -> trunk -> bilinear upsample``; the fast path does the first
    and last steps itself (exactly, in compiled passes), so only the trunk is exported.
    """
    import torch
    from torch import nn

    class _Trunk(nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, h: torch.Tensor) -> torch.Tensor:
            return self.net.trunk(h)

    return _Trunk(model).eval()


def trunk_onnx(model, in_shape: tuple[int, int, int]) -> bytes:
    """``model``'s trunk as an ONNX graph (opset 17), input ``pooled`` ``(1, *in_shape)``, output
    ``evidence``."""
    import torch

    buf = io.BytesIO()
    x = torch.zeros((1, *in_shape), dtype=torch.float32)
    with warnings.catch_warnings(), torch.inference_mode(False), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notices
        torch.onnx.export(
            evnet_trunk(model),
            (x,),
            buf,
            dynamo=False,
            opset_version=17,
            input_names=["pooled"],
            output_names=["evidence"],
        )
    return buf.getvalue()


class TorchRuntime:
    """The trunk on torch, eager, channels-last: the fallback without ONNX Runtime.

    torch.jit trace + freeze and torch.compile (after minutes of compiling) run it faster, both
    slower than ONNX Runtime (``benchmarks/bench_runtime.py``, figures in docs/speed.md).
    """

    name = "torch"

    def __init__(self, model, threads: int = 1):
        import torch

        torch.set_num_threads(threads)
        self._torch = torch
        self._trunk = evnet_trunk(model).to(memory_format=torch.channels_last)

    def __call__(self, pooled: np.ndarray) -> np.ndarray:
        torch = self._torch
        x = torch.from_numpy(pooled).to(memory_format=torch.channels_last)
        with torch.inference_mode():
            e = self._trunk(x)[0]
        return e.numpy()


def ort_available() -> bool:
    """Whether ONNX Runtime and the ONNX package (for the export) are importable."""
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


class OrtRuntime:
    """The trunk on ONNX Runtime (fp32, CPU), exported from the torch model in memory; ``threads``
    intra-op threads."""

    name = "onnxruntime"

    def __init__(self, model, in_shape: tuple[int, int, int], threads: int = 1):
        self._open(trunk_onnx(model, in_shape), in_shape, threads)

    @classmethod
    def from_graph(
        cls, graph: bytes, in_shape: tuple[int, int, int], threads: int = 1
    ) -> OrtRuntime:
        """The runtime on an ONNX graph of the trunk: :func:`trunk_onnx`'s, or one converted from it
        (fp16, int8)."""
        runtime = cls.__new__(cls)
        runtime._open(graph, in_shape, threads)
        return runtime

    def _open(self, graph: bytes, in_shape: tuple[int, int, int], threads: int) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        self._session = ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
        self.in_shape = in_shape

    def __call__(self, pooled: np.ndarray) -> np.ndarray:
        return self._session.run(None, {"pooled": pooled})[0][0]


def make_runtime(
    model, in_shape: tuple[int, int, int], runtime: str = "auto", threads: int = 1
) -> EvNetRuntime:
    """The runtime named ``runtime`` (see :data:`RUNTIMES`) for ``model``'s trunk on inputs
    ``in_shape`` ``(C, h, w)``."""
    global _warned_fallback
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime must be one of {RUNTIMES}, got {runtime!r}")
    if runtime == "onnxruntime" and not ort_available():
        raise ImportError(
            f"the onnxruntime runtime needs onnx and onnxruntime: {install_hint('fast')}"
        )
    if runtime == "auto":
        runtime = "onnxruntime" if ort_available() else "torch"
        if runtime == "torch" and not _warned_fallback:
            _warned_fallback = True
            logger.info(
                "onnxruntime is not installed: Ev-Net runs on torch, slower than on ONNX Runtime "
                f"({install_hint('fast')})"
            )
    if runtime == "onnxruntime":
        return OrtRuntime(model, in_shape, threads)
    return TorchRuntime(model, threads)
