"""Step aligner, staleness, /diagnostics entries and the fault memory, without ROS."""

from __future__ import annotations

import math
import random
import time

import pytest
from toy_bank import toy_config

from fdi_ros.core.faultmemory import FaultMemory, FaultStore
from fdi_ros.core.supervision import (
    STALE,
    WARN,
    Staleness,
    StepAligner,
    pipeline_entry,
)


def test_aligner_waits_for_every_live_model_in_plant_time():
    al = StepAligner(lag_s=0.1)
    al.add_features(0, 0.015)
    al.add_residual("nominal", 0, "r0")
    assert al.ready({"nominal", "a"}) == []  # a missing, features not ahead yet
    al.add_residual("a", 0, "a0")
    (s,) = al.ready({"nominal", "a"})
    assert s.complete and s.index == 0 and set(s.residuals) == {"nominal", "a"}
    assert not al.add_residual("a", 0, "late") and al.late == 1


def test_aligner_skips_incomplete_steps_when_features_run_ahead_and_counts_gaps():
    al = StepAligner(lag_s=0.05)
    for k in range(10):
        al.add_features(k, 0.015 * (k + 1))
        al.add_residual("nominal", k, k)
    al.add_features(12, 0.015 * 13)  # 10 and 11 dropped
    steps = al.ready({"nominal", "a"})
    assert [s.complete for s in steps] == [False] * len(steps) and steps
    assert al.skipped == len(steps) and al.dropped == 2
    assert pipeline_entry(al, warn_lag_s=1.0).level == WARN


def test_aligner_random_arrival_orders_give_the_same_steps():
    """Residuals arriving in any order (bounded lag) give the same complete steps."""
    seed = int(time.time_ns() % 2**31)
    print(f"seed {seed}")
    rng = random.Random(seed)
    events = [("f", k) for k in range(50)] + [(m, k) for k in range(50) for m in "nab"]
    for _ in range(20):
        order = sorted(events, key=lambda e: e[1] + (0 if e[0] == "f" else rng.random() * 3))
        al, taken = StepAligner(lag_s=10.0), []
        for kind, k in order:
            if kind == "f":
                al.add_features(k, k * 0.015)
            else:
                al.add_residual(kind, k, (kind, k))
            taken += al.ready({"n", "a", "b"})
        assert [s.index for s in taken] == list(range(50)), seed
        assert all(s.complete for s in taken) and al.late == 0


def test_staleness_in_plant_and_wall_time():
    st = Staleness(stale_s=0.5, wall_timeout_s=2.0)
    st.seen("sensor_block", 1.0, wall=10.0)
    st.seen("features", 1.0, wall=10.0)
    assert st.stale(10.1) == {}
    st.seen("sensor_block", 1.6, wall=10.6)  # features stopped, blocks go on
    assert list(st.stale(10.6)) == ["features"]
    assert "stale" in st.stale(10.6)["features"]
    assert set(st.stale(13.0)) == {"sensor_block", "features"}  # everything silent
    st.seen("features", 1.6, wall=13.1)
    st.seen("sensor_block", 1.6, wall=13.1)
    assert st.stale(13.2) == {}


def test_fault_memory_debounce_confirm_heal_clear():
    fm = FaultMemory(confirm_s=0.1, heal_s=1.0)
    t = 0.0
    for _ in range(5):  # isolated for 0.06 s only: dropped before confirmation, no trace
        t += 0.015
        fm.update(t, "isolated", ["leak"])
    fm.update(t + 0.015, "no_fault", [])
    assert fm.records == {}
    for _ in range(10):
        t += 0.015
        fm.update(t, "isolated", ["leak"], {"features": {"n": 2000.0}})
    r = fm.records["leak"]
    assert r.status == "CONFIRMED" and r.occurrences == 1
    assert r.freeze_frame["features"] == {"n": 2000.0}
    first = r.first_t_s
    for _ in range(100):  # not a passed test: no healing while only detected
        t += 0.015
        fm.update(t, "detected", [])
    assert r.status == "CONFIRMED"
    for _ in range(80):
        t += 0.015
        fm.update(t, "no_fault", [])
    assert r.status == "HEALED" and r.first_t_s == first
    for _ in range(10):
        t += 0.015
        fm.update(t, "isolated", ["leak"])
    assert r.status == "CONFIRMED" and r.occurrences == 2
    fm.clear()
    assert r.status == "CLEARED"
    with pytest.raises(KeyError):
        fm.clear(["nope"])
    with pytest.raises(ValueError):
        FaultMemory(confirm_s=math.nan)


