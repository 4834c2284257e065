"""Fan work out over scenes: one seam, two engines (docs/cluster.md).

``local`` runs jobs in this process (one worker) or in a pool of fresh interpreters (spawn:
safe with torch's and numba's thread pools). ``ray`` runs them as Ray tasks (the ``ray``
extra). Either way workers compute and return results; the caller, in the driver, writes
every file. A job that raises is reported by its key with its one-line error while the others
go on; a worker process that dies (killed, out of memory) is retried once.
"""

from __future__ import annotations

import multiprocessing as mp
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

__all__ = ["ENGINES", "Outcome", "fan_out"]

ENGINES: tuple[str, ...] = ("local", "ray")


@dataclass(frozen=True)
class Outcome:
    """What one job gave: its key, and its result or the one-line error it raised."""

    key: str
    result: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


_DIED = "its worker process died (killed or out of memory), also when retried"


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


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
    if workers <= 1 or len(jobs) <= 1:
        for key, args in jobs:
            try:
                yield Outcome(key, fn(args))
            except Exception as e:  # reported by key; the other jobs go on
                yield Outcome(key, error=_one_line(e))
        return
    yield from _pool(fn, jobs, workers, retries)


def _pool(
    fn: Callable[[Any], Any], jobs: list[tuple[str, Any]], workers: int, retries: int
) -> Iterator[Outcome]:
    """The local pool. A worker that dies breaks the whole pool and every job in flight in it,
    and the pool cannot say whose worker died; so the jobs in flight are suspects, each run
    again alone in a fresh pool: the one that dies alone is reported, the others finish. At most
    ``workers`` jobs are submitted at a time, so the jobs merely queued are never suspects."""
    tries = {key: 0 for key, _ in jobs}
    todo = deque(jobs)
    suspects: deque[tuple[str, Any]] = deque()

    def died(key: str, args: Any) -> Outcome | None:
        tries[key] += 1
        if tries[key] <= retries:
            suspects.append((key, args))
            return None
        return Outcome(key, error=_DIED)

    while todo or suspects:
        alone = bool(suspects)
        batch = deque([suspects.popleft()]) if alone else todo
        size = 1 if alone else min(workers, len(batch))
        pool = ProcessPoolExecutor(max_workers=size, mp_context=mp.get_context("spawn"))
        with pool:
            running: dict[Any, tuple[str, Any]] = {}
            broken = False
            while batch or running:
                while batch and not broken and len(running) < size:
                    key, args = batch.popleft()
                    running[pool.submit(fn, args)] = (key, args)
                if not running:
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in done:
                    key, args = running.pop(fut)
                    try:
                        yield Outcome(key, fut.result())
                    except BrokenProcessPool:
                        broken = True  # a worker died: the jobs in flight are lost
                        outcome = died(key, args)
                        if outcome is not None:
                            yield outcome
                    except Exception as e:
                        yield Outcome(key, error=_one_line(e))
                if broken:
                    for fut, (key, args) in running.items():
                        fut.cancel()
                        outcome = died(key, args)
                        if outcome is not None:
                            yield outcome
                    running.clear()
                    break
