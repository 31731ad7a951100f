"""Run a graph configuration live with a scenario, watch it, and summarise what happened.

Shared by ``fdi-ros demo``, ``fdi-ros bench graph`` and the graph tests, so they all exercise
the same real thing: separate node processes over DDS, the bank brought on line through the
lifecycle services before the plant starts, a fault injected, the supervisor's answer watched
from this process.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fdi_ros.graphwatch import GraphWatcher, run_ended
from fdi_ros.launcher import MODELS_SECTION, Graph


@dataclass
class LiveRun:
    """What a live run produced (times are plant time [s] unless named wall)."""

    fault_onset: float = math.nan
    fault: str = ""
    first_symptom_t: float = math.nan
    first_symptom: dict = field(default_factory=dict)
    detection_t: float = math.nan
    isolation_t: float = math.nan
    isolated_faults: tuple[str, ...] = ()
    isolations: list[dict] = field(default_factory=list)
    cleared_detections: list[float] = field(default_factory=list)
    switches: list[dict] = field(default_factory=list)
    lifecycle_after: dict[str, str] = field(default_factory=dict)
    segments: int = 0
    final_t: float = math.nan
    wall_s: float = math.nan
    bag: str | None = None
    ended: bool = False  # the data ended and was diagnosed to its end (graphwatch.run_ended)

    def as_dict(self) -> dict:
        def r(x: float) -> float | None:
            return None if x is None or (isinstance(x, float) and math.isnan(x)) else round(x, 4)

        return {
            "fault": self.fault, "fault_onset_s": r(self.fault_onset),
            "first_symptom_s": r(self.first_symptom_t), "first_symptom": self.first_symptom,
            "detection_s": r(self.detection_t),
            "detection_delay_s": r(self.detection_t - self.fault_onset),
            "isolation_s": r(self.isolation_t),
            "isolation_delay_s": r(self.isolation_t - self.fault_onset),
            "isolated_faults": list(self.isolated_faults), "isolations": self.isolations,
            "cleared_detections_s": [round(x, 4) for x in self.cleared_detections],
            "bank_switches": self.switches,
            "lifecycle_states_after": self.lifecycle_after, "segments": self.segments,
            "plant_time_s": r(self.final_t), "wall_s": r(self.wall_s), "bag": self.bag,
        }


def bank_ready(w: GraphWatcher, model_ids: list[str]) -> bool:
    """Every model's node reached the state the supervisor wants (per /diagnostics)."""
    for mid in model_ids:
        st = w.diagnostic_status(f"fdi_supervisor: model {mid}")
        if st is None:
            return False
        kv = {v.key: v.value for v in st.values}
        if kv.get("state") != kv.get("wanted"):
            return False
    return True


def bank_report(w: GraphWatcher, model_ids: list[str]) -> str:
    """What /diagnostics last said of each model (for error messages)."""
    out = []
    for mid in model_ids:
        st = w.diagnostic_status(f"fdi_supervisor: model {mid}")
        out.append(f"{mid}: {st.message if st is not None else 'no status'}")
    return "; ".join(out)