def test_fault_store_survives_reopen_and_rejects_garbage(tmp_path):
    fm = FaultMemory(confirm_s=0.0)
    fm.update(6.4, "isolated", ["leak"], {"residuals": [1.0, math.nan]})
    store = FaultStore(tmp_path / "s" / "faults.sqlite")
    store.save(fm.records.values())
    store.close()
    again = FaultStore(tmp_path / "s" / "faults.sqlite").load(FaultMemory())
    r = again.records["leak"]
    assert (r.status, r.occurrences, r.first_t_s) == ("CONFIRMED", 1, 6.4)
    assert r.freeze_frame["residuals"] == [1.0, None]
    bad = tmp_path / "bad.sqlite"
    bad.write_text("not a database at all" * 100)
    with pytest.raises(ValueError, match="fault memory"):
        FaultStore(bad)


def test_stale_entry_level():
    from fdi_ros.core.supervision import diagnosis_entry

    e = diagnosis_entry(None, "diesel", {"features": "stale: no features for 3.0 s"}, False)
    assert e.level == STALE and "stale" in e.message and "features" in e.message


def test_raw_header_stamp_of_serialized_blocks():
    """The supervisor reads only the stamp of a sensor block: same as full deserialisation."""
    import numpy as np

    from fdi_ros import msgs
    from fdi_ros.core.types import SampleBlock

    fac = msgs.MessageFactory("rosbags")
    b = SampleBlock("diesel", 3, np.array([6.42, 6.435]), np.array([1.0, 2.0]), ("n",),
                    ("rpm",), np.array([[2000.0, 2001.0]]))
    m = fac.sensor_block(b)
    raw = msgs.typestore().serialize_cdr(m, "fdi_msgs/msg/SensorBlock")
    assert msgs.raw_header_stamp(bytes(raw)) == pytest.approx(msgs.stamp_seconds(m.header))
    assert math.isnan(msgs.raw_header_stamp(b"\x00\x01"))


TOY = toy_config(0.3)


def _core(tmp_path, store=None):
    from fdi_ros.core.bankdriver import ACTIVE
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.supervision import SupervisorCore

    cfg_file = tmp_path / "config" / "toy.yaml"
    cfg_file.parent.mkdir(exist_ok=True)
    cfg_file.write_text(TOY)
    core = SupervisorCore(load_graph_config(cfg_file), confirm_s=0.05, store=store)
    for mid in core.driver.nodes:  # the bank on line, as get_state confirmed it
        core.driver.on_get_result(mid, ACTIVE, 0.0)
    return core


def _fv(k, y):
    import numpy as np

    from fdi_ros.core.types import FeatureVector

    t = 0.015 * (k + 1)
    return FeatureVector("toy", k, t - 0.015, t, 0.0, True, "", ("y",), ("1",), np.array([y]))


def _residuals(core, k, y, wall, skip=()):
    import numpy as np

    from fdi_ros.core.types import ResidualVector

    t, out = 0.015 * (k + 1), []
    for mid, off in (("nominal", 0.0), ("a", 1.0), ("b", -1.0)):
        if mid not in skip:
            r = y - off
            out += core.residual(ResidualVector(mid, k, t, True, "", ("r",), ("1",),
                                                np.array([r]), abs(r)), wall)
    return out


def _feed(core, k, y, wall, skip=()):
    return core.features(_fv(k, y), wall) + _residuals(core, k, y, wall, skip)


