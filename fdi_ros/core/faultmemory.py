"""Fault memory in the style of an automotive diagnostic event manager (AUTOSAR DEM).

Per fault a debounced status

    PREFAILED -> CONFIRMED -> HEALED -> CLEARED

* PREFAILED: the diagnosis isolates the fault, the debounce counter runs;
* CONFIRMED: isolated for ``confirm_s`` of plant time without interruption (the counter reached
  its limit); the occurrence count goes up and a freeze frame (features, residuals, symptoms
  at confirmation) is stored;
* HEALED: after confirmation, ``heal_s`` of plant time in which the diagnosis says no fault;
* CLEARED: cleared by the user (``/fdi/clear_faults``); a new isolation starts again.

A PREFAILED fault that the diagnosis drops before confirmation goes back to its former status.
All times are plant time [s] from message stamps. :class:`FaultStore` persists the records in
SQLite (stdlib), one row per fault, written in one transaction per change, so a killed
supervisor loses nothing it had reported.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

STATUSES = ("PREFAILED", "CONFIRMED", "HEALED", "CLEARED")


@dataclass
class FaultRecord:
    fault: str
    status: str = "PREFAILED"
    occurrences: int = 0
    first_t_s: float = math.nan
    last_t_s: float = math.nan
    counter_s: float = 0.0  # debounce: plant time isolated (to CONFIRMED) or passed (to HEALED)
    since_t_s: float = math.nan  # plant time the counter started
    previous: str = ""  # status to fall back to when a PREFAILED fault is dropped
    freeze_frame: dict[str, Any] = field(default_factory=dict)


@dataclass
class FaultMemory:
    """Debounced per-fault status driven by the diagnosis steps (pure; see module doc)."""

    confirm_s: float = 0.1
    heal_s: float = 5.0
    records: dict[str, FaultRecord] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("confirm_s", "heal_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite time >= 0 s, not {v}")

    def update(self, t: float, state: str, isolated: Iterable[str],
               frame: Mapping[str, Any] | None = None) -> list[FaultRecord]:
        """One diagnosis step at plant time ``t``; returns the records whose status changed."""
        iso = set(isolated) if state == "isolated" else set()
        changed = []
        for f in sorted(iso):
            r = self.records.get(f)
            if r is None:
                r = self.records[f] = FaultRecord(f, previous="")
                r.first_t_s = t
                r.since_t_s = t
                changed.append(r)
            elif r.status in ("HEALED", "CLEARED"):
                r.previous, r.status, r.since_t_s = r.status, "PREFAILED", t
                changed.append(r)
            elif r.status == "CONFIRMED":
                r.since_t_s = math.nan  # the heal counter stops
            r.last_t_s = t
            if r.status == "PREFAILED":
                r.counter_s = t - r.since_t_s
                if r.counter_s >= self.confirm_s - 1e-9:
                    r.status, r.occurrences = "CONFIRMED", r.occurrences + 1
                    r.freeze_frame = {"t_s": t, **(dict(frame) if frame else {})}
                    r.since_t_s = math.nan
                    changed.append(r)
        for f, r in self.records.items():
            if f in iso:
                continue
            if r.status == "PREFAILED":
                if r.previous:  # dropped before confirmation: back to what it was
                    r.status, r.previous, r.since_t_s = r.previous, "", math.nan
                    changed.append(r)
                continue  # a new one is forgotten below
            elif r.status == "CONFIRMED":
                if state != "no_fault":
                    r.since_t_s = math.nan  # only a passed test heals (DEM: "test passed")
                    continue
                if math.isnan(r.since_t_s):
                    r.since_t_s = t
                r.counter_s = t - r.since_t_s
                if r.counter_s >= self.heal_s - 1e-9:
                    r.status, r.since_t_s = "HEALED", math.nan
                    changed.append(r)
        # a fault dropped before its first confirmation leaves no trace
        for f in [f for f, r in self.records.items()
                  if r.status == "PREFAILED" and f not in iso and r.occurrences == 0]:
            del self.records[f]
        return changed

    def clear(self, faults: Iterable[str] = ()) -> list[FaultRecord]:
        """Clear the named faults (all when empty); returns the records cleared."""
        names = set(faults) or set(self.records)
        unknown = names - set(self.records)
        if unknown:
            raise KeyError(f"no fault {sorted(unknown)} in the memory")
        out = []
        for f in sorted(names):
            r = self.records[f]
            r.status, r.counter_s, r.since_t_s, r.previous = "CLEARED", 0.0, math.nan, ""
            out.append(r)
        return out

    def confirmed(self) -> list[str]:
        return sorted(f for f, r in self.records.items() if r.status == "CONFIRMED")


def _jsonable(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return _jsonable(x.tolist())
    return x


class FaultStore:
    """SQLite persistence of a :class:`FaultMemory` (one table, one row per fault)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.db = sqlite3.connect(str(self.path))
            with self.db:
                self.db.execute(
                    "CREATE TABLE IF NOT EXISTS faults (fault TEXT PRIMARY KEY, status TEXT "
                    "NOT NULL, occurrences INTEGER NOT NULL, first_t_s REAL, last_t_s REAL, "
                    "previous TEXT, freeze_frame TEXT)")
        except sqlite3.DatabaseError as exc:
            raise ValueError(f"{self.path}: not a fault memory database ({exc})") from exc

    def load(self, memory: FaultMemory) -> FaultMemory:
        """Fill ``memory`` with the stored records (PREFAILED ones are not kept)."""
        rows = self.db.execute("SELECT fault, status, occurrences, first_t_s, last_t_s, "
                               "previous, freeze_frame FROM faults").fetchall()
        for fault, status, occ, first, last, prev, frame in rows:
            if status not in STATUSES or status == "PREFAILED":
                continue
            memory.records[fault] = FaultRecord(
                fault, status, int(occ), math.nan if first is None else float(first),
                math.nan if last is None else float(last), previous=prev or "",
                freeze_frame=json.loads(frame) if frame else {})
        return memory

    def save(self, records: Iterable[FaultRecord]) -> None:
        rows = [(r.fault, r.status, r.occurrences, _jsonable(r.first_t_s),
                 _jsonable(r.last_t_s), r.previous, json.dumps(_jsonable(r.freeze_frame)))
                for r in records if r.status != "PREFAILED"]
        if rows:
            with self.db:
                self.db.executemany("INSERT OR REPLACE INTO faults VALUES (?,?,?,?,?,?,?)",
                                    rows)

    def close(self) -> None:
        self.db.close()


def record_dict(r: FaultRecord) -> dict[str, Any]:
    """The record as JSON-ready data (non-finite numbers as null)."""
    out: dict[str, Any] = _jsonable({k: v for k, v in asdict(r).items() if k != "since_t_s"})
    return out
