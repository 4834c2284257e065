"""The local engine: jobs in this process or in a pool of processes, and what a job gave.

:mod:`evgrid.engine` picks this or the ray engine (:mod:`evgrid.engine_ray`); both yield an
:class:`Outcome` per job.
"""

from __future__ import annotations

import multiprocessing as mp
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

__all__ = ["Outcome", "run_local"]


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


def run_local(
    fn: Callable[[Any], Any], jobs: list[tuple[str, Any]], workers: int, retries: int
) -> Iterator[Outcome]:
    """Each job in this process, in order (``workers`` 1 or a single job), else in a pool."""
    if workers <= 1 or len(jobs) <= 1:
        for key, args in jobs:
            try:
                yield Outcome(key, fn(args))
            except Exception as e:  # reported by key; the other jobs go on
                yield Outcome(key, error=_one_line(e))
        return
    yield from _pool(fn, jobs, workers, retries)


def _one_pool(
    pool: ProcessPoolExecutor,
    fn: Callable[[Any], Any],
    batch: deque[tuple[str, Any]],
    size: int,
    died: Callable[[str, Any], Outcome | None],
) -> Iterator[Outcome]:
    """Run the jobs of ``batch`` in ``pool``, at most ``size`` at a time, until they are done or
    a worker dies (the pool is then broken): every job in flight then goes to ``died``, which
    queues it as a suspect or gives its outcome; the jobs not yet submitted stay in ``batch``."""
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
            yield from _one_pool(pool, fn, batch, size, died)
