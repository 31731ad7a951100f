"""Independent pieces of work on local processes (the standard library's process pool).

Identification builds many models that do not depend on each other (fault hypotheses, the
node models of a grid); on an N-core machine they take about 1/N of the time. Results come
back in the order of the items and equal the serial run's (each piece is a pure function of
its item) up to the rounding of BLAS reductions: a worker runs one BLAS thread, measured
1e-12 relative on the diesel hypotheses. ``workers`` defaults to the cores this process
may use, or ``$FDI_ROS_WORKERS`` (1: in this process, no pool).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def default_workers() -> int:
    """``$FDI_ROS_WORKERS`` if set (>= 1), else the cores this process may run on."""
    env = os.environ.get("FDI_ROS_WORKERS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"FDI_ROS_WORKERS must be an integer >= 1, not {env!r}") from None
        if n < 1:
            raise ValueError(f"FDI_ROS_WORKERS must be an integer >= 1, not {env!r}")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def single_threaded_numerics() -> None:
    """One BLAS thread per worker process: N workers on N cores, not N x threads."""
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass


def map_processes(fn: Callable[[T], R], items: Iterable[T], *, workers: int | None = None,
                  method: str = "spawn", order: Sequence[int] | None = None,
                  progress: Callable[[int, int], None] | None = None) -> list[R]:
    """``[fn(x) for x in items]`` on ``workers`` processes.

    ``fn`` must be a module-level function (pickled by name) and the items picklable.
    ``method``: the start method ("spawn": a clean interpreter, safe beside the threads of
    DDS; "fork": no start-up imports). ``order``: the indices to submit first (the longest
    work first keeps every worker busy to the end). ``progress(done, total)`` after each.
    """
    todo = list(items)
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers must be >= 1, not {workers}")
    if n == 1 or len(todo) <= 1:
        out = []
        for i, x in enumerate(todo):
            out.append(fn(x))
            if progress is not None:
                progress(i + 1, len(todo))
        return out
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    idx = list(order) if order is not None else list(range(len(todo)))
    if sorted(idx) != list(range(len(todo))):
        raise ValueError("order must be a permutation of the item indices")
    results: dict[int, Any] = {}
    with ProcessPoolExecutor(max_workers=min(n, len(todo)), mp_context=mp.get_context(method),
                             initializer=single_threaded_numerics) as pool:
        futures = {pool.submit(fn, todo[i]): i for i in idx}
        for k, f in enumerate(as_completed(futures)):
            results[futures[f]] = f.result()
            if progress is not None:
                progress(k + 1, len(todo))
    return [results[i] for i in range(len(todo))]


class _Done:
    """A finished piece of work, answering like a future (the one-worker case)."""

    def __init__(self, value: Any) -> None:
        self._value = value

    def result(self) -> Any:
        return self._value


class Pool:
    """``submit(fn, x)`` -> a future (``.result()``); work that depends on other work is
    submitted once the futures it needs have their results. One worker: run at once, here."""

    def __init__(self, executor: Any) -> None:
        self._executor = executor

    def submit(self, fn: Callable[[T], R], item: T) -> Any:
        if self._executor is None:
            return _Done(fn(item))
        return self._executor.submit(fn, item)


@contextmanager
def process_pool(workers: int | None = None, method: str = "spawn") -> Iterator[Pool]:
    """A pool of ``workers`` processes (as :func:`map_processes`) for pieces of work with
    dependencies between them, e.g. simulations that several fits need."""
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise ValueError(f"workers must be >= 1, not {workers}")
    if n == 1:
        yield Pool(None)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context(method),
                             initializer=single_threaded_numerics) as ex:
        yield Pool(ex)
