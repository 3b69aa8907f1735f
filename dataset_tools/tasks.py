"""One function over many tasks: inline, in a local process pool, or on a Dask cluster.

A stage hands its per-take (or per-chunk) work here, so that every stage is distributed the same
way: `workers=N` a local pool of N processes, `scheduler="tcp://HOST:PORT"` a Dask cluster (which
retries a task whose worker died). Results come back as the tasks finish.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TypeVar

from manus_core.errors import SchedulerError

T = TypeVar("T")
CONNECT_TIMEOUT_S = 5.0   # a scheduler that has not answered by then is named (the CLI exits 2)


def connect(scheduler: str):
    """A Dask client of `scheduler`; SchedulerError (exit 2) naming it when it does not answer."""
    # Dask is optional and slow to import: only a run on a cluster needs it
    from distributed import Client

    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(f"the Dask scheduler {scheduler} does not answer ({type(exc).__name__} within "
                             f"{CONNECT_TIMEOUT_S:g} s): start one (`dask scheduler`) or leave --scheduler out") from None


def run_tasks(fn: Callable[[T], object], tasks: Sequence[T], workers: int = 1, scheduler: str | None = None,
              key: Callable[[T], str] = str) -> Iterator[tuple[T, object]]:
    """(task, result or the exception it raised) as tasks finish. `key(task)` names a task on the
    Dask dashboard and in its logs."""
    if not tasks:
        return
    if scheduler:
        from distributed import as_completed

        # a key names one result on the scheduler: two runs of the same tasks at once must not share them
        run = uuid.uuid4().hex[:8]
        with connect(scheduler) as client:
            futures = {client.submit(fn, t, pure=False, key=f"{fn.__name__}-{key(t)}-{run}"): t for t in tasks}
            yield from _outcomes(futures, as_completed(futures))
        return
    if workers > 1:
        ctx = multiprocessing.get_context("forkserver")
        share = max(1, len(os.sched_getaffinity(0)) // workers)
        with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_cpu_share,
                                    initargs=(share,)) as pool:
            futures = {pool.submit(fn, t): t for t in tasks}
            yield from _outcomes(futures, cf.as_completed(futures))
        return
    for t in tasks:
        try:
            yield t, fn(t)
        except Exception as exc:  # a failed task is reported, the others go on
            yield t, exc


def _cpu_share(threads: int) -> None:
    """A local worker's share of the CPUs, for the libraries that size their thread pools from
    OMP_NUM_THREADS when they start one (the keypoint models' sessions, keypoints/runtime.py): each of
    N workers taking every core ran N threads a core (detect --workers 2 on 2 cores: 12.1 s against
    9.9 s in one process)."""
    os.environ["OMP_NUM_THREADS"] = str(threads)


def _outcomes(futures: dict, finished: Iterable) -> Iterator[tuple[object, object]]:
    for fut in finished:
        try:
            yield futures[fut], fut.result()
        except Exception as exc:  # a failed task is reported, the others go on
            yield futures[fut], exc
