"""The local engine of evgrid.engine.fan_out: results as jobs finish, failures by key, retries."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from evgrid.engine import ENGINES, Outcome, fan_out

# --- jobs (module level: they pickle into the spawned workers) ----------------------------------


def square(x: int) -> int:
    if x == 3:
        raise ValueError("three is not allowed\nsecond line")
    return x * x


def die_once(args: tuple[int, str]) -> int:
    """``x * x``, after the worker process dies on the first try (a marker file remembers it)."""
    x, marker = args
    if not os.path.exists(marker):
        Path(marker).write_text("tried")
        os._exit(3)  # the worker dies as when killed: no exception, no cleanup
    return x * x


def die_always(x: int) -> int:
    os._exit(3)


def by_key(outcomes) -> dict[str, Outcome]:
    found = {}
    for o in outcomes:
        assert o.key not in found, f"{o.key} reported twice"
        found[o.key] = o
    return found


# --- tests --------------------------------------------------------------------------------------


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_job_is_reported_by_key_while_the_others_finish(workers):
    jobs = [(f"j{x}", x) for x in range(6)]
    out = by_key(fan_out(square, jobs, workers=workers))
    assert set(out) == {k for k, _ in jobs}
    assert not out["j3"].ok
    assert out["j3"].error == "ValueError: three is not allowed second line"  # one line
    assert out["j3"].result is None
    assert {k: o.result for k, o in out.items() if k != "j3"} == {
        f"j{x}": x * x for x in (0, 1, 2, 4, 5)
    }


def test_one_worker_runs_in_order_in_this_process():
    assert [o.key for o in fan_out(square, [("b", 2), ("a", 1), ("c", 4)])] == ["b", "a", "c"]


def test_a_killed_worker_is_retried_once(tmp_path):
    jobs = [("dies", (7, str(tmp_path / "died"))), ("j2", 2), ("j4", 4)]
    out = by_key(fan_out(_dispatch, jobs, workers=2))
    assert out["dies"].ok and out["dies"].result == 49
    assert (tmp_path / "died").read_text() == "tried"  # it did die once
    assert out["j2"].result == 4 and out["j4"].result == 16


def test_a_worker_that_dies_again_is_reported_not_retried_forever():
    out = by_key(fan_out(_dispatch, [("dies", "always"), ("j2", 2)], workers=2, retries=1))
    assert not out["dies"].ok
    assert "worker process died" in out["dies"].error and "also when retried" in out["dies"].error
    assert "\n" not in out["dies"].error
    assert out["j2"].result == 4


def test_no_retries_means_a_dead_worker_is_reported_at_once(tmp_path):
    out = by_key(
        fan_out(_dispatch, [("dies", (7, str(tmp_path / "m"))), ("j2", 2)], workers=2, retries=0)
    )
    assert not out["dies"].ok and "worker process died" in out["dies"].error


def _dispatch(args):
    """One job function for mixed jobs: a marker pair dies once, "always" dies, a number squares."""
    if args == "always":
        return die_always(0)
    if isinstance(args, tuple):
        return die_once(args)
    return square(args)


def test_unknown_engine_is_named():
    with pytest.raises(ValueError, match="unknown engine 'spark'"):
        list(fan_out(square, [("a", 1)], engine="spark"))
    assert ENGINES == ("local", "ray")


def test_no_jobs_yield_nothing():
    assert list(fan_out(square, [], workers=2)) == []


def slow_square(args):
    """``x * x`` after a short wait, so other jobs are in flight or queued when a worker dies."""
    import time

    if args == "always":
        time.sleep(0.3)
        return die_always(0)
    time.sleep(0.2)
    return args * args


def test_a_dying_job_costs_the_other_jobs_nothing():
    """Jobs that were queued or running beside a worker that died are not blamed for it: only
    the job that dies again when run alone is reported, however many jobs were lost with it."""
    jobs = [("dies", "always")] + [(f"j{x}", x) for x in range(8)]
    out = by_key(fan_out(slow_square, jobs, workers=2, retries=1))
    assert not out["dies"].ok and "worker process died" in out["dies"].error
    assert {k: o.result for k, o in out.items() if k != "dies"} == {
        f"j{x}": x * x for x in range(8)
    }