def test_core_external_deactivate_never_isolates_and_memory_reloads(tmp_path):
    from fdi_ros.core.bankdriver import ACTIVE, INACTIVE
    from fdi_ros.core.supervision import Publish

    store = FaultStore(tmp_path / "state" / "toy.sqlite")
    core = _core(tmp_path, store)
    wall = 0.0
    for k in range(20):  # fault free
        wall += 0.015
        _feed(core, k, 0.0, wall)
    assert core.last.state == "no_fault"
    # someone deactivates the nominal model; the plant is fault free but a's residual is
    # smallest among the rest: never isolated
    core.driver.on_transition_event("nominal", ACTIVE, INACTIVE, wall)
    for k in range(20, 80):
        wall += 0.015
        _feed(core, k, 0.4, wall, skip=("nominal",))
    assert core.last.isolated_faults == () and core.last.state == "not_valid"
    names = {e.name: e for e in core.entries(wall)}
    assert "external" in names["fdi_supervisor: model nominal"].message
    # back (reconciled), then a real fault a: isolated, confirmed, persisted
    core.driver.on_transition_event("nominal", INACTIVE, ACTIVE, wall)
    out = []
    for k in range(80, 140):
        wall += 0.015
        out += _feed(core, k, 1.0, wall)
    assert core.last.isolated_faults == ("a",)
    assert [p.value.fault for p in out if isinstance(p, Publish) and p.what == "confirmed"] \
        == ["a"]
    assert core.ring and min(t for t, _, _ in core.ring) >= core.last.t - core.snapshot_s
    store.close()
    again = _core(tmp_path, FaultStore(tmp_path / "state" / "toy.sqlite"))
    assert again.memory.records["a"].status == "CONFIRMED"
    assert again.memory.records["a"].freeze_frame["features"] == {"y": 1.0}


def test_model_confirmed_active_mid_run_is_waited_for_only_from_then_on(tmp_path):
    """A model brought on line while features are in flight computes only what it receives
    once active: the steps before its activation are taken without it (not held until they
    are skipped), every later step waits for it. Random activation points and arrivals."""
    import random

    from fdi_ros.core.bankdriver import ACTIVE, INACTIVE

    rng = random.Random()
    for _ in range(20):
        core = _core(tmp_path)
        core.driver.on_transition_event("b", ACTIVE, INACTIVE, 0.0)
        wall, n_before = 0.0, rng.randint(3, 40)
        for k in range(n_before):  # b off line: its residuals neither come nor are waited for
            wall += 0.015
            core.features(_fv(k, 0.0), wall)
        behind = rng.randint(0, n_before - 1)  # the other models lag by this many segments
        for k in range(n_before - behind):
            _residuals(core, k, 0.0, wall, skip=("b",))
        core.driver.on_transition_event("b", INACTIVE, ACTIVE, wall)  # confirmed active
        for k in range(n_before - behind, n_before):  # the features b never saw
            _residuals(core, k, 0.0, wall, skip=("b",))
        assert core.aligner.next_index == n_before and core.aligner.skipped == 0
        k = n_before
        core.features(_fv(k, 0.0), wall)
        _residuals(core, k, 0.0, wall, skip=("b",))
        assert core.aligner.next_index == k, "a step after the activation waits for b"
        _residuals(core, k, 0.0, wall, skip=("nominal", "a"))
        assert core.aligner.next_index == k + 1 and core.aligner.skipped == 0
        assert core.last.state == "no_fault" and not core.away


def test_core_live_settings_validated(tmp_path):
    core = _core(tmp_path)
    core.set("t0_s", 0.6)
    core.set("explain_norm", 1.5)
    core.set("ambiguity", 0.8)
    core.set("reconcile", "respect")
    assert core.diag.supervisor.t0_s == 0.6 and core.diag.explain_norm == 1.5
    assert core.diag.ambiguity == 0.8
    assert core.driver.policy.policy == "respect"
    for name, bad in (("t0_s", -1.0), ("explain_norm", 0.0), ("ambiguity", 0.0),
                      ("ambiguity", 1.5), ("lag_s", 0.0),
                      ("reconcile", "bogus"), ("reconcile_after_s", math.inf)):
        with pytest.raises(ValueError):
            core.set(name, bad)


def test_threshold_scale_live(diesel_bank):
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.supervision import SupervisorCore

    core = SupervisorCore(load_graph_config(diesel_bank))
    base = core.diag.symptom_gen.config.threshold
    core.set("threshold_scale", 2.0)
    core.set("threshold_scale", 1.5)  # relative to the configured thresholds, not compounded
    assert core.diag.symptom_gen.config.threshold == pytest.approx([1.5 * x for x in base])
    with pytest.raises(ValueError, match="threshold_scale"):
        core.set("threshold_scale", 0.0)


