"""What every benchmark here shares: the machine's description, timing in turns, the scene loop.

Import it from a script of this folder (``from harness import ...``: the script's folder is on
``sys.path`` when it runs). :func:`machine` describes where figures were taken (CPU model and
the SIMD flags that change numba's code, cores, load, commit, versions), :func:`in_turns` times
several variants alternated so that all see the same load (in one process) and
:func:`commands_in_turns` does the same for separate processes (two trees, two settings);
:func:`timings_ms` times one function; :func:`map_timed` is the scene loop (frames into a
mapper, each frame's time); :func:`sim_scene` loads a simulated scene by seed. Figures are
measured and printed, never asserted.
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the tests' helpers (tests/ray_cluster.py) import as ``tests.``
    sys.path.append(str(ROOT))

from evgrid_lab.bench import interleaved_timings, timings_ms  # noqa: E402

__all__ = [
    "ROOT",
    "machine",
    "machine_line",
    "timings_ms",
    "median_min_ms",
    "in_turns",
    "commands_in_turns",
    "map_timed",
    "sim_scene",
]

#: The CPU flags that change what numba and numpy compile to (the rest are left out).
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_vnni")


def _cpu() -> tuple[str, list[str]]:
    model, flags = platform.processor() or platform.machine(), []
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and model in ("", platform.machine()):
                    model = value.strip()
                elif key.strip() == "flags":
                    flags = value.split()
                    break
    except OSError:
        pass
    return model, flags


def commit(tree: Path = ROOT) -> str:
    """The short commit of ``tree`` (``+`` when its work tree differs), or ``unknown``."""
    try:
        rev = subprocess.run(
            ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
        ).stdout.strip()
        return rev + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict[str, Any]:
    """Where a figure was taken: CPU model, its SIMD flags, cores (all and this process's),
    load average, commit, Python, numpy and numba versions."""
    import numba
    import numpy as np

    model, flags = _cpu()
    return {
        "cpu": model,
        "simd": [f for f in SIMD_FLAGS if f in flags],
        "cores": os.cpu_count(),
        "cores_allowed": len(os.sched_getaffinity(0)),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "commit": commit(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }


def machine_line() -> str:
    """:func:`machine` in one line, for the head of a printed table."""
    m = machine()
    return (
        f"{m['cpu']} ({' '.join(m['simd']) or 'no AVX'}), {m['cores_allowed']}/{m['cores']} "
        f"cores, load {m['load_average']}, commit {m['commit']}, numba {m['numba']}"
    )


def median_min_ms(fn: Callable[[], object], repeat: int = 20, prep=None) -> tuple[float, float]:
    """(median, minimum) wall time of ``fn()`` in ms (:func:`timings_ms`)."""
    ts = timings_ms(fn, prep, repeat)
    return float(statistics.median(ts)), float(min(ts))


def in_turns(fns: dict[str, Callable[[], object]], repeat: int = 20) -> dict[str, dict]:
    """Each ``fns[name]()`` timed ``repeat`` times in turns (A, B, A, B ...) after a warm-up call
    of each: per name the median and minimum ms."""
    ts = {k: v.tolist() for k, v in interleaved_timings(fns, repeat).items()}
    return {k: {"median_ms": statistics.median(v), "min_ms": min(v)} for k, v in ts.items()}


def commands_in_turns(
    commands: dict[str, Sequence[str]], rounds: int = 3, env: dict[str, dict] | None = None
) -> dict[str, list[float]]:
    """Run each command (argv) ``rounds`` times in turns, each in its own process (``env[name]``
    added to this environment): per name the wall seconds of each run. For two trees, give
    each its ``PYTHONPATH``; pin with ``taskset -c N`` in the argv to compare on one core."""
    out: dict[str, list[float]] = {k: [] for k in commands}
    for _ in range(rounds):
        for k, argv in commands.items():
            t = time.perf_counter()
            subprocess.run(argv, check=True, env={**os.environ, **(env or {}).get(k, {})})
            out[k].append(time.perf_counter() - t)
    return out


def map_timed(frames: Iterable, config=None, deep=None) -> tuple[Any, list[float]]:
    """The scene loop: ``frames`` into a new :class:`~evgrid.mapper.OccupancyMapper`
    (``config``: a :class:`~evgrid.config.MapperConfig`, default the defaults); the mapper and
    the wall ms of each frame, reading it included."""
    from evgrid.config import MapperConfig
    from evgrid.mapper import OccupancyMapper

    mapper = OccupancyMapper(config or MapperConfig(), deep=deep)
    ms: list[float] = []
    it = iter(frames)
    while True:
        t = time.perf_counter()
        try:
            f = next(it)
        except StopIteration:
            return mapper, ms
        mapper.process(f)
        ms.append((time.perf_counter() - t) * 1e3)


def sim_scene(seed: int, duration_s: float):
    """The simulated scene of ``seed`` as ``evgrid map --scenes`` loads it (frames)."""
    from evgrid.sources import SimSource

    source = SimSource((seed,), duration_s=duration_s)
    return source.load(source.names()[0])
