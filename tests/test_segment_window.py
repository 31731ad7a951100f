"""The per-segment pieces of the diesel bank models that keep state over a window of
segments (live path): incremental forms equal their plain definitions on random streams."""

from __future__ import annotations

from collections import deque

import numpy as np

from fdi_ros.plants.diesel.symptoms import _Window, block_rms


def _block_rms_plain(E: np.ndarray, block: int = 10) -> float:
    E = np.atleast_2d(E)
    k = E.shape[0]
    edges = np.arange(k, 0, -block)[::-1]
    starts = np.concatenate([[0], edges[:-1]])
    means = np.array([E[a:b].mean(axis=0) for a, b in zip(starts, edges)])
    return float(np.sqrt(np.mean(means ** 2)))


def test_window_and_block_rms_equal_the_plain_definitions():
    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    for _ in range(20):
        size = int(rng.integers(1, 60))
        m = int(rng.integers(1, 7))
        win, plain = _Window(size), deque(maxlen=size)
        for k in range(int(rng.integers(1, 300))):
            if rng.random() < 0.02:  # a reset of the model
                win.clear()
                plain.clear()
            a, b = rng.normal(size=m), rng.normal(size=m)
            plain.append((a, b))
            A, B = win.push(a, b)
            assert np.array_equal(A, np.array([x[0] for x in plain])), (seed, k)
            assert np.array_equal(B, np.array([x[1] for x in plain])), (seed, k)
            blk = int(rng.integers(1, 15))
            assert block_rms(A - 0.3 * B, blk) == _block_rms_plain(A - 0.3 * B, blk), seed
