"""The bank driver state machine without ROS: table cases, external transitions under both
policies, time-outs and random event sequences against a simulated lifecycle graph."""

from __future__ import annotations

import random
import time

import pytest

from fdi_ros.core.bankdriver import (
    ACTIVATE,
    ACTIVE,
    CONFIGURE,
    DEACTIVATE,
    INACTIVE,
    UNCONFIGURED,
    BankDriver,
    ChangeState,
    DriverPolicy,
    GetState,
    Note,
)

NODES = [("nominal", "fdi_model_nominal"), ("a", "fdi_model_a"), ("b", "fdi_model_b")]
READY = {m: True for m, _ in NODES}
GOAL = {CONFIGURE: INACTIVE, ACTIVATE: ACTIVE, DEACTIVATE: INACTIVE}


def bring_up(drv: BankDriver, now: float = 0.0) -> float:
    """Answer every request at once (a perfect graph, nodes start unconfigured)."""
    true = {m: v.observed or UNCONFIGURED for m, v in drv.nodes.items()}
    for _ in range(80):
        acts = drv.tick(now, READY)
        while acts:
            a = acts.pop(0)
            if isinstance(a, GetState):
                drv.on_get_result(a.model_id, true[a.model_id], now)
            elif isinstance(a, ChangeState):
                true[a.model_id] = a.goal
                drv.on_transition_event(a.model_id, 0, a.goal, now)
                acts += drv.on_change_result(a.model_id, True, now, a.goal)
        now += 0.05
        if drv.converged() and not any(v.pending for v in drv.nodes.values()):
            break
    return now


def test_bring_up_follows_the_lifecycle_and_confirms():
    drv = BankDriver(NODES)
    drv.set_desired(["nominal", "a"])
    acts = drv.tick(0.0, READY)
    assert all(isinstance(a, GetState) for a in acts) and len(acts) == 3
    drv.on_get_result("nominal", UNCONFIGURED, 0.01)
    (a,) = [x for x in drv.tick(0.02, READY) if x.model_id == "nominal"]
    assert a == ChangeState("nominal", "fdi_model_nominal", CONFIGURE, INACTIVE)
    # confirmed with get_state after a successful change
    assert drv.on_change_result("nominal", True, 0.03, INACTIVE) == [
        GetState("nominal", "fdi_model_nominal")]
    drv.on_get_result("nominal", INACTIVE, 0.04)
    bring_up(drv, 0.1)
    assert [v.observed for v in drv.nodes.values()] == [ACTIVE, ACTIVE, INACTIVE]
    assert drv.live("nominal") and drv.live("a") and not drv.live("b")


def test_refused_transition_takes_the_node_out():
    drv = BankDriver(NODES)
    drv.set_desired(["nominal"])
    drv.tick(0.0, READY)
    drv.on_get_result("b", UNCONFIGURED, 0.0)
    drv.tick(0.1, READY)
    notes = drv.on_change_result("b", False, 0.1, INACTIVE)
    assert any(isinstance(n, Note) and "refused" in n.text for n in notes)
    assert not [a for a in drv.tick(5.0, READY) if a.model_id == "b"]


@pytest.mark.parametrize("policy", ["reconcile", "respect"])
def test_external_deactivate_is_reported_and_handled_by_policy(policy):
    drv = BankDriver(NODES, DriverPolicy(policy=policy, reconcile_after_s=1.0))
    drv.set_desired(["nominal", "a"])
    now = bring_up(drv)
    notes = drv.on_transition_event("nominal", ACTIVE, INACTIVE, now)
    assert any(n.level == "warn" and "external" in n.text and "fdi_model_nominal" in n.text
               for n in notes)
    assert not drv.live("nominal")  # its residuals are not valid while away
    assert not drv.tick(now + 0.5, READY)  # not before reconcile_after_s
    acts = drv.tick(now + 1.5, READY)
    if policy == "respect":
        assert acts == [] and drv.nodes["nominal"].observed == INACTIVE
        return
    assert acts == [ChangeState("nominal", "fdi_model_nominal", ACTIVATE, ACTIVE)]
    drv.on_transition_event("nominal", INACTIVE, ACTIVE, now + 1.51)  # ours: not external
    drv.on_change_result("nominal", True, now + 1.52, ACTIVE)
    drv.on_get_result("nominal", ACTIVE, now + 1.53)
    assert drv.live("nominal") and drv.nodes["nominal"].external_count == 1


def test_own_transition_events_are_not_external():
    drv = BankDriver(NODES)
    drv.set_desired(["nominal", "a"])
    now = bring_up(drv)
    assert all(v.external_count == 0 for v in drv.nodes.values())
    drv.set_desired(["nominal"])  # a bank switch: a goes off line by our request
    (act,) = drv.tick(now, READY)
    assert act.transition == DEACTIVATE
    # the event may come after the answer and the confirmation
    drv.on_change_result("a", True, now, INACTIVE)
    drv.on_get_result("a", INACTIVE, now)
    assert not [n for n in drv.on_transition_event("a", ACTIVE, INACTIVE, now)
                if n.level == "warn"]


