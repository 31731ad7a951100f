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
