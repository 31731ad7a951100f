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
from collections import deque
from collections.abc import Iterable, Mapping
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import Any

from fdi_ros.core.bankdriver import TIMEOUT, BankDriver, Note, label
from fdi_ros.core.diagnoser import Diagnoser
from fdi_ros.core.faultmemory import FaultMemory, FaultRecord
from fdi_ros.core.handshake import unmatched_readers

OK, WARN, ERROR, STALE = 0, 1, 2, 3
# The supervisor's parameters: name: (default, description, read_only, (min, max) or None)
PARAMS = {  # name: (default, description, read_only, (min, max) or None)
    "graph_config": ("", "path of config/<plant>.yaml (required)", True, None),
    "lag_s": (2.0, "plant s the features may run ahead before a step is skipped", False,
              (0.01, 60.0)),
    "stale_s": (0.5, "plant s an input may lag the newest stamp before it is stale", True,
                (0.01, 60.0)),
    "stale_wall_s": (2.0, "wall s without an input before it is reported stale", True,
                     (0.1, 600.0)),
    "model_wall_s": (1.0, "wall s of features without a model's residuals: stale", True,
                     (0.1, 600.0)),
    "t0_s": (math.nan, "isolation hold time T0 [plant s] (default: the graph config)", False,
             None),
    "threshold_scale": (1.0, "symptom thresholds times this (the supervisor's symptoms only)",
                        False, (0.1, 10.0)),
    "explain_norm": (math.nan, "largest residual norm of a hypothesis that explains the data "
                     "(default: the graph config)", False, None),
    "ambiguity": (math.nan, "share of the runner-up hypothesis' norm the best one must stay "
                  "below to isolate; 1: the plain minimum (default: the graph config)", False,
                  None),
    "reconcile": ("reconcile", "external lifecycle changes: 'reconcile' or 'respect'", False,
                  None),
    "reconcile_after_s": (2.0, "wall s before an external change is undone", False,
                          (0.0, 600.0)),
    "confirm_s": (0.1, "plant s a fault stays isolated before CONFIRMED", True, (0.0, 60.0)),
    "heal_s": (5.0, "plant s of passed diagnosis before a fault is HEALED", True, (0.0, 1e6)),
    "state_dir": ("", "graph state directory (default $FDI_ROS_STATE_DIR or out/state)", True,
                  None),
    "snapshot_s": (5.0, "plant s of data before a confirmation in its snapshot bag", True,
                   (0.0, 600.0)),
    "diagnostics_period_s": (1.0, "period of /diagnostics [wall s]", True, (0.05, 60.0)),
    "wait_for_readers": ([""], "nodes that must read /fdi/features, /fdi/residuals and "
                         "/fdi/diagnosis before /fdi/ready (a recorder), or 'node:/topic' one "
                         "of them (a watcher: 'fdi_launch_watcher:/fdi/diagnosis')", True, None),
    "batched": (True, "read the bank's feature and residual vectors a sensor block per message "
                "(/fdi/feature_blocks, /fdi/residual_blocks); false: one per message "
                "(/fdi/features, /fdi/residuals), for model nodes that publish so", True, None),
    "ready_timeout_s": (120.0, "wall s after which /fdi/ready is sent with what is still "
                        "missing named (a source must not wait forever)", True, (0.0, 1e6)),
}
# topics the start-up handshake looks at (who publishes and reads them): the readers named in
# wait_for_readers must read these; the bank's own topics depend on ``batched``
GATE_TOPICS = ("/fdi/features", "/fdi/residuals", "/fdi/diagnosis")
# (features, residuals) the supervisor and the bank exchange, batched or one vector per message
# what the preprocessor writes: the supervisor names their readers when it says ready
# (fdi_ros.nodes.startup.ready_messages), so the writer can hold its first vectors for them
FEATURE_TOPICS = ("/fdi/features", "/fdi/feature_blocks")
DATA_TOPICS = {True: ("/fdi/feature_blocks", "/fdi/residual_blocks"),
               False: ("/fdi/features", "/fdi/residuals")}
  # diagnostic_msgs/DiagnosticStatus levels


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
    def newest_index(self) -> int:
        """The newest feature index seen (-1: none)."""
        return self._newest_index

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

    def ready(self, expected: Mapping[str, int] | Iterable[str],
              through: int | None = None, most: int | None = None) -> list[Step]:
        """Steps that can be taken now, in index order. ``expected``: the models whose
        residuals complete a step, each with the first index it is expected at (a model
        brought on line answers only the features after its activation; a plain iterable:
        every step); ``through``: take every step up to this index now, complete or not (the
        end of the data: no later features will come to push the incomplete ones out by
        ``lag_s``); ``most``: at most this many steps."""
        start = dict(expected) if isinstance(expected, Mapping) else dict.fromkeys(expected, -1)
        out: list[Step] = []
        last = -1 if through is None else through
        while self.next_index is not None and (most is None or len(out) < most):
            k = self.next_index
            if k not in self._feature_t:
                if any(i > k for i in self._feature_t) or k <= last:
                    self.next_index = k + 1  # a dropped feature index: no step for it
                    continue
                break
            got = self._pending.get(k, {})
            complete = all(m in got for m, k0 in start.items() if k0 <= k)
            t = self._feature_t[k]
            if not complete and self.newest_t - t < self.lag_s and k > last:
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
    first_wall: float = math.nan  # wall time of its first message


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
        if math.isnan(s.first_wall):
            s.first_wall = wall
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


