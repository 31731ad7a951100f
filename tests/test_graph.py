"""The live graph over real DDS, each node its own process: a fault injected at run time into
the diesel plant (on /fdi/fault_inject) is detected from the symptoms topic, isolated by the
supervisor, the bank switched through the lifecycle services (checked with get_state),
reported on /diagnostics; a killed model node is reported and the diagnosis goes on; the
recorded bag replayed through the graph, and diagnosed offline, gives the same answer."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fdi_ros.livegraph import first_symptom_arrival, run_live

pytestmark = [pytest.mark.graph, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "diesel.yaml"
SCENARIO = ROOT / "config" / "scenarios" / "demo_diesel_leak.yaml"
ONSET = 6.0  # s, the scenario's 5 mm leak
SEGMENT_S = 0.015  # one 180 deg CA segment at 2000 rpm
MAX_SEGMENTS_TO_SYMPTOM = 5
KILLED = "crankcase_vent_open"
FROZEN = "egr_stuck_open"


@pytest.fixture(scope="module")
def live(diesel_bank, tmp_path_factory):
    import yaml

    from fdi_ros.core.types import FaultEvent

    tmp = tmp_path_factory.mktemp("live")
    out = tmp / "bag"
    # The demo scenario without its scheduled fault: the leak is injected at run time instead,
    # through the plant's /fdi/inject_fault service from this process.
    sc = yaml.safe_load(SCENARIO.read_text())
    sc.pop("faults")
    scenario = tmp / "no_fault.yaml"
    scenario.write_text(yaml.safe_dump(sc))
    done: dict = {}

    def inject_and_kill(graph, w, run):
        d = w.last_diagnosis()
        if d is None:
            return
        if "inject" not in done and d.t >= 1.0:
            done["inject"] = d.t
            done["answer"] = w.inject(FaultEvent(t=ONSET, fault="leak_ic_engine", size=5.0,
                                                 size_unit="mm"))
        node = graph.node(graph.cfg.entry(FROZEN).node_name)
        if "frozen" not in done and d.t >= 2.5:
            os.kill(node.proc.pid, signal.SIGSTOP)  # alive, in the graph, but not answering
            done["frozen"] = d.t
        if "frozen" in done and "thawed" not in done:
            # thawed once the supervisor has said on /diagnostics that it is silent
            st = w.diagnostic_status(f"fdi_supervisor: model {FROZEN}")
            if st is not None and st.message.startswith("stale") or d.t >= 5.5:
                os.kill(node.proc.pid, signal.SIGCONT)
                done["thawed"] = d.t
        if "t" not in done and d.t >= 2.0:
            # kill a bank model's process 2 s into the run (before the fault)
            graph.kill(graph.cfg.entry(KILLED).node_name)
            done["t"] = d.t
            done["n_diag"] = len(w.seen.diagnoses)

    lines: list[str] = []
    # a user's own node (examples/symptom_listener.py) subscribed to the symptoms throughout
    listener = subprocess.Popen([sys.executable, str(ROOT / "examples" / "symptom_listener.py")],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        run, w = run_live(CONFIG, scenario=scenario, record=out, during=inject_and_kill,
                          timeout_s=150, log=lines.append)
    finally:
        listener.send_signal(signal.SIGINT)
        try:
            done["listener"] = listener.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            listener.kill()
            done["listener"] = listener.communicate()[0]
    return run, w, out, done, lines


def test_symptom_arrives_within_a_few_segments(live):
    run, w, _, _, lines = live
    assert run.fault == "leak_ic_engine" and run.fault_onset == ONSET, lines
    first = first_symptom_arrival(w, ONSET)
    assert first is not None, "no symptom after the fault onset"
    _, msg = first
    levels = dict(zip(msg.names, (int(v) for v in msg.levels)))
    # A leak between intercooler and engine: the MAF meters the engine's air AND the air that
    # escapes through the leak, so the measured eta_V = m_maf / m_th exceeds what the engine
    # really draws, f_eta(n, rho2); r_eta = f_eta - eta_V < 0: symptom "-".
    assert levels["s_eta"] == -1, levels
    assert msg.t_s - ONSET <= MAX_SEGMENTS_TO_SYMPTOM * SEGMENT_S + 1e-9, msg.t_s
    # no symptom at all before the fault
    early = [m for _, m in w.seen.symptoms if m.t_s < ONSET and any(int(v) for v in m.levels)]
    assert not early, f"false symptoms before the fault at {[m.t_s for m in early][:5]}"


def test_diagnosis_isolates_the_leak_and_switches_the_bank(live):
    run, w, _, _, lines = live
    assert run.isolated_faults == ("leak_ic_engine",), lines
    assert ONSET < run.isolation_t < ONSET + 2.0
    d = w.last_diagnosis()
    assert d.state == "isolated" and d.fault_model == "leak_ic_engine"
    # bank rules: the leak hypothesis (and the reference model) stay, the others go off line;
    # the states are read back with the standard get_state service
    states = run.lifecycle_after
    assert states["nominal"] == "active" and states["leak_ic_engine"] == "active"
    for mid in ("egr_leaky", "restriction_ic_engine", "swirl_flap_closed", "egr_stuck_open"):
        assert states[mid] == "inactive", states
    assert states[KILLED] == "process gone"
    assert run.switches and "egr_leaky" in run.switches[0]["off_line"]


def test_diagnostics_report_isolation_and_the_dead_node(live):
    run, w, _, killed, _ = live
    diag = w.diagnostic_status("fdi_supervisor: diagnosis")
    assert diag is not None and "leak_ic_engine" in diag.message
    assert diag.level in (b"\x02", 2)  # ERROR: a fault is present
    dead = w.diagnostic_status(f"fdi_supervisor: model {KILLED}")
    assert dead is not None and "failed" in dead.message, dead
    # the supervisor kept diagnosing after the kill: many more diagnoses came afterwards
    assert killed and len(w.seen.diagnoses) - killed["n_diag"] > 500


def test_example_listener_node_sees_symptom_and_isolation(live):
    _, _, _, done, _ = live
    out = done["listener"]
    assert "s_eta: -" in out, out[-2000:]
    assert "state isolated" in out and "leak_ic_engine" in out, out[-2000:]


def test_frozen_model_reported_silent_then_back(live):
    run, w, _, done, lines = live
    assert "frozen" in done and "thawed" in done
    msgs = []
    for _, arr in w.seen.diagnostics:
        for st in arr.status:
            if st.name == f"fdi_supervisor: model {FROZEN}":
                msgs.append(st.message)
    silent = [i for i, m in enumerate(msgs) if m.startswith("stale")]
    assert silent, f"never reported silent: {sorted(set(msgs))}"
    # after SIGCONT it answers again and is reported healthy (it goes off line at isolation)
    assert any(not m.startswith("stale") for m in msgs[silent[-1] + 1:]), msgs[-5:]
    assert run.isolated_faults == ("leak_ic_engine",), lines


@pytest.fixture(scope="module")
def replay(live):
    """The recorded sensor blocks replayed through preprocessor, bank and supervisor at 4 x
    real time: faster than the graph can follow, so the replay is held back by the diagnosis
    (the replayer's max_ahead_s)."""
    return run_live(CONFIG, replay=live[2], realtime_factor=4.0, timeout_s=150)


def test_replay_and_offline_diagnose_agree_with_the_live_run(live, replay, tmp_path):
    run, _, bag_dir, _, _ = live
    # offline, same core, many times faster than real time
    out = tmp_path / "diag.json"
    subprocess.run([sys.executable, "-m", "fdi_ros.cli", "diagnose", str(bag_dir),
                    "--json", str(out)], check=True, cwd=ROOT)
    off = json.loads(out.read_text())
    assert off["isolated_faults"] == ["leak_ic_engine"]
    # the live bank exchanged batched vectors; the bag holds them one per message, as recorded
    from fdi_ros import bag as bagmod

    topics = bagmod.topics(bag_dir)
    assert "/fdi/residuals" in topics and "/fdi/features" in topics
    assert not set(topics) & {"/fdi/feature_blocks", "/fdi/residual_blocks"}, sorted(topics)
    assert {r.model_id for r in bagmod.read_residuals(bag_dir)} >= {"nominal", "leak_ic_engine"}
    assert abs(off["isolation_time_s"] - run.isolation_t) <= SEGMENT_S + 1e-9
    # live replay of the recorded sensor blocks through preprocessor, bank and supervisor
    rep, _ = replay
    assert rep.ended and rep.isolated_faults == ("leak_ic_engine",)
    assert abs(rep.isolation_t - run.isolation_t) <= SEGMENT_S + 1e-9
    assert not math.isnan(rep.first_symptom_t)
    assert abs(rep.first_symptom_t - run.first_symptom_t) <= SEGMENT_S + 1e-9


def test_model_node_that_cannot_load_its_model_is_reported(diesel_bank, tmp_path):
    """A bank entry whose model files are missing: its node refuses `configure` (FAILURE, not
    a swallowed exception), the supervisor says so on /diagnostics and brings the rest of the
    bank on line."""
    import yaml

    from fdi_ros.graphwatch import GraphWatcher
    from fdi_ros.launcher import Graph
    from fdi_ros.livegraph import bank_ready

    doc = yaml.safe_load(CONFIG.read_text())
    doc["fdi_graph"]["bank"] = doc["fdi_graph"]["bank"][:2] + [
        {"id": "broken", "faults": ["broken_fault"],
         "model": {"type": "diesel_reference", "path": str(tmp_path / "no_models_here")}}]
    cfg = tmp_path / "config" / "diesel_broken.yaml"
    cfg.parent.mkdir()
    cfg.write_text(yaml.safe_dump(doc))
    graph = Graph(cfg, echo=None)
    w = GraphWatcher()
    try:
        graph.start(exclude=("fdi_plant",))
        alive = lambda: graph.alive()["fdi_supervisor"]  # noqa: E731

        def reported():
            st = w.diagnostic_status("fdi_supervisor: model broken")
            return st is not None and "failed" in st.message and st

        st = w.spin_until(reported, 60.0, "the broken model reported", alive)
        assert "refused" in st.message, st.message
        w.spin_until(lambda: bank_ready(w, ["nominal", "leak_ic_engine"]), 60.0,
                     "the healthy models on line", alive)
        assert w.lifecycle_state("fdi_model_broken") == "unconfigured"
        assert w.lifecycle_state("fdi_model_nominal") == "active"
    finally:
        graph.stop()
        w.close()


def test_replay_at_rate_4_same_isolation_and_no_segment_skipped(live, replay):
    """A replay faster than the graph can follow is held back by the diagnosis (the
    replayer's max_ahead_s), so it gives the live run's isolation to the segment and skips
    no segment."""
    run = live[0]
    rep, w = replay
    pipe = [st for _, arr in w.seen.diagnostics for st in arr.status
            if st.name == "fdi_supervisor: pipeline"]
    assert rep.ended and rep.isolated_faults == ("leak_ic_engine",), rep.isolations
    assert abs(rep.isolation_t - run.isolation_t) <= SEGMENT_S + 1e-9
    skipped = [int(v.value) for st in pipe for v in st.values if v.key == "skipped_segments"]
    assert skipped and max(skipped) == 0, [st.message for st in pipe][-3:]