@pytest.mark.parametrize("batched", [True, False])
def test_start_gate_names_what_is_missing_until_every_reader_is_there(tmp_path, batched):
    """The start-up handshake: no /fdi/ready until every on-line model is active, reads the
    features and publishes residuals matched here (a sensor block per message or one vector
    per message), the preprocessor is matched and the named readers (a recorder on every
    topic, a watcher on the diagnosis) are in the graph; a model the driver gave up on
    (refused) is not waited for."""
    from fdi_ros.core.bankdriver import ACTIVE, INACTIVE
    from fdi_ros.core.graphconfig import load_graph_config
    from fdi_ros.core.supervision import DATA_TOPICS, GATE_TOPICS, SupervisorCore

    cfg_file = tmp_path / "config" / "toy.yaml"
    cfg_file.parent.mkdir(exist_ok=True)
    cfg_file.write_text(TOY)
    core = SupervisorCore(load_graph_config(cfg_file), batched=batched)
    f_t, r_t = DATA_TOPICS[batched]
    online = list(core.diag.models_online)
    nodes = [core.driver.nodes[m].node for m in online]
    readers = ["fdi_recorder", "fdi_launch_watcher:/fdi/diagnosis"]
    full_subs: dict = {t: set() for t in (*GATE_TOPICS, f_t, r_t)}
    full_subs[f_t] |= {*nodes, "fdi_supervisor"}
    full_subs[r_t] |= {"fdi_supervisor"}
    for t in GATE_TOPICS:
        full_subs[t].add("fdi_recorder")
    full_subs["/fdi/diagnosis"].add("fdi_launch_watcher")
    full_pubs = {f_t: {"fdi_preprocessor"}, r_t: set(nodes)}
    full_matched = {f_t: 1, r_t: len(nodes)}
    # nothing active yet: every model named
    miss = core.waiting_for(full_pubs, full_subs, full_matched, readers)
    assert all(any(n in m for m in miss) for n in nodes), miss
    for mid in core.driver.nodes:
        core.driver.on_get_result(mid, ACTIVE if mid in online else INACTIVE, 0.0)
    assert core.waiting_for(full_pubs, full_subs, full_matched, readers) == []
    rng = random.Random(7)
    for _ in range(30):  # take away one random piece: it is named, nothing else
        subs = {t: set(v) for t, v in full_subs.items()}
        pubs = {t: set(v) for t, v in full_pubs.items()}
        matched = dict(full_matched)
        what = rng.choice(["sub", "pub", "matched"])
        if what == "sub":
            t = rng.choice(sorted(subs))
            gone = rng.choice(sorted(subs[t] - {"fdi_supervisor"}))
            subs[t].discard(gone)
            need = gone in nodes and t == f_t or gone == "fdi_recorder" or \
                gone == "fdi_launch_watcher" and t == "/fdi/diagnosis"
        elif what == "pub":
            gone = rng.choice(nodes)
            pubs[r_t].discard(gone)
            need = True
        else:
            t = rng.choice(sorted(matched))
            matched[t] -= 1
            gone, need = t, True
        miss = core.waiting_for(pubs, subs, matched, readers)
        assert bool(miss) == need, (what, gone, miss)
        assert len(miss) <= 1, miss
    # the supervisor's own diagnosis writer not yet matched to every reader the graph shows
    # (a recorder seen but not yet matched would miss the first diagnoses)
    written = {"/fdi/diagnosis": len(full_subs["/fdi/diagnosis"])}
    assert core.waiting_for(full_pubs, full_subs, full_matched, readers, written) == []
    written["/fdi/diagnosis"] -= 1
    miss = core.waiting_for(full_pubs, full_subs, full_matched, readers, written)
    assert len(miss) == 1 and "/fdi/diagnosis" in miss[0], miss
    # a refused model is out of the bank: not waited for
    core.driver.on_change_result(online[-1], False, 1.0, ACTIVE)
    less = {f_t: 1, r_t: len(nodes) - 1}
    pubs = {f_t: {"fdi_preprocessor"}, r_t: set(nodes[:-1])}
    assert core.waiting_for(pubs, full_subs, less, readers) == []