@dataclass(frozen=True)
class Publish:
    """Action: publish ``what`` ("symptoms": (index, t, SymptomState); "diagnosis": Diagnosis;
    "confirmed": FaultRecord, for a snapshot; "end": (t, last index, why), the end of the
    diagnosis, see :meth:`SupervisorCore.end_of_features`)."""

    what: str
    value: Any


class SupervisorCore:
    """Everything the supervisor node decides, fed with plain events (no rclpy).

    Diagnosis (plant time from stamps): :class:`StepAligner` -> ``Diagnoser`` -> fault memory.
    Health (wall time): :class:`BankDriver`, :class:`Staleness`. The node converts messages
    into calls of ``features``, ``residual``, ``block``, ``transition``, ``tick`` and executes
    the actions returned (service calls, publications, log lines).
    """

    def __init__(self, cfg: Any, *, policy: Any = None, lag_s: float = 2.0,
                 stale_s: float = 0.5, stale_wall_s: float = 2.0, model_wall_s: float = 1.0,
                 confirm_s: float = 0.1, heal_s: float = 5.0, store: Any = None,
                 snapshot_s: float = 5.0, batched: bool = True) -> None:
        self.cfg = cfg
        self.batched = batched  # the bank's vectors a sensor block per message (DATA_TOPICS)
        self.diag = Diagnoser(cfg)
        self.driver = BankDriver([(e.id, e.node_name) for e in cfg.bank], policy)
        self.driver.set_desired(self.diag.models_online)
        self.aligner = StepAligner(lag_s=lag_s)
        self.inputs = Staleness(stale_s=stale_s, wall_timeout_s=stale_wall_s)
        self.models = Staleness(stale_s=math.inf, wall_timeout_s=model_wall_s)
        self.memory = FaultMemory(confirm_s=confirm_s, heal_s=heal_s)
        self.store = store
        if store is not None:
            store.load(self.memory)
        self.last: Any = None
        self._features: dict[int, dict[str, float]] = {}
        self._symptoms: dict[int, Any] = {}
        self._stale: dict[str, str] = {}
        self.away: set[str] = set()  # models the steps do not wait for (see _steps)
        self._live_from: dict[str, int] = {}  # live model -> first feature index it answers
        # model brought on line by a bank switch -> the step after the switch, from which it
        # answers (core.modelfeed) and is waited for, confirmed active or still activating
        self._switched_in: dict[str, int] = {}
        # end of the data: (plant time, last feature index) from the preprocessor, the wall
        # time it came, and whether the end of the diagnosis was said (see end_of_features)
        self.end: tuple[float, int] | None = None
        self._end_wall = math.nan
        self._end_said = False
        self._flush_through: int | None = None
        self._end_why = ""
        # what the start-up handshake still waits for (see waiting_for; set by the node)
        self.waiting: list[str] = ["the first check"]
        # the last snapshot_s of plant time as core records (features, residuals, diagnoses),
        # for the snapshot bag written at a confirmation
        self.snapshot_s = snapshot_s
        self.ring: deque[tuple[float, str, object]] = deque()

    @classmethod
    def from_params(cls, p: Mapping[str, Any]) -> SupervisorCore:
        """From the node's parameters (see :data:`PARAMS`); the fault memory in
        ``<state_dir>/<plant>_faults.sqlite`` (state_dir: the parameter, else
        ``$FDI_ROS_STATE_DIR``, else ``out/state``)."""
        import os
        from pathlib import Path

        from fdi_ros.core.bankdriver import DriverPolicy
        from fdi_ros.core.faultmemory import FaultStore
        from fdi_ros.core.graphconfig import load_graph_config

        if not p["graph_config"]:
            raise ValueError("parameter 'graph_config' is required")
        cfg = load_graph_config(p["graph_config"])
        state = Path(p["state_dir"] or os.environ.get("FDI_ROS_STATE_DIR", "out/state"))
        core = cls(cfg, policy=DriverPolicy(node_timeout_s=cfg.node_timeout_s,
                                            policy=p["reconcile"],
                                            reconcile_after_s=p["reconcile_after_s"]),
                   lag_s=p["lag_s"], stale_s=p["stale_s"], stale_wall_s=p["stale_wall_s"],
                   model_wall_s=p["model_wall_s"], confirm_s=p["confirm_s"],
                   heal_s=p["heal_s"], store=FaultStore(state / f"{cfg.plant}_faults.sqlite"),
                   snapshot_s=p["snapshot_s"], batched=bool(p.get("batched", True)))
        core.set("t0_s", p["t0_s"])
        core.set("explain_norm", p["explain_norm"])
        core.set("ambiguity", p["ambiguity"])
        if core.diag.symptom_gen is not None:
            core.set("threshold_scale", p["threshold_scale"])
        return core

    # -- data (plant time) --------------------------------------------------------------------
    def block(self, t: float, wall: float) -> None:
        if math.isfinite(t):  # a malformed block is not data
            self.inputs.seen("sensor_block", t, wall)

    def features(self, fv: Any, wall: float) -> list[object]:
        """A feature vector (:class:`fdi_ros.core.types.FeatureVector`) arrived."""
        self.inputs.seen("features", fv.t_end, wall)
        if self._end_said and self.end is not None and fv.index > self.end[1]:
            # features after the end said: a new source's data (a second replay into a
            # running graph), whose own end will be said again
            self.end, self._end_said, self._flush_through, self._end_why = None, False, None, ""
        self._track_live()  # a model confirmed active before these features answers them
        self.aligner.add_features(fv.index, fv.t_end)
        self._features[fv.index] = fv.as_dict()
        self._keep(fv.t_end, "features", fv)
        return self._steps()

    def _keep(self, t: float, kind: str, record: Any) -> None:
        self.ring.append((t, kind, record))
        while self.ring and self.ring[0][0] < t - self.snapshot_s:
            self.ring.popleft()

    def snapshot_path(self, r: Any) -> Any:
        """A new bag directory beside the fault memory for a confirmation of record ``r``."""
        base = self.store.path.parent / f"snapshot_{r.fault}_{r.occurrences}_{r.last_t_s:.3f}s"
        path, n = base, 1
        while path.exists():
            path, n = base.with_name(f"{base.name}.{n}"), n + 1
        return path

    def residual(self, rv: Any, wall: float) -> list[object]:
        if rv.model_id not in self.driver.nodes:
            return []
        self.models.seen(f"residuals {rv.model_id}", rv.t, wall)
        out: list[object] = []
        if rv.model_id in self.away and rv.t >= self.aligner.last_t - self.aligner.lag_s / 2:
            # caught up (within half the lag of the diagnosis): waited for again (hysteresis:
            # away at lag_s behind, back at lag_s / 2)
            self.away.discard(rv.model_id)
            out.append(Note("info", rv.model_id, f"model {rv.model_id} has caught up "
                            f"(segment {rv.index}); waited for again"))
        # kept whatever the model's state now: whether it counts is decided when its step is
        # taken (a model confirmed active again must find the residuals it sent meanwhile)
        if not self.aligner.add_residual(rv.model_id, rv.index, rv):
            return out
        self._keep(rv.t, "residuals", rv)
        if not (self.driver.live(rv.model_id) or rv.model_id in self._switched_in) \
                or rv.model_id not in self.diag.models_online:
            return out  # not expected by any step now: it completes none
        if rv.model_id == self.diag.reference_id and rv.index not in self._symptoms:
            s = self.diag.symptoms_of(rv)  # at once: the symptom need not wait for the bank
            self._symptoms[rv.index] = s
            out.append(Publish("symptoms", (rv.index, rv.t, s)))
        return out + self._steps()

    def _track_live(self) -> None:
        """The models the steps wait for, from which feature index. A model the bank switch
        of step k brought on line answers from k + 1, as offline, however late its
        activation (its node keeps the features meanwhile, :mod:`fdi_ros.core.modelfeed`):
        it is waited for from k + 1 while it is wanted, healthy and activating or active.
        Any other model confirmed active (a respawn, an external change undone) computes only
        what it receives once active: it is expected from the features after its
        confirmation, so the steps before do not wait for it."""
        online = set(self.diag.models_online)
        live = {m for m in online if self.driver.live(m)}
        for m, k in list(self._switched_in.items()):
            v = self.driver.nodes[m]
            if m not in online or v.failed or v.external:
                del self._switched_in[m]  # out of the bank again, or unhealthy: as any model
            elif m not in live:
                self._live_from[m] = k
                live.add(m)
            else:
                self._live_from.setdefault(m, k)
                del self._switched_in[m]  # confirmed active: a live model from k on
        for m in set(self._live_from) - live:
            del self._live_from[m]
        for m in live - set(self._live_from):
            self._live_from[m] = self.aligner.newest_index + 1

    def _expected(self) -> dict[str, int]:
        """The models the steps wait for, each with the first feature index it answers."""
        self._track_live()
        return {m: k for m, k in self._live_from.items() if m not in self.away}

    def _steps(self) -> list[object]:
        from dataclasses import replace

        out: list[object] = []
        while True:  # one step at a time: a bank switch changes whom the next ones wait for
            expected = self._expected()
            ready = self.aligner.ready(expected, through=self._flush_through, most=1)
            if not ready:
                break
            st = ready[0]
            sym = self._symptoms.pop(st.index, None)
            # A step still incomplete lag_s of plant time after its features is skipped (not
            # valid), and the models it lacked are *away*: later steps no longer wait for
            # them (the others would pile up) until one of their residuals comes in time
            # again. Decided in plant time only, so a busy machine that stalls a model for
            # less than lag_s changes nothing (the diagnosis equals offline); a silent model
            # is also reported STALE on /diagnostics, which is health only (wall time).
            # No-elimination keeps the rest from isolating a fault an away model would
            # explain, and names it "(model away)". A model away from its desired state (off
            # line, external change) at the step: its residuals are not valid.
            st.residuals = {m: r for m, r in st.residuals.items() if m in expected}
            skip = not st.complete
            if skip:
                lacking = sorted(m for m, k0 in expected.items() if k0 <= st.index
                                 and m not in st.residuals)
                self.away.update(lacking)
                out += [Note("warn", m, f"model {m}: no residuals for segment {st.index} "
                             f"after {self.aligner.lag_s:g} s of plant time; segment skipped, "
                             "the next ones diagnosed without it until it answers in time")
                        for m in lacking]
            step = self.diag.update(st.index, st.t, {} if skip else st.residuals,
                                    symptoms=None if skip else sym)
            d = step.diagnosis
            if skip:
                d = replace(d, state="not_valid" if not d.isolated_faults else d.state,
                            extra={**d.extra, "skipped": True})
            if sym is None and step.symptoms is not None and not skip:
                out.append(Publish("symptoms", (st.index, st.t, step.symptoms)))
            out.append(Publish("diagnosis", d))
            self._keep(d.t, "diagnosis", d)
            if d.state != (self.last.state if self.last is not None else ""):
                out.append(Note("info", "", f"t = {st.t:.3f} s segment {st.index}: {d.state}; "
                                f"I* = {d.min_residual_model or '-'}, candidates "
                                f"{list(d.candidate_faults)}, isolated {list(d.isolated_faults)}"))
            self.last = d
            if step.switched:
                self.driver.set_desired(self.diag.models_online)
                for m in step.removed:
                    self._switched_in.pop(m, None)
                self._switched_in.update(dict.fromkeys(step.added, st.index + 1))
                out.append(Note("info", "", f"bank switch at t = {st.t:.3f} s: off line "
                                f"{list(step.removed)}, on line {list(step.added)}"))
            out += self._remember(d, st, step.symptoms)
            for old in [i for i in self._features if i <= st.index]:
                del self._features[old]
        return out + self._drained()

    # -- end of the data ----------------------------------------------------------------------
    def end_of_features(self, t: float, last_index: int, wall: float) -> list[object]:
        """The preprocessor's end of the features: ``last_index`` is the index of its last
        feature vector (-1: none), ``t`` the plant time the data ended. Once the step of that
        index is taken the supervisor says ``Publish("end", (t, last diagnosed index, why))``:
        the whole run is diagnosed (see :meth:`tick` for residuals or features that never
        come)."""
        if self.end is None:
            self.end, self._end_wall = (float(t), int(last_index)), wall
        return self._steps()

    def _drained(self, force: bool = False) -> list[object]:
        if self.end is None or self._end_said:
            return []
        t, last = self.end
        nxt = self.aligner.next_index
        if not force and last >= 0 and (nxt is None or nxt <= last):
            return []
        # the end names the last segment actually diagnosed (a watcher waits until it has
        # seen that diagnosis): the last feature index unless features never came
        done = int(self.last.index) if self.last is not None else -1
        self._end_said, why = True, self._end_why
        return [Publish("end", (t, done, why)),
                Note("info" if not why else "warn", "", f"end of the data at t = {t:.3f} s: "
                     f"diagnosed through segment {done}{'; ' + why if why else ''}")]

    def _end_overdue(self, now: float) -> list[object]:
        """Health fallback (wall time) at the end of the data: residuals still missing after
        ``stale_wall_s`` of silence are not waited for (those steps are skipped, not valid);
        features that never came are named and the end is said without them."""
        if self.end is None or self._end_said or self._flush_through is not None:
            return []
        quiet = max(self._end_wall, *(s.wall for s in self.models.sources.values()
                                      if not math.isnan(s.wall)), -math.inf)
        if now - quiet <= self.inputs.wall_timeout_s:
            return []
        last, newest = self.end[1], self.aligner.newest_index
        if newest < last:
            self._end_why = f"features {newest + 1}..{last} never came"
        self._flush_through = last
        return self._steps() + self._drained(force=True)

    def _remember(self, d: Any, st: Step, sym: Any) -> list[object]:
        frame = {"features": self._features.get(st.index, {}),
                 "residuals": {m: {"norm": float(r.norm), "values": list(map(float, r.values))}
                               for m, r in st.residuals.items()},
                 "symptoms": dict(zip(sym.names, sym.levels)) if sym is not None else {}}
        changed = self.memory.update(d.t, d.state, d.isolated_faults, frame)
        if self.store is not None and changed:
            self.store.save(changed)
        return [Publish("confirmed", r) for r in changed if r.status == "CONFIRMED"] + [
            Note("info", "", f"fault memory: {r.fault} {r.status}") for r in changed]

    def set(self, name: str, value: Any) -> None:
        """A live parameter change, validated (ValueError if it cannot apply)."""
        from dataclasses import replace

        if name == "t0_s" and not math.isnan(value):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"t0_s must be a finite time >= 0 s, not {value}")
            self.diag.supervisor.t0_s = float(value)
        elif name == "threshold_scale":
            gen = self.diag.symptom_gen
            if gen is None or not (math.isfinite(value) and value > 0):
                raise ValueError(f"threshold_scale {value}: needs a symptom stage and a "
                                 "finite value > 0")
            base = self._base_symptoms = getattr(self, "_base_symptoms", gen.config)
            gen.config = replace(base, threshold=tuple(value * x for x in base.threshold))
        elif name == "explain_norm" and not math.isnan(value):
            if not value > 0:
                raise ValueError(f"explain_norm must be > 0, not {value}")
            self.diag.explain_norm = float(value)
        elif name == "ambiguity" and not math.isnan(value):
            if not 0 < value <= 1:
                raise ValueError(f"ambiguity must be in (0, 1], not {value}")
            self.diag.ambiguity = float(value)
        elif name == "lag_s":
            if not value > 0:
                raise ValueError(f"lag_s must be > 0, not {value}")
            self.aligner.lag_s = float(value)
        elif name in ("reconcile", "reconcile_after_s"):
            key = "policy" if name == "reconcile" else name
            self.driver.policy = replace(self.driver.policy, **{key: value})

    def clear_request(self, faults: list[str]) -> tuple[bool, str, list[FaultRecord]]:
        """The ``/fdi/clear_faults`` answer: (success, message, records cleared)."""
        try:
            cleared = self.clear(faults)
        except KeyError as exc:
            return False, str(exc), []
        return True, f"cleared {len(cleared)} fault(s)", cleared

    def clear(self, faults: list[str]) -> list[FaultRecord]:
        """Clear faults of the memory; clearing all restarts the diagnosis (initial bank)."""
        cleared = self.memory.clear(faults)
        if self.store is not None:
            self.store.save(cleared)
        if not faults:
            self.diag = Diagnoser(self.cfg)
            self.driver.set_desired(self.diag.models_online)
        return cleared

    # -- start-up handshake (graph state) -----------------------------------------------------
    def waiting_for(self, pubs: Mapping[str, Iterable[str]], subs: Mapping[str, Iterable[str]],
                    matched: Mapping[str, int], readers: Iterable[str] = (),
                    written: Mapping[str, int] | None = None) -> list[str]:
        """What the graph still lacks before the data source may send its first block (empty:
        ready). The source's first segments must reach every part that decides, or the
        filters' warm-up (symptom debounce, hypothesis windows) would end at another segment
        than offline, and live would differ from ``fdi-ros diagnose``.

        ``pubs`` / ``subs``: node names publishing / reading each of :data:`GATE_TOPICS` as
        the graph shows them; ``matched``: the publishers *matched* to this node's own
        subscriptions (per topic); ``readers``: nodes that must read every gate topic (a
        recorder), or ``"node:/topic"`` only that one (a watcher of the diagnosis);
        ``written``: the readers *matched* to this node's own publishers (per topic, e.g. the
        diagnosis), each of which must cover the readers the graph shows of it (discovery
        reaches each process at its own pace: a recorder seen but not yet matched would miss
        the first diagnoses).
        Needed: every on-line model confirmed active (a model refused or in a state it cannot
        leave is out of the bank and not waited for), reading the features and publishing
        residuals (on :data:`DATA_TOPICS` of ``self.batched``), all of them matched here; the
        features' publisher matched here.
        """
        f_topic, r_topic = DATA_TOPICS[self.batched]
        out: list[str] = []
        live = 0
        for m in self.diag.models_online:
            v = self.driver.nodes[m]
            if v.failed and not v.failed.startswith(TIMEOUT):
                continue
            if not self.driver.live(m):
                out.append(f"{v.node} {label(v.observed)} (wanted active)")
                continue
            live += 1
            for topic, seen in ((f_topic, subs), (r_topic, pubs)):
                if v.node not in set(seen.get(topic, ())):
                    out.append(f"{v.node} on {topic}")
        if matched.get(f_topic, 0) < 1:
            out.append(f"a publisher of {f_topic} (the preprocessor)")
        if matched.get(r_topic, 0) < live:
            out.append(f"{matched.get(r_topic, 0)}/{live} residual publishers matched")
        for r in (x for x in readers if x):
            node, _, only = r.partition(":")
            out += [f"{node} reading {t}" for t in ((only,) if only else GATE_TOPICS)
                    if node not in set(subs.get(t, ()))]
        w = written or {}
        return out + unmatched_readers(None, {t: subs.get(t, ()) for t in w}, w)

    # -- health (wall time) -------------------------------------------------------------------
    def tick(self, now: float, ready: dict[str, bool], present: AbstractSet[str] | None
             ) -> list[object]:
        out: list[object] = []
        for mid, v in self.driver.nodes.items():
            key = f"residuals {mid}"
            if self.driver.live(mid) and mid in self.diag.models_online:
                if key not in self.models.sources:
                    self.models.expect(key, now)
            else:
                self.models.forget(key)
            if present is not None:
                out += self.driver.on_presence(mid, v.node in present, now)
        stale = {**self.inputs.stale(now), **self._models_stale(now)}
        for k in set(stale) ^ set(self._stale):
            out.append(Note("warn" if k in stale else "info", "",
                            stale.get(k, f"{k}: receiving again")))
        self._stale = stale
        return out + self.driver.tick(now, ready) + self._steps() + self._end_overdue(now)

    def _models_stale(self, now: float) -> dict[str, str]:
        """A model is stale when features kept coming for ``model_wall_s`` after its last
        residuals (frozen or overloaded); without features no model is judged. A model on
        line before the data started is counted from the first features (the start-up
        handshake activates the bank before the source sends anything)."""
        fw = self.inputs.sources.get("features")
        if fw is None or math.isnan(fw.wall):
            return {}
        out = {}
        for k, why in self.models.stale(now).items():
            s = self.models.sources[k]
            last = max(s.wall if not math.isnan(s.wall) else s.since_wall, fw.first_wall)
            if fw.wall - last > self.models.wall_timeout_s:
                out[k] = why
        return out

    def entries(self, now: float) -> list[Entry]:
        warn_lag = self.aligner.lag_s / 2
        return ([diagnosis_entry(self.last, self.cfg.plant, {k: v for k, v in self._stale.items()
                                                             if not k.startswith("residuals")},
                                 self.aligner.skipped > 0),
                 pipeline_entry(self.aligner, warn_lag)]
                + input_entries(self.inputs, self._stale)
                + model_entries(self.driver, self._stale)
                + [Entry(OK, "fdi_supervisor: start-up", "waiting for: " + "; ".join(
                    self.waiting) if self.waiting else "graph ready (/fdi/ready sent)")])
