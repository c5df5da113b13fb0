"""One task executor for every labeling driver: in-process, a local Dask cluster, or a cluster.

``Executor(workers=0)`` runs tasks in this process when their results are asked for (highest
priority first, then in submission order); ``Executor(workers=N)`` starts a Dask
``LocalCluster`` of N single-threaded worker processes; ``Executor(scheduler=ADDRESS)`` uses an
existing Dask cluster. The drivers (:func:`emlpack.qm.labeling.run_labeling`,
:func:`emlpack.qm.cp2k.label_into_store`, :func:`emlpack.qm.relabel.relabel`,
:func:`emlpack.cli.demo.generate_labels`) submit tagged tasks and consume them as they complete,
writing results from the calling process only.
"""

from __future__ import annotations

import heapq
import itertools
import os
from collections.abc import Callable, Iterable, Iterator

from emlpack.optional import import_optional


class _Deferred:
    """A serial task: runs when its result is asked for (once)."""

    def __init__(self, fn: Callable, args: tuple) -> None:
        self._fn, self._args = fn, args
        self._done = False
        self._value = None
        self._error: BaseException | None = None

    def result(self):
        if not self._done:
            try:
                self._value = self._fn(*self._args)
            except Exception as exc:  # noqa: BLE001 - re-raised to the caller of result()
                self._error = exc
            self._done = True
        if self._error is not None:
            raise self._error
        return self._value


class Executor:
    """Runs tasks serially, on a local Dask cluster, or on an existing Dask cluster.

    Args:
        workers: local worker processes (``None``: the CPU count; 0: in this process).
        scheduler: address of an existing Dask scheduler (then ``workers`` is ignored).
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        self.workers = (os.cpu_count() or 1) if workers is None else int(workers)
        self.uses_dask = self.check_backend(workers, scheduler)
        self._client = None
        self._order = itertools.count()
        self._queue: list = []  # serial: (-priority, order, task, tag)
        self._ac = None
        self._tags: dict = {}
        if self.uses_dask:
            from distributed import Client, LocalCluster, as_completed

            if scheduler:
                self._client = Client(scheduler)
            else:
                import dask

                # one malloc arena per worker: tasks run in a worker thread, whose own arena
                # returns freed memory to the kernel, so PySCF's arrays page-fault in again
                # (2nd aziridine label at the paper level in a worker: 49 700 -> 5 400 minor
                # faults, 21.4 -> 17.4 s CPU); glibc reads it at process start
                with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": 1}):
                    cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1,
                                           processes=True, dashboard_address=":0",
                                           silence_logs=40)
                self._client = Client(cluster)
            self._ac = as_completed()

    @staticmethod
    def check_backend(workers: int | None = None, scheduler: str | None = None) -> bool:
        """Whether these settings run on Dask (a scheduler, or ``workers`` other than 0; None
        is the CPU count); raises :class:`~emlpack.errors.MissingDependencyError` when Dask is
        then not installed."""
        uses_dask = bool(scheduler) or workers is None or int(workers) > 0
        if uses_dask:
            for module in ("dask", "distributed"):
                import_optional(module, "labeling in worker processes (Dask)",
                                alternative="run it in this process: --workers 0 (workers=0)")
        return uses_dask

    @property
    def threads_per_task(self) -> int:
        """OpenMP threads a task should use so that the workers fill the CPUs."""
        return max(1, (os.cpu_count() or 1) // max(self.workers, 1))

    def submit(self, fn: Callable, *args, tag: object = None, priority: int = 0) -> None:
        """Queue ``fn(*args)``; :meth:`completed` yields it with ``tag``. Higher ``priority``
        runs first among queued tasks."""
        if self._client is None:
            heapq.heappush(self._queue, (-priority, next(self._order), _Deferred(fn, args), tag))
            return
        fut = self._client.submit(fn, *args, pure=False, priority=priority)
        self._tags[fut.key] = tag
        self._ac.add(fut)

    def completed(self) -> Iterator[tuple[object, object]]:
        """``(tag, future)`` pairs as tasks finish, including tasks submitted meanwhile;
        ``future.result()`` returns the value or raises the task's exception."""
        if self._client is None:
            while self._queue:
                _, _, task, tag = heapq.heappop(self._queue)
                yield tag, task
            return
        for fut in self._ac:
            yield self._tags.pop(fut.key), fut

    def map_ordered(self, fn: Callable, items: Iterable) -> Iterator:
        """``fn(item)`` for every item, yielded in the order of ``items`` (results, or the
        exception raised)."""
        if self._client is None:
            for item in items:
                yield fn(item)
            return
        futures = [self._client.submit(fn, item, pure=False) for item in items]
        for fut in futures:
            yield fut.result()

    def close(self) -> None:
        """Close the Dask client and the local cluster it started, if any (serial: nothing)."""
        if self._client is not None:
            cluster = getattr(self._client, "cluster", None)
            self._client.close()
            if cluster is not None:
                cluster.close()
            self._client = None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