def test_models_on_line_before_the_data_are_not_stale_at_its_first_segment(tmp_path):
    """The start-up handshake activates the bank seconds before the first block: a model is
    judged from the first features on, so the first segments are diagnosed on the whole bank
    (as offline), not declared stale and skipped."""
    core = _core(tmp_path)
    ready = dict.fromkeys(core.driver.nodes, False)
    core.tick(0.0, ready, None)  # the bank on line at wall 0
    notes = []
    for k in range(10):  # the data starts at wall 5
        wall = 5.0 + 0.015 * k
        notes += [a for a in core.tick(wall, ready, None) if hasattr(a, "text")]
        _feed(core, k, 0.0, wall)
    assert not [n.text for n in notes if "stale" in n.text], notes
    assert core.last.state == "no_fault" and core.aligner.skipped == 0
    # a model silent for model_wall_s while the features go on is reported stale (health,
    # wall time) but still waited for: the diagnosis is decided in plant time only
    for k in range(10, 100):
        wall = 5.0 + 0.015 * k
        core.tick(wall, ready, None)
        _feed(core, k, 0.0, wall, skip=("b",))
    assert "residuals b" in core._stale and "b" in core._expected()
    assert core.last.index == 9 and not core.away  # 1.35 s of plant time < lag_s
    # lag_s of plant time without it: that step skipped (not valid), b away, the rest go on
    notes = []
    for k in range(100, 200):
        wall = 5.0 + 0.015 * k
        notes += [a for a in core.tick(wall, ready, None) if hasattr(a, "text")]
        notes += [a for a in _feed(core, k, 0.0, wall, skip=("b",)) if hasattr(a, "text")]
    assert core.away == {"b"} and "b" not in core._expected()
    assert core.aligner.skipped == 1 and core.last.index == 199
    assert core.last.state == "no_fault"
    assert any("model b: no residuals for segment 10" in n.text for n in notes), notes
    # b answers in time again: waited for again
    _feed(core, 200, 0.0, 5.0 + 0.015 * 200)
    assert not core.away and "b" in core._expected()


def test_end_of_the_data_said_once_the_last_segment_is_diagnosed(tmp_path):
    """The preprocessor's end of the features names its last index; the supervisor says the
    end of the diagnosis when that step is taken, not before (whatever the wall time), and
    a residual that never comes is not waited for forever (health fallback)."""
    from fdi_ros.core.supervision import Publish

    def ends(actions):
        return [a.value for a in actions if isinstance(a, Publish) and a.what == "end"]

    core = _core(tmp_path)
    ready = dict.fromkeys(core.driver.nodes, False)
    for k in range(5):
        _feed(core, k, 0.0, 0.0)
    out = core.features(_fv(5, 0.0), 0.0)  # the last features: its residuals not yet here
    out += core.end_of_features(0.09, 5, 0.0)
    out += core.tick(1.0, ready, None)
    assert ends(out) == [] and core.last.index == 4
    out = _residuals(core, 5, 0.0, 1.5)
    assert ends(out) == [(0.09, 5, "")] and core.last.index == 5
    assert ends(core.tick(9.0, ready, None)) == []  # said once
    # a second source's data into the running graph: its own end said in turn
    for k in range(6, 9):
        _feed(core, k, 0.0, 10.0)
    assert ends(core.end_of_features(0.135, 8, 10.0)) == [(0.135, 8, "")]
    # a model that never answers for the last segment: after stale_wall_s of silence the step
    # is taken without it (skipped, not valid) and the end said with the reason
    core = _core(tmp_path)
    for k in range(3):
        _feed(core, k, 0.0, 0.0)
    out = core.features(_fv(3, 0.0), 0.0) + _residuals(core, 3, 0.0, 0.0, skip=("a",))
    out += core.end_of_features(0.06, 3, 0.0) + core.tick(1.0, ready, None)
    assert ends(out) == []
    out = core.tick(10.0, ready, None)
    assert ends(out) == [(0.06, 3, "")] and core.last.index == 3
    assert core.last.state == "not_valid" and core.aligner.skipped == 1
    # features that never came: named
    core = _core(tmp_path)
    for k in range(3):
        _feed(core, k, 0.0, 0.0)
    out = core.end_of_features(0.09, 5, 0.0) + core.tick(10.0, ready, None)
    # the end names the last segment diagnosed (2), which a watcher can see, and why
    assert len(ends(out)) == 1 and ends(out)[0][:2] == (0.09, 2) \
        and "features 3..5 never came" in ends(out)[0][2]
