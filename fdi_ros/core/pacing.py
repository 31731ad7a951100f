"""Plant time against wall time at a rate that can change on line.

A live plant advances to ``target(wall)``; a new rate applies from the moment it is set and
from where the plant actually is, so raising the rate never makes the plant race to catch up
the time already elapsed (and a backlog the plant could not keep up with is not carried over).
"""

from __future__ import annotations

import math

# A live plant more than this much plant time behind its pacer (its process held up) goes on
# at its rate from where it is instead of sending the blocks it missed in one burst.
CATCH_UP_S = 0.1


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

    def target_within(self, wall: float, t_plant: float, behind_s: float) -> float:
        """:meth:`target` for a plant at ``t_plant``, kept at most ``behind_s`` of plant time
        ahead of it: a source that stalled goes on at its rate from where it is (re-anchored)
        instead of racing through everything it missed, which would reach the graph as one
        burst to queue. Plant time is the diagnosis' only clock, so nothing diagnosed
        changes; the data only end later in wall time."""
        target = self.target(wall)
        if math.isfinite(target) and self.rate > 0.0 and target - t_plant > behind_s:
            self.start(wall - behind_s / self.rate, t_plant)
            target = self.target(wall)
        return target


class HoldBack:
    """A replay paced by what the graph can diagnose: the data waits while it is ``ahead_s``
    of plant time ahead of the last diagnosis, so a graph slower than the replay rate holds
    the replay back instead of skipping segments, and every segment is diagnosed as offline
    however high the rate. A diagnosis that has not moved for ``stuck_s`` wall seconds (a
    model that stopped answering) is not waited for (health only): the data goes on and the
    supervisor's plant-time rules decide. Before the first diagnosis the graph gets
    ``start_s`` instead (its first answers can take seconds on a loaded machine; the start-up
    handshake has already made sure every part is there). ``ahead_s`` 0: never wait.
    """

    def __init__(self, ahead_s: float = 1.0, stuck_s: float = 3.0,
                 start_s: float = 15.0) -> None:
        self.ahead_s, self.stuck_s = float(ahead_s), float(stuck_s)
        self.start_s = float(start_s)
        self.diag_t = self._diag_wall = -math.inf
        self._first: float | None = None  # plant time of the first block
        self._since: float | None = None  # wall time the data started to wait
        self.held = 0  # checks that held the data back

    def diagnosis(self, t: float, wall: float) -> None:
        """A diagnosis for plant time ``t`` arrived at ``wall``."""
        if t > self.diag_t:
            self.diag_t, self._diag_wall = float(t), wall

    def hold(self, t: float, wall: float, watched: bool = True) -> bool:
        """Must the block of plant time ``t`` wait? ``watched``: a diagnosis publisher is
        there (without one nothing is waited for)."""
        if math.isnan(t):
            return False  # a block that cannot be placed in plant time is never held
        self._first = t if self._first is None else self._first
        if not self.ahead_s or not watched or t <= max(self._first, self.diag_t) + self.ahead_s:
            self._since = None
            return False
        since = self._since = wall if self._since is None else self._since
        limit = self.stuck_s if math.isfinite(self._diag_wall) else self.start_s
        if wall - max(since, self._diag_wall) > limit:
            return False
        self.held += 1
        return True
