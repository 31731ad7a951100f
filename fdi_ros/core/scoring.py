"""Per-sample scoring of a diagnosis against ground truth (the DX 2025 competition's metrics).

For every sample the diagnosis says whether a fault is detected and which fault class it
isolates ("" for none); the truth says whether a fault is present and which. Then

* false alarm rate: share of fault-free samples with a detection;
* true detection rate: share of faulty samples with a detection;
* fault isolation accuracy: over faulty samples with a detection, the share isolated to the
  true class (a deterministic diagnosis gives the true class probability 1 or 0; "detected,
  not yet isolated" counts 0);
* detection delay: first detection at or after the onset, minus the onset.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class Score:
    fault_free_samples: int
    false_alarms: int
    faulty_samples: int
    detected_faulty: int
    isolated_correct: int
    detection_delay_s: float | None

    @property
    def false_alarm_rate(self) -> float | None:
        return self.false_alarms / self.fault_free_samples if self.fault_free_samples else None

    @property
    def true_detection_rate(self) -> float | None:
        return self.detected_faulty / self.faulty_samples if self.faulty_samples else None

    @property
    def isolation_accuracy(self) -> float | None:
        return self.isolated_correct / self.detected_faulty if self.detected_faulty else None

    def as_dict(self) -> dict[str, int | float | None]:
        def r(x: float | None) -> float | None:
            return None if x is None else round(float(x), 5)

        return {"fault_free_samples": self.fault_free_samples,
                "false_alarms": self.false_alarms, "false_alarm_rate": r(self.false_alarm_rate),
                "faulty_samples": self.faulty_samples, "detected_faulty": self.detected_faulty,
                "true_detection_rate": r(self.true_detection_rate),
                "isolated_correct": self.isolated_correct,
                "fault_isolation_accuracy": r(self.isolation_accuracy),
                "detection_delay_s": r(self.detection_delay_s)}


def score(t: ArrayLike, detected: ArrayLike, isolated: ArrayLike, fault: str = "",
          onset_s: float = math.nan, counted: ArrayLike | None = None) -> Score:
    """Score one run. ``fault`` "" means fault-free throughout; ``counted`` masks samples
    that take no part (e.g. the identification part of a fault-free record)."""
    ts: NDArray[np.float64] = np.asarray(t, dtype=float)
    det: NDArray[np.bool_] = np.asarray(detected, dtype=bool)
    iso = np.asarray(isolated, dtype=object)
    if not (ts.shape == det.shape == iso.shape):
        raise ValueError("t, detected and isolated need one entry per sample")
    use: NDArray[np.bool_] = (np.ones(ts.shape, dtype=np.bool_) if counted is None
                              else np.asarray(counted, dtype=bool))
    faulty: NDArray[np.bool_] = (ts >= onset_s) if fault else np.zeros(ts.shape, dtype=np.bool_)
    ff = use & ~faulty
    fy = use & faulty
    hit = fy & det
    delay = None
    if fault and hit.any():
        delay = float(ts[np.flatnonzero(hit)[0]] - onset_s)
    return Score(fault_free_samples=int(ff.sum()), false_alarms=int((ff & det).sum()),
                 faulty_samples=int(fy.sum()), detected_faulty=int(hit.sum()),
                 isolated_correct=int((hit & (iso == fault)).sum()), detection_delay_s=delay)


def combine(scores: Sequence[Score]) -> Score:
    """Pooled over runs (sample-weighted); the delay is the worst one."""
    delays = [s.detection_delay_s for s in scores if s.detection_delay_s is not None]
    return Score(fault_free_samples=sum(s.fault_free_samples for s in scores),
                 false_alarms=sum(s.false_alarms for s in scores),
                 faulty_samples=sum(s.faulty_samples for s in scores),
                 detected_faulty=sum(s.detected_faulty for s in scores),
                 isolated_correct=sum(s.isolated_correct for s in scores),
                 detection_delay_s=max(delays) if delays else None)