def test_timeouts_retry_and_recover():
    drv = BankDriver(NODES, DriverPolicy(node_timeout_s=2.0, first_contact_retry_s=0.5))
    drv.set_desired(["nominal"])
    first = drv.tick(0.0, READY)
    assert len(first) == 3
    again = drv.tick(0.6, READY)  # first get_state repeated, not failed
    assert len(again) == 3 and not any(v.failed for v in drv.nodes.values())
    notes = drv.tick(2.7, READY)
    assert any(isinstance(n, Note) and n.level == "error" for n in notes)
    back = drv.on_get_result("nominal", UNCONFIGURED, 2.8)
    assert any("answers again" in n.text for n in back)
    assert not drv.nodes["nominal"].failed


def test_bad_policy_rejected():
    with pytest.raises(ValueError, match="policy"):
        DriverPolicy(policy="ignore")
    with pytest.raises(ValueError, match="reconcile_after_s"):
        DriverPolicy(reconcile_after_s=-1)
    with pytest.raises(ValueError, match="duplicate"):
        BankDriver([("a", "x"), ("a", "y")])


def test_random_event_sequences_keep_the_invariants():
    """A simulated lifecycle graph with lost and late answers, refused transitions, external
    transitions and bank switches, driven for many random steps; then quiet: the driver must
    converge (reconcile) and its view equal the nodes' true states."""
    seed = int(time.time_ns() % 2**31)
    print(f"seed {seed}")
    rng = random.Random(seed)
    for _run in range(30):
        drv = BankDriver(NODES, DriverPolicy(node_timeout_s=1.0, first_contact_retry_s=0.3,
                                             reconcile_after_s=0.5))
        true = {m: UNCONFIGURED for m, _ in NODES}
        inflight: list[tuple[float, object]] = []  # (due time, action)
        now, desired = 0.0, {"nominal", "a"}
        drv.set_desired(desired)
        for step in range(400):
            quiet = step >= 250
            now += 0.05
            if not quiet and rng.random() < 0.03:
                desired = {"nominal"} | {m for m in ("a", "b") if rng.random() < 0.5}
                drv.set_desired(desired)
            if not quiet and rng.random() < 0.03:  # someone else moves a node
                m = rng.choice([m for m, _ in NODES])
                if true[m] in (ACTIVE, INACTIVE):
                    old, true[m] = true[m], INACTIVE if true[m] == ACTIVE else ACTIVE
                    v = drv.nodes[m]
                    # an event matching a transition we asked for (whose answer is lost)
                    # cannot be told from ours
                    ours = v.pending or any(g == true[m] for g, _ in v.expected_goals)
                    notes = drv.on_transition_event(m, old, true[m], now)
                    if true[m] != v.desired and not ours:
                        assert any("external" in n.text for n in notes)
            acts = drv.tick(now, READY)
            per_node = [a.model_id for a in acts if not isinstance(a, Note)]
            assert len(per_node) == len(set(per_node)), acts  # one request per node
            for a in acts:
                if isinstance(a, (GetState, ChangeState)):
                    assert not drv.nodes[a.model_id].failed or \
                        drv.nodes[a.model_id].failed.startswith("lifecycle service")
                    lost = not quiet and rng.random() < 0.1
                    if not lost:
                        inflight.append((now + rng.uniform(0, 0.3 if not quiet else 0.1), a))
            due = [x for x in inflight if x[0] <= now]
            inflight = [x for x in inflight if x[0] > now]
            for _, a in due:
                if isinstance(a, GetState):
                    drv.on_get_result(a.model_id, true[a.model_id], now)
                else:
                    ok = GOAL[a.transition] != true[a.model_id] and (
                        true[a.model_id] == {CONFIGURE: UNCONFIGURED, ACTIVATE: INACTIVE,
                                             DEACTIVATE: ACTIVE}[a.transition])
                    if ok:
                        old, true[a.model_id] = true[a.model_id], a.goal
                        drv.on_transition_event(a.model_id, old, a.goal, now)
                    drv.on_change_result(a.model_id, ok, now, a.goal)
            for m, _ in NODES:
                if drv.live(m):
                    assert drv.nodes[m].observed == ACTIVE and m in desired
        # quiet phase: every node that did not fail for good converged to the truth
        for m, v in drv.nodes.items():
            if v.failed and not v.failed.startswith("lifecycle service"):
                continue
            assert v.observed == true[m] == v.desired, (seed, m, v, true)
            assert drv.live(m) == (m in desired)


def test_a_node_missing_from_one_graph_listing_is_not_gone():
    """A busy machine's discovery can drop a live node from a listing: gone only after
    ``absent_s`` of absence, and a node that comes back before that was never failed."""
    drv = BankDriver(NODES, DriverPolicy(absent_s=1.0))
    drv.set_desired(["nominal", "a"])
    now = bring_up(drv)
    rng = random.Random()
    for _ in range(50):  # random blips shorter than absent_s
        t = now + rng.uniform(0.0, 0.9)
        assert drv.on_presence("a", False, now) == [] and drv.on_presence("a", False, t) == []
        assert drv.on_presence("a", True, t + 0.01) == [] and drv.live("a")
        now = t + 0.05
    assert drv.on_presence("a", False, now) == []
    (note,) = drv.on_presence("a", False, now + 1.0)
    assert "vanished" in note.text and not drv.live("a")
    with pytest.raises(ValueError):
        DriverPolicy(absent_s=-1.0)
