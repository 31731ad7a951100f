"""What a plant wing hands the generic graph: a streaming simulator ("runner") and a
preprocessor, plus the one queue in which fault events wait for plant time to reach them.

A runner yields sensor blocks of a scenario one at a time (so the plant node can publish them
at the plant's pace) and accepts fault injections at run time; a preprocessor turns blocks into
feature vectors. Wings are registered in :mod:`fdi_ros.plants`; the core names none of them.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock

__all__ = ["FaultQueue", "PlantRunner", "Preprocessor", "SampledRunner"]


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


class SampledRunner:
    """The bookkeeping of a runner sampled at a fixed period ``ts`` (no crank angle): samples
    and blocks counted, plant time of the last sample, ground truth handed out once plant time
    reaches it (:attr:`_truth`). A subclass sets ``plant``, ``channels`` and ``units``, takes
    the times of its next samples from :meth:`_times` and returns :meth:`_emit` of their
    values (channels x samples)."""

    plant: str
    channels: tuple[str, ...]
    units: tuple[str, ...]

    def __init__(self, ts: float) -> None:
        self.ts = float(ts)
        self._k = 0  # samples emitted
        self._index = 0  # blocks emitted
        self._truth = FaultQueue()

    @property
    def t(self) -> float:
        return max(self._k - 1, 0) * self.ts

    def _times(self, n: int) -> np.ndarray:
        """Plant times [s] of the next ``n`` samples."""
        times: np.ndarray = (self._k + np.arange(n)) * self.ts
        return times

    def _emit(self, t: np.ndarray, values: np.ndarray) -> SampleBlock:
        self._k += values.shape[1]
        block = SampleBlock(plant=self.plant, index=self._index, t=t, alpha=np.empty(0),
                            channels=self.channels, units=self.units, values=values)
        self._index += 1
        return block

    def pop_truth(self) -> list[FaultEvent]:
        return self._truth.due(self.t)
