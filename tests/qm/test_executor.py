"""The one task executor of the labeling drivers: serial priorities, errors, order, Dask."""

from __future__ import annotations

import pytest

from emlpack.qm.executor import Executor


def _square(x):
    if x < 0:
        raise ValueError(f"negative {x}")
    return x * x


def test_serial_runs_by_priority_then_submission_order():
    ran = []

    def task(name):
        ran.append(name)
        return name

    with Executor(workers=0) as ex:
        assert not ex.uses_dask
        ex.submit(task, "prep-a", tag="a", priority=0)
        ex.submit(task, "prep-b", tag="b", priority=0)
        out = []
        for tag, fut in ex.completed():
            out.append((tag, fut.result()))
            if tag == "a":  # submitted while running: a label outranks the queued preparation
                ex.submit(task, "label-a", tag="la", priority=10)
    assert ran == ["prep-a", "label-a", "prep-b"]
    assert [t for t, _ in out] == ["a", "la", "b"]


def test_errors_reach_the_caller_and_map_keeps_order():
    with Executor(workers=0) as ex:
        ex.submit(_square, -1, tag="bad")
        ((tag, fut),) = list(ex.completed())
        with pytest.raises(ValueError, match="negative -1"):
            fut.result()
        assert list(ex.map_ordered(_square, [3, 1, 2])) == [9, 1, 4]


def _malloc_arena_max():
    import os

    return os.environ.get("MALLOC_ARENA_MAX")


def test_dask_local_cluster():
    with Executor(workers=1) as ex:
        assert ex.uses_dask and ex.threads_per_task >= 1
        for x in (1, 2, 3):
            ex.submit(_square, x, tag=x)
        ex.submit(_square, -2, tag=-2)
        results = {}
        for tag, fut in ex.completed():
            try:
                results[tag] = fut.result()
            except ValueError as exc:
                results[tag] = str(exc)
        assert results == {1: 1, 2: 4, 3: 9, -2: "negative -2"}
        assert list(ex.map_ordered(_square, [4, 5])) == [16, 25]
        # one malloc arena in the worker processes (set before they start; see Executor)
        ex.submit(_malloc_arena_max, tag="arena")
        assert [f.result() for _, f in ex.completed()] == ["1"]
