"""core/sliding.SlidingRange equals the scan of the window it replaces, on random streams
with repeated values, NaN samples and gaps longer than the window."""

from __future__ import annotations

import math
import random

from fdi_ros.core.sliding import SlidingRange


def test_sliding_range_equals_the_scan_of_the_window():
    rng = random.Random()
    for _ in range(200):
        window = rng.choice([0.05, 0.5, 3.0])
        r, kept, t = SlidingRange(window), [], 0.0
        levels = [rng.uniform(-1, 1) for _ in range(rng.randint(1, 4))]  # commands repeat
        for _ in range(rng.randint(1, 300)):
            t += rng.choice([0.0, 0.015, 0.015, 0.2, 4.0])
            v = math.nan if rng.random() < 0.1 else rng.choice(levels + [rng.gauss(0, 1)])
            r.push(t, v)
            kept = [(s, x) for s, x in kept + [(t, v)] if s >= t - window]
            finite = [x for _, x in kept if math.isfinite(x)]
            assert r.range() == (max(finite) - min(finite) if finite else None)
        r.clear()
        assert r.range() is None


def test_window_ranges_equal_the_streaming_range_with_restarts():
    """The array form equals pushing the samples through a SlidingRange that is cleared
    where the stream restarts (``start``)."""
    import numpy as np

    from fdi_ros.core.sliding import window_ranges

    rng = random.Random()
    for _ in range(100):
        window = rng.choice([0.05, 0.5, 3.0])
        n = rng.randint(1, 300)
        t = np.cumsum([rng.choice([0.0, 0.015, 0.015, 0.2, 4.0]) for _ in range(n)])
        x = np.array([math.nan if rng.random() < 0.1 else rng.gauss(0, 1) for _ in range(n)])
        restarts = sorted(rng.sample(range(n), k=min(n, rng.randint(0, 4))))
        start = np.zeros(n, dtype=int)
        for k in restarts:
            start[k:] = k
        got = window_ranges(t, x, window, start=start)
        r = SlidingRange(window)
        for k in range(n):
            if k in restarts:
                r.clear()
            r.push(float(t[k]), float(x[k]))
            want = r.range()
            assert (math.isnan(got[k]) if want is None else got[k] == want)