def run_live(config: str | Path, *, scenario: str | Path | None = None,
             record: str | Path | None = None, replay: str | Path | None = None,
             realtime_factor: float = 1.0, timeout_s: float = 120.0,
             during: Callable[[Graph, GraphWatcher, LiveRun], None] | None = None,
             echo: Callable[[str], None] | None = None, watch_features: bool = False,
             watch_blocks: bool = False,
             log: Callable[[str], None] = lambda s: None,
             stop_after_isolation_s: float | None = None,
             hosting: Any = None, hold_back: bool = True,
             batched: bool = True) -> tuple[LiveRun, GraphWatcher]:
    """Launch (the source starts after the start-up handshake: the bank active, every reader
    matched), watch until the source's end-of-data event (or ``stop_after_isolation_s`` plant
    seconds after an isolation), stop.

    ``during(graph, watcher, run)`` is called on every watch iteration (tests kill nodes
    from it). ``hosting``: how the model nodes are hosted (:class:`fdi_ros.launcher.Graph`).
    ``hold_back``: the source waits for a diagnosis more than 1 s of plant time behind (its
    ``max_ahead_s``); False: the source keeps its pace whatever the graph does (throughput
    benchmarks, where falling behind must show). ``batched``: the bank and the supervisor
    exchange a sensor block's vectors per message (False: one vector per message).
    Returns the run summary and the (closed) watcher with everything it saw.
    """
    # the source starts after the start-up handshake (see Graph), so no start delay
    ahead = 1.0 if hold_back else 0.0
    over: dict[str, dict] = {"fdi_plant": {"realtime_factor": realtime_factor,
                                           "start_delay_s": 0.0, "max_ahead_s": ahead},
                             "fdi_replayer": {"rate": realtime_factor, "max_ahead_s": ahead}}
    if scenario is not None:
        over["fdi_plant"]["scenario"] = str(Path(scenario).resolve())
    if not batched:
        over["fdi_supervisor"] = {"batched": False}
        over[MODELS_SECTION] = {"batched": False}
    graph = Graph(config, overrides=over, record=record, replay=replay, echo=echo,
                  extra_block_readers=int(watch_blocks), watcher="fdi_watcher",
                  hosting=hosting)
    w = GraphWatcher("fdi_watcher", watch_features=watch_features, watch_blocks=watch_blocks)
    run = LiveRun(bag=str(record) if record else None)
    bank = [e.id for e in graph.cfg.bank]
    source = graph.source
    wall0 = time.monotonic()
    try:
        graph.start()  # every process at once: the source waits for the handshake
        deadline = time.monotonic() + timeout_s
        last_state = ""
        online: tuple[str, ...] = ()
        seen_switch = scanned = 0
        episode = math.nan
        while time.monotonic() < deadline:
            w.executor.spin_once(timeout_sec=0.05)
            if during is not None:
                during(graph, w, run)
            if w.seen.truth and math.isnan(run.fault_onset):
                ev = w.seen.truth[0][1]
                run.fault_onset, run.fault = ev.t, ev.fault
                log(f"t = {ev.t:7.3f} s  fault injected: {ev.fault} {ev.size:g} {ev.size_unit}")
            scanned = _scan_symptoms(w, run, log, scanned)
            for _, d in w.seen.diagnoses[seen_switch:]:
                seen_switch += 1
                run.segments += 1
                run.final_t = d.t
                if d.state != last_state:
                    log(f"t = {d.t:7.3f} s  supervisor: {d.state}; I* = "
                        f"{d.min_residual_model or '-'}; F* = {d.fault_model}; candidates "
                        f"{list(d.candidate_faults)}")
                    last_state = d.state
                # detection episodes: the one that leads to the first isolation is the
                # detection; those the hold time T0 rejected are reported as cleared
                if d.state == "detected" and math.isnan(episode):
                    episode = d.t
                elif d.state == "no_fault" and not math.isnan(episode):
                    run.cleared_detections.append(episode)
                    episode = math.nan
                if d.state == "isolated" and (not run.isolations or
                                              run.isolations[-1]["model"] != d.fault_model):
                    run.isolations.append({"t": round(d.isolation_time, 4),
                                           "model": d.fault_model,
                                           "detected_t": None if math.isnan(episode)
                                           else round(episode, 4)})
                    if math.isnan(run.isolation_t):
                        run.isolation_t, run.isolated_faults = d.isolation_time, \
                            d.isolated_faults
                        run.detection_t = episode if not math.isnan(episode) \
                            else d.detection_time
                    episode = math.nan
                if online and d.models_online != online:
                    sw = {"t": round(d.t, 4), "off_line": sorted(set(online) -
                                                                  set(d.models_online)),
                          "on_line": sorted(set(d.models_online) - set(online))}
                    run.switches.append(sw)
                    log(f"t = {d.t:7.3f} s  bank switch: off line {sw['off_line']}, on line "
                        f"{sw['on_line']}")
                online = d.models_online
            src = graph.node(source)
            if run_ended(w.seen):
                run.ended = True
                break
            if stop_after_isolation_s is not None and not math.isnan(run.isolation_t) \
                    and run.final_t >= run.isolation_t + stop_after_isolation_s:
                break
            if src.proc is not None and src.proc.poll() is not None:
                raise RuntimeError(f"{source} exited: {src.lines[-5:]}")
        else:
            log(f"timed out after {timeout_s} s")
        if run.switches:  # confirm the bank switch with the standard get_state service
            healthy = [m for m in bank if graph.alive().get(graph.cfg.entry(m).node_name)]
            w.spin_until(lambda: bank_ready(w, healthy), 30.0, "the switched bank")
            for mid in bank:
                e = graph.cfg.entry(mid)
                gone = not graph.alive().get(e.node_name, False)
                run.lifecycle_after[mid] = "process gone" if gone else \
                    w.lifecycle_state(e.node_name)
    finally:
        run.wall_s = time.monotonic() - wall0
        graph.stop()
        w.close()
    return run, w


def _scan_symptoms(w: GraphWatcher, run: LiveRun, log: Callable[[str], None],
                   start: int = 0) -> int:
    """The first symptom after the fault onset among the symptom messages from ``start`` on;
    returns where the next scan starts (a message that failed the test fails it for good:
    the onset, once known, stays; a long fault-free run was rescanned from its first message
    on every turn of the loop, 0.2-0.35 of a core at 100 segments/s)."""
    if not math.isnan(run.first_symptom_t):
        return start
    seen = w.seen.symptoms
    for i in range(start, len(seen)):
        m = seen[i][1]
        if m.valid and any(int(v) for v in m.levels) and m.t_s >= (
                run.fault_onset if not math.isnan(run.fault_onset) else -math.inf):
            run.first_symptom_t = float(m.t_s)
            code = {-1: "-", 0: "o", 1: "+", 2: "++"}
            run.first_symptom = {n: code[int(v)] for n, v in zip(m.names, m.levels)}
            log(f"t = {m.t_s:7.3f} s  first symptom: {run.first_symptom}")
            return i + 1
    return len(seen)


def first_symptom_arrival(w: GraphWatcher, onset: float) -> Any:
    """(wall arrival, message) of the first symptom message at or after the fault onset."""
    for wall, m in w.seen.symptoms:
        if m.valid and any(int(v) for v in m.levels) and m.t_s >= onset:
            return wall, m
    return None
