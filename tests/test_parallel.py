"""core/parallel.map_processes: the same results as the serial loop, in the items' order,
whatever the submission order and worker count; bad settings refused."""

from __future__ import annotations

import random

import pytest

from fdi_ros.core.parallel import default_workers, map_processes


def _work(x: tuple[int, float]) -> tuple[int, float]:
    k, v = x
    return k, sum((v * i) % 7.0 for i in range(2000))


def test_processes_equal_the_serial_loop_in_order():
    rng = random.Random()
    items = [(i, rng.uniform(-5, 5)) for i in range(rng.randint(5, 12))]
    serial = [_work(x) for x in items]
    order = list(range(len(items)))
    rng.shuffle(order)
    seen = []
    got = map_processes(_work, items, workers=2, order=order,
                        progress=lambda k, n: seen.append((k, n)))
    assert got == serial
    assert seen[-1] == (len(items), len(items)) and len(seen) == len(items)
    assert map_processes(_work, items, workers=1) == serial
    assert map_processes(_work, [], workers=2) == []


def test_bad_settings_refused(monkeypatch):
    with pytest.raises(ValueError, match="permutation"):
        map_processes(_work, [(0, 1.0), (1, 2.0)], workers=2, order=[0, 0])
    with pytest.raises(ValueError, match="workers"):
        map_processes(_work, [(0, 1.0)], workers=0)
    monkeypatch.setenv("FDI_ROS_WORKERS", "3")
    assert default_workers() == 3
    for bad in ("0", "two"):
        monkeypatch.setenv("FDI_ROS_WORKERS", bad)
        with pytest.raises(ValueError, match="FDI_ROS_WORKERS"):
            default_workers()


def _combine(x: tuple[tuple[int, float], tuple[int, float]]) -> float:
    (_, a), (_, b) = x
    return a - 2.0 * b


def test_pool_with_dependent_work_equals_the_serial_chain():
    """process_pool: work submitted on the results of other work gives what the serial chain
    gives, with two workers and with one (run in this process)."""
    from fdi_ros.core.parallel import process_pool

    rng = random.Random()
    items = [(i, rng.uniform(-5, 5)) for i in range(rng.randint(3, 8))]
    serial = [_combine((_work(x), _work(items[0]))) for x in items]
    for workers in (2, 1):
        with process_pool(workers) as pool:
            first = [pool.submit(_work, x) for x in items]
            base = first[0].result()
            got = [pool.submit(_combine, (f.result(), base)).result() for f in first]
        assert got == serial
    with pytest.raises(ValueError, match="workers"), process_pool(0):
        pass
