"""The supervisor's bookkeeping around the diagnosis, as pure functions and small records.

* :class:`StepAligner`: one diagnosis step per feature index, taken when every live on-line
  model has sent its residuals for that segment; a step still incomplete when the features are
  ``lag_s`` of **plant time** ahead is *skipped* (diagnosed "not valid"), counted and reported,
  never diagnosed on a subset. Late residuals and gaps in the feature indices are counted.
* :class:`Staleness`: per input (sensor blocks, features, each model's residuals) the plant
  time of its last message and the wall time of its arrival; an input is stale when it is
  ``stale_s`` of plant time behind the newest stamp of any input, or silent for
  ``wall_timeout_s`` wall seconds (health only: is the producer alive?).
* :func:`status_entries`: the /diagnostics entries (level, name, message, key/values) of the
  diagnosis, the pipeline, every input and every model node, from the records above.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from fdi_ros.core.bankdriver import BankDriver, label

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels


@dataclass
class Step:
    """A step ready for the diagnoser: ``complete`` False means skipped (not valid)."""

    index: int
    t: float
    residuals: dict[str, Any]
    complete: bool


@dataclass
class StepAligner:
    """Align the residuals of the bank on feature indices (see the module docstring)."""

    lag_s: float = 2.0
    next_index: int | None = None
    newest_t: float = -math.inf
    last_t: float = -math.inf  # plant time of the last step taken
    late: int = 0
    dropped: int = 0
    skipped: int = 0
    _feature_t: dict[int, float] = field(default_factory=dict)
    _pending: dict[int, dict[str, Any]] = field(default_factory=dict)
    _newest_index: int = -1

    def __post_init__(self) -> None:
        if not self.lag_s > 0:
            raise ValueError(f"lag_s must be > 0, not {self.lag_s}")

    @property
    def lag(self) -> float:
        """Plant seconds between the newest features and the last step taken."""
        return max(0.0, self.newest_t - self.last_t) if math.isfinite(self.last_t) else 0.0

    def add_features(self, index: int, t: float) -> None:
        if self.next_index is None:
            self.next_index = index
        if index <= self._newest_index or (self.next_index is not None
                                           and index < self.next_index):
            return  # repeated or out of order: already decided
        if self._newest_index >= 0 and index > self._newest_index + 1:
            self.dropped += index - self._newest_index - 1
        self._newest_index = index
        self._feature_t[index] = float(t)
        self.newest_t = max(self.newest_t, float(t))

    def add_residual(self, model_id: str, index: int, value: Any) -> bool:
        """Keep a residual for its step; False (and counted late) if that step was taken."""
        if self.next_index is not None and index < self.next_index:
            self.late += 1
            return False
        self._pending.setdefault(index, {})[model_id] = value
        return True

    def ready(self, expected: Iterable[str]) -> list[Step]:
        """Steps that can be taken now, in index order."""
        exp = set(expected)
        out = []
        while self.next_index is not None:
            k = self.next_index
            if k not in self._feature_t:
                if any(i > k for i in self._feature_t):
                    self.next_index = k + 1  # a dropped feature index: no step for it
                    continue
                break
            got = self._pending.get(k, {})
            complete = exp <= set(got)
            t = self._feature_t[k]
            if not complete and self.newest_t - t < self.lag_s:
                break
            if not complete:
                self.skipped += 1
            out.append(Step(k, self._feature_t.pop(k), self._pending.pop(k, {}), complete))
            self.last_t = t
            self.next_index = k + 1
            for old in [i for i in self._pending if i < self.next_index]:
                del self._pending[old]
        return out


@dataclass
class Source:
    t: float = -math.inf  # plant time of the last message
    wall: float = math.nan  # wall time of its arrival (NaN: never seen)
    since_wall: float = math.nan  # wall time it became expected


@dataclass
class Staleness:
    """Per input: stale in plant time (behind the newest stamp) or silent in wall time."""

    stale_s: float = 0.5
    wall_timeout_s: float = 2.0
    sources: dict[str, Source] = field(default_factory=dict)
    newest_t: float = -math.inf

    def seen(self, name: str, t: float, wall: float) -> None:
        s = self.sources.setdefault(name, Source())
        s.t = max(s.t, float(t))
        s.wall = wall
        self.newest_t = max(self.newest_t, float(t))

    def expect(self, name: str, wall: float) -> None:
        """Start watching an input that has not come yet (a model just taken on line)."""
        s = self.sources.setdefault(name, Source())
        s.since_wall = wall
        s.t = max(s.t, self.newest_t)

    def forget(self, name: str) -> None:
        self.sources.pop(name, None)

    def stale(self, now: float) -> dict[str, str]:
        """Stale input name -> why."""
        out = {}
        for name, s in self.sources.items():
            last_wall = s.wall if not math.isnan(s.wall) else s.since_wall
            if math.isnan(last_wall):
                continue
            if now - last_wall > self.wall_timeout_s:
                out[name] = f"stale: no {name} for {now - last_wall:.1f} s (wall)"
            elif self.newest_t - s.t > self.stale_s:
                out[name] = (f"stale: {name} {self.newest_t - s.t:.3f} s of plant time "
                             "behind the other inputs")
        return out


@dataclass(frozen=True)
class Entry:
    """One /diagnostics status, independent of the message class."""

    level: int
    name: str
    message: str
    hardware_id: str = ""
    values: tuple[tuple[str, str], ...] = ()


def diagnosis_entry(d: Any, plant: str, stale: Mapping[str, str],
                    overloaded: bool) -> Entry:
    """The diagnosis as a /diagnostics entry (``d``: the last Diagnosis or None)."""
    name = "fdi_supervisor: diagnosis"
    if stale:
        return Entry(STALE, name, "not valid: " + "; ".join(f"{k} {v}" for k, v in
                                                          sorted(stale.items())), plant,
                     (("state", "not_valid"), ("stale", ",".join(sorted(stale)))))
    if d is None:
        return Entry(OK, name, "waiting for data", plant)
    extra = d.extra or {}
    if d.state == "detected" and extra.get("not_isolable"):
        away = extra.get("away", ())
        msg = ("fault detected, not isolable with the models on line; candidates: "
               + ", ".join(f + (" (model away)" if f in away else "")
                           for f in d.candidate_faults))
        level = WARN
    else:
        level = {"no_fault": OK, "isolated": ERROR}.get(d.state, WARN)
        msg = {"no_fault": "no fault",
               "not_valid": "not valid here (skipped segment or outside the identified "
                            "region)" if overloaded else "not valid here (operating point "
                            "outside the identified region)",
               "detected": "fault detected, isolating",
               "isolated": f"fault isolated: {', '.join(d.isolated_faults)}"
               }.get(d.state, d.state)
    values = (("t_s", f"{d.t:.3f}"), ("state", d.state),
              ("min_residual_model", d.min_residual_model), ("fault_model", d.fault_model),
              ("candidate_faults", ",".join(d.candidate_faults)),
              ("isolated_faults", ",".join(d.isolated_faults)),
              ("models_online", ",".join(d.models_online)),
              ("detection_time_s", f"{d.detection_time:.3f}"),
              ("isolation_time_s", f"{d.isolation_time:.3f}"))
    return Entry(level, name, msg, plant, values)


def pipeline_entry(al: StepAligner, warn_lag_s: float) -> Entry:
    """Can the graph keep up? WARN with the lag and the counts of late/dropped/skipped."""
    over = al.skipped > 0 or al.lag > warn_lag_s
    vals = (("lag_s", f"{al.lag:.3f}"), ("late_residuals", str(al.late)),
            ("dropped_segments", str(al.dropped)), ("skipped_segments", str(al.skipped)))
    if over:
        msg = (f"overload: diagnosis {al.lag:.3f} s of plant time behind the features; "
               f"{al.skipped} segments skipped (not valid), {al.late} late residuals, "
               f"{al.dropped} dropped segments")
        return Entry(WARN, "fdi_supervisor: pipeline", msg, "", vals)
    msg = "keeping up" + (f" ({al.dropped} dropped segments)" if al.dropped else "")
    return Entry(OK, "fdi_supervisor: pipeline", msg, "", vals)


def input_entries(st: Staleness, stale: Mapping[str, str]) -> list[Entry]:
    out = []
    for name in sorted(st.sources):
        s = st.sources[name]
        if name in stale:
            out.append(Entry(STALE, f"fdi_supervisor: input {name}", stale[name], name,
                             (("last_t_s", f"{s.t:.3f}"),)))
        else:
            out.append(Entry(OK, f"fdi_supervisor: input {name}", "receiving", name,
                             (("last_t_s", f"{s.t:.3f}"),)))
    return out


def model_entries(drv: BankDriver, stale: Mapping[str, str]) -> list[Entry]:
    """One entry per model node: always the observed state; failures, external changes,
    staleness of its residuals."""
    out = []
    for v in drv.nodes.values():
        vals = (("state", label(v.observed)), ("wanted", label(v.desired)),
                ("external_transitions", str(v.external_count)),
                ("transitions", ",".join(v.history)))
        key = f"residuals {v.model_id}"
        if v.failed:
            level, msg = ERROR, f"node failed: {v.failed}"
        elif v.external:
            level, msg = WARN, v.external_text
        elif key in stale and drv.live(v.model_id):
            level, msg = STALE, f"{stale[key]} (frozen or overloaded?); its residuals not valid"
        elif v.observed == 0:
            level, msg = WARN, "node not seen yet"
        else:
            level, msg = OK, f"{label(v.observed)} (wanted {label(v.desired)})"
        out.append(Entry(level, f"fdi_supervisor: model {v.model_id}", msg, v.node, vals))
    return out
