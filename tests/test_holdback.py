"""The replay held back by the diagnosis (core/pacing.HoldBack), without ROS: a simulated
graph slower than the replay never lets the data run more than ahead_s of plant time ahead
of the diagnosis, and a diagnosis that stops moving is not waited for."""

from __future__ import annotations

import math
import random

from fdi_ros.core.pacing import HoldBack


def _replay(h: HoldBack, speed: float, stall: tuple[float, float] | None = None,
            seg: float = 0.015, n: int = 2000) -> tuple[float, float]:
    """Blocks every ``seg`` of plant time offered each wall tick of 5 ms; the graph
    diagnoses ``speed`` plant seconds per wall second (stalled for wall times in ``stall``).
    Returns (largest lead of the data over the diagnosis, wall time at the end)."""
    wall, t_data, t_diag, lead = 0.0, 0.0, -math.inf, 0.0
    sent = 0
    while sent < n:
        wall += 0.005
        stalled = stall is not None and stall[0] <= wall < stall[1]
        if not stalled and t_data > 0:
            t_diag = min(t_data, max(t_diag, 0.0) + speed * 0.005)
            h.diagnosis(t_diag, wall)
        for _ in range(20):  # the replay's rate would allow 20 blocks a tick
            if sent >= n or h.hold(t_data, wall):
                break
            t_data += seg
            sent += 1
            lead = max(lead, t_data - max(t_diag, 0.0))
    return lead, wall


def test_a_slow_graph_holds_the_data_within_ahead_s_of_the_diagnosis():
    rng = random.Random()
    for _ in range(20):
        ahead = rng.uniform(0.2, 2.0)
        speed = rng.uniform(0.5, 3.0)  # plant s per wall s the graph manages
        h = HoldBack(ahead_s=ahead, stuck_s=3.0)
        lead, wall = _replay(h, speed)
        assert lead <= ahead + 0.015 + 1e-9, (ahead, speed, lead)
        assert h.held > 0
        # the replay ran at about the graph's speed, not faster
        assert wall >= 2000 * 0.015 / speed * 0.9


def test_a_stuck_diagnosis_is_not_waited_for_and_nan_never_held():
    h = HoldBack(ahead_s=0.5, stuck_s=1.0)
    lead, _ = _replay(h, 1.0, stall=(2.0, 10.0))
    assert lead > 0.5 + 0.1  # the data went on while the diagnosis stood still
    assert not HoldBack().hold(math.nan, 0.0)
    off = HoldBack(ahead_s=0.0)
    assert not any(off.hold(t, 0.0) for t in (0.0, 10.0, 100.0))
    unwatched = HoldBack(ahead_s=0.5)
    assert not any(unwatched.hold(t, 0.0, watched=False) for t in (0.0, 10.0))


def test_the_first_diagnosis_is_waited_for_longer_than_a_stuck_one():
    """A graph whose first diagnosis takes longer than stuck_s (a loaded machine at start-up)
    still holds the data, up to start_s; a diagnosis that stops later is waited for stuck_s
    only."""
    h = HoldBack(ahead_s=0.5, stuck_s=1.0, start_s=4.0)
    assert not h.hold(0.0, 0.0)  # the first block starts the data
    assert h.hold(1.0, 0.1) and h.hold(1.0, 3.9)  # no diagnosis yet: still held at 3.9 s
    assert not h.hold(1.0, 4.2)  # and given up after start_s
    h = HoldBack(ahead_s=0.5, stuck_s=1.0, start_s=4.0)
    assert not h.hold(0.0, 0.0)
    h.diagnosis(0.2, 0.05)
    assert h.hold(1.0, 0.1) and not h.hold(1.0, 1.2)  # stuck 1 s after its first diagnosis

