"""Fan work out over scenes: one seam, two engines (docs/cluster.md).

``local`` (:mod:`evgrid.engine_local`) runs jobs in this process (one worker) or in a pool of
fresh interpreters (spawn: safe with torch's and numba's thread pools). ``ray``
(:mod:`evgrid.engine_ray`) runs them as Ray tasks (the ``ray`` extra). Either way workers
compute and return results; the caller, in the driver, writes every file. A job that raises is
reported by its key with its one-line error while the others go on; a worker process that dies
(killed, out of memory) is retried once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

from evgrid.engine_local import Outcome, run_local

__all__ = ["ENGINES", "Outcome", "fan_out"]

ENGINES: tuple[str, ...] = ("local", "ray")


def fan_out(
    fn: Callable[[Any], Any],
    jobs: Iterable[tuple[str, Any]],
    engine: str = "local",
    workers: int = 1,
    retries: int = 1,
    address: str | None = None,
) -> Iterator[Outcome]:
    """Run ``fn(args)`` for each ``(key, args)`` of ``jobs``; yield an :class:`Outcome` per job
    as it finishes.

    ``fn`` and ``args`` must pickle (a module-level function). ``workers`` bounds the jobs run
    at once (local engine, 1: in this process, in order). A job whose worker died is run
    again up to ``retries`` times; an exception raised by ``fn`` is not retried. ``address``
    (ray engine only) is the Ray cluster to join; by default ``RAY_ADDRESS``, else a local
    instance started for the call (:mod:`evgrid.engine_ray`).
    """
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose from {ENGINES}")
    jobs = list(jobs)
    if engine == "ray":
        from evgrid.engine_ray import fan_out_ray

        yield from fan_out_ray(fn, jobs, workers=workers, retries=retries, address=address)
        return
    if address is not None:
        raise ValueError("an address is for the ray engine only (--engine ray)")
    yield from run_local(fn, jobs, workers, retries)
