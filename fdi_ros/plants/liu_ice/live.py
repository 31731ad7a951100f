"""LiU-ICE as a plant of the graph: measured data replayed sample by sample.

:class:`MeasuredRunner` turns a benchmark CSV (through the column mapping) into sensor blocks
of ``block_samples`` samples (no crank angle) and reports the file's fault ground truth when
plant time reaches the onset; :class:`LiuIcePreprocessor` makes one feature vector per sample.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.types import FaultEvent, FeatureVector, SampleBlock
from fdi_ros.plants.liu_ice import CHANNELS, PLANT, ROOT, UNITS, FileTruth, truth_of

MAPPING = ROOT / "config" / "mappings" / "liu_ice.yaml"


def load_record(path: str | Path, mapping: str | Path | None = None):
    """A benchmark CSV through the LiU-ICE column mapping."""
    from fdi_ros.core.measured import load_csv

    rec = load_csv(path, mapping or MAPPING)
    missing = [c for c in CHANNELS if c not in rec.signals]
    if missing:
        raise ValueError(f"{path}: the LiU-ICE plant needs signals {missing}")
    return rec


def truth_events(truth: FileTruth) -> list[FaultEvent]:
    if not truth.faulty:
        return []
    return [FaultEvent(t=truth.onset_s, fault=truth.fault, size=truth.size,
                       size_unit=truth.size_unit)]


def blocks_of(rec, block_samples: int = 10) -> list[SampleBlock]:
    """The record as sensor blocks of ``block_samples`` samples (the last may be shorter)."""
    if block_samples < 1:
        raise ValueError("block_samples must be >= 1")
    vals = np.vstack([rec[c] for c in CHANNELS])
    out = []
    for i, a in enumerate(range(0, rec.n_samples, block_samples)):
        b = min(a + block_samples, rec.n_samples)
        out.append(SampleBlock(plant=PLANT, index=i, t=rec.t[a:b].copy(), alpha=np.zeros(0),
                               channels=CHANNELS, units=UNITS, values=vals[:, a:b].copy()))
    return out


# Sensor gain faults that can be injected into measured data (the signal the gain acts on).
INJECTABLE = {"f_pic": "p_ic", "f_pim": "p_im", "f_waf": "maf"}


class MeasuredRunner:
    """A measured CSV played as the plant (scenario = the CSV path, or a mapping with
    ``csv``, optional ``mapping``, ``block_samples``, ``onset_s``; a relative path is looked
    up from the working directory, then from the repository root).

    Sensor gain faults can be injected at run time as the benchmark's control unit injects
    them: from the event's time on the sensor reads ``size`` x its measured value
    (``fault`` ``f_pic``, ``f_pim`` or ``f_waf``; ``""`` or ``active = False`` removes it).
    A leak is a process fault: measured data cannot be given one.
    """

    plant = PLANT

    def __init__(self, scenario: str | Path | dict | None = None, *,
                 seed: int | None = None) -> None:
        del seed  # measured data: nothing random
        sc: dict[str, Any] = ({"csv": scenario} if isinstance(scenario, str | Path)
                              else dict(scenario or {}))
        if "csv" not in sc:
            raise ValueError("the liu_ice plant needs a measured CSV (scenario: the CSV path)")
        path = Path(sc["csv"])
        if not path.is_absolute() and not path.exists():
            path = ROOT / path
        sc["csv"] = path
        rec = load_record(path, sc.get("mapping"))
        self._blocks = blocks_of(rec, int(sc.get("block_samples", 10)))
        self._i = 0
        self._t = float(rec.t[0])
        self._truth: list[FaultEvent] = []   # pending, in time order
        self._gains: dict[str, tuple[float, float]] = {}   # channel -> (from t, gain)
        for ev in truth_events(truth_of(sc["csv"], sc.get("onset_s"), unlabelled_ok=True)):
            self._add_truth(ev)

    @property
    def t(self) -> float:
        return self._t

    @property
    def done(self) -> bool:
        return self._i >= len(self._blocks)

    def next_block(self) -> SampleBlock:
        b = self._blocks[self._i]
        self._i += 1
        self._t = float(b.t[-1])
        if self._gains:
            vals = b.values.copy()
            for ch, (t0, g) in self._gains.items():
                row = CHANNELS.index(ch)
                vals[row, b.t >= t0] *= g
            b = SampleBlock(plant=b.plant, index=b.index, t=b.t, alpha=b.alpha,
                            channels=b.channels, units=b.units, values=vals)
        return b

    def inject(self, event: FaultEvent) -> None:
        if not event.fault:
            self._gains.clear()
        elif event.fault not in INJECTABLE:
            raise ValueError(f"measured data can only be given sensor gain faults "
                             f"{sorted(INJECTABLE)}, not {event.fault!r}")
        elif not event.active:
            self._gains.pop(INJECTABLE[event.fault], None)
        else:
            if not (np.isfinite(event.size) and 0.5 <= event.size <= 2.0):
                raise ValueError(f"gain {event.size} outside [0.5, 2]")
            self._gains[INJECTABLE[event.fault]] = (float(event.t), float(event.size))
        self._add_truth(event)

    def _add_truth(self, event: FaultEvent) -> None:
        self._truth = sorted([*self._truth, event], key=lambda e: e.t)

    def pop_truth(self) -> list[FaultEvent]:
        due = [e for e in self._truth if e.t <= self._t]
        self._truth = self._truth[len(due):]
        return due


class LiuIcePreprocessor:
    """One feature vector per sample (time-synchronous plant): the block's channels."""

    def __init__(self, **kwargs) -> None:
        self._index = 0

    def push(self, block: SampleBlock) -> list[FeatureVector]:
        out = []
        for k in range(block.t.shape[0]):
            v = block.values[:, k].astype(float)
            ok = bool(np.all(np.isfinite(v)))
            t = float(block.t[k])
            out.append(FeatureVector(plant=block.plant, index=self._index, t_start=t, t_end=t,
                                     alpha_start=0.0, valid=ok,
                                     status="" if ok else "missing sample",
                                     names=tuple(block.channels), units=tuple(block.units),
                                     values=v))
            self._index += 1
        return out

    def mark_gap(self) -> None:
        pass

    def reset(self) -> None:
        self._index = 0

