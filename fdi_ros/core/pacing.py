"""Plant time against wall time at a rate that can change on line.

A live plant advances to ``target(wall)``; a new rate applies from the moment it is set and
from where the plant actually is, so raising the rate never makes the plant race to catch up
the time already elapsed (and a backlog the plant could not keep up with is not carried over).
"""

from __future__ import annotations

import math


class Pacer:
    """``target(wall) = t_anchor + (wall - wall_anchor) * rate``; rate 0 = no limit.

    Parameters
    ----------
    rate : plant seconds per wall second (>= 0; 0 = as fast as possible).
    """

    def __init__(self, rate: float) -> None:
        self.rate = self._checked(rate)
        self._wall0: float | None = None
        self._t0 = 0.0
        self._ready_at: float | None = None

    @staticmethod
    def _checked(rate: float) -> float:
        rate = float(rate)
        if not (math.isfinite(rate) and rate >= 0.0):
            raise ValueError(f"rate must be finite and >= 0, got {rate}")
        return rate

    @property
    def started(self) -> bool:
        return self._wall0 is not None

    def start(self, wall: float, t_plant: float) -> None:
        """Plant time ``t_plant`` corresponds to wall time ``wall`` from now on."""
        self._wall0, self._t0 = float(wall), float(t_plant)

    def start_when_ready(self, wall: float, t_plant: float, *, readers_ok: bool,
                         delay_s: float = 0.0) -> bool:
        """Start once the readers are there (``readers_ok``) and, from the first time they
        were, ``delay_s`` wall seconds have passed; True once started. No reader, no start."""
        if self.started:
            return True
        if not readers_ok:
            return False
        if self._ready_at is None:
            self._ready_at = float(wall) + float(delay_s)
        if wall < self._ready_at:
            return False
        self.start(wall, t_plant)
        return True

    def set_rate(self, rate: float, wall: float, t_plant: float) -> None:
        """Switch to ``rate`` at wall time ``wall``, where the plant is at ``t_plant``."""
        self.rate = self._checked(rate)
        if self.started:
            self.start(wall, t_plant)

    def target(self, wall: float) -> float:
        """Plant time to reach by wall time ``wall`` (inf with rate 0; none before start)."""
        if self._wall0 is None:
            return -math.inf
        if self.rate == 0.0:
            return math.inf
        return self._t0 + (wall - self._wall0) * self.rate
