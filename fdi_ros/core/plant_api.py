"""What a plant wing hands the generic graph: a streaming simulator ("runner") and a
preprocessor, plus the one queue in which fault events wait for plant time to reach them.

A runner yields sensor blocks of a scenario one at a time (so the plant node can publish them
at the plant's pace) and accepts fault injections at run time; a preprocessor turns blocks into
feature vectors. Wings are registered in :mod:`fdi_ros.plants`; the core names none of them.
"""

from __future__ import annotations

from typing import Protocol

from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock

__all__ = ["FaultQueue", "PlantRunner", "Preprocessor"]


class PlantRunner(Protocol):
    plant: str

    @property
    def t(self) -> float: ...  # plant time of the last sample [s]

    @property
    def done(self) -> bool: ...  # the scenario is over

    def next_block(self) -> SampleBlock: ...

    def inject(self, event: FaultEvent) -> None: ...

    def pop_truth(self) -> list[FaultEvent]: ...  # faults that took effect since last call


class Preprocessor(Protocol):
    def push(self, block: SampleBlock) -> list[FeatureVector]: ...

    def mark_gap(self) -> None: ...  # blocks were lost before the next push

    def reset(self) -> None: ...  # start over (a restarted source)


class FaultQueue:
    """Fault events ordered by plant time; each is handed out once when time reaches it."""

    def __init__(self) -> None:
        self._pending: list[FaultEvent] = []

    def __len__(self) -> int:
        return len(self._pending)

    def add(self, ev: FaultEvent) -> None:
        self._pending.append(ev)
        self._pending.sort(key=lambda e: e.t)

    def due(self, t: float) -> list[FaultEvent]:
        out = [e for e in self._pending if e.t <= t]
        self._pending = [e for e in self._pending if e.t > t]
        return out
