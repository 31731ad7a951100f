"""Range (max - min) of a signal over a sliding window of time, in O(1) amortised per sample.

Two monotonic queues: the maxima candidates (decreasing) and the minima candidates
(increasing); a sample leaves when it is older than the window or a newer sample dominates
it. Used per segment and per bank model on line, where a scan of the window's samples per
segment made the gates the most expensive part of a residual.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np


class SlidingRange:
    """``max - min`` of the finite values pushed within the last ``window`` (time units of
    the stamps; a sample of time ``t0`` stays while ``t0 >= t - window``)."""

    def __init__(self, window: float) -> None:
        self.window = float(window)
        self._hi: deque[tuple[float, float]] = deque()
        self._lo: deque[tuple[float, float]] = deque()

    def clear(self) -> None:
        self._hi.clear()
        self._lo.clear()

    def push(self, t: float, value: float) -> None:
        """A sample at time ``t`` (non-decreasing); non-finite values are not kept, but the
        window still moves to ``t``."""
        if math.isfinite(value):
            while self._hi and self._hi[-1][1] <= value:
                self._hi.pop()
            self._hi.append((t, value))
            while self._lo and self._lo[-1][1] >= value:
                self._lo.pop()
            self._lo.append((t, value))
        self.evict(t)

    def evict(self, t: float) -> None:
        """Drop the samples older than ``t - window``."""
        edge = t - self.window
        for q in (self._hi, self._lo):
            while q and q[0][0] < edge:
                q.popleft()

    def range(self) -> float | None:
        """max - min over the window; None without a finite sample in it."""
        if not self._hi:
            return None
        return self._hi[0][1] - self._lo[0][1]


def window_ranges(t: np.ndarray, x: np.ndarray, window: float,
                  start: np.ndarray | None = None) -> np.ndarray:
    """For every sample k, ``max - min`` of the finite ``x`` within ``t[k] - window .. t[k]``
    and not before ``start[k]`` (e.g. where the stream last restarted); NaN without a finite
    sample there: the array counterpart of pushing the samples through a :class:`SlidingRange`
    (``t`` non-decreasing)."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    k = np.arange(t.size)
    lo = np.searchsorted(t, t - window, side="left")
    if start is not None:
        lo = np.maximum(np.asarray(start), lo)
    lo = np.minimum(lo, k)
    if t.size == 0:
        return np.zeros(0)
    x = np.where(np.isfinite(x), x, np.nan)
    with np.errstate(invalid="ignore"):
        out: np.ndarray = window_reduce(np.fmax, x, lo) - window_reduce(np.fmin, x, lo)
    return out


def window_reduce(op: np.ufunc, x: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """For every row k, ``op`` reduced over ``x[lo[k] .. k]`` (``lo[k] <= k``), all rows at
    once (``op.reduceat``): e.g. ``np.maximum`` for the largest value of a trailing window."""
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    idx = np.empty(2 * n, dtype=np.intp)
    idx[0::2], idx[1::2] = lo, np.arange(1, n + 1)
    out: np.ndarray = op.reduceat(np.append(x, 0.0), idx)[0::2]
    return out
